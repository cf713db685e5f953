"""Fixed-point formats of the drive firmware and the integer helpers it uses.

This module is the ONE place where every integer format inside the drive is
defined.  The firmware (:mod:`firmware_model.control_law`) computes with these formats
only; the host converts its float gains to them with the ``*_to_fixed``
functions below before writing them to the drive (objects in :mod:`bus.objects`).

Notation: ``Qm`` means "integer holding value · 2^m".  All internal arithmetic is
done in 64-bit signed integers; every result that is stored or leaves the loop is
rounded with :func:`rshift_round` (round half up) and saturated with
:func:`sat32` / :func:`sat16` -- nothing ever wraps silently.

==========================  ============  ====================================  ======================================
quantity                    storage       unit / scaling                        float equivalent, range, LSB
==========================  ============  ====================================  ======================================
encoder position            int32         counts (joint side)                   ``* RAD_PER_COUNT`` rad; LSB 5.99e-7 rad
reference position table    int32         counts                                same
reference velocity table    int32         counts/s                              ``* RAD_PER_COUNT`` rad/s
velocity estimate (bus)     int32         counts/s, rounded                     LSB 5.99e-7 rad/s
velocity filter state       int64         counts/s, Q12 (``VEL_STATE_Q``)       LSB 2.44e-4 counts/s
tick rate                   int64         Hz, Q12 (``RATE_Q``)                  1e6 / period_us, 1 kHz -> 4 096 000
velocity filter coeff. a    uint16        Q15 (``VEL_FILTER_Q``), 1..32768      a = 1.0 (32768): unfiltered
position error e            int64->int32  counts, saturated to int32            ref_pos[n] - count
velocity error ė            int64->int32  counts/s, saturated to int32          ref_vel[n] - v_est
Kp                          int32 >= 0    µN·m per count, Q16 (``KP_Q``)        LSB 2.55e-5 N·m/rad; max 54 700 N·m/rad
Kd                          int32 >= 0    µN·m per (count/s), Q16 (``KD_Q``)    LSB 2.55e-5 N·m·s/rad; max 54 700
PD accumulator              int64         µN·m, Q16                             |Kp·e| + |Kd·ė| < 2^63 - 2^32: no overflow
feedback torque             int32         µN·m (acc rounded >> 16, saturated)   ``* TORQUE_LSB_NM`` N·m
feed-forward torque table   int32         µN·m                                  LSB 1e-6 N·m
torque command (io)         int32         µN·m, clamped to +-torque limit       LSB 1e-6 N·m; +-265 N·m = +-2.65e8
torque limit                int64         µN·m = 0x6072 [‰] · 0x6076 [mN·m]     3000 ‰ · 88 200 mN·m = 264.6 N·m
torque actual 0x6077        int16         per-thousand of 0x6076                round(τ_µNm / rated_mNm)
following error window      uint32        counts (0xFFFFFFFF = off)             ``* RAD_PER_COUNT`` rad
control period              uint32        µs (object 0x2300)                    1000 µs = 1 kHz
cascade: position gain Kpp  int32 >= 0    (counts/s) per count, Q16 (``GAIN_Q``)  1/s; 0x60FB:1
cascade: feed-forward gains int32 >= 0    Q16 (``GAIN_Q``), 65536 = 1.0         velocity 0x60FB:2, torque 0x60FB:3
cascade: velocity P Kvp     int32 >= 0    µN·m per (count/s), Q16               as Kd; 0x60F9:1
cascade: velocity I Kvi     int32 >= 0    µN·m per (count/s) per s, Q16         0x60F9:2; per period: Kvi·Ts, nearest
cascade: velocity command   int64->int32  counts/s, saturated                   rshift_round(Kpp·e, 16) + v_ff
cascade: integrator         int64         µN·m, Q16, clamped to +-limit·2^16    sum of Kvi_tick·ė_v
profile position demand     int64         counts, Q16 (``PROFILE_Q``)           LSB 1/65536 count; int32 counts · 2^16
profile velocity            int64         counts/tick, Q16                      0x6081 [counts/s] · Ts · 2^16, nearest
profile accel./decel.       int64         counts/tick², Q16 (>= 1)              0x6083/4/5 [counts/s²] · Ts² · 2^16, nearest
==========================  ============  ====================================  ======================================

Control law of one tick (the float twin in tests/firmware_twin.py is the same in float64)::

    v_raw   = sat32(count[n] - count[n-1]) · rate_q12                 (counts/s, Q12; saturated)
    vf      = vf + rshift_round(a_q15 · (v_raw - vf), 15)             (Q12 first-order IIR)
    v_est   = sat32(rshift_round(vf, 12))                             (counts/s)
    e       = sat32(ref_pos[n] - count);  ė = sat32(ref_vel[n] - v_est)
    fb      = sat32(rshift_round(Kp_q16 · e + Kd_q16 · ė, 16))        (µN·m)
    τ       = clamp(sat32(fb + ff[n]), -limit, +limit)                (µN·m)

Cascade (0x2110:4 = 1; the step is the same function, the PD lines replaced)::

    ff      = sat32(rshift_round(Ktff_q16 · ff[n], 16))                      (µN·m)
    v_cmd   = sat32(rshift_round(Kpp_q16 · e, 16) + rshift_round(Kvff_q16 · ref_vel[n], 16))
    ė_v     = sat32(v_cmd - v_est)                                          (counts/s)
    I'      = sat(I + Kvi_tick_q16 · ė_v, -limit·2^16, +limit·2^16)          (µN·m Q16)
    u       = rshift_round(Kvp_q16 · ė_v + I', 16) + ff
    I       = I' unless (u > limit and ė_v > 0) or (u < -limit and ė_v < 0)  (anti-windup: clamping)
    fb      = sat32(rshift_round(Kvp_q16 · ė_v + I, 16));  τ = clamp(sat32(fb + ff), ±limit)

    Kvi_tick_q16 = (Kvi_q16 · period_us + 500 000) // 1 000 000   (nearest, computed when 0x60F9:2
    or the period is written).  Every product is below 2^62 and |I| <= 2^47: no int64 overflow.

Resolution (why these formats do not limit learning): one torque LSB (1 µN·m) moves the
steady-state position through Kp >= 100 N·m/rad by <= 1e-8 rad = 0.017 encoder counts; the
relative gain quantisation is <= 2.6e-7 for Kp >= 100 and <= 2.6e-6 for Kd >= 10.

Why Q16 for both gains: both products share one shift, so the sum is formed exactly in one
int64 accumulator.  With gains limited to [0, 2^31 - 1] and errors saturated to int32 each
product is below 2^62 and their sum below 2^63 - 2^32, so the accumulator cannot wrap.

The helpers are plain Python functions on ints that are also valid numba nopython code;
:mod:`firmware_model.control_law` compiles them with ``numba.njit`` so the definition exists once.
"""

from __future__ import annotations

import logging
import math

from bus.errors import IlcrigError
from bus.units import RAD_PER_COUNT, TORQUE_LSB_NM

logger = logging.getLogger(__name__)

INT16_MIN: int = -(1 << 15)
INT16_MAX: int = (1 << 15) - 1
INT32_MIN: int = -(1 << 31)
INT32_MAX: int = (1 << 31) - 1
INT64_MIN: int = -(1 << 63)
INT64_MAX: int = (1 << 63) - 1
UINT16_MAX: int = (1 << 16) - 1
UINT32_MAX: int = (1 << 32) - 1

#: Q of Kp (µN·m per count)
KP_Q: int = 16
#: Q of Kd (µN·m per count/s)
KD_Q: int = 16
#: Q of the PD accumulator (= KP_Q = KD_Q, one shift for the sum)
ACC_Q: int = 16
#: Q of the cascade's position gain (counts/s per count) and feed-forward gains (1.0 = 65536)
GAIN_Q: int = 16
#: Q of the velocity filter coefficient (1.0 = 32768 = unfiltered)
VEL_FILTER_Q: int = 15
VEL_FILTER_ONE: int = 1 << VEL_FILTER_Q
#: Q of the internal velocity filter state (counts/s)
VEL_STATE_Q: int = 12
#: Q of the tick rate (Hz) used to turn counts/tick into counts/s
RATE_Q: int = 12
#: Q of the profile generator (position in counts, velocity in counts/tick, acceleration in
#: counts/tick²): profile position, homing hold, CSV integration and the quick-stop ramp
PROFILE_Q: int = 16
#: the position demand range of the profile generator, Q16: the int32 counts
PROFILE_POS_MIN: int = INT32_MIN << PROFILE_Q
PROFILE_POS_MAX: int = INT32_MAX << PROFILE_Q

#: µN·m per count for a gain of 1 N·m/rad (≈ 0.599)
UNM_PER_COUNT_PER_NM_PER_RAD: float = RAD_PER_COUNT / TORQUE_LSB_NM
#: one Kp LSB in N·m/rad (≈ 2.55e-5)
KP_LSB_NM_PER_RAD: float = TORQUE_LSB_NM / RAD_PER_COUNT / (1 << KP_Q)
#: one Kd LSB in N·m·s/rad (≈ 2.55e-5)
KD_LSB_NMS_PER_RAD: float = TORQUE_LSB_NM / RAD_PER_COUNT / (1 << KD_Q)
#: largest representable Kp in N·m/rad
KP_MAX_NM_PER_RAD: float = INT32_MAX * KP_LSB_NM_PER_RAD
#: largest representable Kd in N·m·s/rad
KD_MAX_NMS_PER_RAD: float = INT32_MAX * KD_LSB_NMS_PER_RAD


class FixedPointRangeError(IlcrigError, ValueError):
    """A float quantity cannot be represented in its fixed-point format."""


# ---------------------------------------------------------------- integer helpers
# (Python ints and numba int64 alike; no operation below can overflow int64 when its
# documented preconditions hold.)


def sat32(x: int) -> int:
    """Saturate to the int32 range (never wraps)."""
    return min(max(x, INT32_MIN), INT32_MAX)


def sat16(x: int) -> int:
    """Saturate to the int16 range (never wraps)."""
    return min(max(x, INT16_MIN), INT16_MAX)


def sat(x: int, lo: int, hi: int) -> int:
    """Clamp ``x`` to ``[lo, hi]``."""
    return min(max(x, lo), hi)


def rshift_round(x: int, q: int) -> int:
    """Rounding arithmetic right shift, round half up: ``(x + (1 << (q-1))) >> q``.

    Written as ``(x >> q) + ((x >> (q-1)) & 1)``, which is the same value but cannot
    overflow for x near the int64 limits.  ``q = 0`` returns ``x``.  ``>>`` floors
    (Python and numba alike), so negative halves round toward +inf: -2.5 -> -2.
    """
    if q <= 0:
        return x
    return (x >> q) + ((x >> (q - 1)) & 1)


def sat_add32(a: int, b: int) -> int:
    """Saturating int32 addition of two int32 values (formed in 64 bits, then saturated)."""
    return sat32(a + b)


def sat_add64(a: int, b: int) -> int:
    """Saturating int64 addition that never forms an overflowing intermediate."""
    if b > 0 and a > INT64_MAX - b:
        return INT64_MAX
    if b < 0 and a < INT64_MIN - b:
        return INT64_MIN
    return a + b


# ---------------------------------------------------------------- host-side converters


def _to_fixed(value: float, scale: float, lo: int, hi: int, what: str) -> int:
    if not math.isfinite(value):
        raise FixedPointRangeError(f"{what} must be finite, got {value!r}")
    raw = round(value * scale)
    if raw < lo or raw > hi:
        raise FixedPointRangeError(f"{what} = {value!r} is outside the representable range [{lo / scale:.6g}, {hi / scale:.6g}]")
    return int(raw)


def kp_to_fixed(kp_nm_per_rad: float) -> int:
    """Proportional gain N·m/rad -> Q16 µN·m per count (int32 >= 0), nearest LSB.

    :raises FixedPointRangeError: negative, non-finite or above ``KP_MAX_NM_PER_RAD``.
    """
    return _to_fixed(kp_nm_per_rad, 1.0 / KP_LSB_NM_PER_RAD, 0, INT32_MAX, "Kp [N·m/rad]")


def kp_from_fixed(kp_q16: int) -> float:
    """Q16 µN·m per count -> N·m/rad."""
    return int(kp_q16) * KP_LSB_NM_PER_RAD


def kd_to_fixed(kd_nms_per_rad: float) -> int:
    """Derivative gain N·m·s/rad -> Q16 µN·m per (count/s) (int32 >= 0), nearest LSB.

    :raises FixedPointRangeError: negative, non-finite or above ``KD_MAX_NMS_PER_RAD``.
    """
    return _to_fixed(kd_nms_per_rad, 1.0 / KD_LSB_NMS_PER_RAD, 0, INT32_MAX, "Kd [N·m·s/rad]")


def kd_from_fixed(kd_q16: int) -> float:
    """Q16 µN·m per (count/s) -> N·m·s/rad."""
    return int(kd_q16) * KD_LSB_NMS_PER_RAD


def vel_filter_to_fixed(alpha: float) -> int:
    """First-order IIR coefficient a in (0, 1] -> Q15 in [1, 32768] (1.0 = unfiltered).

    ``v_f[n] = v_f[n-1] + a·(v_raw[n] - v_f[n-1])``; the -3 dB frequency is about
    ``a / (2π Ts)`` for small a.

    :raises FixedPointRangeError: a outside (0, 1] or rounding to 0.
    """
    return _to_fixed(alpha, float(VEL_FILTER_ONE), 1, VEL_FILTER_ONE, "velocity filter coefficient")


def vel_filter_from_fixed(a_q15: int) -> float:
    """Q15 filter coefficient -> float in (0, 1]."""
    return int(a_q15) / VEL_FILTER_ONE


def rate_q12_from_period_us(period_us: int) -> int:
    """Tick rate in Hz as Q12 for a control period in µs (1000 µs -> 4 096 000, exact)."""
    if period_us <= 0:
        raise FixedPointRangeError(f"control period must be > 0 µs, got {period_us}")
    num = 1_000_000 << RATE_Q
    return (2 * num + period_us) // (2 * period_us)  # nearest, exact for divisors of 1 s


def ki_per_tick_q16(ki_q16: int, period_us: int) -> int:
    """The velocity loop's integral gain per control period, Q16 µN·m/(count/s): ``Kvi · Ts``,
    nearest (``ki_q16`` >= 0 [Q16 µN·m/(count/s)/s], ``period_us`` > 0)."""
    return (ki_q16 * period_us + 500_000) // 1_000_000


def per_tick_q16(value: int, period_us: int, power: int) -> int:
    """A rate in counts/s^power (``power`` 1: velocity, 2: acceleration) as counts/tick^power in
    Q16 for a control period of ``period_us`` µs: ``value · period_us^power · 2^16 / 10^(6·power)``,
    nearest (half up).  Exact integer arithmetic; a U32 rate at a period up to 100 ms stays below
    2^63 (velocity < 2^45, acceleration < 2^42)."""
    num = int(value) * int(period_us) ** power << PROFILE_Q
    den = 10 ** (6 * power)
    return (2 * num + den) // (2 * den)


def velocity_from_tick_q16(v_q16: int, period_us: int) -> int:
    """A profile velocity in counts/tick Q16 as counts/s (int32, nearest half up, saturated): the
    velocity reference the control law gets."""
    num = int(v_q16) * 1_000_000
    den = int(period_us) << PROFILE_Q
    return sat32((2 * num + den) // (2 * den))


def profile_position_counts(p_q16: int) -> int:
    """A profile position demand (counts Q16) as int32 counts, nearest (half up), saturated."""
    return sat32(rshift_round(int(p_q16), PROFILE_Q))


def torque_limit_units(max_torque_permille: int, rated_torque_mnm: int) -> int:
    """Torque limit in µN·m from 0x6072 (per-thousand) and 0x6076 (mN·m).

    ‰ · mN·m = (1e-3 · 1e-3) N·m · 1e6 µN·m/N·m → the product is exactly µN·m.
    """
    return int(max_torque_permille) * int(rated_torque_mnm)


def torque_units_to_permille(tau_units: int, rated_torque_mnm: int) -> int:
    """µN·m -> per-thousand of rated torque (0x6077), round half up, saturated to int16."""
    if rated_torque_mnm <= 0:
        return 0
    num = 2 * int(tau_units) + int(rated_torque_mnm)
    return sat16(num // (2 * int(rated_torque_mnm)))


def torque_nm_to_permille(tau_nm: float, rated_torque_mnm: int) -> int:
    """N·m -> per-thousand of rated torque (nearest), for 0x6072 / 0x6071-style objects.

    :raises FixedPointRangeError: non-finite, negative or above 65535 ‰.
    """
    return _to_fixed(tau_nm, 1e6 / rated_torque_mnm, 0, UINT16_MAX, "torque limit [N·m]")


def permille_to_nm(permille: int, rated_torque_mnm: int) -> float:
    """Per-thousand of rated torque -> N·m."""
    return int(permille) * int(rated_torque_mnm) * 1e-6
