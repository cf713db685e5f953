"""Units and integer scalings that drives, plant interface and host must agree on.

This module is the single place where the integer representations crossing a
process boundary are defined (docs/architecture.md §3: "anything both sides must agree on lives
once, in bus/").  The drive firmware's internal Q formats are documented in
:mod:`bus.fixedpoint` (also shared, since the host converts gains to them).

Joint-side quantities everywhere: the emulated drive is configured with the
reducer ratio (like a CiA 402 factor group), so positions are reported at the
joint and torques are joint-side torques.

========================  =====================  ==================================
quantity                  integer type / unit    float equivalent
========================  =====================  ==================================
position                  int32 counts           ``counts * RAD_PER_COUNT`` rad
velocity (bus, recorder)  int32 counts/s         ``v * RAD_PER_COUNT`` rad/s
torque (io, tables, rec)  int32 µN·m             ``t * TORQUE_LSB_NM`` N·m
========================  =====================  ==================================
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

#: encoder resolution at the motor shaft (docs/robot-model.md §5.3: 2**20 counts per motor revolution)
COUNTS_PER_MOTOR_REV: int = 1 << 20
#: reducer ratio n (docs/robot-model.md §2.3, proposed value)
GEAR_RATIO: int = 10
#: encoder counts per joint revolution
COUNTS_PER_JOINT_REV: int = COUNTS_PER_MOTOR_REV * GEAR_RATIO
#: one encoder LSB at the joint, rad (≈ 5.99e-7 rad ≈ 3.43e-5 deg)
RAD_PER_COUNT: float = 2.0 * math.pi / COUNTS_PER_JOINT_REV
#: one encoder LSB at the joint, degrees
DEG_PER_COUNT: float = 360.0 / COUNTS_PER_JOINT_REV
#: torque LSB on the io channel, in feed-forward tables and in the recorder: 1 µN·m
TORQUE_LSB_NM: float = 1e-6

INT32_MIN: int = -(1 << 31)
INT32_MAX: int = (1 << 31) - 1


def rad_to_counts(q_rad: float) -> int:
    """Nearest encoder count for a joint angle (round half away from zero is not needed:
    Python's round-half-even on an exact .5 is as good as any, and never happens in practice)."""
    return int(round(q_rad / RAD_PER_COUNT))


# ---------------------------------------------------------------------- array converters
# (for table downloads; same rounding as the scalar function above: nearest, ties to even,
# which np.rint and Python's round share)


class UnitRangeError(ValueError):
    """A float quantity that does not fit its int32 bus representation."""


def _to_int32_array(x: npt.ArrayLike, lsb: float, what: str) -> npt.NDArray[np.int32]:
    a = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise UnitRangeError(f"{what}: non-finite value")
    r = np.rint(a / lsb)
    if r.size and (r.min() < INT32_MIN or r.max() > INT32_MAX):
        raise UnitRangeError(f"{what}: value outside the int32 range")
    return r.astype(np.int32)


def rad_to_counts_array(q_rad: npt.ArrayLike) -> npt.NDArray[np.int32]:
    """Joint angles (rad) -> int32 counts (nearest); raises UnitRangeError outside int32."""
    return _to_int32_array(q_rad, RAD_PER_COUNT, "position [rad]")


def rad_s_to_counts_s_array(qd_rad_s: npt.ArrayLike) -> npt.NDArray[np.int32]:
    """Joint velocities (rad/s) -> int32 counts/s (nearest); raises UnitRangeError outside int32."""
    return _to_int32_array(qd_rad_s, RAD_PER_COUNT, "velocity [rad/s]")


def nm_to_torque_units_array(tau_nm: npt.ArrayLike) -> npt.NDArray[np.int32]:
    """Joint torques (N·m) -> int32 µN·m (nearest); raises UnitRangeError outside int32
    (no silent saturation of a table value)."""
    return _to_int32_array(tau_nm, TORQUE_LSB_NM, "torque [N·m]")


#: environment variable that stretches every protocol timeout (SDO, heartbeat, tick) by a factor
#: >= 1, for slow hosts such as a VM under software emulation; the default is 1
TIMEOUT_SCALE_ENV: str = "ILCRIG_TIMEOUT_SCALE"


def timeout_scale() -> float:
    """The factor of :data:`TIMEOUT_SCALE_ENV` (1.0 when unset).

    :raises ValueError: not a finite number >= 1.
    """
    import os

    text = os.environ.get(TIMEOUT_SCALE_ENV, "").strip()
    if not text:
        return 1.0
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{TIMEOUT_SCALE_ENV} must be a number >= 1, got {text!r}") from None
    if not (math.isfinite(value) and value >= 1.0):
        raise ValueError(f"{TIMEOUT_SCALE_ENV} must be a number >= 1, got {text!r}")
    return value
