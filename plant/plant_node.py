"""The plant node: the plant as a CANopen slave on the fieldbus and the lockstep clock
master of the io channel.

This module owns :class:`PlantNode`: the trial protocol of the plant side of the rig
(architecture.md "Time and one trial") on top of the generic slave runtime
:class:`bus.cia301.slave.SlaveNode` (NMT, heartbeat, SDO server, EMCY).  Objects: ``bus/plant.eds``,
names and encodings: :mod:`bus.plant_objects`.  :func:`run_plant_role` is the ``ilcrig plant``
process entry; it builds the true plant and the disturbance model of ``plant/`` and passes them
to the node as two factories (tests pass their own):

* ``plant_factory(ts_s, substeps) -> plant`` — an object with ``reset(q0_rad, qd0_rad_s)``,
  ``encoder_counts() -> int (4,)`` [counts] and ``step(torque_units int64 (4,) [µN·m],
  disturbance_nm float64 (4,) [N·m])`` that raises on failure.  The plant is built once and
  kept while the control period and the sub-steps stay the same (and built once at
  :meth:`PlantNode.start`, before the boot-up frame, so compilation never delays a trial);
* ``disturbance_fn(kind, seed, trial, n_ticks, ts_s) -> (n_ticks, 4)`` [N·m], ``kind`` one of
  :class:`bus.plant_objects.DisturbanceKind` (``plant.disturbance.disturbance_torque``).

A trial (host writes 0x2410:3 = 1, start): the plant is reset to the initial state 0x2420,
the disturbance of (kind, seed, trial index, N, Ts) is computed, the TRIAL_START control frame
goes out, then per tick n = 0..N-1:

1. encoder frames of all joints with the counts of q(t_n) (wire tick = origin + n);
2. the four torque frames of tick n are collected; each drive's stream is followed by a
   :class:`bus.io_frames.TickTracker`: a missing, duplicated, stale or early frame, or a
   malformed one, is a fault, never silently used.  A torque frame with the FAULT status bit
   is applied as zero torque;
3. the plant integrates [t_n, t_n + Ts] with the four torques held and disturbance[n].

Real time (0x2400:5 pacing = 1, ``ilcrig run --realtime``): tick n's encoder frames are held
until t0 + n·Ts on the node clock (t0 = one period after TRIAL_START went out: the drives take the
start command in a period of its own, as a real drive's first cycle is the SYNC after the one that
armed it), the wait being part of the select loop (SDO is served meanwhile); a tick whose
torques arrive after t0 + (n + 1)·Ts is a deadline miss and the next tick starts late.  Either
way the trial's timing (duration, and when paced the misses and the lateness of the ticks,
:class:`plant.pacing.TickPacer`) is kept in 0x2440, and the first missed ticks in 0x2441.
Pacing delays frames only; what the plant computes is the same.  The select loop wakes
``spin_s`` before a held tick is due and waits the rest in a loop on the clock (the plant role:
:attr:`PlantNode.REALTIME_SPIN_S`): a timer wake-up comes about 0.1 ms late on the machines here,
a tenth of the period, while the drives wait for the plant at that moment and the core is free.

After tick N-1: TRIAL_STOP, status DONE.  The trial is event driven inside the slave's select
loop, so SDO requests (status polls) are answered during a trial by the same thread, between
ticks.  No answer within ``tick_timeout_s`` [s] (``first_tick_timeout_s`` for tick 0) is a fault
("drive j did not answer tick n").
A bus error frame on io during a trial (a frame damaged on the wire, e.g. ``--inject corrupt``) is a
BAD_FRAME fault.  The host's heartbeat is consumed (0x1016): losing it during a trial is a
HOST_LOST fault (EMCY 0x8130); a failing bus ends the node's loop (:meth:`bus_lost`).
A fault (plant error, tick error, timeout, host abort, host lost, NMT stop/reset) ends the trial:
TRIAL_STOP, one EMCY frame (:data:`bus.plant_objects.FAULT_EMCY`, manufacturer bytes
:func:`bus.plant_objects.fault_emcy_data`), status FAULT with code, tick and node in 0x2410;
the node keeps serving and the next start begins afresh.

The wire tick runs on across trials (each trial's ticks continue the previous ones), so a late
frame of an earlier trial is recognised as stale.  Wall-clock time is used for the tick timeout
and the trial-duration counter only, never in the model.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import can
import numpy as np
import numpy.typing as npt

from bus import io_frames, units
from bus.bus_features import batch_sender
from bus.cia301.nmt import NmtCommand, NmtState, next_state
from bus.cia301.object_store import ObjectStore, Value
from bus.cia301.slave import SlaveNode, install_sigterm
from bus.errors import AbortCode, SdoAbort
from bus.plant_objects import (
    DEFAULT_PLANT_NODE_ID,
    ERROR_REGISTER_INDEX,
    FAULT_EMCY,
    PLANT_EDS_PATH,
    ConfigSub,
    CounterSub,
    DeadlineMiss,
    DeadlineMisses,
    DisturbanceKind,
    InitialStateError,
    PlantCommand,
    PlantFault,
    PlantObj,
    PlantStatus,
    PlantTrialSub,
    TrialTiming,
    fault_emcy_data,
    pack_deadline_misses,
    pack_trial_timing,
    unpack_initial_state,
)
from bus.timer_slack import fine_timer_slack
from bus.transports.config import TransportConfig
from plant.pacing import TickPacer

logger = logging.getLogger(__name__)

_U32 = 0xFFFFFFFF
_TORQUE_LO = io_frames.TORQUE_COB_BASE
_TORQUE_HI = io_frames.TORQUE_COB_BASE + io_frames.N_JOINTS
_FAULT_BIT = int(io_frames.TorqueStatus.FAULT)


class PlantLike(Protocol):
    """The plant as the plant node uses it (``plant.simulator.Plant``)."""

    def reset(self, q0: np.ndarray, qd0: np.ndarray) -> None: ...

    def encoder_counts(self) -> np.ndarray: ...

    def step(self, torque_units: np.ndarray, disturbance_nm: np.ndarray) -> None: ...


PlantFactory = Callable[[float, int], PlantLike]
DisturbanceFn = Callable[[str, int, int, int, float], npt.ArrayLike]


class PlantNode(SlaveNode):
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
        clock in a loop, s (0: the select loop's timer alone; see the module docstring).
    """

    #: the plant role's ``spin_s``: the last part of the wait for a paced tick, spent in a loop
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
    ) -> None:
        if not 0.0 <= spin_s < 0.01:
            raise ValueError(f"spin_s must be in [0, 0.01) s, got {spin_s!r}")
        self.spin_s = float(spin_s)
        self.store = ObjectStore(eds_path, node_id)
        self._nmt_state = NmtState.PRE_OPERATIONAL
        super().__init__(self, fieldbus, io, node_id=node_id, clock=clock)
        self.plant_factory = plant_factory
        self.disturbance_fn = disturbance_fn
        self.tick_timeout_s = float(self.TICK_TIMEOUT_S if tick_timeout_s is None else tick_timeout_s)
        self.first_tick_timeout_s = float(
            max(self.FIRST_TICK_TIMEOUT_S if first_tick_timeout_s is None else first_tick_timeout_s, self.tick_timeout_s)
        )
        if not self.tick_timeout_s > 0:
            raise ValueError(f"tick_timeout_s must be > 0, got {tick_timeout_s!r}")
        self._plant: PlantLike | None = None
        self._plant_key: tuple[float, int] | None = None
        # trial state
        self._status = PlantStatus.IDLE
        self._fault = PlantFault.NONE
        self._fault_tick = 0
        self._fault_node = 0
        self._error_register = 0
        self.last_fault_message = ""
        self._pending_start = False
        self._running = False
        self._n_ticks = 0
        self._tick = 0  # tick n in progress
        self._origin = 0  # full wire tick of the trial's tick 0
        self._wire_next = 0  # full wire tick of the next trial's tick 0
        self._got = 0  # torque frames received for tick n
        self._deadline = 0.0
        self._t_start = 0.0
        self._pacer: TickPacer | None = None
        self._send_at: float | None = None  # paced: when the held encoder frames are due
        self._held_counts: np.ndarray | None = None
        self._timing = TrialTiming(False, 0, 0, 0, 0, 0, 0)
        self._misses = DeadlineMisses(0)
        self._tau = np.zeros(io_frames.N_JOINTS, dtype=np.int64)
        self._dist: np.ndarray = np.zeros((0, io_frames.N_JOINTS))
        # the four encoder frames of a tick go out in one write where the bus can (the hub)
        self._send_batch = batch_sender(io)
        self._trackers = [io_frames.TickTracker(0, f"torque frames of drive {j + 1}") for j in range(io_frames.N_JOINTS)]
        # counters (0x2430)
        self.io_sent = 0
        self.io_received = 0
        self.tick_timeouts = 0
        self.trials_done = 0
        self.last_trial_s = 0.0
        self._install_hooks()

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
            self._abort(f"NMT {cmd.name}")
        if cmd == NmtCommand.RESET_NODE:
            self.store.reset(0x2000, 0x5FFF)
            self._status = PlantStatus.IDLE
            self._fault = PlantFault.NONE
            self._fault_tick = self._fault_node = 0
            self._error_register = 0
            self.io_sent = self.io_received = self.tick_timeouts = self.trials_done = 0
            self.last_trial_s = 0.0
        if cmd in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self.store.reset(0x1000, 0x1FFF)
        self._nmt_state = next_state(self._nmt_state, cmd)
        return self._nmt_state

    def read_object(self, index: int, sub: int) -> bytes:
        return self.store.read_object(index, sub)

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        self.store.write_object(index, sub, data)

    def pop_emcy(self) -> list[tuple[int, int, bytes]]:
        """Always empty: the bench sends its EMCY frames at once (:meth:`SlaveNode.send_emcy`)."""
        return []

    def heartbeat_lost(self, node_id: int) -> None:
        """The heartbeat consumer lost ``node_id`` (the host): a running trial ends with
        HOST_LOST (EMCY 0x8130); outside a trial only the EMCY is sent (logged in NMT STOPPED)."""
        if self._nmt_state == NmtState.STOPPED:
            logger.info("node %d: heartbeat of node %d lost while NMT STOPPED", self.node_id, node_id)
            return
        if self._running or self._pending_start:
            self._fail(
                PlantFault.HOST_LOST,
                0,
                f"heartbeat of node {node_id} (the host) lost at tick {self._tick}",
                started=self._running,
            )
        else:
            code, register = FAULT_EMCY[PlantFault.HOST_LOST]
            logger.warning("node %d: heartbeat of node %d (the host) lost", self.node_id, node_id)
            self.send_emcy(code, register, fault_emcy_data(PlantFault.HOST_LOST, 0, self._tick))

    def bus_lost(self, reason: str) -> None:
        """A bus failed (the hub gone): the trial, if any, ends here (nothing can be sent)."""
        if self._running or self._pending_start:
            self._running = self._pending_start = False
            self._status = PlantStatus.FAULT
            self._fault = PlantFault.ABORTED
            self._fault_tick = self._tick
            logger.warning("node %d: trial aborted at tick %d: bus lost (%s)", self.node_id, self._tick, reason)

    # ------------------------------------------------------------------ public state

    @property
    def status(self) -> PlantStatus:
        return self._status

    @property
    def fault(self) -> PlantFault:
        return self._fault

    @property
    def ticks_done(self) -> int:
        return self._tick if self._status != PlantStatus.IDLE else 0

    # ------------------------------------------------------------------ objects

    def _install_hooks(self) -> None:
        r, w = self.store.read_hooks, self.store.write_hooks
        t = PlantObj.TRIAL
        r[(ERROR_REGISTER_INDEX, 0)] = lambda: self._error_register
        r[(t, PlantTrialSub.STATUS)] = lambda: int(self._status)
        r[(t, PlantTrialSub.TICKS_DONE)] = lambda: self.ticks_done & _U32
        r[(t, PlantTrialSub.FAULT_CODE)] = lambda: int(self._fault)
        r[(t, PlantTrialSub.FAULT_TICK)] = lambda: self._fault_tick & _U32
        r[(t, PlantTrialSub.FAULT_NODE)] = lambda: self._fault_node
        c = PlantObj.COUNTERS
        r[(c, CounterSub.IO_SENT)] = lambda: self.io_sent & _U32
        r[(c, CounterSub.IO_RECEIVED)] = lambda: self.io_received & _U32
        r[(c, CounterSub.TICK_TIMEOUTS)] = lambda: self.tick_timeouts & _U32
        r[(c, CounterSub.TRIALS_DONE)] = lambda: self.trials_done & _U32
        r[(c, CounterSub.LAST_TRIAL_US)] = lambda: min(int(self.last_trial_s * 1e6), _U32)
        r[(PlantObj.TRIAL_TIMING, 0)] = lambda: pack_trial_timing(self._timing)
        r[(PlantObj.DEADLINE_MISSES, 0)] = lambda: pack_deadline_misses(self._misses)
        for sub in ConfigSub:
            w[(PlantObj.CONFIG, sub)] = self._require_idle_hook(f"configuration 0x2400:{int(sub)}")
        w[(t, PlantTrialSub.TRIAL_INDEX)] = self._require_idle_hook("trial index")
        w[(t, PlantTrialSub.N_TICKS)] = self._require_idle_hook("number of ticks")
        w[(t, PlantTrialSub.COMMAND)] = self._on_command
        w[(PlantObj.INITIAL_STATE, 0)] = self._write_initial_state

    def _busy(self) -> bool:
        return self._running or self._pending_start

    def _require_idle_hook(self, what: str) -> Callable[[Value], None]:
        def hook(_value: Value) -> None:
            if self._busy():
                raise SdoAbort(AbortCode.DEVICE_STATE, f"{what} cannot change while a trial runs")

        return hook

    def _write_initial_state(self, value: Value) -> None:
        if self._busy():
            raise SdoAbort(AbortCode.DEVICE_STATE, "initial state cannot change while a trial runs")
        if not isinstance(value, bytes):  # the EDS makes 0x2420 a DOMAIN: decoded as bytes
            raise TypeError(f"initial state 0x2420 must be bytes, got {type(value).__name__}")
        data = bytes(value)
        try:
            unpack_initial_state(data)
        except InitialStateError as err:
            code = AbortCode.LENGTH_MISMATCH if "bytes" in str(err) else AbortCode.VALUE_RANGE
            raise SdoAbort(code, str(err)) from None

    def _on_command(self, value: Value) -> None:
        cmd = int(value)
        if cmd == PlantCommand.START:
            if self._busy():
                raise SdoAbort(AbortCode.DEVICE_STATE, "a trial is already running")
            if len(self.store.get_bytes(PlantObj.INITIAL_STATE)) == 0:
                raise SdoAbort(AbortCode.DEVICE_STATE, "initial state 0x2420 not set")
            # the trial begins after the SDO response is out (on_service), so the host gets
            # its answer at once; the status says RUNNING from now on
            self._pending_start = True
            self._status = PlantStatus.RUNNING
            self._fault = PlantFault.NONE
            self._fault_tick = self._fault_node = 0
            self._tick = 0
        elif cmd == PlantCommand.ABORT:
            self._abort("aborted by the host")
        else:  # the EDS limits make this unreachable over SDO
            raise SdoAbort(AbortCode.VALUE_RANGE, f"unknown plant node command {cmd}")

    # ------------------------------------------------------------------ loop hooks

    def start(self) -> None:
        """Build the plant for the default configuration (compiles it, if needed) and compute a
        disturbance once, then boot: what a first call costs (the disturbance's first imports
        scipy.signal, about a second) is paid here, not while the first trial's start holds the
        select loop that answers the host's SDO requests."""
        ts_s, substeps = self._config_ts_substeps()
        try:
            self._get_plant(ts_s, substeps)
        except Exception:  # a bad factory shows up again, as a fault, at the first trial
            logger.exception("node %d: building the plant failed", self.node_id)
        try:
            self.disturbance_fn(DisturbanceKind.BOTH.label, 0, 0, 2, ts_s)
        except Exception:  # a bad disturbance shows up again, as a fault, at the first trial
            logger.exception("node %d: computing a disturbance failed", self.node_id)
        super().start()

    def next_deadline(self) -> float | None:
        if not self._running:
            return None
        return self._send_at - self.spin_s if self._send_at is not None else self._deadline

    def on_service(self, now: float) -> None:
        if self._pending_start:
            self._pending_start = False
            self._begin_trial()
        elif self._running and self._send_at is not None:
            if self.spin_s and self._send_at - self.spin_s <= now < self._send_at:
                due = self._send_at
                while now < due:  # the last stretch on the clock (bounded by spin_s)
                    now = self._clock()
            if now >= self._send_at:  # paced: the held tick is due
                counts, self._held_counts, self._send_at = self._held_counts, None, None
                assert counts is not None
                self._send_encoders(counts)
        elif self._running and now >= self._deadline:
            missing = [j for j in range(io_frames.N_JOINTS) if self._trackers[j].next_tick == self._origin + self._tick]
            node = missing[0] + 1 if missing else 0
            self.tick_timeouts += 1
            self._fail(
                PlantFault.TICK_TIMEOUT,
                node,
                f"drive {node} did not answer tick {self._tick} within "
                f"{self.tick_timeout_s if self._tick else self.first_tick_timeout_s:g} s "
                f"(missing drives: {[j + 1 for j in missing]})",
            )

    def on_io(self, msg: can.Message) -> None:
        if msg.is_error_frame:  # a frame damaged on the wire: the receivers' controllers saw a CRC error
            if self._running:
                self._fail(PlantFault.BAD_FRAME, 0, f"tick {self._tick}: bus error frame on io (a damaged frame)")
            return
        cob = msg.arbitration_id
        if not _TORQUE_LO <= cob < _TORQUE_HI:
            return  # our own encoder/control frames echoed, or foreign frames
        self.io_received += 1
        if not self._running:
            logger.debug("node %d: torque frame 0x%03X outside a trial ignored", self.node_id, cob)
            return
        j = cob - _TORQUE_LO
        try:
            torque, wire, status = io_frames.torque_fields(msg)
            if io_frames.tick_diff(wire, self._origin) < 0:
                # an answer to a tick of an earlier (e.g. aborted) trial arriving late: wire ticks
                # keep counting across trials, so it cannot be mistaken for one of this trial
                logger.debug("node %d: late torque frame of drive %d from an earlier trial ignored", self.node_id, j + 1)
                return
            tick = self._trackers[j].accept(wire)
        except io_frames.TickError as err:
            self._fail(PlantFault.TICK_SEQUENCE, j + 1, f"tick {self._tick}: {err}")
            return
        except io_frames.IoFrameError as err:
            self._fail(PlantFault.BAD_FRAME, j + 1, f"tick {self._tick}: bad torque frame: {err}")
            return
        if tick != self._origin + self._tick:
            self._fail(PlantFault.TICK_SEQUENCE, j + 1, f"drive {j + 1} sent tick {tick - self._origin} during tick {self._tick}")
            return
        self._tau[j] = 0 if status & _FAULT_BIT else torque
        self._got += 1
        if self._got == io_frames.N_JOINTS:
            self._advance()

    # ------------------------------------------------------------------ trial

    def _config_ts_substeps(self) -> tuple[float, int]:
        period_us = int(self.store.get(PlantObj.CONFIG, ConfigSub.CONTROL_PERIOD_US))
        substeps = int(self.store.get(PlantObj.CONFIG, ConfigSub.SUBSTEPS))
        return period_us / 1_000_000, substeps

    def _get_plant(self, ts_s: float, substeps: int) -> PlantLike:
        key = (ts_s, substeps)
        if self._plant is None or self._plant_key != key:
            self._plant = None
            self._plant = self.plant_factory(ts_s, substeps)
            self._plant_key = key
            logger.info("node %d: plant built (Ts = %g s, %d sub-steps)", self.node_id, ts_s, substeps)
        return self._plant

    def _begin_trial(self) -> None:
        store = self.store
        ts_s, substeps = self._config_ts_substeps()
        kind = int(store.get(PlantObj.CONFIG, ConfigSub.DISTURBANCE))
        seed = int(store.get(PlantObj.CONFIG, ConfigSub.SEED))
        trial = int(store.get(PlantObj.TRIAL, PlantTrialSub.TRIAL_INDEX))
        n_ticks = int(store.get(PlantObj.TRIAL, PlantTrialSub.N_TICKS))
        q0, qd0 = unpack_initial_state(store.get_bytes(PlantObj.INITIAL_STATE))
        self._n_ticks = n_ticks
        self._tick = 0
        self._origin = self._wire_next
        self._t_start = self._clock()
        try:
            plant = self._get_plant(ts_s, substeps)
            dist = np.ascontiguousarray(
                self.disturbance_fn(DisturbanceKind(kind).label, seed, trial, n_ticks, ts_s), dtype=np.float64
            )
            if dist.shape != (n_ticks, io_frames.N_JOINTS):
                raise ValueError(f"disturbance has shape {dist.shape}, expected ({n_ticks}, 4)")
            plant.reset(q0, qd0)
            counts = plant.encoder_counts()
        except Exception as err:  # the plant is a plug-in: any failure is a trial fault
            self._fail(PlantFault.PLANT, 0, f"trial {trial} could not start: {type(err).__name__}: {err}", started=False)
            return
        self._dist = dist
        for tracker in self._trackers:
            tracker.reset(self._origin)
        self._error_register = 0
        self._running = True
        self._send_at = self._held_counts = None
        logger.info(
            "node %d: trial %d starts (N = %d, Ts = %g s, %d sub-steps, disturbance %s, seed %d)",
            self.node_id,
            trial,
            n_ticks,
            ts_s,
            substeps,
            DisturbanceKind(kind).label,
            seed,
        )
        paced = bool(store.get(PlantObj.CONFIG, ConfigSub.PACING))
        self._send_io(io_frames.encode_control(io_frames.ControlCommand.TRIAL_START, self._origin, n_ticks))
        if paced:
            # Tick 0 is due one period after the start command, as a real drive's first cycle is the
            # SYNC after the one that armed it: the drives take TRIAL_START in that period, not in tick 0's.
            self._pacer = TickPacer(ts_s, n_ticks, True, self._clock() + ts_s)
            self._hold(counts, self._pacer.due_s(0))
            return
        self._pacer = TickPacer(ts_s, n_ticks, False, self._clock())
        self._send_encoders(counts)

    def _hold(self, counts: np.ndarray, due_s: float) -> None:
        """Paced: keep the next tick's encoder counts until ``due_s`` (sent by :meth:`on_service`)."""
        self._send_at, self._held_counts = due_s, counts

    def _send_encoders(self, counts: np.ndarray) -> None:
        wire = self._origin + self._tick
        self._send_batch([io_frames.encode_encoder(j, wire, int(counts[j])) for j in range(io_frames.N_JOINTS)])
        self.io_sent += io_frames.N_JOINTS
        self.frames_out += io_frames.N_JOINTS
        self._got = 0
        now = self._clock()
        if self._pacer is not None:
            self._pacer.started(self._tick, now)
        self._deadline = now + (self.tick_timeout_s if self._tick else self.first_tick_timeout_s)

    def _advance(self) -> None:
        """All four torques of tick n are in: integrate [t_n, t_n + Ts], then tick n + 1."""
        n = self._tick
        plant = self._plant
        assert plant is not None
        try:
            plant.step(self._tau, self._dist[n])
            counts = plant.encoder_counts() if n + 1 < self._n_ticks else None
        except Exception as err:  # the plant is a plug-in: any failure is a trial fault
            self._fail(PlantFault.PLANT, 0, f"plant error at tick {n}: {type(err).__name__}: {err}")
            return
        self._tick = n + 1
        pacer = self._pacer
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
        self._running = False
        self._stop_io()
        self._status = PlantStatus.DONE
        self.trials_done += 1
        self.last_trial_s = self._clock() - self._t_start
        self._record_timing()
        logger.info(
            "node %d: trial done, %d ticks in %.3f s (%.0f ticks/s)",
            self.node_id,
            self._n_ticks,
            self.last_trial_s,
            self._n_ticks / self.last_trial_s if self.last_trial_s > 0 else 0.0,
        )

    def _record_timing(self) -> None:
        """Keep the ended trial's timing for 0x2440."""
        if self._pacer is None:
            return
        r = self._pacer.result()
        self._timing = TrialTiming(
            r.paced,
            r.ticks,
            round(r.duration_s * 1e6),
            r.deadline_misses,
            round(r.lateness_p50_s * 1e6),
            round(r.lateness_p99_s * 1e6),
            round(r.lateness_max_s * 1e6),
        )
        # t0 on the node clock (CLOCK_MONOTONIC in the role): a tool on the machine can match the
        # misses with a kernel trace of the same clock (benchmarks/rt_attribution.py)
        self._misses = DeadlineMisses(
            round(r.t0_s * 1e9) if r.paced else 0,
            tuple(DeadlineMiss(m.tick, round(m.started_late_s * 1e6), round(m.overrun_s * 1e6)) for m in r.missed),
        )
        if r.paced:
            logger.info(
                "node %d: paced trial: %d deadline misses, lateness p50 %.0f µs, p99 %.0f µs, max %.0f µs",
                self.node_id,
                r.deadline_misses,
                r.lateness_p50_s * 1e6,
                r.lateness_p99_s * 1e6,
                r.lateness_max_s * 1e6,
            )

    def _stop_io(self) -> None:
        self._send_io(io_frames.encode_control(io_frames.ControlCommand.TRIAL_STOP, self._origin + self._tick, self._n_ticks))
        self._wire_next = self._origin + self._tick + 1

    def _abort(self, why: str) -> None:
        if self._running or self._pending_start:
            self._fail(PlantFault.ABORTED, 0, f"trial {why} at tick {self._tick}", started=self._running)

    def _fail(self, fault: PlantFault, node: int, message: str, *, started: bool = True) -> None:
        """End the trial with ``fault``: TRIAL_STOP (if started), EMCY, status FAULT."""
        self._running = False
        self._pending_start = False
        self._send_at = self._held_counts = None
        if started:
            self._stop_io()
            self._record_timing()
        self._status = PlantStatus.FAULT
        self._fault = fault
        self._fault_tick = self._tick
        self._fault_node = node
        self.last_fault_message = message
        self.last_trial_s = self._clock() - self._t_start
        code, register = FAULT_EMCY[fault]
        self._error_register = register
        logger.warning("node %d: trial fault %s: %s", self.node_id, fault.name, message)
        self.send_emcy(code, register, fault_emcy_data(fault, node, self._tick))

    def _send_io(self, msg: can.Message) -> None:
        self.io.send(msg)
        self.io_sent += 1
        self.frames_out += 1

    # ------------------------------------------------------------------ info

    def info(self) -> dict[str, Any]:
        """Counters and the last fault, for logs and summaries."""
        return {
            "status": self._status.name,
            "fault": self._fault.name,
            "fault_message": self.last_fault_message,
            "io_sent": self.io_sent,
            "io_received": self.io_received,
            "tick_timeouts": self.tick_timeouts,
            "trials_done": self.trials_done,
            "last_trial_s": self.last_trial_s,
        }


def run_plant_role(
    transport: TransportConfig, node_id: int = DEFAULT_PLANT_NODE_ID, stop: threading.Event | None = None
) -> str | None:
    """Plant process entry (``ilcrig plant``): the plant node on both buses of
    ``transport`` (a :class:`bus.transports.config.TransportConfig`), serving until SIGTERM/SIGINT or
    ``stop`` (a :class:`threading.Event`) is set; the buses are closed on the way out.
    Returns None, or why the node stopped early (a bus failed).

    The plant is the true plant (``plant.params.default_true_plant``, encoder and
    torque LSBs of :mod:`bus.units`), rebuilt only when the host changes Ts or the sub-steps;
    the disturbance is :func:`plant.disturbance.disturbance_torque`.
    """
    from plant.disturbance import disturbance_torque
    from plant.params import default_true_plant
    from plant.simulator import Plant, warm_up

    if stop is None:
        stop = threading.Event()
        install_sigterm(stop)
    fine_timer_slack()
    true_plant = default_true_plant()
    logger.info("plant role: kernels ready in %.2f s", warm_up(true_plant))
    # the non-repetitive disturbance imports and runs scipy's filter design on first use: do it
    # now, before the boot-up frame, so that the first disturbed trial is not delayed by it (a
    # slow machine or a VM can take longer than the host's SDO timeout for that import)
    t0 = time.perf_counter()
    disturbance_torque("both", 0, 0, 2, 1e-3)
    logger.info("plant role: disturbance model ready in %.2f s", time.perf_counter() - t0)

    def plant_factory(ts_s: float, substeps: int) -> Plant:
        return Plant(true_plant, ts_s, substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)

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
            )
            node.run(stop)
            return node.bus_error
        finally:
            _quiet_shutdown(io)
    finally:
        _quiet_shutdown(fieldbus)


def _quiet_shutdown(bus: can.BusABC) -> None:
    """Close a bus that may have failed already (the hub gone): never raise on the way out."""
    try:
        bus.shutdown()
    except (can.CanError, OSError) as err:
        logger.debug("closing %s: %s", bus, err)
