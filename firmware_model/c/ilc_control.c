/*
 * ilc_control.c -- the drive's control period in C99, bit-exact with the Python reference model.
 *
 * A port of firmware_model/control_law.py:control_tick (velocity estimate by difference plus a
 * first-order IIR filter; PD or the cascade position P -> velocity PI with clamping anti-windup;
 * the feed-forward table value; the torque clamp; the following-error count; the recorder write)
 * and of the integer helpers of bus/fixedpoint.py it uses (sat32, sat, rshift_round).  The
 * formats are defined in bus/fixedpoint.py; the Q shifts of ilc_drive.h mirror its constants (the test
 * tests/test_firmware_c.py checks that they are equal).
 *
 * Integer semantics (why this is bit-exact and free of undefined behaviour):
 *  - every product and sum is formed in int64_t; for inputs within the ranges of
 *    bus/fixedpoint.py and the EDS (gains 0 .. 2^31-1, errors saturated to int32, rate < 2^32,
 *    filter coefficient <= 2^15, torque limit 0 .. 3000 * (2^32-1) < 2^44, the ranges of
 *    ilc_drive.h) each intermediate is below 2^63 (the bounds are noted beside the lines), so no
 *    signed overflow happens;
 *  - a right shift of a negative value is implementation-defined in C: ilc_asr() forms the
 *    floor division by 2^q as ~((~x) >> q) for negative x, which only shifts non-negative
 *    values; it equals Python's and numba's ">>" (floor) on every int64;
 *  - no left shift of a negative value (undefined in C99): scalings by 2^q are multiplications
 *    by the positive constant (int64_t)1 << q;
 *  - int64_t and int32_t are two's complement by C99 7.18.1.1, so "& 1" on a negative value
 *    reads its lowest bit as Python does.
 * No libc call, no malloc, no floating point: the same file builds for the host and for a
 * Cortex-M4 (where the int64 multiplications are compiler helper calls or UMULL sequences).
 */
#include "ilc_drive.h"

/* the int ranges of bus/fixedpoint.py */
#define ILC_INT32_MIN (-INT64_C(2147483647) - 1)
#define ILC_INT32_MAX INT64_C(2147483647)
#define ILC_INT16_MIN INT64_C(-32768)
#define ILC_INT16_MAX INT64_C(32767)
/* raw velocity (Q12) saturation: the int32 counts/s range, INT32_MIN/MAX << VEL_STATE_Q */
#define ILC_VRAW_MAX (ILC_INT32_MAX * (INT64_C(1) << ILC_VEL_STATE_Q))
#define ILC_VRAW_MIN (ILC_INT32_MIN * (INT64_C(1) << ILC_VEL_STATE_Q))

int64_t ilc_sat32(int64_t x)
{
    return x < ILC_INT32_MIN ? ILC_INT32_MIN : (x > ILC_INT32_MAX ? ILC_INT32_MAX : x);
}

int64_t ilc_sat16(int64_t x)
{
    return x < ILC_INT16_MIN ? ILC_INT16_MIN : (x > ILC_INT16_MAX ? ILC_INT16_MAX : x);
}

int64_t ilc_sat(int64_t x, int64_t lo, int64_t hi)
{
    /* Python: min(max(x, lo), hi) -- hi wins when lo > hi */
    int64_t y = x > lo ? x : lo;
    return y < hi ? y : hi;
}

int64_t ilc_asr(int64_t x, int q)
{
    return x >= 0 ? (x >> q) : ~((~x) >> q);
}

int64_t ilc_rshift_round(int64_t x, int q)
{
    if (q <= 0) {
        return x;
    }
    /* |asr(x, q)| <= 2^62 for q >= 1: adding 1 cannot overflow */
    return ilc_asr(x, q) + (ilc_asr(x, q - 1) & 1);
}

void ilc_state_init(int64_t *st)
{
    int i;
    for (i = 0; i < ILC_N_STATE; ++i) {
        st[i] = 0;
    }
    st[ILC_P_ALPHA] = INT64_C(1) << ILC_VEL_FILTER_Q;  /* 1.0: unfiltered */
    st[ILC_P_RATE] = INT64_C(4096000);                 /* 1 kHz, Hz Q12 */
    st[ILC_P_FE_WINDOW] = -1;                          /* check off */
    st[ILC_P_KVFF] = INT64_C(1) << ILC_GAIN_Q;         /* 1.0 */
    st[ILC_P_KTFF] = INT64_C(1) << ILC_GAIN_Q;         /* 1.0 */
}

int32_t ilc_control_tick(int64_t count, int64_t idx, int64_t rec_idx, int64_t *st,
                         const int32_t *tables, int64_t table_cols,
                         int32_t *rec, int64_t rec_cols, int32_t *status)
{
    const int64_t ref_pos = tables[ILC_ROW_REF_POS * table_cols + idx];
    const int64_t ref_vel = tables[ILC_ROW_REF_VEL * table_cols + idx];
    const int64_t ff_table = tables[ILC_ROW_FF * table_cols + idx];
    const int64_t c = ilc_sat32(count);
    const int64_t lim = st[ILC_P_TLIM];
    int64_t vf = st[ILC_S_VF];
    int64_t v_raw, v_est, e, fb, tau, window;
    int64_t limited = 0;

    /* velocity: difference (|d| <= 2^31, rate < 2^32: product < 2^63) and Q12 first-order IIR */
    if (st[ILC_S_HAVE_PREV] != 0) {
        const int64_t d = ilc_sat32(c - st[ILC_S_PREV_COUNT]);
        v_raw = ilc_sat(d * st[ILC_P_RATE], ILC_VRAW_MIN, ILC_VRAW_MAX);
    } else {
        v_raw = vf; /* first tick after enable or trial start: the estimate is held */
    }
    vf = vf + ilc_rshift_round(st[ILC_P_ALPHA] * (v_raw - vf), ILC_VEL_FILTER_Q); /* < 2^60 */
    v_est = ilc_sat32(ilc_rshift_round(vf, ILC_VEL_STATE_Q));

    e = ilc_sat32(ref_pos - c);
    if (st[ILC_P_LOOP] == ILC_LOOP_CASCADE) {
        const int64_t lim_q = lim * (INT64_C(1) << ILC_ACC_Q); /* < 2^60 */
        const int64_t ff = ilc_sat32(ilc_rshift_round(st[ILC_P_KTFF] * ff_table, ILC_GAIN_Q));
        const int64_t v_ff = ilc_rshift_round(st[ILC_P_KVFF] * ref_vel, ILC_GAIN_Q);
        const int64_t v_cmd = ilc_sat32(ilc_rshift_round(st[ILC_P_KPP] * e, ILC_GAIN_Q) + v_ff);
        const int64_t ev = ilc_sat32(v_cmd - v_est);
        const int64_t p_term = st[ILC_P_KVP] * ev; /* < 2^62 */
        int64_t vint = st[ILC_S_VINT];
        /* |vint| <= 2^60, |Kvi·ev| < 2^62: the sum and p_term + trial_int stay below 2^63 */
        const int64_t trial_int = ilc_sat(vint + st[ILC_P_KVI] * ev, -lim_q, lim_q);
        const int64_t u = ilc_rshift_round(p_term + trial_int, ILC_ACC_Q) + ff;
        /* anti-windup (clamping): integrate unless the torque saturates and ev pushes it further */
        if (!((u > lim && ev > 0) || (u < -lim && ev < 0))) {
            vint = trial_int;
        }
        fb = ilc_sat32(ilc_rshift_round(p_term + vint, ILC_ACC_Q));
        tau = ilc_sat32(fb + ff);
        st[ILC_S_VINT] = vint;
        st[ILC_S_VCMD] = v_cmd;
    } else {
        const int64_t ed = ilc_sat32(ref_vel - v_est);
        const int64_t acc = st[ILC_P_KP] * e + st[ILC_P_KD] * ed; /* each < 2^62, sum < 2^63 - 2^32 */
        fb = ilc_sat32(ilc_rshift_round(acc, ILC_ACC_Q));
        tau = ilc_sat32(fb + ff_table);
    }
    if (tau > lim) {
        tau = lim;
        limited = 1;
    } else if (tau < -lim) {
        tau = -lim;
        limited = 1;
    }

    st[ILC_S_PREV_COUNT] = c;
    st[ILC_S_HAVE_PREV] = 1;
    st[ILC_S_VF] = vf;
    st[ILC_S_VEST] = v_est;
    st[ILC_S_POS] = c;
    st[ILC_S_TAU] = tau;
    st[ILC_S_TAU_FB] = fb;
    st[ILC_S_ERR] = e;
    st[ILC_S_LIMITED] = limited;
    if (rec_idx >= 0) {
        rec[ILC_REC_POS * rec_cols + rec_idx] = (int32_t)c;
        rec[ILC_REC_VEL * rec_cols + rec_idx] = (int32_t)v_est;
        rec[ILC_REC_TAU * rec_cols + rec_idx] = (int32_t)tau;
        rec[ILC_REC_TAU_FB * rec_cols + rec_idx] = (int32_t)fb;
    }
    *status = ILC_STATUS_OK;
    window = st[ILC_P_FE_WINDOW];
    if (window >= 0 && (e > window || -e > window)) {
        st[ILC_S_FE_COUNT] += 1;
        if (st[ILC_S_FE_COUNT] > st[ILC_P_FE_TICKS]) {
            *status = ILC_STATUS_FOLLOWING_ERROR;
        }
    } else {
        st[ILC_S_FE_COUNT] = 0;
    }
    return (int32_t)tau;
}

int64_t ilc_floor_div(int64_t num, int64_t den)
{
    int64_t q = num / den; /* truncates toward 0 (C99 6.5.5) */
    if ((num % den) != 0 && num < 0) {
        q -= 1; /* den > 0: a negative inexact quotient rounds down */
    }
    return q;
}

int32_t ilc_csp_velocity_ref(int64_t target, int64_t prev, int64_t rate_q12)
{
    /* |sat32(.)| <= 2^31, rate < 2^32: the product is below 2^63 */
    return (int32_t)ilc_sat32(ilc_rshift_round(ilc_sat32(target - prev) * rate_q12, ILC_VEL_STATE_Q));
}

int32_t ilc_velocity_from_tick_q16(int64_t v_q16, int64_t period_us)
{
    /* Python: (2·v·10^6 + den) // (2·den), den = period_us · 2^16, which can exceed int64 in the
       numerator.  With v = a·den + b (0 <= b < den <= 2^33): the value is
       a·10^6 + (2·b·10^6 + den) // (2·den), every term below 2^63 once a is saturated. */
    const int64_t den = period_us * (INT64_C(1) << 16);
    const int64_t a = ilc_floor_div(v_q16, den);
    const int64_t b = v_q16 - a * den;
    const int64_t frac = ilc_floor_div(2 * b * INT64_C(1000000) + den, 2 * den); /* 0 or 1 .. 10^6 */
    const int64_t a_sat = ilc_sat(a, ILC_INT32_MIN - 1, ILC_INT32_MAX + 1);    /* keeps the sign, saturates below */
    return (int32_t)ilc_sat32(a_sat * INT64_C(1000000) + frac);
}

int16_t ilc_torque_units_to_permille(int64_t tau_units, int64_t rated_mnm)
{
    if (rated_mnm <= 0) {
        return 0;
    }
    return (int16_t)ilc_sat16(ilc_floor_div(2 * tau_units + rated_mnm, 2 * rated_mnm));
}
