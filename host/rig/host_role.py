"""The host on the real (emulated) fieldbus: a :class:`host.experiment.trials.Bench` whose four drives
and plant are other processes, reached only over CAN with the ``canopen`` library.

* every node is a ``canopen.RemoteNode`` built from its EDS (bus/drive.eds, bus/plant.eds); the
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
  fault, a lost, late, duplicated or damaged io frame reported by the plant node or a drive, the
  host's own loss reported by the nodes), a bus error frame, a full disk under the candump logs.
  At once it broadcasts NMT STOP (torque off on every drive still alive) and cancels the SDO
  requests of the main thread (:meth:`host.nodes.sdo_access.SdoAccess.cancel`), which then ends
  the run through the experiment's one fault path;
* :meth:`RigBench.close` brings every drive still alive to a torque-free state (after a
  completed run: CiA 402 disable voltage, then NMT STOP; after a fault: NMT STOP) and takes the
  evidence from the bus: each live drive's next heartbeat reporting STOPPED
  (:meth:`RigBench.safe_state`, into the summary);
* a passive monitor (a second python-can bus per channel, i.e. an ordinary bus member,
  :class:`host.rig.monitor.ChannelMonitor`) counts frames and bits per channel, writes candump
  logs with python-can's own writer (a full disk stops the log and is a fault) and follows the io
  channel's trial and tick (for the faults' ``tick``);
* with the pdo feed-forward transport, the host configures each drive's RPDO1/TPDO1 with the
  canopen library's PDO API (``node.rpdo`` / ``node.tpdo``: read, map, save) in NMT
  PRE-OPERATIONAL, and during a trial is the SYNC producer of the SYNC/PDO lockstep handshake
  (docs/timing.md §7): per tick it sends the four RPDOs (target position, torque offset) and one
  SYNC, then waits for the four TPDOs of that tick (position actual, torque actual) before the
  next tick's set-points.

:func:`run_host_role` is the ``ilcrig host`` entry point (also what ``ilcrig run`` starts).
"""

from __future__ import annotations

import functools
import gc
import json
import logging
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any, cast

import can
import canopen
import numpy as np

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
from bus.cyclic import (
    CSP_RPDO_MAP,
    RPDO_NUMBER,
    TPDO_MAP,
    TPDO_NUMBER,
    TRANSMISSION_TYPE,
    decode_tpdo,
    rpdo_cob_id,
    tpdo_cob_id,
)
from bus.errors import IlcrigError, SdoAbort
from bus.objects import DRIVE_EDS_PATH, DRIVE_NODE_IDS
from bus.plant_objects import DEFAULT_PLANT_NODE_ID as PLANT_NODE_ID
from bus.plant_objects import PLANT_EDS_PATH, DeadlineMisses, PlantFault, TrialTiming
from bus.traffic import DEFAULT_BITRATE
from bus.transports.config import FIELDBUS, HUB_INTERFACE, IO, TransportConfig
from bus.units import timeout_scale
from host.analysis.session import report_fault, run_session
from host.experiment.config import ExperimentConfig
from host.experiment.console import EXIT_FAULT, print_plan
from host.experiment.faults import FaultKind, FaultRecord, attach_injection, read_injections
from host.experiment.plan import prepare
from host.experiment.trials import CyclicActuals, CyclicSetpoints, TrialFault, interrupt_on_signals
from host.nodes.drive_client import DriveClient
from host.nodes.plant_client import PlantClient, PlantClientError, PlantTrialFault
from host.nodes.sdo_access import SdoAccess, SdoTransportError
from host.rig.bus_time import BusTimeAccounting, bus_time_lines
from host.rig.monitor import ChannelMonitor
from host.rig.realtime import MachineSteal, steal_during, timing_line, timing_summary

logger = logging.getLogger(__name__)

__all__ = ["RigBench", "HostHeartbeat", "run_host_role", "node_name"]

#: the watchdog's period, s
WATCH_PERIOD_S = 0.02
#: after a bench fault, how long the host lets the nodes' EMCY frames arrive before it reports, s
EMCY_SETTLE_S = 0.05


def node_name(node_id: int) -> str:
    """``drive1`` … ``drive4``, ``plant`` (the plant node), ``host`` (127), else ``node N``."""
    if node_id in DRIVE_NODE_IDS:
        return f"drive{node_id}"
    if node_id == PLANT_NODE_ID:
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


#: longest wait for the four TPDOs of one tick (× ILCRIG_TIMEOUT_SCALE), s; the first tick of a
#: trial waits as long as the plant does for its first torque frames
TPDO_TIMEOUT_S = 2.0
FIRST_TPDO_TIMEOUT_S = 10.0


def _node_id(node: canopen.RemoteNode) -> int:
    """``node.id``, which canopen types as Optional (a node may take its id from the EDS); the host
    always adds its nodes by id.

    :raises ValueError: the node has no id.
    """
    if node.id is None:
        raise ValueError(f"canopen node {node!r} has no node id")
    return node.id


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

    def __init__(
        self,
        cfg: ExperimentConfig,
        transport: TransportConfig,
        *,
        out_dir: Path | None,
        wait_s: float = 20.0,
        pause_s: float = 0.0,
        recover_s: float = 0.0,
        realtime: bool = False,
        io_bitrate: int = DEFAULT_BITRATE,
        fieldbus_bitrate: int = DEFAULT_BITRATE,
        bus_time_hub: bool = False,
        rt_scheduling: dict[str, Any] | None = None,
    ) -> None:
        self.cfg = cfg
        self.out_dir = out_dir
        self.bus_time = BusTimeAccounting(
            io_bitrate=io_bitrate,
            fieldbus_bitrate=fieldbus_bitrate,
            ts_s=cfg.ts_s,
            trial_s=round(2 * cfg.cycle_s / cfg.ts_s) * cfg.ts_s,
            heartbeat_ms=NODE_HEARTBEAT_MS,
            n_nodes=len(DRIVE_NODE_IDS) + 2,
        )  # the drives, the bench and the host (HOST_HEARTBEAT_MS, the same)
        self.realtime = realtime
        #: how the launcher scheduled the lockstep processes of a real-time run (realtime.raise_lockstep_priority)
        self.rt_scheduling = rt_scheduling
        self._gc_frozen = False
        #: the hub carries the channels in bus time at these bit rates (``--bus-time``), or None
        self.bus_time_hub = {FIELDBUS: int(fieldbus_bitrate), IO: int(io_bitrate)} if bus_time_hub else None
        self.timings: list[TrialTiming] = []
        #: per trial, the CPU time the hypervisor took from the machine meanwhile (None: not counted here)
        self.steal: list[MachineSteal | None] = []
        self.misses: list[DeadlineMisses | None] = []
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
        self._declaring = False
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
        self.cyclic = cfg.ff_transport == "pdo"
        self._tpdos: queue.Queue[tuple[int, bytes]] = queue.Queue()
        self._rpdo_maps: dict[int, Any] = {}
        self._tpdo_subscribed: set[int] = set()
        self.pdo_frames = {"sync": 0, "rpdo": 0, "tpdo": 0}
        self.network = canopen.Network(transport.open(FIELDBUS))
        try:
            for name in (FIELDBUS, IO):
                log = (out_dir / f"{name}.log") if out_dir is not None else None
                if log is not None:
                    log.parent.mkdir(parents=True, exist_ok=True)
                classify = self.bus_time.add_io if name == IO else self.bus_time.add_fieldbus
                # rounds with pauses only where the hub holds the frames; a kernel socket would drop them
                bulk = transport.channel(name).interface == HUB_INTERFACE
                self.monitors.append(
                    ChannelMonitor(
                        transport.open(name, passive=True),
                        name,
                        log,
                        classify,
                        bulk=bulk,
                        classify_frames=self.bus_time.add_io_frames if name == IO else None,
                    )
                )
            cast(list[Any], self.network.listeners).append(self._fieldbus_errors)  # notes a failing fieldbus
            self.network.connect()
            self.drive_nodes = [self.network.add_node(n, str(DRIVE_EDS_PATH)) for n in DRIVE_NODE_IDS]
            self.bench_node = self.network.add_node(PLANT_NODE_ID, str(PLANT_EDS_PATH))
            for node in (*self.drive_nodes, self.bench_node):
                # generous: 7 processes share 2 cores; a starved node answers late, not never
                node.sdo.RESPONSE_TIMEOUT = 5.0 * self.scale
            self._accesses = [SdoAccess(node) for node in self.drive_nodes]
            self.drives = [DriveClient(acc, nid) for acc, nid in zip(self._accesses, DRIVE_NODE_IDS)]
            self._plant_access = SdoAccess(self.bench_node)
            self._accesses.append(self._plant_access)
            self.plant_node = PlantClient(self._plant_access)
            for nid, node in zip((*DRIVE_NODE_IDS, PLANT_NODE_ID), (*self.drive_nodes, self.bench_node)):
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
            self.emcy.append(
                {
                    "node": node_id,
                    "code": err.code,
                    "register": err.register,
                    "data": bytes(err.data).hex(),
                    "t_s": round(t_rx - self._t_start, 4),
                }
            )
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
        """The tick of the trial running now on the io channel (None between trials)."""
        io_mon = next((m for m in self.monitors if m.name == IO), None)
        return io_mon.follower.tick if io_mon is not None and io_mon.follower.in_trial else None

    def _fault_tick(self) -> int | None:
        """The last tick of the host's current trial seen on the io channel, also when the plant
        has stopped the trial already (it does so on a fault it sees); the monitor reads in rounds,
        so it catches up first."""
        io_mon = next((m for m in self.monitors if m.name == IO), None)
        if io_mon is None:
            return None
        io_mon.catch_up(timeout_s=0.2)
        f = io_mon.follower
        return f.tick if f.trial == self._trial else None

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
                return FaultRecord(
                    FaultKind.BUS_LOST,
                    f"the bus is gone ({channel}: {err})",
                    node=bus_name,
                    detected_by="host",
                    t_detected_mono=t or now,
                    latency_ms=0.0,
                    latency_basis="bus error",
                )
        for m in self.monitors:
            if m.log_error is not None:
                kind = FaultKind.DISK_FULL if m.log_disk_full else FaultKind.OUTPUT_ERROR
                what = "disk full" if m.log_disk_full else "cannot write"
                return FaultRecord(
                    kind,
                    f"{what}: the {m.name}.log candump log stopped ({m.log_error})",
                    detected_by="host",
                    t_detected_mono=m.log_error_t or now,
                    latency_ms=0.0,
                    latency_basis="failed write",
                )
            if m.error_frames:
                return FaultRecord(
                    FaultKind.FRAME_ERROR,
                    f"a damaged frame on {m.name} (bus error frame)",
                    node=m.name,
                    detected_by="host",
                    t_detected_mono=m.first_error_frame_t or now,
                )
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
            everyone = set(DRIVE_NODE_IDS) | {PLANT_NODE_ID}
            with self._lock:
                heard = [self.heartbeats.last_heard(n) for n in everyone]
            quiet = 1.2 * NODE_HEARTBEAT_MS / 1000.0 * self.scale  # > a period: every node missed a beat
            if set(report.overdue) >= everyone or all(t is None or now - t > quiet for t in heard):
                return FaultRecord(
                    FaultKind.BUS_SILENT,
                    f"no heartbeat from any node for {1000 * self.consumer_s:.0f} ms: the bus is silent ({bus_name} stalled?)",
                    node=bus_name,
                    detected_by="host",
                    t_detected_mono=now,
                )
            nid = sorted(report.overdue, key=lambda n: (n == PLANT_NODE_ID, n))[0]
            seen = last.get(nid)
            silent = f"{1000 * (now - seen):.0f} ms" if seen is not None else "ever"
            return FaultRecord(
                FaultKind.NODE_LOST,
                f"heartbeat of {node_name(nid)} lost (silent for {silent}: the process died or stalled)",
                node=node_name(nid),
                node_id=nid,
                detected_by="host",
                t_detected_mono=now,
                latency_ms=1000 * (now - seen) - NODE_HEARTBEAT_MS * self.scale if seen else None,
                latency_basis="its next heartbeat was due" if seen else None,
            )
        if report.booted:
            nid = report.booted[0]
            return FaultRecord(
                FaultKind.NODE_LOST,
                f"{node_name(nid)} booted again during the run (it was reset or restarted)",
                node=node_name(nid),
                node_id=nid,
                detected_by="host",
                t_detected_mono=now,
            )
        return None

    def _classify_emcy(self, node_id: int, code: int, data: bytes, t_mono: float, t_wall: float) -> FaultRecord:
        """The fault an EMCY frame reports (codes: docs/canopen-objects.md §3)."""
        data = data + bytes(8)
        if node_id == PLANT_NODE_ID:
            try:
                fault = PlantFault(data[0])
            except ValueError:
                fault = PlantFault.NONE
            drive, tick = data[1], int.from_bytes(data[2:4], "little")
            kinds = {
                PlantFault.PLANT: FaultKind.PLANT_ERROR,
                PlantFault.TICK_TIMEOUT: FaultKind.FRAME_LOST,
                PlantFault.TICK_SEQUENCE: FaultKind.FRAME_SEQUENCE,
                PlantFault.BAD_FRAME: FaultKind.FRAME_ERROR,
                PlantFault.HOST_LOST: FaultKind.HOST_LOST,
                PlantFault.ABORTED: FaultKind.TRIAL_FAULT,
            }
            texts = {
                PlantFault.PLANT: f"plant error at tick {tick}",
                PlantFault.TICK_TIMEOUT: f"io frame lost or late: no torque frame of drive {drive} for tick {tick} "
                "within the deadline",
                PlantFault.TICK_SEQUENCE: f"io frame out of sequence (duplicated, stale or skipped) from drive {drive} "
                f"at tick {tick}",
                PlantFault.BAD_FRAME: (
                    f"malformed torque frame of drive {drive} at tick {tick}"
                    if drive
                    else f"damaged io frame (bus error frame) at tick {tick}"
                ),
                PlantFault.HOST_LOST: "the host's heartbeat was lost",
                PlantFault.ABORTED: f"the plant node aborted the trial at tick {tick}",
            }
            node = f"drive{drive}" if drive else ("host" if fault == PlantFault.HOST_LOST else "plant")
            return FaultRecord(
                kinds.get(fault, FaultKind.EMCY),
                f"{texts.get(fault, f'fault {int(fault)}')} (EMCY 0x{code:04X} of the plant node)",
                node=node,
                node_id=drive or (HOST_NODE_ID if fault == PlantFault.HOST_LOST else PLANT_NODE_ID),
                tick=tick,
                detected_by="plant",
                t_detected_mono=t_mono,
                t_detected_wall=t_wall,
            )
        name = node_name(node_id)
        if code == 0x8130:
            return FaultRecord(
                FaultKind.HOST_LOST,
                f"the host's heartbeat was lost (EMCY 0x8130 of {name})",
                node="host",
                node_id=HOST_NODE_ID,
                detected_by=name,
                t_detected_mono=t_mono,
                t_detected_wall=t_wall,
            )
        if code == 0x8200:
            expected, got = int.from_bytes(data[1:3], "little"), int.from_bytes(data[3:5], "little")
            return FaultRecord(
                FaultKind.FRAME_SEQUENCE,
                f"io tick out of sequence at {name}: expected tick {expected}, got {got} (EMCY 0x8200)",
                node=name,
                node_id=node_id,
                tick=expected,
                detected_by=name,
                t_detected_mono=t_mono,
                t_detected_wall=t_wall,
            )
        what = "following error" if code == 0x8611 else "fault"
        return FaultRecord(
            FaultKind.EMCY,
            f"{what} of {name} (EMCY 0x{code:04X})",
            node=name,
            node_id=node_id,
            detected_by=name,
            t_detected_mono=t_mono,
            t_detected_wall=t_wall,
        )

    def _declare(self, record: FaultRecord) -> None:
        """The run is over: keep ``record`` (the first fault), torque off everywhere at once
        (NMT STOP broadcast), wake the main thread's SDO requests."""
        with self._lock:
            if self._fault is not None or self._declaring:
                return
            self._declaring = True
        self._nmt_stop_all()  # first: torque off
        if record.trial is None:
            record.trial = self._trial
        if record.tick is None:
            record.tick = self._fault_tick()
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
        for acc in self._accesses:
            acc.cancel(f"the run stopped: {record.message}")
        self._tpdos.put((0, b""))  # wakes a SYNC producer waiting for TPDOs

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
        return dict(zip((*DRIVE_NODE_IDS, PLANT_NODE_ID), (*self.drive_nodes, self.bench_node)))

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
                raise TrialFault(f"node(s) {', '.join(map(str, sorted(waiting)))} did not answer within {self.wait_s:g} s {what}")
        consumer_ms = min(round(CONSUMER_TIME_MS * self.scale), 0xFFFF)
        for nid in sorted(node_ids):
            nodes[nid].sdo.download(0x1017, 0, NODE_HEARTBEAT_MS.to_bytes(2, "little"))
            nodes[nid].sdo.download(CONSUMER_HEARTBEAT_INDEX, 1, consumer_entry(HOST_NODE_ID, consumer_ms).to_bytes(4, "little"))
            with self._lock:
                self.heartbeats.watch(nid, self.consumer_s)
        if self.cyclic:
            for nid in sorted(node_ids & set(DRIVE_NODE_IDS)):
                self._configure_pdos(nodes[nid])
        for nid in sorted(node_ids):
            nodes[nid].nmt.send_command(NmtCommand.START)
        if PLANT_NODE_ID in node_ids:
            self.plant_node.configure(self.cfg.ts_s, self.cfg.substeps, self.cfg.disturbance, self.cfg.seed, paced=self.realtime)
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

    def _configure_pdos(self, node: Any) -> None:
        """RPDO1 (target position, torque offset) and TPDO1 (position actual, torque actual), both
        synchronous, with the canopen library's PDO API; the mapping may change only in NMT
        PRE-OPERATIONAL (CiA 301), so the node is put there first."""
        node.nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)
        node.rpdo.read()
        node.tpdo.read()
        for pdo_map, mapping, cob_id in (
            (node.rpdo[RPDO_NUMBER], CSP_RPDO_MAP, rpdo_cob_id(node.id)),
            (node.tpdo[TPDO_NUMBER], TPDO_MAP, tpdo_cob_id(node.id)),
        ):
            pdo_map.clear()
            for index, sub, bits in mapping:
                pdo_map.add_variable(index, sub, bits)
            pdo_map.cob_id = cob_id
            pdo_map.trans_type = TRANSMISSION_TYPE
            pdo_map.enabled = True
            pdo_map.save()
        self._rpdo_maps[node.id] = node.rpdo[RPDO_NUMBER]
        if node.id not in self._tpdo_subscribed:  # the map object (and its callbacks) lives on
            self._tpdo_subscribed.add(node.id)
            node.tpdo[TPDO_NUMBER].add_callback(lambda m, nid=node.id: self._tpdos.put((nid, bytes(m.data))))
        logger.info("node %d: RPDO1 0x%03X and TPDO1 0x%03X configured", node.id, rpdo_cob_id(node.id), tpdo_cob_id(node.id))

    def start(self) -> None:
        """Wait for all five nodes' boot-up, then as :meth:`_bring_up`; from now on the watchdog
        ends the run on any fault."""
        node_ids, what = set(DRIVE_NODE_IDS) | {PLANT_NODE_ID}, "(are the drive and plant processes running on this bus?)"
        self._await_boot_ups(node_ids, what)
        self._bring_up(node_ids, what)
        self._watching = True

    def _await_boot_ups(self, node_ids: set[int], what: str) -> None:
        """NMT reset communication (broadcast), then wait for every node's boot-up: a running node
        announces itself again, one still starting (compiling) when it is up. So no SDO request
        goes to a node that is not running yet (it would time out, and canopen logs the abort
        at ERROR level)."""
        booted: set[int] = set()
        all_booted = threading.Event()

        def on_boot_up(can_id: int, data: bytearray, timestamp: float) -> None:
            if data[:1] == bytes([NmtState.BOOT_UP]):
                booted.add(can_id - 0x700)
                if booted >= node_ids:
                    all_booted.set()

        for nid in node_ids:
            self.network.subscribe(0x700 + nid, on_boot_up)
        try:
            self.network.nmt.send_command(NmtCommand.RESET_COMMUNICATION)
            if not all_booted.wait(self.wait_s):
                raise TrialFault(
                    f"no boot-up from node(s) {', '.join(map(str, sorted(node_ids - booted)))} within {self.wait_s:g} s {what}"
                )
        finally:
            for nid in node_ids:
                self.network.unsubscribe(0x700 + nid, on_boot_up)

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
            self.recoveries.append(
                {
                    "node": nid,
                    "before_trial": trial,
                    "heartbeat_lost": nid in report.overdue,
                    "boot_up_seen": nid in report.booted,
                }
            )
        return [DRIVE_NODE_IDS.index(n) for n in sorted(lost) if n in DRIVE_NODE_IDS]

    def run_trial(
        self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray, cyclic: CyclicSetpoints | None = None
    ) -> CyclicActuals | None:
        self._trial = trial
        self._raise_if_fault()
        if not self._gc_frozen:
            # What the host holds at its first trial (numba, scipy, canopen, rerun, pyarrow: about a
            # million objects) lives as long as the process: frozen out of the cycle collector's
            # reach, a full collection during a trial costs about a millisecond instead of 50-150 ms
            # of one of the two cores the lockstep needs (refcounting still frees them). No
            # gc.collect() first: it would hold the GIL for that long itself (seconds in an emulated
            # VM, near the drives' heartbeat consumer time); the little garbage frozen with the rest
            # is kept once.
            gc.freeze()
            self._gc_frozen = True
        self._in_trial = True
        actuals = None

        def trial_body() -> None:
            nonlocal actuals
            self.plant_node.start_trial(trial, n_ticks, q0, qd0)
            if cyclic is not None:
                actuals = self._stream(trial, n_ticks, cyclic)
            # generous: lockstep over a loaded 2-core machine; faults come back much sooner
            self.plant_node.wait_trial(timeout_s=60.0 + n_ticks * 0.01, poll_s=0.02)

        try:
            steal = steal_during(trial_body)
        except (PlantClientError, SdoAbort, SdoTransportError) as exc:
            if self._fault is None:
                time.sleep(EMCY_SETTLE_S)  # let the nodes' EMCY frames arrive: they say who saw it first
                self._watch_once()
            record = self._fault or self.describe_fault(exc, trial)
            raise TrialFault(record.message if record else f"trial {trial}: {exc}", record) from exc
        finally:
            self._in_trial = False
        self._watch_once()
        self._raise_if_fault()
        timing = self.plant_node.trial_timing()
        self.timings.append(timing)
        # which ticks missed, only when some did: a run that keeps up moves the same frames as before
        self.misses.append(self.plant_node.deadline_misses() if timing.paced and timing.deadline_misses else None)
        self.steal.append(steal)
        return actuals

    def describe_fault(self, exc: BaseException, trial: int) -> FaultRecord | None:
        """What the host knows about ``exc``: the watchdog's record, else the bench's state."""
        if self._fault is not None:
            return self._fault
        now = time.monotonic()
        if isinstance(exc, PlantTrialFault):
            st = exc.state
            kinds = {
                PlantFault.PLANT: FaultKind.PLANT_ERROR,
                PlantFault.TICK_TIMEOUT: FaultKind.FRAME_LOST,
                PlantFault.TICK_SEQUENCE: FaultKind.FRAME_SEQUENCE,
                PlantFault.BAD_FRAME: FaultKind.FRAME_ERROR,
                PlantFault.HOST_LOST: FaultKind.HOST_LOST,
            }
            record = FaultRecord(
                kinds.get(st.fault, FaultKind.TRIAL_FAULT),
                f"plant node: {st.describe()}",
                node=f"drive{st.fault_node}" if st.fault_node else "plant",
                node_id=st.fault_node or PLANT_NODE_ID,
                trial=trial,
                tick=st.fault_tick,
                detected_by="plant",
                t_detected_mono=now,
            )
        elif isinstance(exc, SdoTransportError | SdoAbort):
            nid = getattr(exc, "node_id", None)
            record = FaultRecord(
                FaultKind.SDO_ERROR,
                str(exc),
                node=node_name(nid) if nid else None,
                node_id=nid,
                trial=trial,
                detected_by="host",
                t_detected_mono=now,
            )
        else:
            return None
        if self.out_dir is not None:
            attach_injection(record, read_injections(self.out_dir))
        return record

    def progress(self) -> int | None:
        """The last tick of the current trial as the io channel shows it (None before its first)."""
        return self._fault_tick()

    def _stream(self, trial: int, n_ticks: int, cyclic: CyclicSetpoints) -> CyclicActuals:
        """The SYNC producer's side of the lockstep handshake (docs/timing.md §7): per tick n the
        four RPDOs with the set-points of n, one SYNC, then the four TPDOs of n."""
        while True:  # TPDOs of an earlier, faulted trial
            try:
                self._tpdos.get_nowait()
            except queue.Empty:
                break
        index = {nid: j for j, nid in enumerate(DRIVE_NODE_IDS)}
        rpdos = [self._rpdo_maps[nid] for nid in DRIVE_NODE_IDS]
        n_drives = len(rpdos)
        pos = np.zeros((n_ticks, n_drives), dtype=np.int64)
        torque = np.zeros((n_ticks, n_drives), dtype=np.int64)
        target, offset = cyclic.target_counts, cyclic.torque_offset_permille
        scale = timeout_scale()
        sync = self.network.sync
        for n in range(n_ticks):
            for j, rpdo in enumerate(rpdos):
                rpdo[0].raw = int(target[n, j])
                rpdo[1].raw = int(offset[n, j])
                rpdo.transmit()
            sync.transmit()
            self.pdo_frames["rpdo"] += n_drives
            self.pdo_frames["sync"] += 1
            seen = [False] * n_drives
            deadline = time.monotonic() + (FIRST_TPDO_TIMEOUT_S if n == 0 else TPDO_TIMEOUT_S) * scale
            for _ in range(n_drives):
                try:
                    nid, data = self._tpdos.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    missing = [DRIVE_NODE_IDS[j] for j in range(n_drives) if not seen[j]]
                    self.plant_node.wait_trial(timeout_s=1.0 * scale)  # a bench fault explains it better
                    raise TrialFault(f"trial {trial}: no TPDO from drive(s) {missing} for tick {n}") from None
                if nid == 0:  # the watchdog declared a fault
                    self._raise_if_fault()
                    continue
                j = index[nid]
                if seen[j]:
                    raise TrialFault(f"trial {trial}: two TPDOs from drive {nid} in tick {n}")
                seen[j] = True
                pos[n, j], torque[n, j] = decode_tpdo(data)
            self.pdo_frames["tpdo"] += n_drives
        return CyclicActuals(pos, torque)

    def info(self) -> dict[str, Any]:
        wall = time.monotonic() - self._t_start
        channels = {}
        for m in self.monitors:
            m.catch_up()
            with m.lock:
                c = m.counter
                channels[m.name] = {
                    **c.as_dict(),
                    "emulator_throughput_bits_per_s": c.bits_worst_case / wall if wall > 0 else 0.0,
                    "log": f"{m.name}.log" if m.log is not None or m.log_error else None,
                    "error_frames": m.error_frames,
                }
        return {
            "transport": self.transport.as_dict(),
            "channels": channels,
            "channels_basis": "every frame seen on the channel since the host started; emulator_throughput_bits_per_s: "
            "their bits (worst-case stuffing) per second of wall time, a speed of the emulator, "
            "not a bus load (see bus_time)",
            "bus_time": self.bus_time.summary(len(self.timings)),
            "bus_time_hub": self.bus_time_hub,
            "elapsed_s": wall,
            "heartbeat": {
                "host_node_id": HOST_NODE_ID,
                "host_period_ms": HOST_HEARTBEAT_MS,
                "node_period_ms": NODE_HEARTBEAT_MS,
                "consumer_time_ms": CONSUMER_TIME_MS * self.scale,
            },
            "timing": timing_summary(self.timings, self.cfg.ts_s, self.realtime, self.rt_scheduling, self.steal, self.misses),
            "emcy": self.emcy,
            "recoveries": self.recoveries,
        } | ({"pdo_frames": dict(self.pdo_frames)} if self.cyclic else {})

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
            alive = {
                nid
                for nid in (*DRIVE_NODE_IDS, PLANT_NODE_ID)
                if (t := self.heartbeats.last_heard(nid)) is not None and now - t <= self.consumer_s
            }
        how = "NMT STOP"
        if bus_ok and not faulted and self.drives:
            if self._in_trial or self._tick() is not None:
                try:
                    self.plant_node.abort()
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
                out.append(
                    {
                        "node": name,
                        "node_id": nid,
                        "torque": "off",
                        "nmt": "STOPPED",
                        "evidence": f"{how}; its heartbeat reported STOPPED {1000 * (seen[nid] - t_stop):.0f} ms later",
                    }
                )
            elif nid in alive:
                out.append(
                    {
                        "node": name,
                        "node_id": nid,
                        "torque": "unknown",
                        "nmt": None,
                        "evidence": f"{how} sent; no STOPPED heartbeat within {1000 * (deadline - t_stop):.0f} ms",
                    }
                )
            else:
                out.append(
                    {
                        "node": name,
                        "node_id": nid,
                        "torque": "unknown",
                        "nmt": None,
                        "evidence": "no heartbeat (the node or the bus is lost): its own fault reaction applies (see its log)",
                    }
                )
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
        bench = RigBench(
            cfg,
            transport,
            out_dir=out,
            wait_s=args.wait,
            pause_s=args.pause,
            recover_s=getattr(args, "recover", 0.0) or 0.0,
            realtime=bool(args.realtime),
            rt_scheduling=json.loads(args.rt_scheduling) if getattr(args, "rt_scheduling", None) else None,
            io_bitrate=args.io_bitrate or DEFAULT_BITRATE,
            fieldbus_bitrate=cfg.fieldbus_bitrate,
            bus_time_hub=bool(getattr(args, "bus_time", False)),
        )
    except (OSError, can.CanError, IlcrigError) as exc:
        sys.stderr.write(f"ilcrig: error: cannot open the bus ({transport.name}): {exc}\n")
        return EXIT_FAULT
    with interrupt_on_signals():
        res = run_session(
            plan, bench, out, mode="rig", stream=sys.stdout, fail_writes_from_trial=getattr(args, "inject_disk_full", None)
        )
    s = res.summary
    ch = s.get("bench", {}).get("channels", {})
    fb = ch.get(FIELDBUS, {})
    timing = s.get("bench", {}).get("timing")
    if timing and timing.get("trials"):
        sys.stdout.write(timing_line(timing) + "\n")
    hub_rates = s.get("bench", {}).get("bus_time_hub")
    if hub_rates:
        sys.stdout.write(
            f"bus-time hub: io at {hub_rates[IO] / 1000:g} kbit/s, fieldbus at {hub_rates[FIELDBUS] / 1000:g} "
            f"kbit/s: frames delivered in arbitration order, each after its bit time\n"
        )
    bus_time = s.get("bench", {}).get("bus_time")
    if bus_time and s["iterations"]:
        sys.stdout.write("".join(line + "\n" for line in bus_time_lines(bus_time)))
    sys.stdout.write(
        f"{s['ticks']} ticks, {s['ticks_per_s']:.0f} ticks/s in trials (host's wall clock); fieldbus {fb.get('frames', 0)} "
        f"frames, io {ch.get(IO, {}).get('frames', 0)} frames; "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / 'summary.json'}\n"
    )
    sys.stdout.flush()
    return report_fault(res, out / "summary.json")
