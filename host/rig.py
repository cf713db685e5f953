"""The host on the real (emulated) fieldbus: a :class:`host.experiment.Bench` whose four drives
and plant are other processes, reached only over CAN with the ``canopen`` library.

* every node is a ``canopen.RemoteNode`` built from its EDS (bus/drive.eds, bus/bench.eds); the
  host reads and writes objects by SDO (block transfer for tables and recorder data), so the
  hand-written drives are checked against an independent CANopen implementation;
* NMT start/stop, heartbeat consumption (0x1017 set by the host) and EMCY listening: a lost
  node or an EMCY during a trial is a :class:`host.experiment.TrialFault`;
* a passive monitor (a second python-can bus per channel, i.e. an ordinary bus member) counts
  frames and bits per channel and writes candump logs with python-can's own writer.

:func:`run_host_role` is the ``ilcrig host`` entry point (also what ``ilcrig run`` starts).
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

import canopen
import can
import numpy as np

from bus import emcy as emcy_codec
from bus.busload import BusLoadCounter
from bus.canlog import open_log
from bus.errors import IlcrigError, SdoAbort
from bus.nmt import HeartbeatConsumer, NmtState
from bus.transport import FIELDBUS, IO, TransportConfig
from bus.units import timeout_scale
from host.bench_client import BenchClient, BenchClientError
from host.config import ExperimentConfig
from host.drive_client import DriveClient
from host.experiment import TrialFault
from host.sdo_access import SdoAccess, SdoTransportError

logger = logging.getLogger(__name__)

__all__ = ["RigBench", "run_host_role", "DRIVE_NODE_IDS", "BENCH_NODE_ID"]

DRIVE_NODE_IDS: tuple[int, ...] = (1, 2, 3, 4)
BENCH_NODE_ID = 32
_BUS_DIR = Path(__file__).resolve().parent.parent / "bus"
DRIVE_EDS = _BUS_DIR / "drive.eds"
BENCH_EDS = _BUS_DIR / "bench.eds"
HEARTBEAT_MS = 100
HEARTBEAT_TIMEOUT_S = 1.0  # 10 missed periods: generous, the machine has 2 cores for 7 processes
NMT_START, NMT_STOP = 0x01, 0x02


class ChannelMonitor(can.Listener):
    """Counts frames/bits of one channel and writes its candump log (a plain bus member)."""

    def __init__(self, bus: can.BusABC, name: str, log_path: Path | None) -> None:
        self.bus = bus
        self.name = name
        self.counter = BusLoadCounter()
        self.log = open_log(log_path, name) if log_path is not None else None
        self.lock = threading.Lock()
        listeners: list[can.Listener] = [self]
        self.notifier = can.Notifier(bus, listeners, timeout=0.1)

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.counter.add(msg)
            if self.log is not None:
                self.log.on_message_received(msg)

    def stop(self) -> None:
        """can.Listener hook (called by the notifier when it stops): nothing to do here."""

    def close(self) -> None:
        """Stop receiving, close the log and the bus."""
        self.notifier.stop(timeout=2.0)
        with self.lock:
            if self.log is not None:
                self.log.stop()
        self.bus.shutdown()


class RigBench:
    """Drives and plant as CANopen nodes on the fieldbus (see module docstring)."""

    def __init__(self, cfg: ExperimentConfig, transport: TransportConfig, *,
                 out_dir: Path | None, wait_s: float = 20.0, pause_s: float = 0.0) -> None:
        self.cfg = cfg
        self.pause_s = pause_s
        self.recoveries: list[dict[str, Any]] = []
        self.transport = transport
        self.wait_s = wait_s
        self.emcy: list[dict[str, Any]] = []
        self._pending_faults: list[str] = []
        self._lock = threading.Lock()
        self.heartbeats = HeartbeatConsumer()
        self.monitors: list[ChannelMonitor] = []
        self._t_start = time.monotonic()
        self.network = canopen.Network(transport.open(FIELDBUS))
        try:
            for name in (FIELDBUS, IO):
                log = (out_dir / f"{name}.log") if out_dir is not None else None
                if log is not None:
                    log.parent.mkdir(parents=True, exist_ok=True)
                self.monitors.append(ChannelMonitor(transport.open(name), name, log))
            self.network.connect()
            self.drive_nodes = [self.network.add_node(n, str(DRIVE_EDS)) for n in DRIVE_NODE_IDS]
            self.bench_node = self.network.add_node(BENCH_NODE_ID, str(BENCH_EDS))
            for node in self.drive_nodes:
                # generous: 7 processes share 2 cores; a starved node answers late, not never
                node.sdo.RESPONSE_TIMEOUT = 5.0 * timeout_scale()
            self.bench_node.sdo.RESPONSE_TIMEOUT = 5.0 * timeout_scale()
            self.drives = [DriveClient(SdoAccess(node), node.id) for node in self.drive_nodes]
            self.bench = BenchClient(SdoAccess(self.bench_node))
            for nid in (*DRIVE_NODE_IDS, BENCH_NODE_ID):
                self.network.subscribe(0x700 + nid, self._on_heartbeat)
                self.network.subscribe(0x080 + nid, self._on_emcy)
        except Exception:
            self.close()
            raise

    # -- listeners (run in the canopen notifier thread) ---------------------------------
    def _on_heartbeat(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self.heartbeats.on_frame(cob_id, bytes(data), time.monotonic())

    def _on_emcy(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        msg = emcy_codec.decode_emcy(bytes(data))
        node = cob_id - 0x080
        with self._lock:
            self.emcy.append({"node": node, "code": msg.code, "register": msg.register,
                              "data": bytes(msg.manufacturer).hex(), "t_s": round(time.monotonic() - self._t_start, 4)})
            if not msg.is_reset:
                self._pending_faults.append(f"node {node}: EMCY 0x{msg.code:04X}")

    # -- Bench protocol ----------------------------------------------------------------
    @property
    def _nodes(self) -> dict[int, Any]:
        return {n.id: n for n in (*self.drive_nodes, self.bench_node)}

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
        for nid in sorted(node_ids):
            self.network.send_message(0x000, bytes([NMT_START, nid]))
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
        """Wait until all five nodes answer SDO, NMT-start them, set up heartbeats."""
        self._bring_up(set(DRIVE_NODE_IDS) | {BENCH_NODE_ID},
                       "(are the drive and plant processes running on this bus?)")

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

    def run_trial(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray) -> None:
        self._check_health()
        try:
            self.bench.start_trial(trial, n_ticks, q0, qd0)
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
                    "log": f"{m.name}.log" if m.log is not None else None,
                }
        return {
            "transport": self.transport.as_dict(),
            "channels": channels,
            "bus_load_basis": "bits of every frame seen on the channel (classic CAN, worst-case stuffing) "
                              "divided by the run's wall time at 1 Mbit/s",
            "elapsed_s": wall,
            "emcy": self.emcy,
            "recoveries": self.recoveries,
        }

    def close(self) -> None:
        try:
            if getattr(self.network, "bus", None) is not None:
                for d in getattr(self, "drives", []):
                    try:
                        d.disable()
                    except Exception:  # closing must never hide the original error
                        logger.debug("disable failed", exc_info=True)
                self.network.send_message(0x000, bytes([NMT_STOP, 0]))
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
    from host.cli import EXIT_FAULT, _print_header, _print_row
    from host.experiment import prepare, run_experiment

    out = Path(args.out) if args.out else Path("runs") / time.strftime("rig-%Y%m%d-%H%M%S")
    plan = prepare(cfg)
    c = plan.check
    sys.stdout.write(
        f"ilcrig host: law {cfg.law}, path {cfg.path}, cycle {cfg.cycle_s} s, profile {cfg.profile}, "
        f"disturbance {cfg.disturbance}, {cfg.iterations} iterations, N = {plan.n_ticks} ticks/trial, "
        f"transport {transport.name}\n"
        f"convergence check: spectral radius {c.rho_max:.4f} ({'ok' if c.ok else 'VIOLATED: expect divergence'}), "
        f"predicted error ratio after {c.iterations} trials {c.predicted_ratio:.3g}, after {c.long_horizon} "
        f"{c.predicted_ratio_long:.3g}{' (diverges if run longer)' if c.predicted_ratio_long > 1 else ''}\n")
    sys.stdout.flush()
    out.mkdir(parents=True, exist_ok=True)
    try:
        bench = RigBench(cfg, transport, out_dir=out, wait_s=getattr(args, "wait", 20.0),
                         pause_s=getattr(args, "pause", 0.0))
    except (OSError, can.CanError, IlcrigError) as exc:
        sys.stderr.write(f"ilcrig: error: cannot open the bus ({transport.name}): {exc}\n")
        return EXIT_FAULT
    _print_header(sys.stdout)
    from host.recording import RunRecorder

    recorder = RunRecorder(out / "recording.rrd", recording_id=out.name, config_summary=cfg.as_dict())
    res = run_experiment(plan, bench, out, mode="rig", on_trial=lambda m: _print_row(sys.stdout, m),
                         recorder=recorder)
    s = res.summary
    if s["iterations"]:
        from host.report import write_run_report

        write_run_report(out, s)  # report.md + convergence plot next to the summary
    ch = s.get("bench", {}).get("channels", {})
    fb = ch.get(FIELDBUS, {})
    sys.stdout.write(
        f"{s['ticks']} ticks, {s['ticks_per_s']:.0f} ticks/s in trials; fieldbus {fb.get('frames', 0)} frames "
        f"({fb.get('load_percent_worst_case', 0.0):.1f} % of 1 Mbit/s), io {ch.get(IO, {}).get('frames', 0)} frames; "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / 'summary.json'}\n")
    sys.stdout.flush()
    if res.fault:
        sys.stderr.write(f"ilcrig: fault: {res.fault} (torque removed; {len(s['iterations'])} trials kept)\n")
        return EXIT_FAULT
    return 0
