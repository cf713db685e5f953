"""The drive's per-tick fixed-point control law (numba kernel on integer arrays).

Owns the arithmetic of one control tick: velocity estimate by difference plus a
first-order IIR filter, the feedback -- one of two structures, ``P_LOOP``:

* ``LOOP_PD`` (0, the paper's loop and the default of the ILC experiments): PD with Q16 gains
  in a 64-bit accumulator (0x2110:1/2);
* ``LOOP_CASCADE`` (1, a servo drive's cascade, the default of robot mode): position loop P
  (0x60FB:1) with velocity feed-forward (0x60FB:2) → velocity loop PI (0x60F9:1/2) with
  anti-windup by *clamping* (conditional integration: the integrator holds while the torque is
  at its limit and the velocity error would drive it further; it is also bounded by the limit)
  → torque, plus the torque feed-forward (0x60FB:3);

the feed-forward table value, the torque clamp, the following-error check and the
recorder write.  The step is one function with explicit inputs and outputs per period
(:func:`control_tick`: encoder count, set-points, the ``st`` vector in, torque and status out).
Every format is defined in :mod:`bus.fixedpoint` (the integer
helpers used here are compiled from there, so they exist once).  The Python glue lives
beside it: the operation modes that call the kernel (:mod:`firmware_model.modes`), the tick
sequence, tables and recorder (:mod:`firmware_model.playback`), the parameter objects
(:mod:`firmware_model.od_hooks`) and the power stage (:mod:`firmware_model.power_stage`).

This kernel is the reference model of the drive's control period.  The same period in C99,
bit for bit, is ``firmware_model/c/ilc_control.c`` (interface ``c/ilc_drive.h``; the extension
:mod:`firmware_model._fwcore`); which of the two a drive runs is
:mod:`firmware_model.firmware_select` (``--firmware``, docs/firmware.md).  A change here is a change
there too: tests/test_firmware_c.py checks them against each other.

Arrays the kernel works on (allocate them with :func:`new_state`, :func:`new_tables`,
:func:`new_recorder`):

* ``st`` int64 (``N_STATE``,): parameters (``P_*``, written by the drive's object
  callbacks) and loop state (``S_*``).
* ``tables`` int32 (3, capacity + 1): rows ``ROW_REF_POS`` (counts), ``ROW_REF_VEL``
  (counts/s), ``ROW_FF`` (µN·m); column ``capacity`` is the *hold slot* used when no
  trial is playing (the held reference).
* ``rec`` int32 (4, capacity): rows position counts, velocity estimate counts/s,
  torque total µN·m, torque feedback µN·m.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, TypeAlias, cast

import numpy as np
import numpy.typing as npt
from numba import njit

from bus import fixedpoint as fp

logger = logging.getLogger(__name__)

#: An integer scalar inside the kernel: a Python int or a numpy integer (numba: int64).
_Int = int | np.integer[Any]

#: the kernel's arrays (see the module docstring): parameters and state ``st``, the tables
#: (3, capacity + 1) and the recorder (4, capacity)
StateArray: TypeAlias = npt.NDArray[np.int64]
TableArray: TypeAlias = npt.NDArray[np.int32]
RecorderArray: TypeAlias = npt.NDArray[np.int32]

# numba's stubs give a dispatcher the call signature of the Python function (``x: int``), but
# the compiled helpers take any integer scalar, here also the np.int64 values of the kernel:
# the casts declare that (they return the dispatchers unchanged).
_sat32 = cast(Callable[[_Int], int], njit(inline="always")(fp.sat32))
_sat = cast(Callable[[_Int, _Int, _Int], int], njit(inline="always")(fp.sat))
_rshift_round = cast(Callable[[_Int, int], int], njit(inline="always")(fp.rshift_round))

# ---------------------------------------------------------------- st[] layout
P_KP = 0  #: Kp, Q16 µN·m/count
P_KD = 1  #: Kd, Q16 µN·m/(count/s)
P_ALPHA = 2  #: velocity filter coefficient, Q15
P_RATE = 3  #: tick rate, Hz Q12
P_TLIM = 4  #: torque limit, µN·m (>= 0)
P_FE_WINDOW = 5  #: following-error window, counts; < 0 = check off
S_PREV_COUNT = 6  #: previous encoder count
S_HAVE_PREV = 7  #: 1 when S_PREV_COUNT is valid
S_VF = 8  #: velocity filter state, counts/s Q12
S_VEST = 9  #: velocity estimate, counts/s
S_POS = 10  #: last encoder count (position actual)
S_TAU = 11  #: last torque command, µN·m
S_TAU_FB = 12  #: last feedback torque, µN·m
S_ERR = 13  #: last position error, counts
S_LIMITED = 14  #: 1 when the last torque was clamped
P_LOOP = 15  #: feedback structure: LOOP_PD or LOOP_CASCADE
P_KPP = 16  #: position loop gain, Q16 (counts/s)/count (cascade)
P_KVFF = 17  #: velocity feed-forward gain, Q16 (65536 = 1.0) (cascade)
P_KTFF = 18  #: torque feed-forward gain, Q16 (65536 = 1.0) (cascade)
P_KVP = 19  #: velocity loop P gain, Q16 µN·m/(count/s) (cascade)
P_KVI = 20  #: velocity loop I gain per control period, Q16 µN·m/(count/s) (cascade)
S_VINT = 21  #: velocity loop integrator, µN·m Q16 (cascade), |.| <= torque limit
S_VCMD = 22  #: last velocity command of the position loop, counts/s (cascade)
P_FE_TICKS = 23  #: following-error time-out, control periods (0x6066 · 1000 // 0x2300)
S_FE_COUNT = 24  #: control periods in a row with |e| above the following-error window
N_STATE = 26

#: P_LOOP values
LOOP_PD = 0
LOOP_CASCADE = 1

ROW_REF_POS = 0
ROW_REF_VEL = 1
ROW_FF = 2

REC_POS = 0
REC_VEL = 1
REC_TAU = 2
REC_TAU_FB = 3

#: raw velocity (Q12) saturation: the int32 counts/s range
_VRAW_MAX = fp.INT32_MAX << fp.VEL_STATE_Q
_VRAW_MIN = fp.INT32_MIN << fp.VEL_STATE_Q

#: kernel status codes (second return value)
STATUS_OK = 0
STATUS_FOLLOWING_ERROR = 1


def new_state() -> npt.NDArray[np.int64]:
    """A zeroed parameter/state vector with an unfiltered velocity and a 1 kHz rate."""
    st = np.zeros(N_STATE, dtype=np.int64)
    st[P_ALPHA] = fp.VEL_FILTER_ONE
    st[P_RATE] = fp.rate_q12_from_period_us(1000)
    st[P_FE_WINDOW] = -1
    st[P_KVFF] = 1 << fp.GAIN_Q
    st[P_KTFF] = 1 << fp.GAIN_Q
    return st


def new_tables(capacity: int) -> npt.NDArray[np.int32]:
    """Zeroed tables (3, capacity + 1); the last column is the hold slot."""
    return np.zeros((3, capacity + 1), dtype=np.int32)


def new_recorder(capacity: int) -> npt.NDArray[np.int32]:
    """Zeroed recorder (4, capacity)."""
    return np.zeros((4, capacity), dtype=np.int32)


@njit(cache=True)
def control_tick(count: int, idx: int, rec_idx: int, st: StateArray, tables: TableArray, rec: RecorderArray) -> tuple[int, int]:
    """One control tick.  Returns ``(torque µN·m, status)``.

    :param count: encoder count (counts), saturated to int32 on entry.
    :param idx: table column to play (``capacity`` = the hold slot).
    :param rec_idx: recorder column to write, or -1 for none.
    :param st: parameters/state (updated in place).
    :param tables: reference position/velocity and feed-forward tables.
    :param rec: recorder planes (written at ``rec_idx``).

    Status ``STATUS_FOLLOWING_ERROR`` means |e| exceeded the window for more than ``P_FE_TICKS``
    periods in a row (0x6066 following error time-out; 0: at once); the caller removes torque.
    Velocity: with no previous count (first tick after enable or trial start)
    the raw velocity is taken equal to the filter state, i.e. the estimate is held.
    """
    c = _sat32(count)
    vf = st[S_VF]
    if st[S_HAVE_PREV] != 0:
        d = _sat32(c - st[S_PREV_COUNT])
        v_raw = _sat(d * st[P_RATE], _VRAW_MIN, _VRAW_MAX)
    else:
        v_raw = vf
    vf = vf + _rshift_round(st[P_ALPHA] * (v_raw - vf), fp.VEL_FILTER_Q)
    v_est = _sat32(_rshift_round(vf, fp.VEL_STATE_Q))

    e = _sat32(np.int64(tables[ROW_REF_POS, idx]) - c)
    lim = st[P_TLIM]
    if st[P_LOOP] == LOOP_CASCADE:
        ff = _sat32(_rshift_round(st[P_KTFF] * np.int64(tables[ROW_FF, idx]), fp.GAIN_Q))
        v_ff = _rshift_round(st[P_KVFF] * np.int64(tables[ROW_REF_VEL, idx]), fp.GAIN_Q)
        v_cmd = _sat32(_rshift_round(st[P_KPP] * e, fp.GAIN_Q) + v_ff)
        ev = _sat32(v_cmd - v_est)
        p_term = st[P_KVP] * ev  # < 2^62
        vint = st[S_VINT]
        trial_int = _sat(vint + st[P_KVI] * ev, -(lim << fp.ACC_Q), lim << fp.ACC_Q)
        u = _rshift_round(p_term + trial_int, fp.ACC_Q) + ff
        # anti-windup (clamping): integrate unless the torque saturates and ev pushes it further
        if not ((u > lim and ev > 0) or (u < -lim and ev < 0)):
            vint = trial_int
        fb = _sat32(_rshift_round(p_term + vint, fp.ACC_Q))
        tau = _sat32(fb + ff)
        st[S_VINT] = vint
        st[S_VCMD] = v_cmd
    else:
        ed = _sat32(np.int64(tables[ROW_REF_VEL, idx]) - v_est)
        acc = st[P_KP] * e + st[P_KD] * ed  # each < 2^62, sum < 2^63 - 2^32
        fb = _sat32(_rshift_round(acc, fp.ACC_Q))
        tau = _sat32(fb + np.int64(tables[ROW_FF, idx]))
    limited = 0
    if tau > lim:
        tau = lim
        limited = 1
    elif tau < -lim:
        tau = -lim
        limited = 1

    st[S_PREV_COUNT] = c
    st[S_HAVE_PREV] = 1
    st[S_VF] = vf
    st[S_VEST] = v_est
    st[S_POS] = c
    st[S_TAU] = tau
    st[S_TAU_FB] = fb
    st[S_ERR] = e
    st[S_LIMITED] = limited
    if rec_idx >= 0:
        rec[REC_POS, rec_idx] = c
        rec[REC_VEL, rec_idx] = v_est
        rec[REC_TAU, rec_idx] = tau
        rec[REC_TAU_FB, rec_idx] = fb
    window = st[P_FE_WINDOW]
    if window >= 0 and (e > window or -e > window):
        st[S_FE_COUNT] += 1
        if st[S_FE_COUNT] > st[P_FE_TICKS]:
            return tau, STATUS_FOLLOWING_ERROR
    else:
        st[S_FE_COUNT] = 0
    return tau, STATUS_OK


def csp_velocity_ref(target: int, prev: int, rate_q12: int) -> int:
    """CSP's velocity reference from two successive targets [counts]: ``(target − prev)·rate`` in
    the loop's Q12 arithmetic, rounded half up and saturated to int32 [counts/s] (the C core's
    ``ilc_csp_velocity_ref``)."""
    return fp.sat32(fp.rshift_round(fp.sat32(int(target) - int(prev)) * int(rate_q12), fp.VEL_STATE_Q))


def run_table(
    counts: npt.NDArray[np.int64],
    st: npt.NDArray[np.int64],
    tables: npt.NDArray[np.int32],
    n_table: int,
    rec: npt.NDArray[np.int32],
) -> npt.NDArray[np.int64]:
    """Open-loop helper for tests/benchmarks: play ``counts`` through the kernel.

    Tick n uses table column ``min(n, n_table - 1)`` and records while n < n_table.
    Returns the torque sequence (µN·m).
    """
    out = np.zeros(len(counts), dtype=np.int64)
    for n in range(len(counts)):
        idx = n if n < n_table else n_table - 1
        rec_idx = n if n < rec.shape[1] and n < n_table else -1
        out[n] = control_tick(int(counts[n]), idx, rec_idx, st, tables, rec)[0]
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) the control kernel now, so that a drive process pays
    for it before it boots, not on the first tick of its first trial."""
    control_tick(0, 0, 0, new_state(), new_tables(1), new_recorder(1))
