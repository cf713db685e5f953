"""The plant node: the plant as a CANopen slave on the fieldbus and the lockstep clock master of
the io channel, and the ``ilcrig plant`` process entry.

This module owns :class:`PlantNode`, the composition of the plant side of the rig on top of the
generic slave runtime :class:`bus.cia301.slave.SlaveNode` (select loop, NMT, heartbeat, SDO
server, EMCY), and :func:`run_plant_role`.  Its parts, one concern each:

* :mod:`plant.plant_node_trial` — the trial protocol: lockstep tick master, tick timeouts,
  real-time pacing, io counters (architecture.md "Time and one trial");
* :mod:`plant.plant_node_model` — what a trial simulates: the plant and the disturbance;
* :mod:`plant.plant_node_status` — the outcome the host reads: status, fault record and EMCY,
  trial timing;
* :mod:`plant.plant_node_hooks` — the object hooks (objects: ``bus/plant.eds``, names and
  encodings: :mod:`bus.plant_objects`).

:class:`PlantNode` itself is the slave application (NMT, object access, heartbeat consumer and
bus loss) and hands the select loop's hooks to the trial master.  The plant and the disturbance
model come as two factories (:mod:`plant.plant_node_model`; :func:`run_plant_role` builds them
from ``plant/``, tests pass their own); the plant is built, and a disturbance computed, once at
:meth:`PlantNode.start`, before the boot-up frame, so compilation never delays a trial.

The trial is event driven inside the slave's select loop, so SDO requests (status polls) are
answered during a trial by the same thread, between ticks.  The host's heartbeat is consumed
(0x1016): losing it during a trial is a HOST_LOST fault (EMCY 0x8130), outside a trial only the
EMCY is sent (only logged in NMT STOPPED); NMT stop and the resets abort a running trial; a failing
bus ends the node's loop (:meth:`PlantNode.bus_lost`).  After a fault the node keeps serving and
the next start begins afresh.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from bus import io_frames, units
from bus.atomic import atomic_write
from bus.bus_features import data_frame_sender, frame_answerer, frame_gatherer
from bus.cia301.answering import AnsweringNode
from bus.cia301.nmt import NmtCommand, NmtState, next_state
from bus.cia301.object_store import ObjectStore
from bus.cia301.slave import install_sigterm, quiet_shutdown
from bus.exit_codes import EXIT_FAULT, EXIT_OK
from bus.fastmsg import new_message
from bus.lockstep_process import freeze_heap, numba_without_blas, spin_in_this_class
from bus.plant_objects import (
    DEFAULT_PLANT_NODE_ID,
    PLANT_EDS_PATH,
    DisturbanceKind,
    PlantFault,
    PlantObj,
    PlantStatus,
    RobotMode,
    RobotSub,
)
from bus.timer_slack import fine_timer_slack
from bus.transports.config import TransportConfig
from plant.mechanics import MechanicalLimits
from plant.plant_node_hooks import install_hooks
from plant.plant_node_model import DisturbanceFn, PlantFactory, TrialModel
from plant.plant_node_robot import SYNC_COB_ID, RobotLoop
from plant.plant_node_status import Emcy, TrialStatus, fault_emcy
from plant.plant_node_trial import LockstepMaster

logger = logging.getLogger(__name__)

__all__ = ["PlantNode", "PlantOptions", "run_plant", "run_plant_role"]

_TORQUE_LO = io_frames.TORQUE_COB_BASE
_TORQUE_HI = io_frames.TORQUE_COB_BASE + io_frames.N_JOINTS
#: the frames a trial's answer loop hands to the plant: the four torque frames
_ANSWER_RX = (_TORQUE_LO, _TORQUE_HI - _TORQUE_LO, io_frames.TORQUE_LEN)


class PlantNode(AnsweringNode):
    """The plant as CANopen node ``node_id`` and io clock master.

    :param fieldbus: python-can bus of the fieldbus.
    :param io: python-can bus of the io channel.
    :param plant_factory: ``(ts_s, substeps) -> plant`` (see module docstring).
    :param disturbance_fn: ``(kind, seed, trial, n_ticks, ts_s) -> (n_ticks, 4)`` N·m.
    :param node_id: CANopen node id (default 32).
    :param tick_timeout_s: longest wait for the torque frames of one tick, s.
    :param first_tick_timeout_s: the same for tick 0 of a trial, s (drives may load their
        compiled kernels on their first tick; default :attr:`FIRST_TICK_TIMEOUT_S`).
    :param clock: monotonic time source [s] (protocol timing only).
    :param eds_path: the EDS (default ``bus/plant.eds``).
    :param spin_s: real time: wake this long before a held tick is due and wait the rest on the
        clock in a loop, s (0: the select loop's timer alone; :mod:`plant.plant_node_trial`).
    :param spin_when: whether a paced trial spins ``spin_s`` (asked at its start; None: always).
    :param robot_mode: the robot mode the node starts in (0x2450:1; :mod:`plant.plant_node_robot`).
    :param limits: the robot's mechanical limits (default :class:`plant.mechanics.MechanicalLimits`).
    :param trace_path: where the robot writes its period trace (None: no trace).

    :ivar store: the object store.
    :ivar model: the plant and the disturbance.
    :ivar lockstep: the trial protocol.
    :ivar trial_status: the outcome of the trials.
    :ivar robot: the robot between trials (SYNC-stepped periods).
    """

    #: the plant role's ``spin_s``: the last part of the wait for a paced tick, spent in a loop (a
    #: timer wake-up comes about 0.1 ms late on the machines here, a tenth of the period, while the
    #: drives wait for the plant at that moment and the core is free)
    REALTIME_SPIN_S: float = 250e-6

    #: Default longest wait for the four torque frames of one tick, s.
    TICK_TIMEOUT_S: float = io_frames.TICK_TIMEOUT_S
    #: Default longest wait for the torque frames of tick 0, s.
    FIRST_TICK_TIMEOUT_S: float = io_frames.FIRST_TICK_TIMEOUT_S

    def __init__(
        self,
        fieldbus: can.BusABC,
        io: can.BusABC,
        *,
        plant_factory: PlantFactory,
        disturbance_fn: DisturbanceFn,
        node_id: int = DEFAULT_PLANT_NODE_ID,
        tick_timeout_s: float | None = None,
        first_tick_timeout_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        eds_path: str | Path = PLANT_EDS_PATH,
        spin_s: float = 0.0,
        spin_when: Callable[[], bool] | None = None,
        robot_mode: RobotMode = RobotMode.OFF,
        limits: MechanicalLimits | None = None,
        trace_path: str | None = None,
        disturbance: str = "both",
    ) -> None:
        if not 0.0 <= spin_s < 0.01:
            raise ValueError(f"spin_s must be in [0, 0.01) s, got {spin_s!r}")
        tick_s = float(self.TICK_TIMEOUT_S if tick_timeout_s is None else tick_timeout_s)
        if not tick_s > 0:
            raise ValueError(f"tick_timeout_s must be > 0, got {tick_timeout_s!r}")
        first_s = float(max(self.FIRST_TICK_TIMEOUT_S if first_tick_timeout_s is None else first_tick_timeout_s, tick_s))
        self.store = ObjectStore(eds_path, node_id)
        self._warm_disturbance = disturbance
        self._nmt_state = NmtState.PRE_OPERATIONAL
        super().__init__(self, fieldbus, io, node_id=node_id, clock=clock)
        self.trial_status = TrialStatus(self.node_id)
        # the four encoder frames of a tick go out in one write where the bus can (the hub), packed
        # without a can.Message each
        self._data_frames = data_frame_sender(io)
        # a trial's torque frames read and its encoder frames written outside the interpreter where
        # the io bus can (the hub client in C, :meth:`step`); on the monotonic clock only
        self._answer = frame_answerer(io) if clock is time.monotonic else None
        self._outbox: list[tuple[int, bytes]] | None = None  # encoder frames for the C loop to write
        self.model = TrialModel(self.node_id, plant_factory, disturbance_fn)
        self.lockstep = LockstepMaster(
            self.node_id,
            self.store,
            self.trial_status,
            self.model,
            send=self._send_io,
            send_batch=self._send_io_batch,
            send_emcy=self._send_fault_emcy,
            # in a trial the hub hands the plant the four torque frames of a tick in one write
            gather=frame_gatherer(io),
            clock=clock,
            tick_timeout_s=tick_s,
            first_tick_timeout_s=first_s,
            spin_s=float(spin_s),
            spin_when=spin_when,
        )
        self.robot = RobotLoop(
            self.node_id,
            self.store,
            self.lockstep,
            self.model,
            send_batch=self._send_io_batch,
            send_emcy=self._send_fault_emcy,
            # and in the robot's periods likewise (the trial's end sets it back to 0)
            gather=frame_gatherer(io),
            clock=clock,
            tick_timeout_s=tick_s,
            spin_s=float(spin_s),
            limits=limits,
            trace_path=trace_path,
        )
        self._robot_mode = RobotMode(robot_mode)
        # the EDS gives 0x2450:1 as ``ilcrig robot`` boots; the robot comes on at start() (if at all)
        self.store.values[(PlantObj.ROBOT, RobotSub.MODE)] = int(RobotMode.OFF)
        install_hooks(self.store, self.lockstep, self.trial_status, self.robot)

    # ------------------------------------------------------------------ slave app interface

    @property
    def nmt_state(self) -> int:
        return int(self._nmt_state)

    def nmt_command(self, cs: int) -> NmtState:
        """Apply an NMT command.  STOP and the resets abort a running trial; reset node
        restores every object's default (configuration, initial state, counters).

        :raises ValueError: unknown command specifier.
        """
        cmd = NmtCommand(cs)
        if cmd in (NmtCommand.STOP, NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self.lockstep.abort(f"NMT {cmd.name}")
        if cmd == NmtCommand.RESET_NODE:
            mode = self.robot.mode
            self.store.reset(0x2000, 0x5FFF)
            self.trial_status.reset()
            self.lockstep.reset_counters()
            if mode != RobotMode.OFF:  # the robot stays on where it stands; a reset clears its fault
                self.robot.set_mode(mode)
                self.robot.fault_reset()
            else:  # and off stays off (the EDS default is ``ilcrig robot``'s)
                self.store.values[(PlantObj.ROBOT, RobotSub.MODE)] = int(RobotMode.OFF)
        if cmd in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self.store.reset(0x1000, 0x1FFF)
        self._nmt_state = next_state(self._nmt_state, cmd)
        return self._nmt_state

    def read_object(self, index: int, sub: int) -> bytes:
        return self.store.read_object(index, sub)

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        self.store.write_object(index, sub, data)

    def pop_emcy(self) -> list[Emcy]:
        """Always empty: the plant node sends its EMCY frames at once (:meth:`SlaveNode.send_emcy`)."""
        return []

    def heartbeat_lost(self, node_id: int) -> None:
        """The heartbeat consumer lost ``node_id`` (the host): a running trial ends with
        HOST_LOST (EMCY 0x8130); outside a trial only the EMCY is sent (logged in NMT STOPPED)."""
        if self._nmt_state == NmtState.STOPPED:
            logger.info("node %d: heartbeat of node %d lost while NMT STOPPED", self.node_id, node_id)
            return
        lockstep = self.lockstep
        if lockstep.busy:
            message = f"heartbeat of node {node_id} (the host) lost at tick {lockstep.tick}"
            lockstep.fail(PlantFault.HOST_LOST, 0, message, started=lockstep.running)
        else:
            logger.warning("node %d: heartbeat of node %d (the host) lost", self.node_id, node_id)
            self._send_fault_emcy(fault_emcy(PlantFault.HOST_LOST, 0, lockstep.tick))

    def frames_lost(self) -> None:
        """The fieldbus receiver overflowed (frames lost; :meth:`bus.cia301.slave.SlaveNode.on_frames_lost`):
        the robot faults (a SYNC may be lost, :meth:`plant.plant_node_robot.RobotLoop.frames_lost`);
        a running trial ends with FRAMES_LOST (EMCY 0x8110); otherwise that EMCY alone says so (the
        host's request that was lost would time out on its side)."""
        if self.robot.on:  # stepping on SYNC in every NMT state (its EMCY is not sent in STOPPED)
            self.robot.frames_lost()
            return
        if self._nmt_state == NmtState.STOPPED:
            logger.warning("node %d: fieldbus frames lost while NMT STOPPED", self.node_id)
            return
        lockstep = self.lockstep
        message = f"fieldbus frames lost in the plant's receiver at tick {lockstep.tick} (receive overflow)"
        if lockstep.busy:
            lockstep.fail(PlantFault.FRAMES_LOST, 0, message, started=lockstep.running)
        else:
            logger.warning("node %d: %s", self.node_id, message)
            self._send_fault_emcy(fault_emcy(PlantFault.FRAMES_LOST, 0, lockstep.tick))

    def bus_lost(self, reason: str) -> None:
        """A bus failed (the hub gone): the trial, if any, ends here (nothing can be sent)."""
        self.lockstep.bus_lost(reason)

    # ------------------------------------------------------------------ public state

    @property
    def status(self) -> PlantStatus:
        return self.trial_status.status

    @property
    def fault(self) -> PlantFault:
        return self.trial_status.fault_code

    @property
    def last_fault_message(self) -> str:
        return self.trial_status.last_fault_message

    @property
    def ticks_done(self) -> int:
        return self.lockstep.ticks_done

    @property
    def tick_timeouts(self) -> int:
        return self.lockstep.tick_timeouts

    @property
    def trials_done(self) -> int:
        return self.lockstep.trials_done

    @property
    def spin_s(self) -> float:
        return self.lockstep.spin_s

    def info(self) -> dict[str, Any]:
        """Counters and the last fault, for logs and summaries."""
        lockstep, status = self.lockstep, self.trial_status
        return {
            "status": status.status.name,
            "fault": status.fault_code.name,
            "fault_message": status.last_fault_message,
            "io_sent": lockstep.io_sent,
            "io_received": lockstep.io_received,
            "tick_timeouts": lockstep.tick_timeouts,
            "trials_done": lockstep.trials_done,
            "last_trial_s": status.last_trial_s,
            **({"robot": self.robot.info()} if self.robot.on else {}),
        }

    # ------------------------------------------------------------------ loop hooks

    def start(self) -> None:
        """Build the plant for the default configuration (compiles it, if needed) and compute a
        disturbance of the kind the node was told to expect once, then boot: what a first call
        costs (a non-repetitive disturbance's first imports scipy.signal, about a second) is paid
        here, not while the first trial's start holds the select loop that answers the host's SDO
        requests."""
        self.model.warm_up(*self.lockstep.config_ts_substeps(), self._warm_disturbance)
        if self._robot_mode != RobotMode.OFF:
            self.robot.set_mode(self._robot_mode)
        super().start()

    def after_stall(self, due_s: float, now_s: float) -> None:
        """:meth:`SlaveNode.after_stall`, the deadlines of a trial's tick and of the robot's period too."""
        super().after_stall(due_s, now_s)
        self.lockstep.grace(now_s)
        self.robot.grace(now_s)

    def next_deadline(self) -> float | None:
        trial = self.lockstep.next_deadline()
        robot = self.robot.next_deadline()
        if trial is None or robot is None:
            return robot if trial is None else trial
        return min(trial, robot)

    def io_settled(self) -> bool:
        """The torque frames of a wake-up completed ticks (or periods) or wait for the others, and
        left no deadline earlier than the one the service knows (a tick sent re-arms its timeout
        later; a held tick or period is due earlier and is served): the service may wait for it.
        Faults need no service: the plant sends their EMCY at once."""
        if self.lockstep.pending_start:
            return False
        due = self.next_deadline()
        return due is None or due >= self._due_s

    def on_service(self, now: float) -> None:
        if self.lockstep.pending_start:
            self.robot.interrupt()
        self.lockstep.service(now)
        self.robot.service(now)

    def on_io(self, msg: can.Message) -> None:
        if self.robot.expecting_io and not self.lockstep.busy:
            if _TORQUE_LO <= msg.arbitration_id < _TORQUE_HI:
                self.lockstep.io_received += 1
            self.robot.on_io(msg)
        else:
            self.lockstep.on_io(msg)

    def consumed_fieldbus_ids(self) -> set[int]:
        """SYNC while the robot mode is on (:mod:`plant.plant_node_robot`)."""
        return {SYNC_COB_ID} if self.robot.on else set()

    def on_fieldbus(self, msg: can.Message) -> None:
        if msg.arbitration_id == SYNC_COB_ID and len(msg.data) <= 1:
            self.robot.on_sync(self._clock())

    # ------------------------------------------------------------------ sending

    def _send_io(self, msg: can.Message) -> None:
        if self._outbox:  # what the C loop would write comes first
            self._data_frames(self._outbox)
            self._outbox.clear()
        self.io.send(msg)
        self.frames_out += 1

    def _send_io_batch(self, frames: list[tuple[int, bytes]]) -> None:
        if self._outbox is not None:
            self._outbox.extend(frames)  # written by the C loop right after this frame's call
        else:
            self._data_frames(frames)
        self.frames_out += len(frames)

    # ------------------------------------------------------------------ a trial's frames in C

    def step(self, max_wait_s: float) -> int:
        """:meth:`SlaveNode.step`; during a trial, while the last wake-up left the service nothing to
        do, first the torque frames that come before its deadline, read by the io transport outside
        the interpreter (:class:`bus.bus_features.FrameAnswerer`: the hub client's C loop), each
        handed to :meth:`LockstepMaster.on_torque` as :meth:`on_io` would, the next tick's encoder
        frames written by the loop. It hands back at the deadline, at a fieldbus frame, at any other
        io frame and after a frame that ended the trial or left the service something to do."""
        answer = self._answer
        if answer is None or not self.lockstep.running or self.robot.expecting_io or not self.answering_now():
            return super().step(max_wait_s)
        return self.step_answering(answer, _ANSWER_RX, self._answer_torque, max_wait_s)

    def _answer_torque(self, j: int, data: bytes) -> list[tuple[int, bytes]] | None:
        """A torque frame of drive ``j + 1`` read in C (:meth:`step`): the encoder frames it makes
        due (none until the tick's fourth), or None after the Python path handled it (the trial
        ended, the service has something to do)."""
        lockstep = self.lockstep
        if not lockstep.running or self.robot.expecting_io:  # the trial ended in this read
            self.on_io(new_message(_TORQUE_LO + j, bytearray(data)))
            return None
        lockstep.io_received += 1
        outbox: list[tuple[int, bytes]] = []
        self._outbox = outbox
        try:
            lockstep.on_torque(j, *io_frames.torque_data_fields(data))
        finally:
            self._outbox = None
        if lockstep.running and self._clock() < self._serve_by_s and self.io_settled():
            return outbox
        if outbox:
            self._data_frames(outbox)
        return None

    def _send_fault_emcy(self, emcy: Emcy) -> None:
        code, register, data = emcy
        self.send_emcy(code, register, data)


def run_plant_role(
    transport: TransportConfig,
    node_id: int = DEFAULT_PLANT_NODE_ID,
    stop: threading.Event | None = None,
    *,
    robot_mode: RobotMode = RobotMode.OFF,
    trace_path: str | None = None,
    summary_path: str | None = None,
    disturbance: str = DisturbanceKind.BOTH.label,
) -> str | None:
    """Plant process entry (``ilcrig plant``): the plant node on both buses of
    ``transport`` (a :class:`bus.transports.config.TransportConfig`), serving until SIGTERM/SIGINT or
    ``stop`` (a :class:`threading.Event`) is set; the buses are closed on the way out.
    Returns None, or why the node stopped early (a bus failed).

    The plant is the true plant (``plant.params.default_true_plant`` with the plant-uncertainty
    factors 0x2400:6..9, encoder and torque LSBs of :mod:`bus.units`), rebuilt only when the host
    changes Ts, the sub-steps or the factors; the disturbance is
    :func:`plant.disturbance.disturbance_torque`.  ``robot_mode``: the robot mode the node starts in
    (``ilcrig robot``), ``trace_path`` its period trace; on the way out the node's counters and the
    robot's session go to ``summary_path`` (JSON), if given. ``disturbance``: the kind the host
    will ask for, prepared before boot-up (:data:`PlantOptions.disturbance`).
    """
    from plant.disturbance import disturbance_torque
    from plant.params import PlantScales, default_true_plant, scaled_true_plant
    from plant.simulator import Plant, warm_up

    if stop is None:
        stop = threading.Event()
        install_sigterm(stop)
    fine_timer_slack()
    true_plant = default_true_plant()
    with numba_without_blas("plant role"):  # its kernels solve with their own LU: 0.3 s of CPU less at start
        logger.info("plant role: kernels ready in %.2f s", warm_up(true_plant))
    # the non-repetitive disturbance imports and runs scipy's filter design on first use: do it
    # now, before the boot-up frame, so that the first disturbed trial is not delayed by it (a
    # slow machine or a VM can take longer than the host's SDO timeout for that import); only for
    # the kind the host will ask for: scipy.signal is 1.4 s of CPU while every process starts
    t0 = time.perf_counter()
    disturbance_torque(disturbance, 0, 0, 2, 1e-3)
    logger.info("plant role: disturbance model (%s) ready in %.2f s", disturbance, time.perf_counter() - t0)

    def plant_factory(ts_s: float, substeps: int, scales: tuple[float, ...] | None = None) -> Plant:
        config = true_plant if scales is None else scaled_true_plant(true_plant, PlantScales(*scales))
        return Plant(config, ts_s, substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)

    fieldbus = transport.open("fieldbus")
    try:
        io = transport.open("io")
        try:
            scale = units.timeout_scale()
            node = PlantNode(
                fieldbus,
                io,
                plant_factory=plant_factory,
                disturbance_fn=disturbance_torque,
                node_id=node_id,
                tick_timeout_s=io_frames.TICK_TIMEOUT_S * scale,
                first_tick_timeout_s=io_frames.FIRST_TICK_TIMEOUT_S * scale,
                spin_s=PlantNode.REALTIME_SPIN_S,
                spin_when=spin_in_this_class,
                robot_mode=robot_mode,
                trace_path=trace_path,
                disturbance=disturbance,
            )
            freeze_heap("plant role")
            try:
                node.run(stop)
            finally:
                node.robot.close()
                if summary_path is not None:
                    _write_summary(Path(summary_path), node)
            return node.bus_error
        finally:
            quiet_shutdown(io)
    finally:
        quiet_shutdown(fieldbus)


def _write_summary(path: Path, node: PlantNode) -> None:
    """The node's counters and the robot's session as JSON (written atomically; a failure is logged)."""
    info = {"node": node.node_id, "bus_error": node.bus_error, **node.info()}
    try:
        atomic_write(path, json.dumps(info, indent=2) + "\n")
    except OSError as err:
        logger.error("cannot write the plant summary %s: %s", path, err)


@dataclass(frozen=True)
class PlantOptions:
    """The plant process's options (``ilcrig plant``, parsed by :mod:`host.cli.plant`)."""

    transport: TransportConfig
    node_id: int = DEFAULT_PLANT_NODE_ID
    robot_mode: RobotMode = RobotMode.OFF
    #: with a robot mode: the period trace file
    trace_path: str | None = None
    #: the node's counters as JSON on exit
    summary_path: str | None = None
    #: the disturbance kind (:data:`plant.disturbance.KINDS`) the host will ask for: prepared before
    #: boot-up; another kind is computed when a trial asks for it, its first one paying for the
    #: imports (a non-repetitive one: scipy.signal, ~1.4 s of CPU). ``both`` prepares every kind.
    disturbance: str = DisturbanceKind.BOTH.label


def run_plant(opts: PlantOptions) -> int:
    """The plant process: :func:`run_plant_role` with ``opts``; returns the exit code (3 when a bus
    failed and the node stopped early, 0 otherwise)."""
    lost = run_plant_role(
        opts.transport,
        node_id=opts.node_id,
        robot_mode=opts.robot_mode,
        trace_path=opts.trace_path,
        summary_path=opts.summary_path,
        disturbance=opts.disturbance,
    )
    return EXIT_FAULT if lost else EXIT_OK
