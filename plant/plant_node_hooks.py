"""The plant node's object hooks: what reading or writing one of its objects does.

Owns the link between the node's object store (``bus/plant.eds``; names and encodings:
:mod:`bus.plant_objects`) and its trial machinery: read hooks give the live trial status and
fault record (0x2410:4..8, 0x1001), the counters (0x2430, U32, wrapping; the last trial's
duration in µs, saturated) and the last trial's timing and deadline misses (0x2440, 0x2441);
write hooks refuse configuration (0x2400; the plant-uncertainty factors 0x2400:6..9 validated,
abort 0x06090030 out of range), trial index and length (0x2410:1, 2) and the initial
state (0x2420, validated: 64 bytes of finite float64) while a trial runs (abort 0x08000022), and
carry out the trial command (0x2410:3: start, abort).  The robot's objects (0x2450..0x2453,
:mod:`plant.plant_node_robot`): mode (written: the robot comes on or goes off), fault reset,
state, counters, fault record, brakes; joint positions [counts], TCP pose [µm, µrad] and the
mechanical limits, read live.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from bus import units
from bus.cia301.object_store import ObjectStore, Value
from bus.errors import AbortCode, SdoAbort
from bus.plant_objects import (
    ERROR_REGISTER_INDEX,
    PLANT_SCALE_SUBS,
    ConfigSub,
    CounterSub,
    InitialStateError,
    LimitSub,
    PlantCommand,
    PlantObj,
    PlantTrialSub,
    RobotCommand,
    RobotMode,
    RobotSub,
    pack_deadline_misses,
    pack_trial_timing,
    plant_scale_error,
    unpack_initial_state,
)
from plant.plant_node_robot import RobotLoop
from plant.plant_node_status import TrialStatus
from plant.plant_node_trial import LockstepMaster

_U32 = 0xFFFFFFFF


def install_hooks(store: ObjectStore, lockstep: LockstepMaster, status: TrialStatus, robot: RobotLoop) -> None:
    """Install the plant node's read and write hooks into ``store`` (see the module docstring)."""
    r, w = store.read_hooks, store.write_hooks
    t = PlantObj.TRIAL
    r[(ERROR_REGISTER_INDEX, 0)] = lambda: status.error_register | robot.error_register
    r[(t, PlantTrialSub.STATUS)] = lambda: int(status.status)
    r[(t, PlantTrialSub.TICKS_DONE)] = lambda: lockstep.ticks_done & _U32
    r[(t, PlantTrialSub.FAULT_CODE)] = lambda: int(status.fault_code)
    r[(t, PlantTrialSub.FAULT_TICK)] = lambda: status.fault_tick & _U32
    r[(t, PlantTrialSub.FAULT_NODE)] = lambda: status.fault_node
    c = PlantObj.COUNTERS
    r[(c, CounterSub.IO_SENT)] = lambda: lockstep.io_sent & _U32
    r[(c, CounterSub.IO_RECEIVED)] = lambda: lockstep.io_received & _U32
    r[(c, CounterSub.TICK_TIMEOUTS)] = lambda: lockstep.tick_timeouts & _U32
    r[(c, CounterSub.TRIALS_DONE)] = lambda: lockstep.trials_done & _U32
    r[(c, CounterSub.LAST_TRIAL_US)] = lambda: min(int(status.last_trial_s * 1e6), _U32)
    r[(PlantObj.TRIAL_TIMING, 0)] = lambda: pack_trial_timing(status.timing)
    r[(PlantObj.DEADLINE_MISSES, 0)] = lambda: pack_deadline_misses(status.misses)

    def require_idle(what: str) -> Callable[[Value], None]:
        def hook(_value: Value) -> None:
            if lockstep.busy:
                raise SdoAbort(AbortCode.DEVICE_STATE, f"{what} cannot change while a trial runs")

        return hook

    def write_initial_state(value: Value) -> None:
        if lockstep.busy:
            raise SdoAbort(AbortCode.DEVICE_STATE, "initial state cannot change while a trial runs")
        if not isinstance(value, bytes):  # the EDS makes 0x2420 a DOMAIN: decoded as bytes
            raise TypeError(f"initial state 0x2420 must be bytes, got {type(value).__name__}")
        try:
            unpack_initial_state(bytes(value))
        except InitialStateError as err:
            code = AbortCode.LENGTH_MISMATCH if "bytes" in str(err) else AbortCode.VALUE_RANGE
            raise SdoAbort(code, str(err)) from None

    def write_command(value: Value) -> None:
        cmd = int(value)
        if cmd == PlantCommand.START:
            if lockstep.busy:
                raise SdoAbort(AbortCode.DEVICE_STATE, "a trial is already running")
            if len(store.get_bytes(PlantObj.INITIAL_STATE)) == 0:
                raise SdoAbort(AbortCode.DEVICE_STATE, "initial state 0x2420 not set")
            lockstep.request_start()
        elif cmd == PlantCommand.ABORT:
            lockstep.abort("aborted by the host")
        else:  # the EDS limits make this unreachable over SDO
            raise SdoAbort(AbortCode.VALUE_RANGE, f"unknown plant node command {cmd}")

    _install_robot_hooks(store, robot)
    for sub in ConfigSub:
        w[(PlantObj.CONFIG, sub)] = require_idle(f"configuration 0x2400:{int(sub)}")

    def scale_hook(sub: int) -> Callable[[Value], None]:
        idle = require_idle(f"configuration 0x2400:{sub}")

        def hook(value: Value) -> None:
            idle(value)
            why = plant_scale_error(sub, float(value))
            if why is not None:
                raise SdoAbort(AbortCode.VALUE_RANGE, why)

        return hook

    for sub in PLANT_SCALE_SUBS:
        w[(PlantObj.CONFIG, sub)] = scale_hook(int(sub))
    w[(t, PlantTrialSub.TRIAL_INDEX)] = require_idle("trial index")
    w[(t, PlantTrialSub.N_TICKS)] = require_idle("number of ticks")
    w[(t, PlantTrialSub.COMMAND)] = write_command
    w[(PlantObj.INITIAL_STATE, 0)] = write_initial_state


def _install_robot_hooks(store: ObjectStore, robot: RobotLoop) -> None:
    """The robot's objects 0x2450..0x2453 (:mod:`plant.plant_node_robot`)."""
    r, w = store.read_hooks, store.write_hooks
    o = PlantObj.ROBOT
    r[(o, RobotSub.STATE)] = lambda: int(robot.state)
    r[(o, RobotSub.PERIODS)] = lambda: robot.periods & _U32
    r[(o, RobotSub.SYNCS)] = lambda: robot.syncs & _U32
    r[(o, RobotSub.LATE_SYNCS)] = lambda: (robot.pacing.late if robot.pacing is not None else 0) & _U32
    r[(o, RobotSub.MISSING_SYNCS)] = lambda: (robot.pacing.missing if robot.pacing is not None else 0) & _U32
    r[(o, RobotSub.SYNC_OVERRUNS)] = lambda: robot.overruns & _U32
    r[(o, RobotSub.FAULT_CODE)] = lambda: int(robot.fault)
    r[(o, RobotSub.FAULT_JOINT)] = lambda: robot.fault_joint
    r[(o, RobotSub.FAULT_PERIOD)] = lambda: robot.fault_period & _U32
    r[(o, RobotSub.BRAKES)] = lambda: robot.brakes
    r[(o, RobotSub.LATE_PERIODS)] = lambda: (robot.pacing.late_periods if robot.pacing is not None else 0) & _U32
    w[(o, RobotSub.MODE)] = lambda value: robot.set_mode(RobotMode(int(value)))

    def command(value: Value) -> None:
        if int(value) == RobotCommand.FAULT_RESET:
            robot.fault_reset()
        else:  # the EDS limits make this unreachable over SDO
            raise SdoAbort(AbortCode.VALUE_RANGE, f"unknown robot command {int(value)}")

    w[(o, RobotSub.COMMAND)] = command
    for j in range(4):
        r[(PlantObj.JOINT_POSITION, j + 1)] = _joint_reader(robot, j)
        r[(PlantObj.TCP_POSE, j + 1)] = _tcp_reader(robot, j)
    lim = robot.limits
    r[(PlantObj.MECHANICAL_LIMITS, LimitSub.JOINT_LOW_COUNTS)] = lambda: _i32(lim.q_min_rad / units.RAD_PER_COUNT)
    r[(PlantObj.MECHANICAL_LIMITS, LimitSub.JOINT_HIGH_COUNTS)] = lambda: _i32(lim.q_max_rad / units.RAD_PER_COUNT)
    r[(PlantObj.MECHANICAL_LIMITS, LimitSub.GAP_MIN_UM)] = lambda: _i32(lim.gap_min_m * 1e6)
    r[(PlantObj.MECHANICAL_LIMITS, LimitSub.GAP_MAX_UM)] = lambda: _i32(lim.gap_max_m * 1e6)


def _joint_reader(robot: RobotLoop, j: int) -> Callable[[], Value]:
    return lambda: robot.joint_counts()[j]


def _tcp_reader(robot: RobotLoop, j: int) -> Callable[[], Value]:
    return lambda: _i32(robot.tcp_pose()[j] * 1e6)  # m → µm, rad → µrad


def _i32(value: float) -> int:
    """Nearest int32 (0 for a value that is not finite)."""
    if not math.isfinite(value):
        return 0
    return max(-(1 << 31), min((1 << 31) - 1, round(value)))
