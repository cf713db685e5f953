"""The host on the real (emulated) fieldbus: a :class:`host.experiment.loop.Bench` whose four drives
and plant are other processes, reached only over CAN with the ``canopen`` library.

* every node is a ``canopen.RemoteNode`` built from its EDS (bus/drive.eds, bus/bench.eds); the
  host reads and writes objects by SDO (block transfer for tables and recorder data), so the
  hand-written drives are checked against an independent CANopen implementation;
* heartbeats both ways (timing: :mod:`bus.cia301.nmt`): the host is node 127 and produces its
  heartbeat (0x77F) from its own thread (:class:`HostHeartbeat`, sent with canopen's
  ``Network.send_message``); it gives every node a producer period (0x1017) and a consumer entry
  for itself (0x1016:1), so the nodes notice its loss; it consumes the nodes' heartbeats
  (canopen's ``RemoteNode.nmt`` callbacks into :class:`bus.cia301.nmt.HeartbeatConsumer`);
* a watchdog thread (every :data:`WATCH_PERIOD_S`) turns whatever it sees into one
  :class:`host.experiment.faults.FaultRecord` — a node's heartbeat lost (a dead or stalled
  process), no node heard at all (the hub stalled), the bus gone (the hub dead), an EMCY (a drive
  fault, a lost, late, duplicated or damaged io frame reported by the test bench or a drive, the
  host's own loss reported by the nodes), a bus error frame, a full disk under the candump logs.
  At once it broadcasts NMT STOP (torque off on every drive still alive) and cancels the SDO
  requests of the main thread (:meth:`host.nodes.sdo_access.SdoAccess.cancel`), which then ends
  the run through the experiment's one fault path;
* :meth:`RigBench.close` brings every drive still alive to a torque-free state (after a
  completed run: CiA 402 disable voltage, then NMT STOP; after a fault: NMT STOP) and takes the
  evidence from the bus: each live drive's next heartbeat reporting STOPPED
  (:meth:`RigBench.safe_state`, into the summary);
* a passive monitor (a second python-can bus per channel, i.e. an ordinary bus member) counts
  frames and bits per channel, writes candump logs with python-can's own writer (a full disk
  stops the log and is a fault) and follows the io channel's trial and tick (for the faults'
  ``tick``).

:func:`run_host_role` is the ``ilcrig host`` entry point (also what ``ilcrig run`` starts).
"""

from __future__ import annotations

import functools
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any, cast

import can
import canopen
import numpy as np

from bus import io_frames
from bus.bench_objects import BENCH_EDS_PATH, BenchFault
from bus.bench_objects import DEFAULT_BENCH_NODE_ID as BENCH_NODE_ID
from bus.busload import BusLoadCounter
from bus.canlog import open_log
from bus.cia301.nmt import (
    CONSUMER_HEARTBEAT_INDEX,
    CONSUMER_TIME_MS,
    HOST_HEARTBEAT_MS,
    HOST_NODE_ID,
    NODE_HEARTBEAT_MS,
    HeartbeatConsumer,
    NmtCommand,
    NmtState,
    consumer_entry,
    heartbeat_cob_id,
)
from bus.errors import IlcrigError, SdoAbort
from bus.objects import DRIVE_EDS_PATH, DRIVE_NODE_IDS
from bus.transports.config import FIELDBUS, IO, TransportConfig
from bus.units import timeout_scale
from host.analysis.session import report_fault, run_session
from host.experiment.config import ExperimentConfig
from host.experiment.console import EXIT_FAULT, print_plan
from host.experiment.faults import FaultKind, FaultRecord, attach_injection, read_injections
from host.experiment.loop import TrialFault, interrupt_on_signals
from host.experiment.outputs import is_disk_full
from host.experiment.plan import prepare
from host.nodes.bench_client import BenchClient, BenchClientError, BenchTrialFault
from host.nodes.drive_client import DriveClient
from host.nodes.sdo_access import SdoAccess, SdoTransportError

logger = logging.getLogger(__name__)

__all__ = ["RigBench", "HostHeartbeat", "run_host_role", "node_name"]

#: the watchdog's period, s
WATCH_PERIOD_S = 0.02
#: after a bench fault, how long the host lets the nodes' EMCY frames arrive before it reports, s
EMCY_SETTLE_S = 0.05


def node_name(node_id: int) -> str:
    """``drive1`` … ``drive4``, ``plant`` (the test bench), ``host`` (127), else ``node N``."""
    if node_id in DRIVE_NODE_IDS:
        return f"drive{node_id}"
    if node_id == BENCH_NODE_ID:
        return "plant"
    if node_id == HOST_NODE_ID:
        return "host"
    return f"node {node_id}"


class HostHeartbeat(threading.Thread):
    """The host's heartbeat producer: state OPERATIONAL on COB-ID ``0x700 + HOST_NODE_ID`` every
    ``period_s``, sent with canopen's ``Network.send_message`` from this thread.  A failing send
    (the bus gone) ends the thread and is kept in :attr:`error`."""

    def __init__(self, network: canopen.Network, period_s: float, node_id: int = HOST_NODE_ID) -> None:
        super().__init__(name="host heartbeat", daemon=True)
        self.network = network
        self.period_s = float(period_s)
        self.cob_id = heartbeat_cob_id(node_id)
        self.error: str | None = None
        self.sent = 0
        self._stop_event = threading.Event()

    def run(self) -> None:
        due = time.monotonic()
        while not self._stop_event.is_set():
            try:
                self.network.send_message(self.cob_id, bytes([NmtState.OPERATIONAL]))
                self.sent += 1
            except (can.CanError, OSError) as exc:
                self.error = f"{type(exc).__name__}: {exc}"
                logger.warning("host heartbeat stopped: %s", self.error)
                return
            due += self.period_s
            now = time.monotonic()
            if due < now:  # this process was not running (stopped): no burst of late beats
                due = now + self.period_s
            self._stop_event.wait(due - now)

    def stop(self) -> None:
        """Stop producing (the nodes' consumers notice it unless they are NMT STOPPED)."""
        self._stop_event.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=1.0)


class ChannelMonitor(can.Listener):
    """Counts frames/bits of one channel and writes its candump log (a plain bus member); notes
    bus error frames, a failing bus and a failing log; on io it follows the trials and ticks."""

    def __init__(self, bus: can.BusABC, name: str, log_path: Path | None) -> None:
        self.bus = bus
        self.name = name
        self.counter = BusLoadCounter()
        self.log = open_log(log_path, name) if log_path is not None else None
        self.log_error: str | None = None
        self.log_disk_full = False
        self.log_error_t: float | None = None
        self.bus_error: str | None = None
        self.bus_error_t: float | None = None
        self.error_frames = 0
        self.first_error_frame_t: float | None = None
        # io: trials and ticks as the plant's frames show them
        self.follower = io_frames.TrialTickFollower()
        self.lock = threading.Lock()
        listeners: list[can.Listener] = [self]
        self.notifier = can.Notifier(bus, listeners, timeout=0.1)

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.counter.add(msg)
            if msg.is_error_frame:
                self.error_frames += 1
                if self.first_error_frame_t is None:
                    self.first_error_frame_t = time.monotonic()
            elif self.name == IO:
                self.follower.on_frame(msg.arbitration_id, msg.data)
            if self.log is not None:
                try:
                    self.log.on_message_received(msg)
                except (OSError, ValueError) as err:  # ValueError: a write to a file closed by a failure
                    self._log_failed(err)

    def _log_failed(self, err: BaseException) -> None:
        self.log_error = f"{getattr(err, 'strerror', None) or err}"
        self.log_disk_full = is_disk_full(err)
        self.log_error_t = time.monotonic()
        logger.warning("%s log stopped: %s", self.name, self.log_error)
        log, self.log = self.log, None
        try:
            if log is not None:
                log.stop()
        except (OSError, ValueError):
            pass

    def on_error(self, exc: Exception) -> None:
        """The bus failed (python-can's notifier calls this instead of raising): noted once; the
        notifier retries, so this also paces it."""
        if self.bus_error is None:
            self.bus_error = f"{type(exc).__name__}: {exc}"
            self.bus_error_t = time.monotonic()
            logger.warning("%s monitor: bus failed: %s", self.name, self.bus_error)
        time.sleep(0.1)

    def stop(self) -> None:
        """can.Listener hook (called by the notifier when it stops): nothing to do here."""

    def close(self) -> None:
        """Stop receiving, close the log and the bus."""
        self.notifier.stop(timeout=2.0)
        with self.lock:
            if self.log is not None:
                try:
                    self.log.stop()
                except (OSError, ValueError) as err:
                    self._log_failed(err)
        try:
            self.bus.shutdown()
        except (can.CanError, OSError) as err:
            logger.debug("closing the %s monitor bus: %s", self.name, err)


class _FieldbusErrors(can.Listener):
    """A listener on the canopen network's notifier that notes a failing fieldbus."""

    def __init__(self) -> None:
        self.error: str | None = None
        self.error_t: float | None = None

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        if self.error is None:
            self.error = f"{type(exc).__name__}: {exc}"
            self.error_t = time.monotonic()
            logger.warning("fieldbus failed: %s", self.error)
        time.sleep(0.1)


class RigBench:
    """Drives and plant as CANopen nodes on the fieldbus (see module docstring).

    :param recover_s: > 0: a node lost or rebooted *between* trials is waited for (up to
        ``wait_s``) and set up again instead of ending the run (during a trial it always ends it)
    """

    def __init__(self, cfg: ExperimentConfig, transport: TransportConfig, *,
                 out_dir: Path | None, wait_s: float = 20.0, pause_s: float = 0.0, recover_s: float = 0.0) -> None:
        self.cfg = cfg
        self.out_dir = out_dir
        self.pause_s = pause_s
        self.recover_s = recover_s
        self.recoveries: list[dict[str, Any]] = []
        self.transport = transport
        self.wait_s = wait_s
        self.emcy: list[dict[str, Any]] = []
        self._pending_emcy: list[tuple[int, int, bytes, float, float]] = []
        self._lock = threading.Lock()
        self.scale = timeout_scale()
        self.consumer_s = CONSUMER_TIME_MS / 1000.0 * self.scale
        self.heartbeats = HeartbeatConsumer()
        self.monitors: list[ChannelMonitor] = []
        self.drives: list[DriveClient] = []
        self._accesses: list[SdoAccess] = []
        self._fault: FaultRecord | None = None
        self._watching = False
        self._in_trial = False
        self._trial = 0
        self._safe_state: list[dict[str, Any]] = []
        self._closed = False
        self._t_start = time.monotonic()
        self._fieldbus_errors = _FieldbusErrors()
        self._heartbeat: HostHeartbeat | None = None
        self._stop_watch = threading.Event()
        self._watchdog: threading.Thread | None = None
        self.network = canopen.Network(transport.open(FIELDBUS))
        try:
            for name in (FIELDBUS, IO):
                log = (out_dir / f"{name}.log") if out_dir is not None else None
                if log is not None:
                    log.parent.mkdir(parents=True, exist_ok=True)
                self.monitors.append(ChannelMonitor(transport.open(name), name, log))
            cast(list[Any], self.network.listeners).append(self._fieldbus_errors)  # notes a failing fieldbus
            self.network.connect()
            self.drive_nodes = [self.network.add_node(n, str(DRIVE_EDS_PATH)) for n in DRIVE_NODE_IDS]
            self.bench_node = self.network.add_node(BENCH_NODE_ID, str(BENCH_EDS_PATH))
            for node in (*self.drive_nodes, self.bench_node):
                # generous: 7 processes share 2 cores; a starved node answers late, not never
                node.sdo.RESPONSE_TIMEOUT = 5.0 * self.scale
            self._accesses = [SdoAccess(node) for node in self.drive_nodes]
            self.drives = [DriveClient(acc, nid) for acc, nid in zip(self._accesses, DRIVE_NODE_IDS)]
            self._bench_access = SdoAccess(self.bench_node)
            self._accesses.append(self._bench_access)
            self.bench = BenchClient(self._bench_access)
            for nid, node in zip((*DRIVE_NODE_IDS, BENCH_NODE_ID), (*self.drive_nodes, self.bench_node)):
                # canopen's own consumers: RemoteNode.nmt hears the heartbeats, .emcy the EMCYs
                node.nmt.add_heartbeat_callback(functools.partial(self._on_heartbeat, nid))
                node.emcy.add_callback(functools.partial(self._on_emcy, nid))
            self._heartbeat = HostHeartbeat(self.network, HOST_HEARTBEAT_MS / 1000.0)
            self._heartbeat.start()
            self._watchdog = threading.Thread(target=self._watch_loop, name="host watchdog", daemon=True)
            self._watchdog.start()
        except Exception:
            self.close()
            raise

    # -- listeners (run in the canopen notifier thread) ---------------------------------
    def _on_heartbeat(self, node_id: int, state: int) -> None:
        with self._lock:
            self.heartbeats.on_heartbeat(node_id, bytes([state]), time.monotonic())

    def _on_emcy(self, node_id: int, err: canopen.emcy.EmcyError) -> None:
        t_rx, now_wall = time.monotonic(), time.time()
        stamp = float(getattr(err, "timestamp", 0.0) or 0.0)
        # the frame's own time (the hub's receive stamp, wall clock) when plausible: a host that
        # was stopped reads it late, but the node sent it when it detected the fault
        late = now_wall - stamp if 0.0 <= now_wall - stamp < 3600.0 else 0.0
        with self._lock:
            self.emcy.append({"node": node_id, "code": err.code, "register": err.register,
                              "data": bytes(err.data).hex(), "t_s": round(t_rx - self._t_start, 4)})
            if err.code & 0xFF00:  # not an error reset
                self._pending_emcy.append((node_id, int(err.code), bytes(err.data), t_rx - late, now_wall - late))

    # -- the watchdog ---------------------------------------------------------------------
    def _watch_loop(self) -> None:
        last = time.monotonic()
        while not self._stop_watch.wait(WATCH_PERIOD_S):
            now = time.monotonic()
            with self._lock:
                if now - last > self.consumer_s:
                    # this process did not run (it was stopped): let the notifier read what queued up
                    self.heartbeats.grace(now)
                    last = now
                    continue
                last = now
            record = self._detect(now)
            if record is not None:
                self._declare(record)

    def _watch_once(self) -> None:
        """One watchdog round in the caller's thread (after a bench fault: the EMCYs are in)."""
        record = self._detect(time.monotonic())
        if record is not None:
            self._declare(record)

    def _tick(self) -> int | None:
        io_mon = next((m for m in self.monitors if m.name == IO), None)
        return io_mon.follower.tick if io_mon is not None and io_mon.follower.in_trial else None

    def _detect(self, now: float) -> FaultRecord | None:
        """The first fault visible now (None: all is well), in order: the bus, the logs, error
        frames, EMCYs, heartbeats."""
        if not self._watching or self._fault is not None:
            return None
        bus_name = "hub" if self.transport.needs_hub else self.transport.name
        errors = [(self._fieldbus_errors.error, self._fieldbus_errors.error_t, FIELDBUS)]
        errors += [(m.bus_error, m.bus_error_t, m.name) for m in self.monitors]
        if self._heartbeat is not None and self._heartbeat.error:
            errors.append((self._heartbeat.error, now, FIELDBUS))
        for err, t, channel in errors:
            if err is not None:
                return FaultRecord(FaultKind.BUS_LOST, f"the bus is gone ({channel}: {err})", node=bus_name,
                                   detected_by="host", t_detected_mono=t or now, latency_ms=0.0,
                                   latency_basis="bus error")
        for m in self.monitors:
            if m.log_error is not None:
                kind = FaultKind.DISK_FULL if m.log_disk_full else FaultKind.OUTPUT_ERROR
                what = "disk full" if m.log_disk_full else "cannot write"
                return FaultRecord(kind, f"{what}: the {m.name}.log candump log stopped ({m.log_error})",
                                   detected_by="host", t_detected_mono=m.log_error_t or now, latency_ms=0.0,
                                   latency_basis="failed write")
            if m.error_frames:
                return FaultRecord(FaultKind.FRAME_ERROR, f"a damaged frame on {m.name} (bus error frame)",
                                   node=m.name, detected_by="host", t_detected_mono=m.first_error_frame_t or now)
        with self._lock:
            pending, self._pending_emcy = self._pending_emcy, []
        if pending:
            return self._classify_emcy(*min(pending, key=lambda p: p[3]))
        if not self._in_trial and self.recover_s > 0:
            return None  # between trials a lost node is waited for (recover)
        with self._lock:
            report = self.heartbeats.check(now)
            last = {n: self.heartbeats.last_heard(n) for n in report.overdue}
        if report.overdue:
            everyone = set(DRIVE_NODE_IDS) | {BENCH_NODE_ID}
            with self._lock:
                heard = [self.heartbeats.last_heard(n) for n in everyone]
            quiet = 1.2 * NODE_HEARTBEAT_MS / 1000.0 * self.scale  # > a period: every node missed a beat
            if set(report.overdue) >= everyone or all(t is None or now - t > quiet for t in heard):
                return FaultRecord(FaultKind.BUS_SILENT, f"no heartbeat from any node for {1000 * self.consumer_s:.0f} ms: "
                                   f"the bus is silent ({bus_name} stalled?)", node=bus_name, detected_by="host",
                                   t_detected_mono=now)
            nid = sorted(report.overdue, key=lambda n: (n == BENCH_NODE_ID, n))[0]
            seen = last.get(nid)
            silent = f"{1000 * (now - seen):.0f} ms" if seen is not None else "ever"
            return FaultRecord(FaultKind.NODE_LOST, f"heartbeat of {node_name(nid)} lost (silent for {silent}: "
                               "the process died or stalled)", node=node_name(nid), node_id=nid, detected_by="host",
                               t_detected_mono=now,
                               latency_ms=1000 * (now - seen) - NODE_HEARTBEAT_MS * self.scale if seen else None,
                               latency_basis="its next heartbeat was due" if seen else None)
        if report.booted:
            nid = report.booted[0]
            return FaultRecord(FaultKind.NODE_LOST, f"{node_name(nid)} booted again during the run (it was reset "
                               "or restarted)", node=node_name(nid), node_id=nid, detected_by="host", t_detected_mono=now)
        return None

    def _classify_emcy(self, node_id: int, code: int, data: bytes, t_mono: float, t_wall: float) -> FaultRecord:
        """The fault an EMCY frame reports (codes: docs/canopen-objects.md §3)."""
        data = data + bytes(8)
        if node_id == BENCH_NODE_ID:
            try:
                fault = BenchFault(data[0])
            except ValueError:
                fault = BenchFault.NONE
            drive, tick = data[1], int.from_bytes(data[2:4], "little")
            kinds = {BenchFault.PLANT: FaultKind.PLANT_ERROR, BenchFault.TICK_TIMEOUT: FaultKind.FRAME_LOST,
                     BenchFault.TICK_SEQUENCE: FaultKind.FRAME_SEQUENCE, BenchFault.BAD_FRAME: FaultKind.FRAME_ERROR,
                     BenchFault.HOST_LOST: FaultKind.HOST_LOST, BenchFault.ABORTED: FaultKind.TRIAL_FAULT}
            texts = {
                BenchFault.PLANT: f"plant error at tick {tick}",
                BenchFault.TICK_TIMEOUT: f"io frame lost or late: no torque frame of drive {drive} for tick {tick} "
                                         "within the deadline",
                BenchFault.TICK_SEQUENCE: f"io frame out of sequence (duplicated, stale or skipped) from drive {drive} "
                                          f"at tick {tick}",
                BenchFault.BAD_FRAME: (f"malformed torque frame of drive {drive} at tick {tick}" if drive
                                       else f"damaged io frame (bus error frame) at tick {tick}"),
                BenchFault.HOST_LOST: "the host's heartbeat was lost",
                BenchFault.ABORTED: f"the test bench aborted the trial at tick {tick}",
            }
            node = f"drive{drive}" if drive else ("host" if fault == BenchFault.HOST_LOST else "plant")
            return FaultRecord(kinds.get(fault, FaultKind.EMCY),
                               f"{texts.get(fault, f'fault {int(fault)}')} (EMCY 0x{code:04X} of the test bench)",
                               node=node, node_id=drive or (HOST_NODE_ID if fault == BenchFault.HOST_LOST else BENCH_NODE_ID),
                               tick=tick, detected_by="plant", t_detected_mono=t_mono, t_detected_wall=t_wall)
        name = node_name(node_id)
        if code == 0x8130:
            return FaultRecord(FaultKind.HOST_LOST, f"the host's heartbeat was lost (EMCY 0x8130 of {name})", node="host",
                               node_id=HOST_NODE_ID, detected_by=name, t_detected_mono=t_mono, t_detected_wall=t_wall)
        if code == 0x8200:
            expected, got = int.from_bytes(data[1:3], "little"), int.from_bytes(data[3:5], "little")
            return FaultRecord(FaultKind.FRAME_SEQUENCE, f"io tick out of sequence at {name}: expected tick {expected}, "
                               f"got {got} (EMCY 0x8200)", node=name, node_id=node_id, tick=expected, detected_by=name,
                               t_detected_mono=t_mono, t_detected_wall=t_wall)
        what = "following error" if code == 0x8611 else "fault"
        return FaultRecord(FaultKind.EMCY, f"{what} of {name} (EMCY 0x{code:04X})", node=name, node_id=node_id,
                           detected_by=name, t_detected_mono=t_mono, t_detected_wall=t_wall)

    def _declare(self, record: FaultRecord) -> None:
        """The run is over: keep ``record`` (the first fault), torque off everywhere at once
        (NMT STOP broadcast), wake the main thread's SDO requests."""
        if record.trial is None:
            record.trial = self._trial
        if record.tick is None:
            record.tick = self._tick()
        if self.out_dir is not None:
            attach_injection(record, read_injections(self.out_dir))
        with self._lock:
            if self._fault is not None:
                return
            self._fault = record
        logger.warning("fault: %s (%s) at trial %s, tick %s, detected by %s", record.message, record.kind,
                       record.trial, record.tick, record.detected_by)
        self._nmt_stop_all()
        for acc in self._accesses:
            acc.cancel(f"the run stopped: {record.message}")

    def _nmt_stop_all(self) -> bool:
        try:
            self.network.nmt.send_command(NmtCommand.STOP)  # all nodes: torque off
            return True
        except (can.CanError, OSError, AttributeError) as exc:
            logger.info("NMT stop not sent: %s", exc)
            return False

    def _raise_if_fault(self) -> None:
        if self._fault is not None:
            raise TrialFault(self._fault.message, self._fault)

    # -- Bench protocol ----------------------------------------------------------------
    @property
    def _nodes(self) -> dict[int, Any]:
        return dict(zip((*DRIVE_NODE_IDS, BENCH_NODE_ID), (*self.drive_nodes, self.bench_node)))

    def _bring_up(self, node_ids: set[int], what: str) -> None:
        """Wait until ``node_ids`` answer SDO, give them a heartbeat and a consumer of the host's,
        NMT-start them and wait for their first operational heartbeat."""
        nodes = self._nodes
        deadline = time.monotonic() + self.wait_s
        waiting = set(node_ids)
        while waiting:
            for nid in sorted(waiting):
                try:
                    nodes[nid].sdo.upload(0x1000, 0)
                    waiting.discard(nid)
                except (canopen.SdoCommunicationError, canopen.SdoAbortedError):
                    pass
            self._raise_if_fault()
            if waiting and time.monotonic() > deadline:
                raise TrialFault(f"node(s) {', '.join(map(str, sorted(waiting)))} did not answer within "
                                 f"{self.wait_s:g} s {what}")
        consumer_ms = min(round(CONSUMER_TIME_MS * self.scale), 0xFFFF)
        for nid in sorted(node_ids):
            nodes[nid].sdo.download(0x1017, 0, NODE_HEARTBEAT_MS.to_bytes(2, "little"))
            nodes[nid].sdo.download(CONSUMER_HEARTBEAT_INDEX, 1,
                                    consumer_entry(HOST_NODE_ID, consumer_ms).to_bytes(4, "little"))
            with self._lock:
                self.heartbeats.watch(nid, self.consumer_s)
        for nid in sorted(node_ids):
            nodes[nid].nmt.send_command(NmtCommand.START)
        if BENCH_NODE_ID in node_ids:
            self.bench.configure(self.cfg.ts_s, self.cfg.substeps, self.cfg.disturbance, self.cfg.seed)
        t_end = time.monotonic() + 5.0
        while True:
            with self._lock:
                states = {nid: self.heartbeats.state(nid) for nid in node_ids}
            if all(s == NmtState.OPERATIONAL for s in states.values()):
                break
            if time.monotonic() > t_end:
                raise TrialFault(f"nodes not operational after NMT start: {states}")
            time.sleep(0.02)
        with self._lock:
            self.heartbeats.check(time.monotonic())  # forget the boot-ups seen while starting

    def start(self) -> None:
        """Wait until all five nodes answer SDO, NMT-start them, set up heartbeats; from now on the
        watchdog ends the run on any fault."""
        self._bring_up(set(DRIVE_NODE_IDS) | {BENCH_NODE_ID},
                       "(are the drive and plant processes running on this bus?)")
        self._watching = True

    def recover(self, trial: int) -> list[int]:
        """Before ``trial``: with ``recover_s`` > 0, nodes whose heartbeat was lost or that booted
        again are waited for (up to ``wait_s``) and brought up again; returns the indices of the
        drives that the host must configure again (gains, reference, enable). Without it (the
        default) a lost node has ended the run already (the watchdog)."""
        self._trial = trial
        if trial > 0 and self.pause_s > 0:
            time.sleep(self.pause_s)
        self._raise_if_fault()
        if self.recover_s <= 0:
            self._watch_once()
            self._raise_if_fault()
            return []
        with self._lock:
            report = self.heartbeats.check(time.monotonic())
        lost = set(report.overdue) | set(report.booted)
        if not lost:
            return []
        logger.warning("node(s) %s lost or rebooted before trial %d: waiting for them", sorted(lost), trial)
        self._bring_up(lost, "after losing them")
        for nid in sorted(lost):
            self.recoveries.append({"node": nid, "before_trial": trial,
                                    "heartbeat_lost": nid in report.overdue, "boot_up_seen": nid in report.booted})
        return [DRIVE_NODE_IDS.index(n) for n in sorted(lost) if n in DRIVE_NODE_IDS]

    def run_trial(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray) -> None:
        self._trial = trial
        self._raise_if_fault()
        self._in_trial = True
        try:
            self.bench.start_trial(trial, n_ticks, q0, qd0)
            # generous: lockstep over a loaded 2-core machine; faults come back much sooner
            self.bench.wait_trial(timeout_s=60.0 + n_ticks * 0.01, poll_s=0.02)
        except (BenchClientError, SdoAbort, SdoTransportError) as exc:
            if self._fault is None:
                time.sleep(EMCY_SETTLE_S)  # let the nodes' EMCY frames arrive: they say who saw it first
                self._watch_once()
            record = self._fault or self.describe_fault(exc, trial)
            raise TrialFault(record.message if record else f"trial {trial}: {exc}", record) from exc
        finally:
            self._in_trial = False
        self._watch_once()
        self._raise_if_fault()

    def describe_fault(self, exc: BaseException, trial: int) -> FaultRecord | None:
        """What the host knows about ``exc``: the watchdog's record, else the bench's state."""
        if self._fault is not None:
            return self._fault
        now = time.monotonic()
        if isinstance(exc, BenchTrialFault):
            st = exc.state
            kinds = {BenchFault.PLANT: FaultKind.PLANT_ERROR, BenchFault.TICK_TIMEOUT: FaultKind.FRAME_LOST,
                     BenchFault.TICK_SEQUENCE: FaultKind.FRAME_SEQUENCE, BenchFault.BAD_FRAME: FaultKind.FRAME_ERROR,
                     BenchFault.HOST_LOST: FaultKind.HOST_LOST}
            record = FaultRecord(kinds.get(st.fault, FaultKind.TRIAL_FAULT), f"test bench: {st.describe()}",
                                 node=f"drive{st.fault_node}" if st.fault_node else "plant",
                                 node_id=st.fault_node or BENCH_NODE_ID, trial=trial, tick=st.fault_tick,
                                 detected_by="plant", t_detected_mono=now)
        elif isinstance(exc, SdoTransportError | SdoAbort):
            nid = getattr(exc, "node_id", None)
            record = FaultRecord(FaultKind.SDO_ERROR, str(exc), node=node_name(nid) if nid else None, node_id=nid,
                                 trial=trial, detected_by="host", t_detected_mono=now)
        else:
            return None
        if self.out_dir is not None:
            attach_injection(record, read_injections(self.out_dir))
        return record

    def progress(self) -> int | None:
        """The tick of the trial in progress as the io channel shows it (None between trials)."""
        return self._tick()

    def info(self) -> dict[str, Any]:
        wall = time.monotonic() - self._t_start
        channels = {}
        for m in self.monitors:
            with m.lock:
                c = m.counter
                channels[m.name] = {
                    **c.as_dict(),
                    "load_percent_worst_case": c.load_percent(wall, worst_case=True),
                    "load_percent_no_stuffing": c.load_percent(wall, worst_case=False),
                    "log": f"{m.name}.log" if m.log is not None or m.log_error else None,
                    "error_frames": m.error_frames,
                }
        return {
            "transport": self.transport.as_dict(),
            "channels": channels,
            "bus_load_basis": "bits of every frame seen on the channel (classic CAN, worst-case stuffing) "
                              "divided by the run's wall time at 1 Mbit/s",
            "elapsed_s": wall,
            "heartbeat": {"host_node_id": HOST_NODE_ID, "host_period_ms": HOST_HEARTBEAT_MS,
                          "node_period_ms": NODE_HEARTBEAT_MS, "consumer_time_ms": CONSUMER_TIME_MS * self.scale},
            "emcy": self.emcy,
            "recoveries": self.recoveries,
        }

    def safe_state(self) -> list[dict[str, Any]]:
        """Per drive, after :meth:`close`: torque off and the evidence from the bus."""
        return list(self._safe_state)

    def close(self) -> None:
        """Every drive still alive to a torque-free state, evidence from the heartbeats, then
        release the bus (see the module docstring). Never raises."""
        if self._closed:
            return
        self._closed = True
        self._watching = False
        faulted = self._fault is not None
        bus_ok = self.network.bus is not None and self._fieldbus_errors.error is None
        now = time.monotonic()
        with self._lock:
            alive = {nid for nid in (*DRIVE_NODE_IDS, BENCH_NODE_ID)
                     if (t := self.heartbeats.last_heard(nid)) is not None and now - t <= self.consumer_s}
        how = "NMT STOP"
        if bus_ok and not faulted and self.drives:
            if self._in_trial or self._tick() is not None:
                try:
                    self.bench.abort()
                except Exception:  # noqa: BLE001 - closing must never hide the original error
                    logger.debug("bench abort failed", exc_info=True)
            for nid, d in zip(DRIVE_NODE_IDS, self.drives):
                if nid not in alive:
                    continue
                try:
                    d.disable()  # CiA 402 disable voltage: torque off, Switch on disabled
                except Exception:  # noqa: BLE001
                    logger.debug("disable of drive %d failed", nid, exc_info=True)
            how = "CiA 402 disable voltage, NMT STOP"
        t_stop = time.monotonic()
        sent = bus_ok and self._nmt_stop_all()
        self._safe_state = self._evidence(alive if sent else set(), t_stop, how)
        if self._heartbeat is not None:
            self._heartbeat.stop()
        self._stop_watch.set()
        if self._watchdog is not None and self._watchdog is not threading.current_thread():
            self._watchdog.join(timeout=1.0)
        try:
            self.network.disconnect()
        except Exception:  # noqa: BLE001
            logger.debug("disconnect failed", exc_info=True)
        for m in self.monitors:
            try:
                m.close()
            except Exception:  # noqa: BLE001
                logger.warning("closing the %s monitor failed", m.name, exc_info=True)
        self.monitors = []

    def _evidence(self, alive: set[int], t_stop: float, how: str) -> list[dict[str, Any]]:
        """Wait (at most one consumer time and a period) for every live drive's heartbeat to
        report STOPPED after ``t_stop``; one entry per drive."""
        deadline = t_stop + self.consumer_s + NODE_HEARTBEAT_MS / 1000.0 * self.scale
        seen: dict[int, float] = {}
        while True:
            with self._lock:
                for nid in alive:
                    t = self.heartbeats.last_heard(nid)
                    if nid not in seen and t is not None and t > t_stop and self.heartbeats.state(nid) == NmtState.STOPPED:
                        seen[nid] = t
            if all(n in seen for n in alive if n in DRIVE_NODE_IDS) or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        out = []
        for nid in DRIVE_NODE_IDS:
            name = node_name(nid)
            if nid in seen:
                out.append({"node": name, "node_id": nid, "torque": "off", "nmt": "STOPPED",
                            "evidence": f"{how}; its heartbeat reported STOPPED {1000 * (seen[nid] - t_stop):.0f} ms later"})
            elif nid in alive:
                out.append({"node": name, "node_id": nid, "torque": "unknown", "nmt": None,
                            "evidence": f"{how} sent; no STOPPED heartbeat within "
                                        f"{1000 * (deadline - t_stop):.0f} ms"})
            else:
                out.append({"node": name, "node_id": nid, "torque": "unknown", "nmt": None,
                            "evidence": "no heartbeat (the node or the bus is lost): its own fault reaction applies "
                                        "(see its log)"})
        return out


def run_host_role(args: Any, cfg: ExperimentConfig, transport: TransportConfig) -> int:
    """``ilcrig host``: run the experiment over the bus; summary mode ``rig``."""
    from host.experiment.outputs import check_out_dir

    out = Path(args.out) if args.out else Path("runs") / time.strftime("rig-%Y%m%d-%H%M%S")
    check_out_dir(out, iterations=cfg.iterations, create=False)
    plan = prepare(cfg)
    check_out_dir(out, iterations=cfg.iterations)
    print_plan(sys.stdout, "host", plan, extra=f", transport {transport.name}")
    try:
        bench = RigBench(cfg, transport, out_dir=out, wait_s=args.wait, pause_s=args.pause,
                         recover_s=getattr(args, "recover", 0.0) or 0.0)
    except (OSError, can.CanError, IlcrigError) as exc:
        sys.stderr.write(f"ilcrig: error: cannot open the bus ({transport.name}): {exc}\n")
        return EXIT_FAULT
    with interrupt_on_signals():
        res = run_session(plan, bench, out, mode="rig", stream=sys.stdout,
                          fail_writes_from_trial=getattr(args, "inject_disk_full", None))
    s = res.summary
    ch = s.get("bench", {}).get("channels", {})
    fb = ch.get(FIELDBUS, {})
    sys.stdout.write(
        f"{s['ticks']} ticks, {s['ticks_per_s']:.0f} ticks/s in trials; fieldbus {fb.get('frames', 0)} frames "
        f"({fb.get('load_percent_worst_case', 0.0):.1f} % of 1 Mbit/s), io {ch.get(IO, {}).get('frames', 0)} frames; "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / 'summary.json'}\n")
    sys.stdout.flush()
    return report_fault(res, out / "summary.json")
