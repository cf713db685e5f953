"""What the host hears from its nodes on the fieldbus: heartbeats and EMCY frames.

This module owns :class:`NodeEvents`, a thread-safe record fed by canopen's own consumers
(``RemoteNode.nmt`` heartbeat callbacks and ``RemoteNode.emcy`` callbacks, in the canopen
notifier's thread): the nodes' heartbeats in a :class:`bus.cia301.nmt.HeartbeatConsumer` (their NMT
state, when last heard, overdue nodes, boot-ups), every EMCY frame for the summary, and the EMCY
frames with an error code that the watchdog has not looked at yet.  The bring-up, the watchdog and
the shutdown ask it; times are ``time.monotonic()`` seconds.
"""

from __future__ import annotations

import functools
import threading
import time
from typing import Any

import canopen

from bus.cia301.nmt import HeartbeatConsumer, HeartbeatReport, NmtState
from bus.objects import DRIVE_NODE_IDS
from bus.plant_objects import DEFAULT_PLANT_NODE_ID as PLANT_NODE_ID
from bus.run_queue import RunQueueLedger
from host.rig.fault_classify import EmcyFrame

__all__ = ["NODE_IDS", "NodeEvents"]

#: the nodes of the rig: the four drives and the plant node
NODE_IDS = (*DRIVE_NODE_IDS, PLANT_NODE_ID)


class NodeEvents:
    """The nodes' heartbeats and EMCY frames as heard (see the module docstring).

    :param consumer_s: the host's consumer time of a node's heartbeat, s
    :param t_start: the host's start (``time.monotonic()``, s), origin of the EMCY log's ``t_s``
    :param ledger: the waits for a CPU of the hub that carries the heartbeats (:mod:`bus.run_queue`)
    :ivar emcy: every EMCY frame heard: node, code, register, data (hex), ``t_s``
    """

    def __init__(self, consumer_s: float, t_start: float, ledger: RunQueueLedger | None = None) -> None:
        self.consumer_s = consumer_s
        self.emcy: list[dict[str, Any]] = []
        self._t_start = t_start
        self._heartbeats = HeartbeatConsumer(ledger=ledger)
        self._pending_emcy: list[EmcyFrame] = []
        self._lock = threading.Lock()

    def listen_to(self, node_id: int, node: canopen.RemoteNode) -> None:
        """Hear ``node``'s heartbeats and EMCY frames."""
        node.nmt.add_heartbeat_callback(functools.partial(self.on_heartbeat, node_id))
        node.emcy.add_callback(functools.partial(self.on_emcy, node_id))

    def on_heartbeat(self, node_id: int, state: int) -> None:
        with self._lock:
            self._heartbeats.on_heartbeat(node_id, bytes([state]), time.monotonic())

    def on_emcy(self, node_id: int, err: canopen.emcy.EmcyError) -> None:
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
                self._pending_emcy.append(EmcyFrame(node_id, int(err.code), bytes(err.data), t_rx - late, now_wall - late))

    def take_emcy(self) -> list[EmcyFrame]:
        """The EMCY frames with an error code heard since the last call."""
        with self._lock:
            pending, self._pending_emcy = self._pending_emcy, []
        return pending

    def watch(self, node_id: int) -> None:
        """Judge ``node_id``'s heartbeat from now on (consumer time :attr:`consumer_s`)."""
        with self._lock:
            self._heartbeats.watch(node_id, self.consumer_s)

    def grace(self, now: float) -> None:
        """Count every watched node as heard at ``now`` (this process could not run meanwhile)."""
        with self._lock:
            self._heartbeats.grace(now)

    def states(self, node_ids: set[int]) -> dict[int, NmtState | None]:
        """The NMT state each node last reported (None: never heard)."""
        with self._lock:
            return {nid: self._heartbeats.state(nid) for nid in node_ids}

    def last_heard(self) -> dict[int, float | None]:
        """When each node of the rig was last heard (None: never)."""
        with self._lock:
            return {nid: self._heartbeats.last_heard(nid) for nid in NODE_IDS}

    def alive(self, now: float) -> set[int]:
        """The nodes heard within the consumer time before ``now``."""
        return {nid for nid, t in self.last_heard().items() if t is not None and now - t <= self.consumer_s}

    def stopped_since(self, node_id: int, t: float) -> float | None:
        """When ``node_id`` reported NMT STOPPED in a heartbeat heard after ``t`` (None: not yet)."""
        with self._lock:
            last = self._heartbeats.last_heard(node_id)
            if last is not None and last > t and self._heartbeats.state(node_id) == NmtState.STOPPED:
                return last
        return None

    def report(self, now: float | None = None) -> HeartbeatReport:
        """The watched nodes overdue at ``now`` (default: now) and the boot-ups since the last
        report, which it forgets."""
        with self._lock:
            return self._heartbeats.report_at(time.monotonic() if now is None else now)
