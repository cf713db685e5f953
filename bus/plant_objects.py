"""Object-dictionary indices and value encodings of the plant node (the plant on the bus).

Owns the names of every object the plant node exposes (described in full, with data
types, access and limits, by ``bus/plant.eds``), the trial command/status/fault enumerations,
the disturbance-kind codes, the bench's EMCY codes and the byte layout of the initial state.
Both :mod:`plant.plant_node` (server) and :mod:`host.nodes.plant_client` (client) use these.

======  ===  ========================  =======  ==========================================
index   sub  name                      type     meaning / unit
======  ===  ========================  =======  ==========================================
0x1016  1    consumer heartbeat        U32      node id << 16 | ms (the host's heartbeat), 0 = off
0x1017  0    producer heartbeat        U16      ms, 0 = off
0x1018  1-4  identity                  U32      vendor, product 0xBE4C, revision, serial
0x2400  1    control period            U32      µs (Ts), 1..1 000 000, default 1000
0x2400  2    RK4 sub-steps             U16      per control period, 1..1000, default 4
0x2400  3    disturbance kind          U8       :class:`DisturbanceKind` 0..3
0x2400  4    seed                      U32      seed of the non-repetitive disturbance
0x2400  5    pacing                    U8       0 lockstep as fast as possible, 1 real time
0x2400  6-9  plant uncertainty         REAL64   factors on the emulated robot: inertias, masses,
                                                    friction, payload (1.0 = as built; PLANT_SCALE_SUBS)
0x2410  1    trial index               U32      k (selects the non-repetitive draw)
0x2410  2    number of ticks           U32      N ≥ 1
0x2410  3    command                   U8       wo: :class:`PlantCommand` 1 start, 2 abort
0x2410  4    status                    U8       ro: :class:`PlantStatus`
0x2410  5    ticks done                U32      ro: plant steps completed in this trial
0x2410  6    fault code                U8       ro: :class:`PlantFault` (0..6)
0x2410  7    fault tick                U32      ro: tick n at which the fault happened
0x2410  8    fault node                U8       ro: drive node id involved (0 = none)
0x2420  0    initial state             DOMAIN   64 bytes: q0[4] rad, qd0[4] rad/s, float64 LE
0x2430  1    io frames sent            U32      ro, since boot (wraps)
0x2430  2    io frames received        U32      ro, since boot (wraps)
0x2430  3    tick timeouts             U32      ro, since boot
0x2430  4    trials completed          U32      ro, since boot
0x2430  5    last trial duration       U32      ro, µs wall clock (diagnostics only)
0x2440  0    last trial timing         DOMAIN   ro, 25 bytes: :class:`TrialTiming` (wall clock)
0x2441  0    last trial's misses       DOMAIN   ro, 10 + 12·k bytes: :class:`DeadlineMisses` (paced)
0x2450  1    robot mode                U8       :class:`RobotMode`: 0 off, 1 SYNC-stepped, 2 real time
0x2450  2    robot command             U8       wo: :class:`RobotCommand` 1 fault reset
0x2450  3    robot state               U8       ro: :class:`RobotState`
0x2450  4    periods stepped           U32      ro, since the robot mode came on (wraps)
0x2450  5    SYNCs seen                U32      ro, SYNC frames (COB-ID 0x080) received
0x2450  6    late SYNCs                U32      ro, real time: SYNCs after their period's window
0x2450  7    missing SYNCs             U32      ro, real time: whole periods without a SYNC
0x2450  8    SYNC overruns             U32      ro, SYNCs that came with SYNC_BACKLOG_MAX waiting (served late)
0x2450  9    robot fault code          U8       ro: :class:`RobotFault`
0x2450  10   robot fault joint         U8       ro: joint 1..4 (or drive node) involved, 0 none
0x2450  11   robot fault period        U32      ro: period at which the fault happened
0x2450  12   brakes closed             U8       ro: bit j-1 = joint j held by its brake
0x2450  13   late periods              U32      ro, real time: periods started late or completed after the next one's time
0x2451  1-4  joint position            I32      ro: q_j of the robot, counts (the encoder's units)
0x2452  1-4  TCP pose                  I32      ro: x, y, z [µm], θ [µrad] (forward kinematics)
0x2453  1-4  mechanical limits         I32      ro: joint end stops low/high [counts], screw gap min/max [µm]
======  ===  ========================  =======  ==========================================

Pacing (0x2400:5 = 1, ``ilcrig run --realtime``): tick n of a trial starts (its encoder frames go
out) at t0 + n·Ts on the plant's monotonic clock, t0 being one period after the trial's start
command (TRIAL_START on io); a tick whose torques arrive after t0 + (n + 1)·Ts misses its
deadline and the next one starts late.
0x2440 reports the last trial's timing in either mode (lateness only when paced); 0x2441 lists
the first :data:`DEADLINE_MISSES_KEPT` ticks of it that missed their deadline, with t0 on the
plant's ``CLOCK_MONOTONIC`` so that a tool on the same machine (``benchmarks/rt_attribution.py``)
can put them beside a kernel trace.

Configuration, trial index, number of ticks and initial state cannot be written while a trial
runs (abort 0x08000022).

The robot (0x2450..0x2453, ``ilcrig robot``, docs/robot.md): with the robot mode on, the plant
node steps one control period per SYNC frame it sees between trials (:mod:`plant.plant_node_robot`);
a robot fault (an end stop, the screw's travel, a drive that does not answer) sends one EMCY from
the plant node (:data:`ROBOT_FAULT_EMCY`; manufacturer bytes :func:`robot_fault_emcy_data`) and
holds every joint by its brake until the fault reset (0x2450:2 = 1, EMCY 0x0000).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt

from bus.fixedpoint import sat

logger = logging.getLogger(__name__)

#: The EDS of the plant node.
PLANT_EDS_PATH: Final[Path] = Path(__file__).resolve().parent / "plant.eds"
#: Default CANopen node id of the plant node.
DEFAULT_PLANT_NODE_ID: Final[int] = 32

HEARTBEAT_INDEX: Final[int] = 0x1017
IDENTITY_INDEX: Final[int] = 0x1018
ERROR_REGISTER_INDEX: Final[int] = 0x1001
PLANT_PRODUCT_CODE: Final[int] = 0x0000BE4C


class PlantObj(IntEnum):
    """Manufacturer object indices of the plant node."""

    CONFIG = 0x2400
    TRIAL = 0x2410
    INITIAL_STATE = 0x2420
    COUNTERS = 0x2430
    TRIAL_TIMING = 0x2440
    DEADLINE_MISSES = 0x2441
    ROBOT = 0x2450
    JOINT_POSITION = 0x2451
    TCP_POSE = 0x2452
    MECHANICAL_LIMITS = 0x2453


class ConfigSub(IntEnum):
    CONTROL_PERIOD_US = 1
    SUBSTEPS = 2
    DISTURBANCE = 3
    SEED = 4
    PACING = 5
    INERTIA_SCALE = 6
    MASS_SCALE = 7
    FRICTION_SCALE = 8
    PAYLOAD_SCALE = 9


#: 0x2400:6..9, the plant-uncertainty factors (plant.params.PlantScales: inertia, mass, friction,
#: payload), REAL64; inertia and mass > 0, friction and payload >= 0, all finite
PLANT_SCALE_SUBS: Final[tuple[ConfigSub, ConfigSub, ConfigSub, ConfigSub]] = (
    ConfigSub.INERTIA_SCALE,
    ConfigSub.MASS_SCALE,
    ConfigSub.FRICTION_SCALE,
    ConfigSub.PAYLOAD_SCALE,
)
#: the factors of the robot as built
PLANT_SCALES_AS_BUILT: Final[tuple[float, float, float, float]] = (1.0, 1.0, 1.0, 1.0)


def plant_scale_error(sub: int, value: float) -> str | None:
    """Why ``value`` cannot be the factor of 0x2400:``sub`` (one line), or None."""
    name = ConfigSub(sub).name.lower()
    if not math.isfinite(value):
        return f"{name} must be finite, got {value!r}"
    if sub in (ConfigSub.INERTIA_SCALE, ConfigSub.MASS_SCALE) and not value > 0:
        return f"{name} must be > 0, got {value!r}"
    if value < 0:
        return f"{name} must be >= 0, got {value!r}"
    return None


class PlantTrialSub(IntEnum):
    TRIAL_INDEX = 1
    N_TICKS = 2
    COMMAND = 3
    STATUS = 4
    TICKS_DONE = 5
    FAULT_CODE = 6
    FAULT_TICK = 7
    FAULT_NODE = 8


class CounterSub(IntEnum):
    IO_SENT = 1
    IO_RECEIVED = 2
    TICK_TIMEOUTS = 3
    TRIALS_DONE = 4
    LAST_TRIAL_US = 5


class RobotSub(IntEnum):
    """Sub-indices of 0x2450 (the robot)."""

    MODE = 1
    COMMAND = 2
    STATE = 3
    PERIODS = 4
    SYNCS = 5
    LATE_SYNCS = 6
    MISSING_SYNCS = 7
    SYNC_OVERRUNS = 8
    FAULT_CODE = 9
    FAULT_JOINT = 10
    FAULT_PERIOD = 11
    BRAKES = 12
    LATE_PERIODS = 13


class LimitSub(IntEnum):
    """Sub-indices of 0x2453 (the mechanical limits)."""

    JOINT_LOW_COUNTS = 1
    JOINT_HIGH_COUNTS = 2
    GAP_MIN_UM = 3
    GAP_MAX_UM = 4


class RobotMode(IntEnum):
    """0x2450:1: how the robot's periods are stepped between trials."""

    OFF = 0  #: trials only (``ilcrig run``)
    SYNC = 1  #: one control period per SYNC, as fast as the SYNCs come (deterministic)
    REALTIME = 2  #: one control period per SYNC, none before its time t0 + n·Ts on the wall clock


#: the values a plant node without the robot mode (``ilcrig plant``, ``ilcrig run``) boots with where
#: they differ from the EDS: bus/plant.eds gives 0x2450–0x2453 as ``ilcrig robot`` boots them
#: (SYNC-stepped, the robot at its home pose, every brake closed; ``--realtime`` has 0x2450:1 = 2)
ROBOT_OFF_BOOT_VALUES: Final[dict[tuple[int, int], int]] = {
    (int(PlantObj.ROBOT), int(RobotSub.MODE)): int(RobotMode.OFF),
    (int(PlantObj.ROBOT), int(RobotSub.STATE)): 0,
    **{(int(PlantObj.JOINT_POSITION), j): 0 for j in range(1, 5)},
    (int(PlantObj.TCP_POSE), 3): 0,
}


class RobotCommand(IntEnum):
    FAULT_RESET = 1


class RobotState(IntEnum):
    OFF = 0  #: robot mode off
    READY = 1  #: stepping a period per SYNC
    FAULT = 2  #: a robot fault: every joint held by its brake until the fault reset


class RobotFault(IntEnum):
    """Why the robot stopped (0x2450:9)."""

    NONE = 0
    END_STOP = 1  #: a joint reached its mechanical end stop
    SCREW_STOP = 2  #: the screw between the sub-platforms reached the end of its travel
    MECHANISM = 3  #: the mechanism cannot follow (forward kinematics fails: a rod at full stretch, a singularity)
    PERIOD_TIMEOUT = 4  #: a drive did not answer a period's encoder frame in time
    TICK_SEQUENCE = 5  #: a torque frame was missing, duplicated, stale or early
    BAD_FRAME = 6  #: a malformed torque frame, or a bus error frame on io
    SYNC_OVERRUN = 7  #: SYNC-stepped: more than bus.cyclic.SYNC_BACKLOG_MAX SYNCs waiting (served late all the same)
    FRAMES_LOST = 8  #: the plant's fieldbus receiver lost frames (overflowed): a SYNC may be among them
    IO_FRAMES_LOST = 9  #: the plant's io receiver lost frames (overflowed): a torque frame of the period never comes


#: EMCY error code and error register per robot fault (0xFF1x: manufacturer specific, mechanical)
ROBOT_FAULT_EMCY: Final[dict[RobotFault, tuple[int, int]]] = {
    RobotFault.END_STOP: (0xFF10, 0x81),
    RobotFault.SCREW_STOP: (0xFF11, 0x81),
    RobotFault.MECHANISM: (0xFF12, 0x81),
    RobotFault.PERIOD_TIMEOUT: (0x8100, 0x11),
    RobotFault.TICK_SEQUENCE: (0x8200, 0x11),
    RobotFault.BAD_FRAME: (0x8200, 0x11),
    RobotFault.SYNC_OVERRUN: (0x8110, 0x11),
    RobotFault.FRAMES_LOST: (0x8110, 0x11),
    RobotFault.IO_FRAMES_LOST: (0x8110, 0x11),
}
#: bit 7 of a plant node EMCY's first manufacturer byte: the code is a :class:`RobotFault`
ROBOT_EMCY_FLAG: Final[int] = 0x80


class PlantCommand(IntEnum):
    START = 1
    ABORT = 2


class PlantStatus(IntEnum):
    IDLE = 0
    RUNNING = 1
    DONE = 2
    FAULT = 3


class PlantFault(IntEnum):
    """Why the last trial stopped early (0x2410:6)."""

    NONE = 0
    PLANT = 1  #: the plant raised (FK failure, singularity, non-finite state, bad reset)
    TICK_TIMEOUT = 2  #: a drive did not answer a tick in time
    TICK_SEQUENCE = 3  #: a torque frame was missing, duplicated, stale or early
    ABORTED = 4  #: the host aborted (command 2) or NMT stopped/reset the node
    BAD_FRAME = 5  #: a malformed torque frame, or a bus error frame on io (a frame damaged on the wire)
    HOST_LOST = 6  #: the host's heartbeat was lost (consumer 0x1016)
    FRAMES_LOST = 7  #: the plant node's fieldbus receiver lost frames (overflowed; e.g. the host's request)
    IO_FRAMES_LOST = 8  #: the plant node's io receiver lost frames (overflowed): a torque frame of the tick never comes


class DisturbanceKind(IntEnum):
    """0x2400:3, the wire code of a disturbance kind.  The member's lower-case name is the kind's
    name as the plant's disturbance model takes it (``plant.disturbance.KINDS``; a test checks
    that the two lists agree)."""

    NONE = 0
    REPETITIVE = 1
    NONREPETITIVE = 2
    BOTH = 3

    @property
    def label(self) -> str:
        """The kind's name, e.g. ``"nonrepetitive"``."""
        return self.name.lower()


def disturbance_code(name: str) -> DisturbanceKind:
    """The 0x2400:3 code of a disturbance name.

    :raises ValueError: unknown name
    """
    try:
        return DisturbanceKind[name.upper()]
    except KeyError:
        known = ", ".join(k.label for k in DisturbanceKind)
        raise ValueError(f"unknown disturbance {name!r}; choose from {known}") from None


#: EMCY error code per fault (error register bit: generic 0x01 / communication 0x11).
FAULT_EMCY: Final[dict[PlantFault, tuple[int, int]]] = {
    PlantFault.PLANT: (0xFF00, 0x81),  # device specific, manufacturer bit
    PlantFault.TICK_TIMEOUT: (0x8100, 0x11),  # communication
    PlantFault.TICK_SEQUENCE: (0x8200, 0x11),  # protocol error
    PlantFault.ABORTED: (0xFF01, 0x81),
    PlantFault.BAD_FRAME: (0x8200, 0x11),
    PlantFault.HOST_LOST: (0x8130, 0x11),  # heartbeat consumer (life guard) event
    PlantFault.FRAMES_LOST: (0x8110, 0x11),  # CAN overrun (objects lost)
    PlantFault.IO_FRAMES_LOST: (0x8110, 0x11),
}

_EMCY_DATA = struct.Struct("<BBH")


def fault_emcy_data(fault: PlantFault, node: int, tick: int) -> bytes:
    """5 manufacturer bytes of a plant node EMCY: u8 fault code, u8 node id, u16 tick (low bits), 0."""
    return _EMCY_DATA.pack(int(fault), node & 0xFF, tick & 0xFFFF) + b"\x00"


def robot_fault_emcy_data(fault: RobotFault, joint: int, period: int) -> bytes:
    """5 manufacturer bytes of a robot fault's EMCY: u8 0x80 | fault code, u8 joint (or drive node),
    u16 period (low bits), 0."""
    return _EMCY_DATA.pack(ROBOT_EMCY_FLAG | int(fault), joint & 0xFF, period & 0xFFFF) + b"\x00"


# -- initial state ------------------------------------------------------------------------

_STATE = struct.Struct("<8d")
INITIAL_STATE_BYTES: Final[int] = _STATE.size  # 64


class InitialStateError(ValueError):
    """q0/qd0 are not 4 finite float64 each, or the DOMAIN has the wrong length."""


def pack_initial_state(q0_rad: npt.ArrayLike, qd0_rad_s: npt.ArrayLike) -> bytes:
    """q0 [rad] and qd0 [rad/s] (4 each) as 8 little-endian float64 (exact bits).

    :raises InitialStateError: wrong shape or non-finite value
    """
    q = np.asarray(q0_rad, dtype=np.float64).reshape(-1)
    qd = np.asarray(qd0_rad_s, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or qd.shape != (4,):
        raise InitialStateError(f"q0 and qd0 must have 4 values each, got {q.shape} and {qd.shape}")
    vals = [float(v) for v in q] + [float(v) for v in qd]
    if not all(math.isfinite(v) for v in vals):
        raise InitialStateError(f"initial state must be finite, got {vals}")
    return _STATE.pack(*vals)


def unpack_initial_state(data: bytes) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Inverse of :func:`pack_initial_state`: (q0, qd0), float64 (4,) each.

    :raises InitialStateError: not 64 bytes or non-finite values
    """
    if len(data) != INITIAL_STATE_BYTES:
        raise InitialStateError(f"initial state must be {INITIAL_STATE_BYTES} bytes, got {len(data)}")
    vals = np.array(_STATE.unpack(bytes(data)), dtype=np.float64)
    if not np.all(np.isfinite(vals)):
        raise InitialStateError("initial state must be finite")
    return vals[:4].copy(), vals[4:].copy()


# -- trial timing -------------------------------------------------------------------------

_U32_MAX: Final[int] = 0xFFFF_FFFF
_U64_MAX: Final[int] = 0xFFFF_FFFF_FFFF_FFFF
_TIMING = struct.Struct("<B6I")
TRIAL_TIMING_BYTES: Final[int] = _TIMING.size  # 25


@dataclass(frozen=True)
class TrialTiming:
    """Wall-clock timing of one trial as the plant measured it (0x2440), diagnostics only.

    :ivar paced: the trial was paced to the wall clock (real-time mode)
    :ivar ticks: ticks completed
    :ivar duration_us: from the trial start (tick 0 sent) to the last tick completed, µs
    :ivar deadline_misses: ticks whose torques arrived after the start of the next period (paced)
    :ivar lateness_p50_us: median of (start of tick n − (t0 + n·Ts)) over the ticks, µs (paced)
    :ivar lateness_p99_us: its 99th percentile, µs (paced)
    :ivar lateness_max_us: its maximum, µs (paced)
    """

    paced: bool
    ticks: int
    duration_us: int
    deadline_misses: int
    lateness_p50_us: int
    lateness_p99_us: int
    lateness_max_us: int

    @property
    def ticks_per_s(self) -> float:
        """The rate the trial ran at (ticks over the duration), 0 if unknown."""
        return self.ticks / (self.duration_us * 1e-6) if self.duration_us > 0 else 0.0


def pack_trial_timing(t: TrialTiming) -> bytes:
    """:class:`TrialTiming` as the 25 bytes of 0x2440 (values clamped to u32)."""
    u32 = [
        sat(int(v), 0, _U32_MAX)
        for v in (t.ticks, t.duration_us, t.deadline_misses, t.lateness_p50_us, t.lateness_p99_us, t.lateness_max_us)
    ]
    return _TIMING.pack(int(bool(t.paced)), *u32)


def unpack_trial_timing(data: bytes) -> TrialTiming:
    """Inverse of :func:`pack_trial_timing`.

    :raises ValueError: not 25 bytes
    """
    if len(data) != TRIAL_TIMING_BYTES:
        raise ValueError(f"trial timing must be {TRIAL_TIMING_BYTES} bytes, got {len(data)}")
    paced, *vals = _TIMING.unpack(bytes(data))
    return TrialTiming(bool(paced), *vals)


# -- deadline misses ----------------------------------------------------------------------

#: how many missed ticks of a trial 0x2441 lists (the count in 0x2440 goes on beyond)
DEADLINE_MISSES_KEPT: Final[int] = 64
_MISSES_HEAD = struct.Struct("<QH")
_MISS = struct.Struct("<3I")


@dataclass(frozen=True)
class DeadlineMiss:
    """One tick of a paced trial that completed after the start of the next period.

    :ivar tick: the tick's index n in the trial
    :ivar started_late_us: how late its encoder frames went out: start(n) − (t0 + n·Ts), µs
    :ivar overrun_us: how far past its deadline it completed: done(n) − (t0 + (n + 1)·Ts), µs
    """

    tick: int
    started_late_us: int
    overrun_us: int


@dataclass(frozen=True)
class DeadlineMisses:
    """The last trial's deadline misses as the plant measured them (0x2441), diagnostics only.

    :ivar t0_ns: when tick 0 was due, ns on the plant's ``CLOCK_MONOTONIC`` (the machine's), 0 if
        the trial was not paced
    :ivar misses: the first :data:`DEADLINE_MISSES_KEPT` misses, in tick order
    """

    t0_ns: int
    misses: tuple[DeadlineMiss, ...] = ()


def pack_deadline_misses(m: DeadlineMisses) -> bytes:
    """:class:`DeadlineMisses` as the bytes of 0x2441: u64 t0 ns, u16 k, then k × (u32 tick, u32
    started late µs, u32 overrun µs), little-endian; values clamped to their type, at most
    :data:`DEADLINE_MISSES_KEPT` entries."""
    kept = m.misses[:DEADLINE_MISSES_KEPT]
    out = bytearray(_MISSES_HEAD.pack(sat(int(m.t0_ns), 0, _U64_MAX), len(kept)))
    for x in kept:
        out += _MISS.pack(*(sat(int(v), 0, _U32_MAX) for v in (x.tick, x.started_late_us, x.overrun_us)))
    return bytes(out)


def unpack_deadline_misses(data: bytes) -> DeadlineMisses:
    """Inverse of :func:`pack_deadline_misses`.

    :raises ValueError: the length does not match the count, or more than
        :data:`DEADLINE_MISSES_KEPT` entries
    """
    data = bytes(data)
    if len(data) < _MISSES_HEAD.size:
        raise ValueError(f"deadline misses need at least {_MISSES_HEAD.size} bytes, got {len(data)}")
    t0_ns, k = _MISSES_HEAD.unpack_from(data)
    if k > DEADLINE_MISSES_KEPT:
        raise ValueError(f"deadline misses list {k} entries, at most {DEADLINE_MISSES_KEPT} allowed")
    if len(data) != _MISSES_HEAD.size + k * _MISS.size:
        raise ValueError(f"deadline misses with {k} entries must be {_MISSES_HEAD.size + k * _MISS.size} bytes, got {len(data)}")
    misses = tuple(DeadlineMiss(*_MISS.unpack_from(data, _MISSES_HEAD.size + i * _MISS.size)) for i in range(k))
    return DeadlineMisses(t0_ns, misses)
