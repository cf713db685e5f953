"""The host's heartbeat producer (node 127) on the fieldbus.

This module owns :class:`HostHeartbeat`: a thread that sends state OPERATIONAL on COB-ID
``0x700 + HOST_NODE_ID`` every period with canopen's ``Network.send_message``.  Every node
consumes it (0x1016, set up by :mod:`host.rig.bring_up`), so the nodes notice when the host is
lost; timing: :mod:`bus.cia301.nmt`.  It keeps the longest gap between two of its beats (this
process stopped, or starved of the CPU): a gap longer than the nodes' consumer time means they
have lost the host (:meth:`HostHeartbeat.take_gap`).
"""

from __future__ import annotations

import logging
import threading
import time

import can
import canopen

from bus.cia301.nmt import HOST_NODE_ID, NmtState, heartbeat_cob_id

logger = logging.getLogger(__name__)

__all__ = ["HostHeartbeat"]


class HostHeartbeat(threading.Thread):
    """The host's heartbeat producer: state OPERATIONAL on COB-ID ``0x700 + node_id`` every
    ``period_s`` seconds, sent with canopen's ``Network.send_message`` from this thread.  A failing
    send (the bus gone) ends the thread and is kept in :attr:`error`."""

    def __init__(self, network: canopen.Network, period_s: float, node_id: int = HOST_NODE_ID) -> None:
        super().__init__(name="host heartbeat", daemon=True)
        self.network = network
        self.period_s = float(period_s)
        self.cob_id = heartbeat_cob_id(node_id)
        #: why the producer stopped on its own (the bus failed), else None
        self.error: str | None = None
        #: when that was seen (``time.monotonic()``, s)
        self.error_t: float | None = None
        self.sent = 0
        self._stop_event = threading.Event()
        self._lock = threading.Lock()
        self._last_sent: float | None = None
        #: the longest gap between two beats not taken yet: (gap s, t_mono of the beat that ended it)
        self._gap: tuple[float, float] | None = None

    def run(self) -> None:
        due = time.monotonic()
        while not self._stop_event.is_set():
            try:
                self.network.send_message(self.cob_id, bytes([NmtState.OPERATIONAL]))
                self.sent += 1
                self._note_beat(time.monotonic())
            except (can.CanError, OSError) as exc:
                self.error_t = time.monotonic()
                self.error = f"{type(exc).__name__}: {exc}"
                logger.warning("host heartbeat stopped: %s", self.error)
                return
            due += self.period_s
            now = time.monotonic()
            if due < now:  # this process was not running (stopped): no burst of late beats
                due = now + self.period_s
            self._stop_event.wait(due - now)

    def _note_beat(self, t: float) -> None:
        with self._lock:
            if self._last_sent is not None:
                gap = t - self._last_sent
                if self._gap is None or gap > self._gap[0]:
                    self._gap = (gap, t)
            self._last_sent = t

    def take_gap(self, longer_than_s: float, since: float | None = None) -> tuple[float, float] | None:
        """The longest gap between two beats (s, and ``t_mono`` of the beat that ended it) if it was
        longer than ``longer_than_s`` and began after ``since``; forgets it. Also the gap running
        now (no beat for that long: this process runs again, its heartbeat thread not yet)."""
        now = time.monotonic()
        with self._lock:
            gap, self._gap = self._gap, None
            if (
                self._last_sent is not None
                and now - self._last_sent > longer_than_s
                and (gap is None or now - self._last_sent > gap[0])
            ):
                gap = (now - self._last_sent, now)
        if gap is None or gap[0] <= longer_than_s or (since is not None and gap[1] - gap[0] < since):
            return None
        return gap

    def stop(self) -> None:
        """Stop producing (the nodes' consumers notice it unless they are NMT STOPPED)."""
        self._stop_event.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=1.0)
