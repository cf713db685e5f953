/*
 * ilc_drive.h -- the drive firmware's real-time part in C99: the interface.
 *
 * What a drive's control interrupt runs each control period, ported bit for bit from the Python
 * reference model (firmware_model/control_law.py:control_tick and the integer helpers of
 * bus/fixedpoint.py).  Every fixed-point format (Q16 gains, Q12 velocity state, Q15 filter
 * coefficient, µN·m torque, ...) is defined once, in bus/fixedpoint.py; this header only names
 * the array slots.
 *
 * Portability: C99, <stdint.h> only; no libc call, no malloc, no floating point.  Builds for the
 * host (gcc, the CPython extension firmware_model._fwcore) and for a Cortex-M4
 * (arm-none-eabi-gcc -mcpu=cortex-m4 -mthumb).  No signed overflow happens for inputs within the
 * documented ranges (those of bus/fixedpoint.py): every intermediate is an int64 below 2^63.
 *
 * Calling convention (the "init, step, parameter write" of a drive):
 *   init:            fill st[] with ilc_state_init() (zeroed state, an unfiltered velocity,
 *                    a 1 kHz rate, following-error check off, feed-forward gains 1.0);
 *   parameter write: store the converted value in st[ILC_P_*] (the object callbacks of the
 *                    drive do this; formats: bus/fixedpoint.py);
 *   step:            ilc_control_tick() once per control period.
 */
#ifndef ILC_DRIVE_H
#define ILC_DRIVE_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---------------------------------------------------------------- st[] layout
 * int64 st[ILC_N_STATE]; == firmware_model.control_law.N_STATE, the indices mirror P_* / S_*. */
#define ILC_N_STATE 26
#define ILC_P_KP 0          /* Kp, Q16 µN·m/count (0 .. INT32_MAX) */
#define ILC_P_KD 1          /* Kd, Q16 µN·m/(count/s) (0 .. INT32_MAX) */
#define ILC_P_ALPHA 2       /* velocity filter coefficient, Q15 (1 .. 32768) */
#define ILC_P_RATE 3        /* tick rate, Hz Q12 (> 0, < 2^32: a period >= 1 µs) */
#define ILC_P_TLIM 4        /* torque limit, µN·m = 0x6072 · 0x6076 (0 .. 3000 · (2^32 - 1) < 2^44) */
#define ILC_P_FE_WINDOW 5   /* following-error window, counts; < 0: check off */
#define ILC_S_PREV_COUNT 6  /* previous encoder count */
#define ILC_S_HAVE_PREV 7   /* 1 when ILC_S_PREV_COUNT is valid */
#define ILC_S_VF 8          /* velocity filter state, counts/s Q12 */
#define ILC_S_VEST 9        /* velocity estimate, counts/s */
#define ILC_S_POS 10        /* last encoder count (position actual) */
#define ILC_S_TAU 11        /* last torque command, µN·m */
#define ILC_S_TAU_FB 12     /* last feedback torque, µN·m */
#define ILC_S_ERR 13        /* last position error, counts */
#define ILC_S_LIMITED 14    /* 1 when the last torque was clamped */
#define ILC_P_LOOP 15       /* feedback structure: ILC_LOOP_PD or ILC_LOOP_CASCADE */
#define ILC_P_KPP 16        /* position loop gain, Q16 (counts/s)/count (cascade) */
#define ILC_P_KVFF 17       /* velocity feed-forward gain, Q16, 65536 = 1.0 (0 .. INT32_MAX) */
#define ILC_P_KTFF 18       /* torque feed-forward gain, Q16, 65536 = 1.0 (0 .. INT32_MAX) */
#define ILC_P_KVP 19        /* velocity loop P gain, Q16 µN·m/(count/s) (cascade) */
#define ILC_P_KVI 20        /* velocity loop I gain per period, Q16 µN·m/(count/s) (0 .. INT32_MAX) */
#define ILC_S_VINT 21       /* velocity loop integrator, µN·m Q16, |.| <= limit·2^16 (cascade) */
#define ILC_S_VCMD 22       /* last velocity command, counts/s (cascade) */
#define ILC_P_FE_TICKS 23   /* following-error time-out, control periods (0 .. 2^31) */
#define ILC_S_FE_COUNT 24   /* periods in a row with |e| above the window */

/* P_LOOP values */
#define ILC_LOOP_PD 0
#define ILC_LOOP_CASCADE 1

/* tables rows (int32, row-major (3, table_cols)) and recorder rows (int32, (4, rec_cols)) */
#define ILC_ROW_REF_POS 0   /* reference position, counts */
#define ILC_ROW_REF_VEL 1   /* reference velocity, counts/s */
#define ILC_ROW_FF 2        /* feed-forward torque, µN·m */
#define ILC_REC_POS 0       /* position, counts */
#define ILC_REC_VEL 1       /* velocity estimate, counts/s */
#define ILC_REC_TAU 2       /* torque command, µN·m */
#define ILC_REC_TAU_FB 3    /* feedback torque, µN·m */

/* Q shifts of bus/fixedpoint.py (defined there; mirrored here for C code, checked equal by
   tests/test_firmware_c.py) */
#define ILC_ACC_Q 16        /* ACC_Q: the PD / velocity-loop accumulator */
#define ILC_GAIN_Q 16       /* GAIN_Q: cascade gains */
#define ILC_VEL_FILTER_Q 15 /* VEL_FILTER_Q: filter coefficient */
#define ILC_VEL_STATE_Q 12  /* VEL_STATE_Q: velocity filter state */
#define ILC_RATE_Q 12       /* RATE_Q: tick rate */

/* status codes of ilc_control_tick */
#define ILC_STATUS_OK 0
#define ILC_STATUS_FOLLOWING_ERROR 1

/* ---------------------------------------------------------------- control period */

/* One control period. tables: int32 row-major (3, table_cols): ref position counts, ref velocity
   counts/s, feed-forward µN·m; rec: int32 row-major (4, rec_cols). Returns torque µN·m; *status.

   count: encoder count, saturated to int32 on entry.  idx: table column to play,
   0 <= idx < table_cols (table_cols - 1 is the hold slot of a trial's tables).  rec_idx: recorder
   column to write (0 <= rec_idx < rec_cols), or -1 for none.  st: parameters and state, updated in
   place.  *status: ILC_STATUS_FOLLOWING_ERROR when |e| exceeded the window for more than
   st[ILC_P_FE_TICKS] periods in a row (the caller removes torque), else ILC_STATUS_OK.
   The indices are preconditions (not checked here: the callers check them once). */
int32_t ilc_control_tick(int64_t count, int64_t idx, int64_t rec_idx, int64_t *st,
                         const int32_t *tables, int64_t table_cols,
                         int32_t *rec, int64_t rec_cols, int32_t *status);

/* Fill st[ILC_N_STATE] as firmware_model.control_law.new_state(): zeros, ILC_P_ALPHA = 1.0,
   ILC_P_RATE = 1 kHz, following-error check off, feed-forward gains 1.0. */
void ilc_state_init(int64_t *st);

/* ---------------------------------------------------------------- integer helpers
 * bus/fixedpoint.py's helpers (the same names without the prefix), exported so a user's own
 * control law in C uses the same rounding and saturation. */

/* Saturate to the int32 range (never wraps). */
int64_t ilc_sat32(int64_t x);
/* Saturate to the int16 range (never wraps). */
int64_t ilc_sat16(int64_t x);
/* Clamp x to [lo, hi] (lo <= hi). */
int64_t ilc_sat(int64_t x, int64_t lo, int64_t hi);
/* Floor of x / 2^q (an arithmetic right shift, written portably for negative x), 0 <= q < 63. */
int64_t ilc_asr(int64_t x, int q);
/* Rounding right shift, round half up (toward +inf; -2.5 -> -2), as Python's
   (x >> q) + ((x >> (q-1)) & 1); q <= 0 returns x.  Cannot overflow for any int64 x. */
int64_t ilc_rshift_round(int64_t x, int q);

/* Floor division num // den as Python's (rounds toward -inf; C's "/" truncates), den > 0. */
int64_t ilc_floor_div(int64_t num, int64_t den);

/* ---------------------------------------------------------------- set-points and the power stage
 * The other pure integer steps of the drive's control period (their Python twins in brackets;
 * the drive's Python glue calls those, these are for a drive that runs the whole period in C and
 * are checked bit for bit against them by tests/test_firmware_c.py). */

/* CSP velocity reference, counts/s, from two successive target positions (int32 counts) and the
   tick rate st[ILC_P_RATE] [Hz Q12]: sat32(rshift_round(sat32(target - prev) · rate, 12))
   (firmware_model/modes.py, CspMode). */
int32_t ilc_csp_velocity_ref(int64_t target, int64_t prev, int64_t rate_q12);

/* A profile velocity in counts/tick Q16 as counts/s, nearest (half up), saturated to int32
   (bus.fixedpoint.velocity_from_tick_q16); period_us 1 .. 100000, |v_q16| < 2^62 (formed
   without the 128-bit product of the Python formula). */
int32_t ilc_velocity_from_tick_q16(int64_t v_q16, int64_t period_us);

/* Torque µN·m as per-thousand of the rated torque (0x6077 torque actual), round half up,
   saturated to int16; 0 when rated_mnm <= 0 (bus.fixedpoint.torque_units_to_permille);
   |tau_units| < 2^61, rated_mnm < 2^32. */
int16_t ilc_torque_units_to_permille(int64_t tau_units, int64_t rated_mnm);

#ifdef __cplusplus
}
#endif

#endif /* ILC_DRIVE_H */
