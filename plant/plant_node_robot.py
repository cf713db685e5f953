"""The robot between trials: one control period per SYNC, holding brakes, mechanical limits.

Owns :class:`RobotLoop`, the plant node's robot mode (0x2450:1, ``ilcrig robot``; docs/robot.md):
while no trial runs, every SYNC frame (COB-ID 0x080) the plant node sees advances the robot by one
control period Ts (0x2400:1, with the sub-steps of 0x2400:2), whoever sends it — a PLC, ros2_canopen,
a python-canopen script:

1. encoder frames of all joints with the counts of q at the start of the period (one wire tick,
   claimed from the trial protocol's counter, :meth:`plant.plant_node_trial.LockstepMaster.claim_wire_tick`,
   so that a later trial recognises these frames as stale);
2. the four torque frames of that wire tick are collected (each drive's stream followed by a
   :class:`bus.io_frames.TickTracker`; where the transport gathers, the hub hands them over in one
   write, as in a trial); a drive whose frame does not say ENABLED (power stage off,
   or in fault) gives no torque and its joint is held by its brake;
3. the robot integrates the period (:class:`plant.mechanics.Mechanics`: brakes, end stops, the
   screw's travel, the mechanism's limits) and the period goes into the trace
   (:class:`plant.trace.TraceWriter`).

A master faster than the robot is served late, never dropped: a SYNC that comes during a period
waits in order (the drives' frames wait behind it likewise, :mod:`firmware_model.sync_backlog`).
The one that finds :data:`bus.cyclic.SYNC_BACKLOG_MAX` waiting is a SYNC overrun (0x2450:8; SYNC-
stepped a robot fault, EMCY 0x8110, once per episode; in real time a counted miss), served late all
the same: periods stepped = SYNCs seen, the same master sequence the same trace.  Every kernel a
period may use is compiled before the node boots (:func:`plant.mechanics.warm_up_robot`).

Real time (mode 2): periods are also paced to the wall clock (the schedule and its figures:
:class:`plant.plant_node_robot_pacing.RobotPacing`).

Faults (one EMCY each, from the plant node; :data:`bus.plant_objects.ROBOT_FAULT_EMCY`): a
mechanical limit (the robot stops at it), a drive that does not answer within ``tick_timeout_s``
(the period is dropped), a torque frame out of sequence or malformed.  A fault holds every joint by
its brake — the drives' torques are not applied — until the fault reset (0x2450:2 = 1 or NMT reset
node; EMCY 0x0000); the periods go on meanwhile, so the drives and the master see the robot
standing.  A trial (the ILC host) takes precedence: while one is requested or runs, SYNCs only
count; the robot goes on from where the trial left the plant.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can
import numpy as np

from bus import io_frames
from bus.can_errors import is_receive_overflow
from bus.cia301.emcy import EmcyCode
from bus.cia301.object_store import ObjectStore
from bus.cyclic import SYNC_BACKLOG_MAX
from bus.plant_objects import (
    ROBOT_FAULT_EMCY,
    ConfigSub,
    PlantObj,
    RobotFault,
    RobotMode,
    RobotState,
    RobotSub,
    robot_fault_emcy_data,
)
from plant.mechanics import LimitHit, MechanicalLimits, Mechanics, warm_up_robot
from plant.plant_node_model import TrialModel
from plant.plant_node_robot_pacing import RobotPacing
from plant.plant_node_status import Emcy
from plant.plant_node_trial import LockstepMaster
from plant.simulator import Plant
from plant.trace import FLAG_FAULT, FLAG_LATE, TraceWriter

logger = logging.getLogger(__name__)

__all__ = ["RobotLoop", "SYNC_COB_ID", "robot_info"]

#: the SYNC the robot steps on (CiA 301 predefined connection set)
SYNC_COB_ID: int = 0x080

_N = io_frames.N_JOINTS
_TORQUE_LO = io_frames.TORQUE_COB_BASE
_TORQUE_HI = io_frames.TORQUE_COB_BASE + _N
_ENABLED = int(io_frames.TorqueStatus.ENABLED)
_FAULT_BIT = int(io_frames.TorqueStatus.FAULT)
_LIMIT_FAULTS = {"end_stop": RobotFault.END_STOP, "screw_stop": RobotFault.SCREW_STOP, "mechanism": RobotFault.MECHANISM}
#: faults kept with their details for the session summary
FAULTS_KEPT: int = 100

_ALL_HELD = (1 << _N) - 1
#: the brakes of a period (bit j: joint j + 1 held) as the plant's ``locked`` mask; None when no
#: joint is held (the plant's step then looks at no mask)
_HELD_MASKS: list[np.ndarray | None] = [None] + [np.array([bool(bits >> j & 1) for j in range(_N)]) for bits in range(1, 1 << _N)]

_IDLE, _HELD, _SENT = 0, 1, 2


class RobotLoop:
    """The plant node's robot mode (see the module docstring).

    :param node_id: CANopen node id (log messages).
    :param store: the node's object store (0x2400 configuration, 0x2450 mode).
    :param lockstep: the trial protocol (precedence, the wire tick counter).
    :param model: the plant (shared with the trials).
    :param send_batch: sends the four encoder frames of a period ((COB-ID, data) pairs).
    :param send_emcy: sends one EMCY ``(error code, error register, data)``.
    :param gather: asks the io transport to deliver the plant's frames n at a time
        (:func:`bus.bus_features.frame_gatherer`): 4 while the robot steps — the four torque frames
        of a period wake the plant once —, 0 when it goes off (a trial sets its own and 0 at its end).
    :param clock: monotonic time source [s].
    :param tick_timeout_s: longest wait for the torque frames of one period, s.
    :param spin_s: real time: the last part of the wait for a held period, spent in a loop, s.
    :param limits: the mechanical limits (default :class:`plant.mechanics.MechanicalLimits`).
    :param trace_path: the period trace to write (None: none).
    """

    def __init__(
        self,
        node_id: int,
        store: ObjectStore,
        lockstep: LockstepMaster,
        model: TrialModel,
        *,
        send_batch: Callable[[list[tuple[int, bytes]]], None],
        send_emcy: Callable[[Emcy], None],
        gather: Callable[[int], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        tick_timeout_s: float,
        spin_s: float = 0.0,
        limits: MechanicalLimits | None = None,
        trace_path: str | None = None,
    ) -> None:
        self.node_id = node_id
        self.store = store
        self.lockstep = lockstep
        self.model = model
        self._send_batch = send_batch
        self._send_emcy = send_emcy
        self._gather = gather
        self._gathering = False  # the transport gathers the torque frames four at a time
        self._clock = clock
        self.tick_timeout_s = tick_timeout_s
        self.spin_s = spin_s
        self.limits = limits if limits is not None else MechanicalLimits()
        self.trace_path = trace_path
        self.trace: TraceWriter | None = None
        self.mechanics: Mechanics | None = None
        self._trackers = [io_frames.TickTracker(0, f"torque frames of drive {j + 1}") for j in range(_N)]
        self._tau = np.zeros(_N, dtype=np.int64)
        self._tau_w = self._tau.data  # its items written without a numpy call per torque frame
        self._enabled_bits = 0  # bit j: drive j+1's torque frame of the period said ENABLED
        self._state = _IDLE
        self._wire = 0
        self._got = 0
        self._deadline = 0.0
        self._send_at = 0.0
        self._pending: deque[float] = deque()  # arrival times of the SYNCs waiting for their periods
        self._late = False
        self.pacing: RobotPacing | None = None
        self.periods = 0
        self.syncs = 0
        self.overruns = 0
        self.backlog_max = 0  # the most SYNCs that waited behind a period in progress
        self._overrunning = False  # an overrun episode: more than SYNC_BACKLOG_MAX waited (reported once)
        self.timeouts = 0
        self.dropped = 0  # periods started, then dropped (docs/robot.md, What a session leaves)
        self.unstepped = 0  # SYNCs that never started a period (seen while off or in a trial, or waiting then)
        self.fault = RobotFault.NONE
        self.fault_joint = 0
        self.fault_period = 0
        self.fault_message = ""
        self.fault_time_s = 0.0  # wall clock (time.time()) of the fault in force, s
        self.faults: list[dict[str, Any]] = []
        self.faults_total = 0
        self.error_register = 0
        self._held_bits = 0xF

    # ------------------------------------------------------------------ mode

    @property
    def mode(self) -> RobotMode:
        return RobotMode(int(self.store.get(PlantObj.ROBOT, RobotSub.MODE)))

    @property
    def on(self) -> bool:
        return int(self.store.get(PlantObj.ROBOT, RobotSub.MODE)) != RobotMode.OFF  # every SYNC: no enum built

    @property
    def state(self) -> RobotState:
        if not self.on:
            return RobotState.OFF
        return RobotState.FAULT if self.fault != RobotFault.NONE else RobotState.READY

    @property
    def brakes(self) -> int:
        """0x2450:12: bit j-1 set while joint j is held by its brake (after the last period)."""
        return self._held_bits

    def set_mode(self, mode: RobotMode) -> None:
        """0x2450:1 written (or the role's choice): the robot comes on at its home pose (the first
        time; later it goes on from where it stands), or goes off after the period in progress."""
        self.store.values[(PlantObj.ROBOT, RobotSub.MODE)] = int(mode)
        if mode == RobotMode.OFF:
            self._forget_periods()
            if self._gathering and self._gather is not None:
                self._gather(0)
            self._gathering = False
            return
        self._robot()
        if mode == RobotMode.REALTIME and self.pacing is None:
            self.pacing = RobotPacing(self._ts_substeps()[0])
        elif mode != RobotMode.REALTIME:
            self.pacing = None
        logger.info("node %d: robot mode %s", self.node_id, mode.name)

    def _ts_substeps(self) -> tuple[float, int]:
        period_us = int(self.store.get(PlantObj.CONFIG, ConfigSub.CONTROL_PERIOD_US))
        return period_us / 1_000_000, int(self.store.get(PlantObj.CONFIG, ConfigSub.SUBSTEPS))

    def _robot(self) -> Mechanics:
        """The mechanics on the model's plant for the configured Ts; homed when the plant is new."""
        ts_s, substeps = self._ts_substeps()
        plant = self.model.plant(ts_s, substeps)
        mech = self.mechanics
        if mech is None or mech.plant is not plant:
            if not isinstance(plant, Plant):
                raise TypeError(f"the robot mode needs a plant.simulator.Plant, got {type(plant).__name__}")
            mech = self.mechanics = Mechanics(plant, self.limits)
            mech.home()
            try:
                scratch = self.model.plant_factory(ts_s, substeps)
                if isinstance(scratch, Plant):
                    warm_up_robot(scratch, self.limits)
            except Exception:  # the robot goes on; the first periods pay for it
                logger.exception("node %d: warming up the robot's kernels failed", self.node_id)
            logger.info("node %d: robot at its home pose, q = %s deg", self.node_id, np.round(np.degrees(plant.q), 3).tolist())
            if self.trace is not None:
                self.trace.close()
            if self.trace_path is not None:
                try:
                    self.trace = TraceWriter(self.trace_path, ts_s, substeps)
                except OSError as err:  # the robot goes on without its trace
                    self.trace = None
                    logger.error("node %d: cannot write the robot trace %s: %s", self.node_id, self.trace_path, err)
        return mech

    # ------------------------------------------------------------------ loop hooks

    def on_sync(self, now: float) -> None:
        """A SYNC frame: a period starts, or waits in order behind the one in progress (past
        :data:`bus.cyclic.SYNC_BACKLOG_MAX` waiting: an overrun, SYNC-stepped a robot fault)."""
        self.syncs += 1
        if not self.on or self.lockstep.busy:
            self.unstepped += 1
            return
        if self._state == _IDLE:
            self._start(now, now)
            return
        pending = self._pending
        waiting = len(pending)
        if waiting >= SYNC_BACKLOG_MAX:
            self.overruns += 1
            if not self._overrunning:
                self._overrunning = True
                logger.warning("node %d: SYNC overrun in period %d: %d SYNCs wait", self.node_id, self.periods, waiting)
                if self.pacing is None:
                    text = f"SYNC {self.syncs} came in period {self.periods} with {waiting} SYNCs waiting (bus.cyclic."
                    text += "SYNC_BACKLOG_MAX): the master outruns the robot; every SYNC served late, torque-free until reset"
                    self._fail(RobotFault.SYNC_OVERRUN, 0, text)
        pending.append(now)
        if waiting >= self.backlog_max:
            self.backlog_max = waiting + 1

    def frames_lost(self) -> None:
        """The fieldbus receiver overflowed: a SYNC may be lost (robot fault FRAMES_LOST, EMCY 0x8110)."""
        self._fail(RobotFault.FRAMES_LOST, 0, f"fieldbus frames lost in period {self.periods}: a SYNC may be among them")

    def interrupt(self) -> None:
        """A trial begins: the period in progress is dropped (its frames are stale for the trial); the
        trial sets the transport's gathering for itself (and 0 at its end)."""
        self._forget_periods()
        self._gathering = False

    def _forget_periods(self) -> None:
        """The period in progress is dropped and the SYNCs waiting are not stepped (counted)."""
        self._end_period()
        self.unstepped += len(self._pending)
        self._pending.clear()

    def _end_period(self) -> None:
        """The period in progress, if any, is dropped (counted)."""
        if self._state != _IDLE:
            self.dropped += 1
            self._state = _IDLE

    def next_deadline(self) -> float | None:
        if self._state == _HELD:
            return self._send_at - self.spin_s
        if self._state == _SENT:
            return self._deadline
        return None

    def grace(self, now: float) -> None:
        """The plant did not run until ``now`` (:meth:`PlantNode.after_stall`): the period's torques get their time from now."""
        self._deadline = max(self._deadline, now + self.tick_timeout_s)

    def service(self, now: float) -> None:
        """Send a held period that is due, or detect a period whose torques did not come."""
        if self._state == _HELD:
            if self.spin_s and self._send_at - self.spin_s <= now < self._send_at:
                while now < self._send_at:  # the last stretch on the clock (bounded by spin_s)
                    now = self._clock()
            if now >= self._send_at:
                self._send_encoders(now)
        elif self._state == _SENT and now >= self._deadline:
            missing = [j + 1 for j in range(_N) if self._trackers[j].next_tick == self._wire]
            self.timeouts += 1
            self._end_period()
            what = f"drive(s) {missing} did not answer period {self.periods} within {self.tick_timeout_s:g} s"
            self._fail(RobotFault.PERIOD_TIMEOUT, missing[0] if missing else 0, what)
            self._next(now)

    @property
    def expecting_io(self) -> bool:
        """True while a period waits for its torque frames."""
        return self._state == _SENT

    def on_io(self, msg: can.Message) -> None:
        """One io frame while a period waits for its torques."""
        if msg.is_error_frame:
            lost = is_receive_overflow(msg)  # this receiver dropped frames: a torque frame never comes
            what = "io frames lost in the plant's receiver (receive overflow)" if lost else "bus error frame on io (damaged)"
            self._fail(RobotFault.IO_FRAMES_LOST if lost else RobotFault.BAD_FRAME, 0, f"period {self.periods}: {what}")
            self._drop_period()
            return
        cob = msg.arbitration_id
        if not _TORQUE_LO <= cob < _TORQUE_HI or self._state != _SENT:
            return
        j = cob - _TORQUE_LO
        try:
            torque, wire, status = io_frames.torque_fields(msg)
            if io_frames.tick_diff(wire, self._wire) < 0:
                return  # an answer to an earlier (dropped) period or trial
            self._trackers[j].accept(wire)
        except io_frames.TickError as err:
            self._fail(RobotFault.TICK_SEQUENCE, j + 1, f"period {self.periods}: {err}")
            self._drop_period()
            return
        except io_frames.IoFrameError as err:
            self._fail(RobotFault.BAD_FRAME, j + 1, f"period {self.periods}: bad torque frame: {err}")
            self._drop_period()
            return
        if status & _ENABLED and not status & _FAULT_BIT:
            self._enabled_bits |= 1 << j
            self._tau_w[j] = torque
        else:
            self._enabled_bits &= ~(1 << j)
            self._tau_w[j] = 0
        self._got += 1
        if self._got == _N:
            self._advance()

    # ------------------------------------------------------------------ periods

    def _start(self, arrival: float, now: float) -> None:
        self._late = False
        pacing = self.pacing
        if pacing is not None:
            due, self._late = pacing.schedule(arrival)
            if now < due:
                self._state, self._send_at = _HELD, due
                return
        self._send_encoders(now)

    def _send_encoders(self, now: float) -> None:
        # the period is in progress from here, before anything is sent: a send that fails (the hub
        # gone as the session ends) leaves it counted as the period in progress — never a SYNC
        # that no count of the session holds
        self._wire = wire = self.lockstep.claim_wire_tick()
        for tracker in self._trackers:
            tracker.reset(wire)
        self._got, self._state, self._deadline = 0, _SENT, now + self.tick_timeout_s
        mech = self._robot()
        if not self._gathering and self._gather is not None:
            # one write of the hub per period for the four torques; a frame too many or too few (a bus error
            # frame, a drive that does not answer) is held at most BULK_HOLD_S, the next four come together again
            self._gather(_N)
            self._gathering = True
        self._send_batch(io_frames.encoder_frames(wire, mech.plant.encoder_counts_list()))
        if self.pacing is not None:
            self.pacing.started(now)

    def _advance(self) -> None:
        """All four torques are in: the robot integrates the period, the next one may start."""
        mech = self._robot()
        faulted = self.fault != RobotFault.NONE
        self._held_bits = _ALL_HELD if faulted else _ALL_HELD & ~self._enabled_bits
        hit = mech.step(self._tau, _HELD_MASKS[self._held_bits])
        if hit is not None:
            self._limit(hit)
        if self.trace is not None:
            flags = (FLAG_LATE if self._late else 0) | (FLAG_FAULT if self.fault != RobotFault.NONE else 0)
            self.trace.add(self.periods, mech.plant.q_list(), self._tau, self._held_bits, flags)
        self.periods += 1
        now = self._clock()
        if self.pacing is not None:
            self.pacing.completed(now)
        self._state = _IDLE
        self._next(now)

    def _next(self, now: float) -> None:
        pending = self._pending
        if pending:
            self._start(pending.popleft(), now)
            if self._overrunning and len(pending) < SYNC_BACKLOG_MAX // 2:
                self._overrunning = False  # caught up: a new overrun is a new episode

    def _drop_period(self) -> None:
        self._end_period()
        self._next(self._clock())

    # ------------------------------------------------------------------ faults

    def _limit(self, hit: LimitHit) -> None:
        if self.fault == RobotFault.NONE:
            self._fail(_LIMIT_FAULTS[hit.kind], hit.joint, hit.message)
        else:
            logger.info("node %d: %s (robot in fault already)", self.node_id, hit.message)

    def _fail(self, fault: RobotFault, joint: int, message: str) -> None:
        """A robot fault: EMCY, every joint braked until the fault reset."""
        self.faults_total += 1
        if len(self.faults) < FAULTS_KEPT:
            self.faults.append(
                {"fault": fault.name, "joint": joint, "period": self.periods, "t_s": time.time(), "message": message}
            )
        if self.fault != RobotFault.NONE:
            logger.warning("node %d: robot fault %s while in fault: %s", self.node_id, fault.name, message)
            return
        self.fault, self.fault_joint, self.fault_period, self.fault_message = fault, joint, self.periods, message
        self.fault_time_s = time.time()
        code, register = ROBOT_FAULT_EMCY[fault]
        self.error_register = register
        logger.warning("node %d: robot fault %s: %s", self.node_id, fault.name, message)
        self._send_emcy((code, register, robot_fault_emcy_data(fault, joint, self.periods)))

    def fault_reset(self) -> None:
        """0x2450:2 = 1 (or NMT reset node): the fault is cleared (EMCY 0x0000), the brakes follow
        the drives again."""
        if self.fault == RobotFault.NONE:
            return
        logger.info("node %d: robot fault %s reset", self.node_id, self.fault.name)
        self.fault, self.fault_joint, self.fault_period, self.fault_message = RobotFault.NONE, 0, 0, ""
        self.error_register = 0
        self._send_emcy((int(EmcyCode.ERROR_RESET), 0, bytes(5)))

    # ------------------------------------------------------------------ reporting

    def joint_counts(self) -> list[int]:
        """0x2451: the joint angles in encoder counts (rounded)."""
        mech = self.mechanics
        if mech is None:
            return [0] * _N
        return [int(c) for c in mech.plant.encoder_counts()]

    def tcp_pose(self) -> tuple[float, float, float, float]:
        """X = (x, y, z [m], θ [rad]) of the robot now (forward kinematics)."""
        mech = self.mechanics
        if mech is None:
            return (math.nan,) * 4
        x = mech.plant.task_pose()
        return float(x[0]), float(x[1]), float(x[2]), float(x[3])

    def close(self) -> None:
        """Write the rest of the trace and close it."""
        if self.trace is not None:
            self.trace.close()

    def info(self) -> dict[str, Any]:
        """The session so far, for the summary (:func:`robot_info`)."""
        return robot_info(self)

    @property
    def in_period(self) -> bool:
        """A period has started (its encoder frames sent or held) and not completed."""
        return self._state != _IDLE

    @property
    def syncs_waiting(self) -> int:
        """SYNCs waiting behind the period in progress."""
        return len(self._pending)

    @property
    def ts_s(self) -> float:
        """The control period Ts (0x2400:1), s."""
        return self._ts_substeps()[0]


def robot_info(loop: RobotLoop) -> dict[str, Any]:
    """The session of robot loop ``loop`` so far, for the summary (docs/robot.md, What a session leaves)."""
    out: dict[str, Any] = {
        "mode": loop.mode.name.lower(),
        "state": loop.state.name.lower(),
        "periods": loop.periods,
        "syncs": loop.syncs,
        "sync_overruns": loop.overruns,
        "sync_backlog_max": loop.backlog_max,
        "syncs_waiting": loop.syncs_waiting,
        "period_in_progress": int(loop.in_period),
        "periods_dropped": loop.dropped,
        "syncs_unstepped": loop.unstepped,
        "period_timeouts": loop.timeouts,
        "faults_total": loop.faults_total,
        "faults": list(loop.faults),
        "fault": None
        if loop.fault == RobotFault.NONE
        else {
            "fault": loop.fault.name,
            "joint": loop.fault_joint,
            "period": loop.fault_period,
            "t_s": loop.fault_time_s,
            "message": loop.fault_message,
        },
        "brakes": loop.brakes,
        "ts_s": loop.ts_s,
    }
    if loop.pacing is not None:
        out["realtime"] = loop.pacing.info()
    if loop.mechanics is not None:
        out["q_rad"] = [float(v) for v in loop.mechanics.plant.q]
        out["tcp"] = list(loop.tcp_pose())
    if loop.trace is not None:
        trace = loop.trace
        # records: in the file; not_written: the periods a failed write lost (trace.error says why)
        out["trace"] = {
            "path": str(trace.path),
            "records": trace.written,
            "not_written": trace.records - trace.written,
            "error": trace.error,
        }
    return out
