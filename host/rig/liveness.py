"""The launcher's heartbeat consumer and stop watch: every process of the run watched from its
start to the end of the run, also where the host does not watch (the bring-up before the nodes'
heartbeats are configured; after its bench closed, while it writes its final outputs).

:class:`StopWatch` (called by :class:`host.rig.supervisor.Supervisor` every round) notes a process
stopped (SIGSTOP) for longer than the consumer time: a stall whose heartbeat nobody consumes then.

This module owns :class:`LivenessWatch`, a thread of the launcher that joins the fieldbus as a
passive member (acceptance filter: the heartbeats ``0x701``–``0x77E``, the host's ``0x77F`` left
out: it stops on purpose when the host closes) and consumes each node's heartbeat with the nodes'
consumer time (:data:`bus.cia301.nmt.CONSUMER_TIME_MS` × ``ILCRIG_TIMEOUT_SCALE``). A node silent
for longer is a :class:`Silence` (noticed when its consumer time ran out, with where the run was
then; ended when it is heard again). A boot-up message (NMT state 0) starts the node's watch
afresh: after a reset its heartbeat is off until the host configures it again. When the launcher
itself did not run for half a consumer time (a loaded machine), what it did not hear meanwhile is
not judged. Every tracked node silent together is the hub's silence (``hub``).

:meth:`LivenessWatch.settle` ends the watch once each node was heard again after the host ended
(or a consumer time passed), so a silence that began just before is seen too.

What a silence is (:func:`judge_silences`): noticed while the run's results were not yet safe
(before the host ended) — a fault (``node_lost`` of the node, ``bus_silent`` of the hub, detected
by the launcher, placed where the run was); noticed after — a liveness incident for the summary.

May import: ``bus``, ``can``, :mod:`host.experiment` (faults, fault_placement).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can

from bus.cia301.nmt import CONSUMER_TIME_MS, HEARTBEAT_BASE, HOST_NODE_ID
from bus.run_queue import RunQueueLedger
from bus.transports.config import FIELDBUS, TransportConfig
from bus.units import timeout_scale
from host.experiment.fault_placement import place
from host.experiment.faults import FaultKind, FaultRecord, attach_injection, node_name, position_of
from host.rig.processes import node_id_of

logger = logging.getLogger(__name__)

__all__ = ["LivenessWatch", "Silence", "StopWatch", "judge_silences"]

#: the watch's read period, s
POLL_S: float = 0.05


@dataclass
class Silence:
    """A node not heard for longer than its consumer time.

    :ivar node_id: its CANopen node id (None: every node at once, the hub)
    :ivar t_last_mono: when it was last heard (CLOCK_MONOTONIC, s)
    :ivar t_noticed_mono: when its consumer time ran out
    :ivar t_noticed_wall: the same on the wall clock
    :ivar t_heard_mono: when it was heard again (None: not before the watch ended)
    :ivar where: the run's position when it was noticed (:class:`host.rig.run_watch.Where`), or None
    :ivar kept: the trials in the summary when it was noticed
    :ivar how: ``heartbeat`` (its heartbeat not heard), ``stopped`` (its process stopped, SIGSTOP)
        or ``waited`` (while ``carrier`` waited ``waited_s`` for a CPU: not a fault, :mod:`bus.run_queue`)
    :ivar carrier: the process that waited (``waited``), else None
    :ivar waited_s: how long it waited for a CPU meanwhile, s (``waited``)
    """

    node_id: int | None
    t_last_mono: float
    t_noticed_mono: float
    t_noticed_wall: float
    t_heard_mono: float | None = None
    where: Any = None
    kept: int = 0
    how: str = "heartbeat"
    carrier: str | None = None
    waited_s: float = 0.0

    @property
    def node(self) -> str:
        """``drive2``, ``plant``, ``host``, or ``hub`` (node id None)."""
        return "hub" if self.node_id is None else node_name(self.node_id)

    @property
    def silent_ms(self) -> float | None:
        """How long it was silent, ms (None while it still is)."""
        return None if self.t_heard_mono is None else 1000.0 * (self.t_heard_mono - self.t_last_mono)


class LivenessWatch(threading.Thread):
    """The launcher's heartbeat consumer (see the module docstring).

    :param transport: the run's transport (the hub's address)
    :param where: the run's position now, or None
    :param kept: the trials the summary holds now
    :param pids: the run's processes now, name → pid (``hub``, ``drive1`` …): a node's silence
        explained by its own process's or the hub's wait for a CPU is no silence
        (:mod:`bus.run_queue`), kept as a ``waited`` silence for the summary's incidents
    """

    def __init__(
        self,
        transport: TransportConfig,
        where: Callable[[], Any] | None = None,
        kept: Callable[[], int] | None = None,
        pids: Callable[[], dict[str, int]] | None = None,
    ) -> None:
        super().__init__(name="liveness watch", daemon=True)
        self.transport = transport
        self.where = where
        self.kept = kept
        self.consumer_s = CONSUMER_TIME_MS / 1000.0 * timeout_scale()
        self.silences: list[Silence] = []
        self._last: dict[int, float] = {}
        self._open: dict[int, Silence] = {}
        self._stop_event = threading.Event()
        self._lock = threading.Lock()
        self._bus: can.BusABC | None = None
        self._pids = pids
        self._ledger = RunQueueLedger(self._carriers) if pids is not None else None

    def _carriers(self, node_id: int) -> list[int]:
        """The pids node ``node_id``'s heartbeat passes through: its own process's, the hub's."""
        pids = self._pids() if self._pids is not None else {}
        return [pids[name] for name in (node_name(node_id), "hub") if name in pids]

    def run(self) -> None:
        try:
            bus = self._bus = self.transport.open(FIELDBUS, passive=True)
            bus.set_filters([{"can_id": HEARTBEAT_BASE, "can_mask": 0x780}])
            prev = time.monotonic()
            while not self._stop_event.is_set():
                msg = bus.recv(timeout=POLL_S)
                now = time.monotonic()
                with self._lock:
                    if now - prev > self.consumer_s / 2:  # the launcher did not run: nothing judged
                        for nid in self._last:
                            self._heard_at(nid, now)
                    prev = now
                    if msg is not None:
                        self._heard(msg, now)
                    self._judge(now)
        except (can.CanError, OSError, ValueError) as exc:
            if not self._stop_event.is_set():
                logger.info("liveness watch stopped: %s", exc)  # the bus is gone (the hub ended)
        finally:
            if self._bus is not None:
                with contextlib.suppress(can.CanError, OSError):
                    self._bus.shutdown()

    def _heard(self, msg: can.Message, now: float) -> None:
        nid = msg.arbitration_id - HEARTBEAT_BASE
        if not 0 < nid < HOST_NODE_ID or msg.is_remote_frame:
            return
        if msg.data[:1] == b"\x00":  # boot-up: heartbeats off until the host configures them again
            self._last.pop(nid, None)
            self._close(nid, now)
            return
        self._heard_at(nid, now)
        self._close(nid, now)

    def _heard_at(self, nid: int, now: float) -> None:
        self._last[nid] = now
        if self._ledger is not None:
            self._ledger.heard(nid)

    def _waited(self, overdue: list[int], now: float, where: Any, kept: int) -> list[int]:
        """``overdue`` without the nodes whose silence a wait for a CPU explains (each kept as a
        ``waited`` silence, judged from now)."""
        if self._ledger is None:
            return overdue
        names = {pid: name for name, pid in (self._pids() if self._pids is not None else {}).items()}
        left = []
        for nid in overdue:
            excuse = self._ledger.judge(nid, now - self._last[nid], self.consumer_s)
            if excuse is None:
                left.append(nid)
                continue
            if excuse.pending:  # its process or the hub waits for a CPU now: the next round judges
                continue
            carrier = names.get(excuse.pid, f"pid {excuse.pid}")
            silence = Silence(nid, self._last[nid], now, time.time(), now, where, kept, "waited", carrier, excuse.waited_s)
            self.silences.append(silence)
            self._last[nid] = now  # judged from now
        return left

    def _close(self, nid: int, now: float) -> None:
        for key in (nid, -1):  # the node's own silence, or the hub's
            silence = self._open.pop(key, None)
            if silence is not None and silence.t_heard_mono is None:
                silence.t_heard_mono = now

    def _judge(self, now: float) -> None:
        overdue = [nid for nid, t in self._last.items() if now - t > self.consumer_s and nid not in self._open]
        if not overdue or -1 in self._open:
            return
        where = self.where() if self.where is not None else None
        kept = self.kept() if self.kept is not None else 0
        overdue = self._waited(overdue, now, where, kept)
        if not overdue:
            return
        silent_all = len(self._last) > 1 and all(now - t > self.consumer_s for t in self._last.values())
        if silent_all:
            silence = Silence(None, max(self._last.values()), now, time.time(), where=where, kept=kept)
            self._open[-1] = silence
            for nid in self._last:
                self._open[nid] = silence
            self.silences.append(silence)
            logger.info("every node silent for %.0f ms: the bus (hub)", 1000 * (now - silence.t_last_mono))
            return
        for nid in overdue:
            silence = Silence(nid, self._last[nid], now, time.time(), where=where, kept=kept)
            self._open[nid] = silence
            self.silences.append(silence)
            logger.info("node %d silent for %.0f ms", nid, 1000 * (now - silence.t_last_mono))

    def heard(self, node_id: int) -> bool:
        """Whether ``node_id``'s heartbeat was heard since its last boot-up (the host consumes it
        then, and notices when it stops)."""
        with self._lock:
            return node_id in self._last

    def settle(self, since: float) -> list[Silence]:
        """Wait until every tracked node was heard after ``since`` (``t_mono``, the host's end) or
        a consumer time passed, then stop; every silence seen."""
        deadline = since + self.consumer_s + POLL_S
        while self.is_alive() and time.monotonic() < deadline:
            with self._lock:
                if all(t > since for t in self._last.values()) and not self._open:
                    break
            time.sleep(POLL_S / 2)
        self.stop()
        with self._lock:
            return list(self.silences)

    def stop(self) -> None:
        """End the watch (idempotent)."""
        self._stop_event.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=1.0)


class StopWatch:
    """Processes seen stopped (``T`` in ``/proc/PID/stat``: SIGSTOP) for longer than the nodes'
    consumer time, by the launcher's watch loop (:meth:`look`, every few tens of ms): the stall of
    a process whose heartbeat nobody consumes at that moment (the bring-up, before its heartbeat is
    configured; the host after its own heartbeat stopped) is seen too.

    :param where: the run's position now, or None
    :param kept: the trials the summary holds now
    """

    def __init__(self, where: Callable[[], Any] | None = None, kept: Callable[[], int] | None = None) -> None:
        self.where, self.kept = where, kept
        self.consumer_s = CONSUMER_TIME_MS / 1000.0 * timeout_scale()
        self.silences: list[Silence] = []
        self._since: dict[str, float] = {}
        self._open: dict[str, Silence] = {}

    def look(self, procs: dict[str, int]) -> None:
        """One look at the processes ``procs`` (name → pid)."""
        now = time.monotonic()
        for name, pid in procs.items():
            if process_stopped(pid):
                since = self._since.setdefault(name, now)
                if name not in self._open and now - since > self.consumer_s:
                    nid = None if name == "hub" else node_id_of(name)
                    where = self.where() if self.where is not None else None
                    kept = self.kept() if self.kept is not None else 0
                    silence = Silence(nid, since, now, time.time(), where=where, kept=kept, how="stopped")
                    self._open[name] = silence
                    self.silences.append(silence)
                    logger.info("%s (pid %d) stopped for %.0f ms", name, pid, 1000 * (now - since))
            else:
                self._since.pop(name, None)
                ended = self._open.pop(name, None)
                if ended is not None:
                    ended.t_heard_mono = now


def process_stopped(pid: int) -> bool:
    """The process is stopped (state ``T``: SIGSTOP); False when it is gone or cannot be read."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            stat = fh.read()
    except OSError:
        return False
    return stat.rsplit(b")", 1)[-1].split()[:1] == [b"T"]


def first_per_node(silences: list[Silence]) -> list[Silence]:
    """The first silence of each node (the heartbeat consumer and the stop watch see the same
    stall), in the order noticed."""
    seen: set[str] = set()
    out = []
    for s in sorted(silences, key=lambda x: x.t_noticed_mono):
        if s.node not in seen:
            seen.add(s.node)
            out.append(s)
    return out


def judge_silences(
    silences: list[Silence], planned: int, t_safe_mono: float, injections: list[dict[str, Any]]
) -> tuple[list[FaultRecord], list[dict[str, Any]]]:
    """The silences noticed before ``t_safe_mono`` (the results were not yet safe) as fault
    records, the later ones as incidents (JSON-ready); ``planned``: the run's trials."""
    faults: list[FaultRecord] = []
    incidents: list[dict[str, Any]] = []
    for s in silences:
        if s.how == "waited":  # no fault, said in the summary
            position, trial = position_of(s.kept, planned, False)
            silent_ms = 1000.0 * (s.t_noticed_mono - s.t_last_mono)
            incidents.append(
                {
                    "node": s.node,
                    "what": (
                        f"{s.node} silent for {silent_ms:.0f} ms while {s.carrier} waited {1000 * s.waited_s:.0f} ms "
                        "for a CPU (the machine had none to spare): judged from then on, not a fault"
                    ),
                    "silent_ms": round(silent_ms, 1),
                    "position": str(position),
                    "trial": trial,
                    "t_noticed_mono": s.t_noticed_mono,
                    "t_noticed_wall": s.t_noticed_wall,
                    "detected_by": "launcher",
                }
            )
    for s in first_per_node([s for s in silences if s.how != "waited"]):
        node = s.node
        w = s.where
        in_trial = w is not None and bool(getattr(w, "in_trial", False)) and w.trial >= s.kept and s.kept < planned
        silent = s.silent_ms
        verb = "stopped" if s.how == "stopped" else "silent"
        text = f"{verb} for {silent:.0f} ms" if silent is not None else f"{verb} until the end of the run"
        if s.t_noticed_mono >= t_safe_mono:
            position, trial = position_of(s.kept, planned, False)
            incidents.append(
                {
                    "node": node,
                    "what": f"{node} {text} ({s.how}; results safe already)",
                    "silent_ms": None if silent is None else round(silent, 1),
                    "position": str(position),
                    "trial": trial,
                    "t_noticed_mono": s.t_noticed_mono,
                    "t_noticed_wall": s.t_noticed_wall,
                    "detected_by": "launcher",
                }
            )
            continue
        if s.how == "stopped":
            what = f"{node} {text} (its process stopped, seen by the launcher)"
        else:
            what = f"{'every node' if s.node_id is None else 'heartbeat of ' + node} {text} (the launcher's heartbeat consumer)"
        kind = FaultKind.NODE_LOST
        if s.node_id is None:
            kind = FaultKind.BUS_SILENT
        elif s.node_id == HOST_NODE_ID:
            kind = FaultKind.HOST_LOST
        record = FaultRecord(
            kind,
            what,
            node=node,
            node_id=s.node_id,
            tick=w.tick if in_trial and w is not None else None,
            detected_by="launcher",
            t_detected_mono=s.t_noticed_mono,
            t_detected_wall=s.t_noticed_wall,
            latency_ms=1000.0 * (s.t_noticed_mono - s.t_last_mono),
            latency_basis="its last heartbeat (consumer time)" if s.how == "heartbeat" else "its stop (consumer time)",
        )
        attach_injection(record, injections)
        place(record, None, s.kept, planned, in_trial)
        faults.append(record)
    return faults, incidents
