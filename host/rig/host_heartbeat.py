"""The host's heartbeat producer (node 127) on the fieldbus.

This module owns :class:`HostHeartbeat`: a thread that sends state OPERATIONAL on COB-ID
``0x700 + HOST_NODE_ID`` every period with canopen's ``Network.send_message``.  Every node
consumes it (0x1016, set up by :mod:`host.rig.bring_up`), so the nodes notice when the host is
lost; timing: :mod:`bus.cia301.nmt`.
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

    def run(self) -> None:
        due = time.monotonic()
        while not self._stop_event.is_set():
            try:
                self.network.send_message(self.cob_id, bytes([NmtState.OPERATIONAL]))
                self.sent += 1
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

    def stop(self) -> None:
        """Stop producing (the nodes' consumers notice it unless they are NMT STOPPED)."""
        self._stop_event.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=1.0)
