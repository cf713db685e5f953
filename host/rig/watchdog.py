"""The host's watchdog: everything it hears about the nodes and the bus turned into one fault.

This module owns :class:`Watchdog`, the one place where a fault of the rig is detected and
declared, whether a trial runs or not:

* it hears the nodes through :class:`host.rig.node_events.NodeEvents` (their heartbeats and EMCY
  frames, canopen's ``RemoteNode.nmt`` / ``RemoteNode.emcy`` callbacks) and the canopen
  notifier's errors and its own receiver's overflows (:class:`FieldbusErrors`: a frame the host's
  protocol side lost -- a boot-up, an SDO response, an EMCY -- is a fault of the run, as a bus
  error frame of the fieldbus, even when the channel monitors' receivers kept every frame);
* a thread (every :data:`WATCH_PERIOD_S`), or :meth:`Watchdog.watch_round` in the caller's thread,
  looks at what it has heard, the channels (:class:`host.rig.channels.RigChannels`) and the host's
  heartbeat producer and classifies the first fault visible (:mod:`host.rig.fault_classify`), in
  order: a bus gone, a channel's log stopped or a bus error frame, an EMCY, the host itself
  stopped for longer than the nodes' consumer time while they are NMT STOPPED (its heartbeat's gap,
  when no node's EMCY says so within :data:`STALL_SETTLE_S`; while they consume it and none reports
  its loss, they did not run either -- the whole machine stopped -- and the gap is kept in
  :attr:`Watchdog.stalls`, not a fault), a node's heartbeat lost or its boot-up, no node heard at all;
  a round that comes more than a consumer time after the last one (this process did not run)
  judges no heartbeat: the frames that queued meanwhile are read first;
* before the first :meth:`Watchdog.arm` (the nodes being brought up) a bus fault or a node's EMCY,
  and once it was called any fault, is declared: NMT STOP broadcast at once
  (torque off on every drive still alive), the record kept (the trial and the io channel's tick
  filled in, the injection that caused it attached), and the fault hooks run (the bench cancels
  its SDO requests and wakes a SYNC producer waiting for TPDOs); the main thread then ends the
  run through the experiment's one fault path (:meth:`Watchdog.raise_if_fault`).

It is armed from the bring-up on (once every node's heartbeat is watched) until the bench has
brought the drives to their safe state at its close, so a fault before the first trial, between
trials, after the last one and during the shutdown is declared like one during a trial.  Between
trials a lost node may be tolerated (``tolerate_lost_between_trials``, ``--recover``): then
heartbeats are not judged outside a trial and the bench brings the node up again.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import canopen

from bus.can_errors import is_receive_overflow
from bus.cia301.nmt import CONSUMER_TIME_MS, NODE_HEARTBEAT_MS, NmtCommand
from bus.errors import SdoAbort
from bus.run_queue import carrier_ledger
from bus.transports.config import FIELDBUS
from host.experiment.bench import TrialFault
from host.experiment.faults import FaultKind, FaultRecord, attach_injection, read_injections
from host.nodes.plant_client import PlantTrialFault
from host.nodes.sdo_access import SdoTransportError
from host.rig.channels import RigChannels
from host.rig.fault_classify import (
    BusError,
    ChannelTrouble,
    DetectionTimes,
    bus_fault,
    channel_fault,
    emcy_fault,
    heartbeat_fault,
    host_stall_fault,
    plant_trial_fault,
    sdo_fault,
    with_wall_time,
)
from host.rig.host_heartbeat import HostHeartbeat
from host.rig.node_events import NodeEvents

logger = logging.getLogger(__name__)

__all__ = ["EMCY_SETTLE_S", "STALL_SETTLE_S", "WATCH_PERIOD_S", "FieldbusErrors", "Watchdog", "nmt_stop_all"]

#: the watchdog's period, s
WATCH_PERIOD_S = 0.02
#: after a fault the bench saw itself, how long the host lets the nodes' EMCY frames arrive
#: before it decides what happened, s
EMCY_SETTLE_S = 0.05
#: after this process was stopped for longer than the nodes' consumer time, how long the host
#: waits for their EMCY 0x8130 (queued meanwhile) before it declares the host's loss itself, s
STALL_SETTLE_S = 0.2


def nmt_stop_all(network: canopen.Network) -> bool:
    """NMT STOP to all nodes (broadcast): torque off on every drive that hears it. False when it
    could not be sent (the bus is gone)."""
    try:
        network.nmt.send_command(NmtCommand.STOP)
        return True
    except (can.CanError, OSError, AttributeError) as exc:
        logger.info("NMT stop not sent: %s", exc)
        return False


class FieldbusErrors(can.Listener):
    """A listener on the canopen network's notifier that notes a failing fieldbus, and the bus
    error frames that say the network's own receiver lost frames (:func:`bus.can_errors.is_receive_overflow`:
    udp_multicast reports a datagram the kernel dropped on the host's socket so, SocketCAN a
    controller's receive overflow).

    :ivar overflows: such error frames heard; the first at ``overflow_t`` (monotonic, s)
    """

    def __init__(self) -> None:
        self.error: str | None = None
        self.error_t: float | None = None
        self.overflows = 0
        self.overflow_t: float | None = None

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame and is_receive_overflow(msg):
            if self.overflow_t is None:
                self.overflow_t = time.monotonic()
                logger.warning("the host's fieldbus receiver lost frames (receive overflow)")
            self.overflows += 1

    def on_error(self, exc: Exception) -> None:
        if self.error is None:
            self.error = f"{type(exc).__name__}: {exc}"
            self.error_t = time.monotonic()
            logger.warning("fieldbus failed: %s", self.error)
        time.sleep(0.1)


class Watchdog:
    """Fault detection and declaration for the rig (see the module docstring).

    :param network: the canopen network of the fieldbus (NMT STOP goes out on it)
    :param channels: the channel monitors (bus errors, logs, error frames, the io tick)
    :param bus_name: what a silent or lost bus is called in a fault: ``hub`` or the transport's name
    :param out_dir: the run folder, whose injection records a fault is matched with (None: none)
    :param scale: the timeout scale (``ILCRIG_TIMEOUT_SCALE``) of the consumer time
    :param tolerate_lost_between_trials: judge heartbeats only during a trial (``--recover``)
    :param t_start: the host's start (``time.monotonic()``, s), origin of the EMCY log's ``t_s``
    """

    def __init__(
        self,
        network: canopen.Network,
        channels: RigChannels,
        *,
        bus_name: str,
        out_dir: Path | None,
        scale: float,
        tolerate_lost_between_trials: bool = False,
        t_start: float | None = None,
    ) -> None:
        self.network = network
        self.channels = channels
        self.bus_name = bus_name
        self.out_dir = out_dir
        #: the host's consumer time of the nodes' heartbeats, s
        self.consumer_s = CONSUMER_TIME_MS / 1000.0 * scale
        #: the nodes' heartbeat period as the host allows for it, s
        self.period_s = NODE_HEARTBEAT_MS / 1000.0 * scale
        #: what the detectors wait for (the latencies of the records)
        self.times = DetectionTimes.scaled(scale)
        self.tolerate_lost_between_trials = tolerate_lost_between_trials
        #: the nodes' heartbeats and EMCY frames
        self.events = NodeEvents(
            self.consumer_s, time.monotonic() if t_start is None else t_start, carrier_ledger(getattr(network, "bus", None))
        )
        self.fieldbus_errors = FieldbusErrors()
        #: the host's heartbeat producer, whose failure is a lost bus (set by the bench)
        self.producer: HostHeartbeat | None = None
        #: the trial in progress or next (0-based), and whether it runs now
        self.trial = 0
        self.in_trial = False
        self._lock = threading.Lock()
        self._fault: FaultRecord | None = None
        self._declaring = False
        self._armed = False
        #: until the first :meth:`arm` (the run's start): a bus fault or a node's EMCY is declared
        #: already, by the thread's rounds too; heartbeats are not judged yet
        self._starting = True
        self._hooks: list[Callable[[FaultRecord], None]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_round: float | None = None
        #: when this process was last stopped for longer than the consumer time: (gap s, its end),
        #: and the trial then (its number, whether it ran)
        self._stall: tuple[float, float] | None = None
        self._stall_where = (0, False)
        #: from this time (``t_mono``) on the nodes are NMT STOPPED on purpose (the shutdown): a
        #: stall of the host that begins later costs them nothing
        self.stopped_at: float | None = None
        #: the host's stalls longer than the consumer time that no node reported while they consumed
        #: its heartbeat (they did not run either: the whole machine stopped), for the summary:
        #: ``{"what", "gap_ms", "trial", "in_trial", "t_end_mono"}`` -- not faults
        self.stalls: list[dict[str, object]] = []

    # -- the thread ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the watchdog thread (until :meth:`arm` it declares only a bus fault or a node's
        EMCY: the nodes are being brought up)."""
        self._thread = threading.Thread(target=self._loop, name="host watchdog", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Declare no more faults and end the thread."""
        self._armed = self._starting = False
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)

    def arm(self) -> None:
        """From now on any fault seen is declared (ends the run; again: nothing changes)."""
        if not self._armed and self.producer is not None:
            self.producer.take_gap(float("inf"))  # a gap before the nodes consumed the heartbeat counts for nothing
        self._armed = True
        self._starting = False

    def disarm(self) -> None:
        """Declare no more faults (the thread keeps running until :meth:`stop`)."""
        self._armed = self._starting = False

    def on_fault(self, hook: Callable[[FaultRecord], None]) -> None:
        """Run ``hook(record)`` when a fault is declared (after NMT STOP; in the declaring thread)."""
        self._hooks.append(hook)

    def _loop(self) -> None:
        self._last_round = time.monotonic()
        while not self._stop.wait(WATCH_PERIOD_S):
            try:
                self._round(time.monotonic())
            except Exception as exc:  # noqa: BLE001 - a watchdog that dies unseen would leave the run unwatched
                self._failed(exc)
                return

    def _failed(self, exc: Exception) -> None:
        """A round of the thread raised ``exc``: the run is no longer watched, which is the run's fault
        (declared, its traceback in the host's log), never a thread that ends unseen while the trials go on."""
        logger.error("the host's watchdog failed; the run is no longer watched", exc_info=exc)
        record = FaultRecord(
            FaultKind.TRIAL_FAULT,
            f"the host's watchdog failed ({type(exc).__name__}: {exc}): the run was no longer watched (the host's log has where)",
            node="host",
            detected_by="host",
            t_detected_mono=time.monotonic(),
        )
        try:
            self.declare(record)
        except Exception:  # noqa: BLE001 - the record stays the fault; what failed is in the log
            logger.exception("declaring the watchdog's failure failed")
            with self._lock:
                if self._fault is None:
                    self._fault = record

    # -- detection and declaration --------------------------------------------------------------
    @property
    def fault(self) -> FaultRecord | None:
        """The declared fault (the first), None while all is well."""
        return self._fault

    @property
    def fieldbus_ok(self) -> bool:
        """The fieldbus is open and the canopen notifier has seen no error on it."""
        return self.network.bus is not None and self.fieldbus_errors.error is None

    def watch_round(self) -> None:
        """One watchdog round in the caller's thread."""
        self._round(time.monotonic())

    def settle_and_check(self) -> None:
        """After a fault the bench saw itself: let the nodes' EMCY frames arrive (they say who saw
        it first), then one round."""
        if self._fault is None:
            time.sleep(EMCY_SETTLE_S)
            self.watch_round()

    def check_settled(self) -> None:
        """One round now, and while this process was stopped a moment ago (its heartbeat's gap)
        the rounds until the nodes' EMCY frames about it had time to arrive (before a trial, and at
        the run's end: a stop of the host is declared before anything goes on)."""
        self.watch_round()
        self.watch_round()  # the first round after a stop only lets the queued frames in
        deadline = time.monotonic() + STALL_SETTLE_S + WATCH_PERIOD_S
        while self._fault is None and self._stall is not None and time.monotonic() < deadline:
            time.sleep(WATCH_PERIOD_S)
            self.watch_round()

    def raise_if_fault(self) -> None:
        """:raises TrialFault: a fault was declared."""
        if self._fault is not None:
            raise TrialFault(self._fault.message, self._fault)

    @contextlib.contextmanager
    def during_trial(self, trial: int) -> Iterator[None]:
        """Mark ``trial`` as running while the block runs."""
        self.trial = trial
        self.in_trial = True
        try:
            yield
        finally:
            self.in_trial = False

    def _round(self, now: float) -> None:
        """One round at ``now``: after a gap of the rounds longer than the consumer time (this
        process did not run) every node counts as heard now, else the faults visible now are
        declared.  Two threads run rounds (the watchdog's, the trial loop's :meth:`watch_round`):
        the round that sees the gap takes it and applies the grace under one lock, so a round of the
        other thread that comes meanwhile waits for the grace instead of judging the heartbeats of
        before the gap (its own gap is the first one's end: it sees none)."""
        with self._lock:
            last, self._last_round = self._last_round, now
            gap_s = now - last if last is not None else 0.0
            if gap_s > self.consumer_s:
                # this process did not run (it was stopped): let the notifier read what queued up first
                self.events.grace(now)
        if gap_s > self.consumer_s:
            logger.info("the watchdog did not run for %.0f ms: the nodes' heartbeats judged from now", 1000 * gap_s)
            return
        record = self.detect(now)
        if record is not None:
            self.declare(record)

    def detect(self, now: float) -> FaultRecord | None:
        """The first fault visible now (None: all is well, or declared already; not armed: only a
        bus fault or an EMCY at the run's start, :attr:`_starting`)."""
        if self._fault is not None:
            return None
        if not self._armed:
            return self._cause_heard(now) if self._starting else None
        record = self._cause_heard(now)
        if record is not None:
            return record
        if self.producer is not None:
            gap = self.producer.take_gap(self.consumer_s)
            if gap is not None and (self.stopped_at is None or gap[1] - gap[0] < self.stopped_at):
                self._stall, self._stall_where = gap, (self.trial, self.in_trial)
        if self._stall is not None and now - self._stall[1] >= STALL_SETTLE_S:
            if self.stopped_at is not None:  # the nodes are STOPPED: they report no loss, the host's gap is the fault
                return host_stall_fault(*self._stall, self.times)
            self._note_stall(*self._stall)  # operational consumers, none lost the host: they did not run either
        if not self.in_trial and self.tolerate_lost_between_trials:
            return None  # between trials a lost node is waited for (recover)
        report, last = self.events.report(now), self.events.last_heard()
        return heartbeat_fault(report, last, now, consumer_s=self.consumer_s, period_s=self.period_s, bus_name=self.bus_name)

    def _note_stall(self, gap_s: float, t_end: float) -> None:
        """The host did not run for ``gap_s`` (ending at ``t_end``, ``t_mono``), longer than the
        nodes' consumer time, and no node's EMCY 0x8130 came within :data:`STALL_SETTLE_S` while
        every node consumed its heartbeat: they did not run either (the whole machine stopped: a
        virtual machine not scheduled, every process of the run stopped), and each judges its
        producers from when it ran again (:meth:`bus.cia301.nmt.NodeHeartbeatConsumer.grace`).
        Lockstep time stood still with them: not a fault, kept for the summary and logged."""
        self._stall = None
        trial, in_trial = self._stall_where
        where = f"in trial {trial}" if in_trial else f"before trial {trial}"
        what = (
            f"the host did not run for {1000 * gap_s:.0f} ms ({where}) and no node reported losing its heartbeat: "
            "the nodes did not run either (the whole machine was stopped); not a fault"
        )
        logger.warning("%s", what)
        self.stalls.append(
            {"what": what, "gap_ms": round(1000 * gap_s, 1), "trial": trial, "in_trial": in_trial, "t_end_mono": t_end}
        )

    def _bus_fault(self, now: float) -> FaultRecord | None:
        """A bus gone, a channel's log stopped or a bus error frame heard (None: none)."""
        errors: list[BusError] = []
        if self.fieldbus_errors.error is not None:
            errors.append(BusError(FIELDBUS, self.fieldbus_errors.error, self.fieldbus_errors.error_t))
        errors += self.channels.bus_errors()
        if self.producer is not None and self.producer.error is not None:
            errors.append(BusError(FIELDBUS, self.producer.error, self.producer.error_t))
        troubles = self.channels.troubles()
        own = self.fieldbus_errors
        if own.overflows:  # the host's own receiver: before the monitors' troubles
            own_lost = ChannelTrouble(
                FIELDBUS,
                error_frames=own.overflows,
                first_error_frame_t=own.overflow_t,
                overflows=own.overflows,
                first_overflow_t=own.overflow_t,
            )
            troubles = [own_lost, *troubles]
        return bus_fault(errors, self.bus_name, now) or channel_fault(troubles, now)

    def raise_if_start_fault(self) -> None:
        """While the nodes are brought up (their boot-ups and first SDO answers awaited; at the
        run's start the watchdog is not armed yet): a bus fault heard already (:meth:`_bus_fault`:
        a frame the host's receiver lost may have been the boot-up awaited) or a node's EMCY (a
        drive whose receiver lost the NMT command or the SDO request says so with EMCY 0x8110)
        is the run's fault now, declared and raised, not an answer awaited until ``--wait`` runs
        out.

        :raises TrialFault: a fault was declared (now or before)."""
        if self._fault is None:
            record = self._cause_heard(time.monotonic())
            if record is not None:
                self.declare(record)
        self.raise_if_fault()

    def _cause_heard(self, now: float) -> FaultRecord | None:
        """A bus fault (:meth:`_bus_fault`) or a node's EMCY heard and not declared yet (None: none)."""
        record = self._bus_fault(now)
        if record is None:
            pending = self.events.take_emcy()
            if pending:
                record = emcy_fault(min(pending, key=lambda f: f.t_mono), self.times)
        return record

    def declare(self, record: FaultRecord) -> None:
        """The run is over: keep ``record`` (the first fault), torque off everywhere at once (NMT
        STOP broadcast), run the fault hooks."""
        with self._lock:
            if self._fault is not None or self._declaring:
                return
            self._declaring = True
        nmt_stop_all(self.network)  # first: torque off
        if record.trial is None:
            record.trial = self.trial
        if record.tick is None:
            record.tick = self.channels.trial_tick(self.trial)
        with_wall_time(record)
        if self.out_dir is not None:
            attach_injection(record, read_injections(self.out_dir))
        with self._lock:
            self._fault = record
        logger.warning(
            "fault: %s (%s) at trial %s, tick %s, detected by %s",
            record.message,
            record.kind,
            record.trial,
            record.tick,
            record.detected_by,
        )
        for hook in self._hooks:
            hook(record)

    def describe(self, exc: BaseException, trial: int) -> FaultRecord | None:
        """What the host knows about ``exc``: the declared fault, else the record of the exception
        (the plant node's fault state, an SDO error), else None.  An SDO request that failed after
        a bus fault or a node's EMCY was heard (not declared yet: the watchdog not armed, or its
        round not come) failed because of it: that cause is declared and is the record (a lost SDO
        response after the host's receiver overflowed, a request that a drive's full receiver
        dropped and said so with EMCY 0x8110)."""
        if self._fault is not None:
            return self._fault
        now = time.monotonic()
        if isinstance(exc, PlantTrialFault):
            record = plant_trial_fault(exc, trial, now, self.times)
        elif isinstance(exc, SdoTransportError | SdoAbort):
            cause = self._cause_heard(now)
            if cause is not None:
                self.declare(cause)
                return self._fault
            record = sdo_fault(exc, trial, now)
        else:
            return None
        with_wall_time(record)
        if self.out_dir is not None:
            attach_injection(record, read_injections(self.out_dir))
        return record
