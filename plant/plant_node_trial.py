"""The plant node's trial protocol: the lockstep tick master of the io channel, with pacing.

Owns :class:`LockstepMaster` (architecture.md "Time and one trial"): the tick in progress, the
torque frames collected for it, the tick timeouts, real-time pacing
(:class:`plant.pacing.TickPacer`) and the io counters (0x2430).  It steps the trial's plant and
disturbance (:class:`plant.plant_node_model.TrialModel`), sends io frames through the node
(:mod:`plant.plant_node`) and reports the outcome, timing included (0x2440, 0x2441), to
:class:`plant.plant_node_status.TrialStatus`.

A trial (host writes 0x2410:3 = 1, start; :meth:`LockstepMaster.request_start`, begun by
:meth:`LockstepMaster.service` once the SDO response is out): the plant is reset to the initial
state 0x2420, the disturbance of (kind, seed, trial index, N, Ts) is computed, the TRIAL_START
control frame goes out, then per tick n = 0..N-1:

1. encoder frames of all joints with the counts of q(t_n) (wire tick = origin + n);
2. the four torque frames of tick n are collected (:meth:`LockstepMaster.on_io`); each drive's
   stream is followed by a :class:`bus.io_frames.TickTracker`: a missing, duplicated, stale or
   early frame, or a malformed one, is a fault, never silently used.  A torque frame with the
   FAULT status bit is applied as zero torque;
3. the plant integrates [t_n, t_n + Ts] with the four torques held and disturbance[n].

From TRIAL_START to TRIAL_STOP the plant asks its io transport to deliver the frames for it four
at a time (``gather``; the hub's gather record, :mod:`bus.transports.hub.wire`): the four torques
of a tick wake the plant once, not once per drive.

After tick N-1: TRIAL_STOP, status DONE.  No answer within ``tick_timeout_s`` [s]
(``first_tick_timeout_s`` for tick 0) is a TICK_TIMEOUT fault; a bus error frame on io is
BAD_FRAME, one that says the plant's io receiver overflowed (frames lost, :mod:`bus.can_errors`)
IO_FRAMES_LOST, at once; a plant that raises is PLANT.  A fault ends the trial: TRIAL_STOP (if it had
started), one EMCY, status FAULT.  The wire tick runs on across trials, so a late frame of an
earlier trial is recognised as stale.

Real time (0x2400:5 pacing = 1): tick n's encoder frames are held until t0 + n·Ts on the node
clock (t0 = one period after TRIAL_START went out: the drives take the start command in a period
of its own, as a real drive's first cycle is the SYNC after the one that armed it); the node's
select loop wakes ``spin_s`` before a held tick is due and :meth:`LockstepMaster.service` waits
the rest in a loop on the clock (in the trials ``spin_when`` allows: the plant role's, only in a
real-time scheduling class), or sleeps until the due time.  A tick whose torques arrive after t0 + (n + 1)·Ts is a deadline
miss and the next tick starts late.  Pacing delays frames only; what the plant computes is the
same.  Wall-clock time is used for the tick timeout and the trial timing only, never in the model.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import can
import numpy as np

from bus import io_frames
from bus.can_errors import is_receive_overflow
from bus.cia301.object_store import ObjectStore
from bus.plant_objects import (
    PLANT_SCALE_SUBS,
    ConfigSub,
    DisturbanceKind,
    PlantFault,
    PlantObj,
    PlantStatus,
    PlantTrialSub,
    unpack_initial_state,
)
from plant.pacing import TickPacer
from plant.plant_node_model import TrialModel
from plant.plant_node_status import Emcy, TrialStatus

logger = logging.getLogger(__name__)

_N = io_frames.N_JOINTS
_TORQUE_LO = io_frames.TORQUE_COB_BASE
_TORQUE_HI = io_frames.TORQUE_COB_BASE + _N
_FAULT_BIT = int(io_frames.TorqueStatus.FAULT)


class LockstepMaster:
    """The trials of the plant node (see the module docstring).

    :param node_id: CANopen node id (log messages).
    :param store: the node's object store (configuration 0x2400, trial 0x2410, initial state 0x2420).
    :param status: where the outcome of each trial goes.
    :param model: the plant and the disturbance of the trials.
    :param send: sends one io frame; ``send_batch`` sends the four encoder frames of a tick
        ((COB-ID, data) pairs, :class:`bus.bus_features.DataFrameSender`).
    :param send_emcy: sends one EMCY ``(error code, error register, data)``.
    :param gather: asks the io transport to deliver the frames for the plant n at a time
        (:func:`bus.bus_features.frame_gatherer`): 4 from a trial's start (the torques of a tick
        come in one wake-up), 0 once it stopped; None: every frame as it comes.
    :param clock: monotonic time source [s].
    :param tick_timeout_s: longest wait for the torque frames of one tick, s; ``first_tick_timeout_s``
        the same for tick 0.
    :param spin_s: real time: the last part of the wait for a held tick, spent in a loop on the clock, s.
    :param spin_when: asked at the start of each paced trial: whether to spin ``spin_s`` in it (None:
        always). The plant role spins only in a real-time scheduling class: in normal scheduling the
        spinning would count against the process's fair share, and a process that used more
        than its share waits for the CPU when it wakes (docs/timing.md §1).
    """

    def __init__(
        self,
        node_id: int,
        store: ObjectStore,
        status: TrialStatus,
        model: TrialModel,
        *,
        send: Callable[[can.Message], None],
        send_batch: Callable[[list[tuple[int, bytes]]], None],
        send_emcy: Callable[[Emcy], None],
        gather: Callable[[int], None] | None = None,
        clock: Callable[[], float],
        tick_timeout_s: float,
        first_tick_timeout_s: float,
        spin_s: float,
        spin_when: Callable[[], bool] | None = None,
    ) -> None:
        self.node_id = node_id
        self.store = store
        self.status = status
        self.model = model
        self._send = send
        self._send_batch = send_batch
        self._send_emcy = send_emcy
        self._gather = gather
        self._clock = clock
        self.tick_timeout_s = tick_timeout_s
        self.first_tick_timeout_s = first_tick_timeout_s
        self.spin_s = spin_s
        self._spin_when = spin_when
        self._spin_s = spin_s  # of the trial in progress
        self.pending_start = False
        self.running = False
        self.n_ticks = 0
        self.tick = 0  # tick n in progress
        self._origin = 0  # full wire tick of the trial's tick 0
        self._wire_next = 0  # full wire tick of the next trial's tick 0
        self._got = 0  # torque frames received for tick n
        self._deadline = 0.0
        self._t_start = 0.0
        self.pacer: TickPacer | None = None
        self._send_at: float | None = None  # paced: when the held encoder frames are due
        self._held_counts: np.ndarray | None = None
        self._tau = np.zeros(_N, dtype=np.int64)
        self._trackers = [io_frames.TickTracker(0, f"torque frames of drive {j + 1}") for j in range(_N)]
        self.reset_counters()

    def reset_counters(self) -> None:
        """0x2430 counters to 0 (NMT reset node)."""
        self.io_sent = 0
        self.io_received = 0
        self.tick_timeouts = 0
        self.trials_done = 0

    @property
    def ticks_done(self) -> int:
        """0x2410:5: plant steps completed in the current or last trial (0 before the first)."""
        return self.tick if self.status.status != PlantStatus.IDLE else 0

    @property
    def busy(self) -> bool:
        """True from the start command to the end of the trial."""
        return self.running or self.pending_start

    # ------------------------------------------------------------------ configuration

    def config_ts_substeps(self) -> tuple[float, int]:
        """(Ts [s], RK4 sub-steps) of the configuration 0x2400."""
        period_us = int(self.store.get(PlantObj.CONFIG, ConfigSub.CONTROL_PERIOD_US))
        substeps = int(self.store.get(PlantObj.CONFIG, ConfigSub.SUBSTEPS))
        return period_us / 1_000_000, substeps

    def claim_wire_tick(self) -> int:
        """The wire tick of one io exchange outside a trial (a period of the robot,
        :mod:`plant.plant_node_robot`); the next trial starts after it."""
        wire = self._wire_next
        self._wire_next = wire + 1
        return wire

    # ------------------------------------------------------------------ loop hooks

    def request_start(self) -> None:
        """The start command was accepted: the trial begins after the SDO response is out (at the
        next :meth:`service`); the status says RUNNING from now on."""
        self.pending_start = True
        self.status.begin()
        self.tick = 0

    @property
    def _tick_timeout_s(self) -> float:
        """The current tick's deadline after its encoder frames, s (tick 0's is longer)."""
        return self.tick_timeout_s if self.tick else self.first_tick_timeout_s

    def grace(self, now: float) -> None:
        """The plant did not run until ``now`` (:meth:`plant.plant_node.PlantNode.after_stall`): the
        tick's torques get their time from now."""
        if self.running:
            self._deadline = max(self._deadline, now + self._tick_timeout_s)

    def next_deadline(self) -> float | None:
        """Clock time [s] by which :meth:`service` must run (None: no trial)."""
        if not self.running:
            return None
        return self._send_at - self._spin_s if self._send_at is not None else self._deadline

    def service(self, now: float) -> None:
        """Begin a requested trial, send a held tick that is due, or detect a tick timeout."""
        if self.pending_start:
            self.pending_start = False
            self._begin()
        elif self.running and self._send_at is not None:
            if self._spin_s and self._send_at - self._spin_s <= now < self._send_at:
                due = self._send_at
                while now < due:  # the last stretch on the clock (bounded by spin_s)
                    now = self._clock()
            if now >= self._send_at:  # paced: the held tick is due
                counts, self._held_counts, self._send_at = self._held_counts, None, None
                assert counts is not None
                self._send_encoders(counts)
        elif self.running and now >= self._deadline:
            missing = [j for j in range(_N) if self._trackers[j].next_tick == self._origin + self.tick]
            node = missing[0] + 1 if missing else 0
            self.tick_timeouts += 1
            self.fail(
                PlantFault.TICK_TIMEOUT,
                node,
                f"drive {node} did not answer tick {self.tick} within "
                f"{self._tick_timeout_s:g} s "
                f"(missing drives: {[j + 1 for j in missing]})",
            )

    def on_io(self, msg: can.Message) -> None:
        """One io frame: a torque frame of the tick in progress, or a fault."""
        if msg.is_error_frame:
            if not self.running:
                return
            if is_receive_overflow(msg):  # this receiver dropped frames: a torque frame never comes
                self.fail(
                    PlantFault.IO_FRAMES_LOST, 0, f"tick {self.tick}: io frames lost in the plant's receiver (receive overflow)"
                )
            else:  # a frame damaged on the wire: the receivers' controllers saw a CRC error
                self.fail(PlantFault.BAD_FRAME, 0, f"tick {self.tick}: bus error frame on io (a damaged frame)")
            return
        cob = msg.arbitration_id
        if not _TORQUE_LO <= cob < _TORQUE_HI:
            return  # our own encoder/control frames echoed, or foreign frames
        self.io_received += 1
        if not self.running:
            logger.debug("node %d: torque frame 0x%03X outside a trial ignored", self.node_id, cob)
            return
        j = cob - _TORQUE_LO
        try:
            torque, wire, status = io_frames.torque_fields(msg)
        except io_frames.IoFrameError as err:
            self.fail(PlantFault.BAD_FRAME, j + 1, f"tick {self.tick}: bad torque frame: {err}")
            return
        self.on_torque(j, torque, wire, status)

    def on_torque(self, j: int, torque: int, wire: int, status: int) -> None:
        """The fields of a well-formed torque frame of drive ``j + 1`` during a trial (:meth:`on_io`;
        the plant node's frames read in C, :meth:`plant.plant_node.PlantNode.step`)."""
        try:
            if io_frames.tick_diff(wire, self._origin + self.tick) < -self.tick:
                # an answer to a tick of an earlier (e.g. aborted) trial arriving late: wire ticks
                # keep counting across trials, so it is further back than this trial's tick 0 (the
                # distance is taken from the current tick: a trial may be longer than the wire
                # counter's half range of 2**15 ticks)
                logger.debug("node %d: late torque frame of drive %d from an earlier trial ignored", self.node_id, j + 1)
                return
            tick = self._trackers[j].accept(wire)
        except io_frames.TickError as err:
            self.fail(PlantFault.TICK_SEQUENCE, j + 1, f"tick {self.tick}: {err}")
            return
        except io_frames.IoFrameError as err:
            self.fail(PlantFault.BAD_FRAME, j + 1, f"tick {self.tick}: bad torque frame: {err}")
            return
        if tick != self._origin + self.tick:
            self.fail(PlantFault.TICK_SEQUENCE, j + 1, f"drive {j + 1} sent tick {tick - self._origin} during tick {self.tick}")
            return
        self._tau[j] = 0 if status & _FAULT_BIT else torque
        self._got += 1
        if self._got == _N:
            self._advance()

    # ------------------------------------------------------------------ the trial

    def _begin(self) -> None:
        store = self.store
        ts_s, substeps = self.config_ts_substeps()
        kind = int(store.get(PlantObj.CONFIG, ConfigSub.DISTURBANCE))
        seed = int(store.get(PlantObj.CONFIG, ConfigSub.SEED))
        trial = int(store.get(PlantObj.TRIAL, PlantTrialSub.TRIAL_INDEX))
        n_ticks = int(store.get(PlantObj.TRIAL, PlantTrialSub.N_TICKS))
        q0, qd0 = unpack_initial_state(store.get_bytes(PlantObj.INITIAL_STATE))
        self.n_ticks = n_ticks
        self.tick = 0
        self._origin = self._wire_next
        self._t_start = self._clock()
        try:
            label = DisturbanceKind(kind).label
            scales = tuple(float(store.get(PlantObj.CONFIG, sub)) for sub in PLANT_SCALE_SUBS)
            counts = self.model.begin(ts_s, substeps, label, seed, trial, n_ticks, q0, qd0, scales)
        except Exception as err:  # the plant is a plug-in: any failure is a trial fault
            self.fail(PlantFault.PLANT, 0, f"trial {trial} could not start: {type(err).__name__}: {err}", started=False)
            return
        for tracker in self._trackers:
            tracker.reset(self._origin)
        self.status.error_register = 0
        self.running = True
        self._send_at = self._held_counts = None
        logger.info(
            "node %d: trial %d starts (N = %d, Ts = %g s, %d sub-steps, disturbance %s, seed %d)",
            self.node_id,
            trial,
            n_ticks,
            ts_s,
            substeps,
            label,
            seed,
        )
        paced = bool(store.get(PlantObj.CONFIG, ConfigSub.PACING))
        self._spin_s = self.spin_s if paced and (self._spin_when is None or self._spin_when()) else 0.0
        if self._gather is not None:  # before TRIAL_START: the hub takes it first
            self._gather(_N)
        self._send_io(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, self._origin, n_ticks))
        if paced:
            # Tick 0 is due one period after the start command, as a real drive's first cycle is the
            # SYNC after the one that armed it: the drives take TRIAL_START in that period, not in tick 0's.
            self.pacer = TickPacer(ts_s, n_ticks, True, self._clock() + ts_s)
            self._hold(counts, self.pacer.due_s(0))
            return
        self.pacer = TickPacer(ts_s, n_ticks, False, self._clock())
        self._send_encoders(counts)

    def _hold(self, counts: np.ndarray, due_s: float) -> None:
        """Paced: keep the next tick's encoder counts until ``due_s`` (sent by :meth:`service`)."""
        self._send_at, self._held_counts = due_s, counts

    def _send_encoders(self, counts: np.ndarray) -> None:
        wire = self._origin + self.tick
        self._send_batch(io_frames.encoder_frames(wire, counts.tolist()))
        self.io_sent += _N
        self._got = 0
        now = self._clock()
        if self.pacer is not None:
            self.pacer.started(self.tick, now)
        self._deadline = now + self._tick_timeout_s

    def _advance(self) -> None:
        """All four torques of tick n are in: integrate [t_n, t_n + Ts], then tick n + 1."""
        n = self.tick
        try:
            counts = self.model.step(n, self._tau, last=n + 1 == self.n_ticks)
        except Exception as err:  # the plant is a plug-in: any failure is a trial fault
            self.fail(PlantFault.PLANT, 0, f"plant error at tick {n}: {type(err).__name__}: {err}")
            return
        self.tick = n + 1
        pacer = self.pacer
        if pacer is not None:
            now = self._clock()
            pacer.completed(n, now)
            if counts is not None and pacer.paced and now < pacer.due_s(n + 1):
                self._hold(counts, pacer.due_s(n + 1))
                return
        if counts is None:
            self._finish()
        else:
            self._send_encoders(counts)

    def _finish(self) -> None:
        self.running = False
        self._stop_io()
        self.trials_done += 1
        duration_s = self._clock() - self._t_start
        self.status.done(duration_s)
        if self.pacer is not None:
            self.status.record_timing(self.pacer)
        rate = self.n_ticks / duration_s if duration_s > 0 else 0.0
        logger.info("node %d: trial done, %d ticks in %.3f s (%.0f ticks/s)", self.node_id, self.n_ticks, duration_s, rate)

    def _stop_io(self) -> None:
        self._send_io(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, self._origin + self.tick, self.n_ticks))
        self._wire_next = self._origin + self.tick + 1
        if self._gather is not None:  # outside a trial every frame comes as it comes
            self._gather(0)

    def _send_io(self, msg: can.Message) -> None:
        self._send(msg)
        self.io_sent += 1

    # ------------------------------------------------------------------ ending early

    def abort(self, why: str) -> None:
        """End a started or requested trial with ABORTED (the host's abort command, NMT stop/reset)."""
        if self.busy:
            self.fail(PlantFault.ABORTED, 0, f"trial {why} at tick {self.tick}", started=self.running)

    def fail(self, fault: PlantFault, node: int, message: str, *, started: bool = True) -> None:
        """End the trial with ``fault`` involving drive ``node`` (0: none): TRIAL_STOP (if
        ``started``), status FAULT, EMCY."""
        self.running = False
        self.pending_start = False
        self._send_at = self._held_counts = None
        if started:
            self._stop_io()
            if self.pacer is not None:
                self.status.record_timing(self.pacer)
        emcy = self.status.fault(fault, node, self.tick, message, self._clock() - self._t_start)
        self._send_emcy(emcy)

    def bus_lost(self, reason: str) -> None:
        """A bus failed: the trial, if any, ends here (nothing can be sent)."""
        if self.busy:
            self.running = self.pending_start = False
            self.status.bus_lost(self.tick)
            logger.warning("node %d: trial aborted at tick %d: bus lost (%s)", self.node_id, self.tick, reason)
