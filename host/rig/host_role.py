"""The host on the real (emulated) fieldbus: a :class:`host.experiment.loop.Bench` whose four drives
and plant are other processes, reached only over CAN with the ``canopen`` library.

* every node is a ``canopen.RemoteNode`` built from its EDS (bus/drive.eds, bus/bench.eds); the
  host reads and writes objects by SDO (block transfer for tables and recorder data), so the
  hand-written drives are checked against an independent CANopen implementation;
* NMT start/stop, heartbeat consumption (0x1017 set by the host) and EMCY listening: a lost
  node or an EMCY during a trial is a :class:`host.experiment.loop.TrialFault`;
* a passive monitor (a second python-can bus per channel, i.e. an ordinary bus member,
  :class:`host.rig.monitor.ChannelMonitor`) counts frames and bits per channel and writes candump
  logs with python-can's own writer;
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
import logging
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np

from bus.bench_objects import BENCH_EDS_PATH, TrialTiming
from bus.bench_objects import DEFAULT_BENCH_NODE_ID as BENCH_NODE_ID
from bus.bustime import DEFAULT_BITRATE
from bus.cia301.nmt import HeartbeatConsumer, NmtCommand, NmtState
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
from bus.transports.config import FIELDBUS, HUB_INTERFACE, IO, TransportConfig
from bus.units import timeout_scale
from host.analysis.session import report_fault, run_session
from host.experiment.config import ExperimentConfig
from host.experiment.console import EXIT_FAULT, print_plan
from host.experiment.loop import CyclicActuals, CyclicSetpoints, TrialFault
from host.experiment.plan import prepare
from host.nodes.bench_client import BenchClient, BenchClientError
from host.nodes.drive_client import DriveClient
from host.nodes.sdo_access import SdoAccess, SdoTransportError
from host.rig.bus_time import BusTimeAccounting, bus_time_lines
from host.rig.monitor import ChannelMonitor
from host.rig.realtime import timing_line, timing_summary

logger = logging.getLogger(__name__)

__all__ = ["RigBench", "run_host_role"]

#: producer heartbeat period the host gives every node (0x1017), ms
HEARTBEAT_MS = 100
#: the host's consumer timeout: 10 missed periods, generous (2 cores for 7 processes), s
HEARTBEAT_TIMEOUT_S = 1.0
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


class RigBench:
    """Drives and plant as CANopen nodes on the fieldbus (see module docstring)."""

    def __init__(self, cfg: ExperimentConfig, transport: TransportConfig, *,
                 out_dir: Path | None, wait_s: float = 20.0, pause_s: float = 0.0, realtime: bool = False,
                 io_bitrate: int = DEFAULT_BITRATE, fieldbus_bitrate: int = DEFAULT_BITRATE) -> None:
        self.cfg = cfg
        self.bus_time = BusTimeAccounting(
            io_bitrate=io_bitrate, fieldbus_bitrate=fieldbus_bitrate, ts_s=cfg.ts_s,
            trial_s=round(2 * cfg.cycle_s / cfg.ts_s) * cfg.ts_s, heartbeat_ms=HEARTBEAT_MS,
            n_nodes=len(DRIVE_NODE_IDS) + 1)
        self.realtime = realtime
        self.timings: list[TrialTiming] = []
        self.pause_s = pause_s
        self.recoveries: list[dict[str, Any]] = []
        self.transport = transport
        self.wait_s = wait_s
        self.emcy: list[dict[str, Any]] = []
        self._pending_faults: list[str] = []
        self._lock = threading.Lock()
        self.heartbeats = HeartbeatConsumer()
        self.monitors: list[ChannelMonitor] = []
        self.drives: list[DriveClient] = []
        self._t_start = time.monotonic()
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
                self.monitors.append(ChannelMonitor(
                    transport.open(name, passive=True), name, log, classify, bulk=bulk,
                    classify_frames=self.bus_time.add_io_frames if name == IO else None))
            self.network.connect()
            self.drive_nodes = [self.network.add_node(n, str(DRIVE_EDS_PATH)) for n in DRIVE_NODE_IDS]
            self.bench_node = self.network.add_node(BENCH_NODE_ID, str(BENCH_EDS_PATH))
            for node in self.drive_nodes:
                # generous: 7 processes share 2 cores; a starved node answers late, not never
                node.sdo.RESPONSE_TIMEOUT = 5.0 * timeout_scale()
            self.bench_node.sdo.RESPONSE_TIMEOUT = 5.0 * timeout_scale()
            self.drives = [DriveClient(SdoAccess(node), _node_id(node)) for node in self.drive_nodes]
            self.bench = BenchClient(SdoAccess(self.bench_node))
            for node in (*self.drive_nodes, self.bench_node):
                # canopen's own consumers: RemoteNode.nmt hears the heartbeats, .emcy the EMCYs
                node.nmt.add_heartbeat_callback(functools.partial(self._on_heartbeat, _node_id(node)))
                node.emcy.add_callback(functools.partial(self._on_emcy, _node_id(node)))
        except Exception:
            self.close()
            raise

    # -- listeners (run in the canopen notifier thread) ---------------------------------
    def _on_heartbeat(self, node_id: int, state: int) -> None:
        with self._lock:
            self.heartbeats.on_heartbeat(node_id, bytes([state]), time.monotonic())

    def _on_emcy(self, node_id: int, err: canopen.emcy.EmcyError) -> None:
        with self._lock:
            self.emcy.append({"node": node_id, "code": err.code, "register": err.register,
                              "data": bytes(err.data).hex(), "t_s": round(time.monotonic() - self._t_start, 4)})
            if err.code & 0xFF00:  # not an error reset
                self._pending_faults.append(f"node {node_id}: EMCY 0x{err.code:04X}")

    # -- Bench protocol ----------------------------------------------------------------
    @property
    def _nodes(self) -> dict[int, Any]:
        return {_node_id(n): n for n in (*self.drive_nodes, self.bench_node)}

    def _bring_up(self, node_ids: set[int], what: str) -> None:
        """Wait until ``node_ids`` answer SDO, give them a heartbeat, NMT-start them and wait
        for their first operational heartbeat."""
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
            if waiting and time.monotonic() > deadline:
                raise TrialFault(f"node(s) {', '.join(map(str, sorted(waiting)))} did not answer within "
                                 f"{self.wait_s:g} s {what}")
        for nid in sorted(node_ids):
            nodes[nid].sdo.download(0x1017, 0, HEARTBEAT_MS.to_bytes(2, "little"))
            with self._lock:
                self.heartbeats.watch(nid, HEARTBEAT_TIMEOUT_S * timeout_scale())
        if self.cyclic:
            for nid in sorted(node_ids & set(DRIVE_NODE_IDS)):
                self._configure_pdos(nodes[nid])
        for nid in sorted(node_ids):
            nodes[nid].nmt.send_command(NmtCommand.START)
        if BENCH_NODE_ID in node_ids:
            self.bench.configure(self.cfg.ts_s, self.cfg.substeps, self.cfg.disturbance, self.cfg.seed,
                                 paced=self.realtime)
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
        for pdo_map, mapping, cob_id in ((node.rpdo[RPDO_NUMBER], CSP_RPDO_MAP, rpdo_cob_id(node.id)),
                                         (node.tpdo[TPDO_NUMBER], TPDO_MAP, tpdo_cob_id(node.id))):
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
            node.tpdo[TPDO_NUMBER].add_callback(
                lambda m, nid=node.id: self._tpdos.put((nid, bytes(m.data))))
        logger.info("node %d: RPDO1 0x%03X and TPDO1 0x%03X configured", node.id, rpdo_cob_id(node.id),
                    tpdo_cob_id(node.id))

    def start(self) -> None:
        """Wait for all five nodes' boot-up, then as :meth:`_bring_up`."""
        node_ids, what = set(DRIVE_NODE_IDS) | {BENCH_NODE_ID}, "(are the drive and plant processes running on this bus?)"
        self._await_boot_ups(node_ids, what)
        self._bring_up(node_ids, what)

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
                raise TrialFault(f"no boot-up from node(s) {', '.join(map(str, sorted(node_ids - booted)))} "
                                 f"within {self.wait_s:g} s {what}")
        finally:
            for nid in node_ids:
                self.network.unsubscribe(0x700 + nid, on_boot_up)

    def recover(self, trial: int) -> list[int]:
        """Before ``trial``: nodes whose heartbeat was lost or that booted again are waited for
        (up to ``wait_s``) and brought up again; returns the indices of the drives that the host
        must configure again (gains, reference, enable). EMCY faults are not recovered."""
        if trial > 0 and self.pause_s > 0:
            time.sleep(self.pause_s)
        with self._lock:
            report = self.heartbeats.check(time.monotonic())
            faults, self._pending_faults = self._pending_faults, []
        if faults:
            raise TrialFault("; ".join(faults))
        lost = set(report.overdue) | set(report.booted)
        if not lost:
            return []
        logger.warning("node(s) %s lost or rebooted before trial %d: waiting for them", sorted(lost), trial)
        self._bring_up(lost, "after losing them")
        for nid in sorted(lost):
            self.recoveries.append({"node": nid, "before_trial": trial,
                                    "heartbeat_lost": nid in report.overdue, "boot_up_seen": nid in report.booted})
        return [DRIVE_NODE_IDS.index(n) for n in sorted(lost) if n in DRIVE_NODE_IDS]

    def _check_health(self) -> None:
        with self._lock:
            report = self.heartbeats.check(time.monotonic())
            faults, self._pending_faults = self._pending_faults, []
        if report.overdue:
            faults.append("heartbeat lost from node(s) " + ", ".join(map(str, sorted(report.overdue))))
        if report.booted:
            faults.append("node(s) rebooted: " + ", ".join(map(str, sorted(report.booted))))
        if faults:
            raise TrialFault("; ".join(faults))

    def run_trial(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray,
                  cyclic: CyclicSetpoints | None = None) -> CyclicActuals | None:
        self._check_health()
        actuals = None
        try:
            self.bench.start_trial(trial, n_ticks, q0, qd0)
            if cyclic is not None:
                actuals = self._stream(trial, n_ticks, cyclic)
            # generous: lockstep over a loaded 2-core machine; faults come back much sooner
            self.bench.wait_trial(timeout_s=60.0 + n_ticks * 0.01, poll_s=0.02)
        except (BenchClientError, SdoAbort, SdoTransportError) as exc:
            time.sleep(0.05)  # let EMCY frames of the drives arrive for the report
            extra = ""
            with self._lock:
                if self._pending_faults:
                    extra = " (" + "; ".join(self._pending_faults) + ")"
                    self._pending_faults = []
            raise TrialFault(f"trial {trial}: {exc}{extra}") from exc
        self._check_health()
        self.timings.append(self.bench.trial_timing())
        return actuals

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
                    self.bench.wait_trial(timeout_s=1.0 * scale)  # a bench fault explains it better
                    raise TrialFault(f"trial {trial}: no TPDO from drive(s) {missing} for tick {n}") from None
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
                    "log": f"{m.name}.log" if m.log is not None else None,
                }
        return {
            "transport": self.transport.as_dict(),
            "channels": channels,
            "channels_basis": "every frame seen on the channel since the host started; emulator_throughput_bits_per_s: "
                              "their bits (worst-case stuffing) per second of wall time, a speed of the emulator, "
                              "not a bus load (see bus_time)",
            "bus_time": self.bus_time.summary(len(self.timings)),
            "elapsed_s": wall,
            "timing": timing_summary(self.timings, self.cfg.ts_s, self.realtime),
            "emcy": self.emcy,
            "recoveries": self.recoveries,
        } | ({"pdo_frames": dict(self.pdo_frames)} if self.cyclic else {})

    def close(self) -> None:
        try:
            if self.network.bus is not None:
                for d in self.drives:
                    try:
                        d.disable()
                    except Exception:  # closing must never hide the original error
                        logger.debug("disable failed", exc_info=True)
                self.network.nmt.send_command(NmtCommand.STOP)  # all nodes: torque off
        except Exception:
            logger.debug("NMT stop failed", exc_info=True)
        try:
            self.network.disconnect()
        except Exception:
            logger.debug("disconnect failed", exc_info=True)
        for m in self.monitors:
            try:
                m.close()
            except Exception:
                logger.warning("closing the %s monitor failed", m.name, exc_info=True)
        self.monitors = []


def run_host_role(args: Any, cfg: ExperimentConfig, transport: TransportConfig) -> int:
    """``ilcrig host``: run the experiment over the bus; summary mode ``rig``."""
    out = Path(args.out) if args.out else Path("runs") / time.strftime("rig-%Y%m%d-%H%M%S")
    plan = prepare(cfg)
    print_plan(sys.stdout, "host", plan, extra=f", transport {transport.name}")
    out.mkdir(parents=True, exist_ok=True)
    try:
        bench = RigBench(cfg, transport, out_dir=out, wait_s=args.wait, pause_s=args.pause,
                         realtime=bool(args.realtime),
                         io_bitrate=args.io_bitrate or DEFAULT_BITRATE,
                         fieldbus_bitrate=cfg.fieldbus_bitrate)
    except (OSError, can.CanError, IlcrigError) as exc:
        sys.stderr.write(f"ilcrig: error: cannot open the bus ({transport.name}): {exc}\n")
        return EXIT_FAULT
    res = run_session(plan, bench, out, mode="rig", stream=sys.stdout)
    s = res.summary
    ch = s.get("bench", {}).get("channels", {})
    fb = ch.get(FIELDBUS, {})
    timing = s.get("bench", {}).get("timing")
    if timing and timing.get("trials"):
        sys.stdout.write(timing_line(timing) + "\n")
    bus_time = s.get("bench", {}).get("bus_time")
    if bus_time and s["iterations"]:
        sys.stdout.write("".join(line + "\n" for line in bus_time_lines(bus_time)))
    sys.stdout.write(
        f"{s['ticks']} ticks, {s['ticks_per_s']:.0f} ticks/s in trials (host's wall clock); fieldbus {fb.get('frames', 0)} "
        f"frames, io {ch.get(IO, {}).get('frames', 0)} frames; "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / 'summary.json'}\n")
    sys.stdout.flush()
    return report_fault(res)
