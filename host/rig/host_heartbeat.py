"""The host's heartbeat producer (node 127) on the fieldbus.

This module owns :class:`HostHeartbeat`: state OPERATIONAL on COB-ID ``0x700 + HOST_NODE_ID`` every
period.  Every node consumes it (0x1016, set up by :mod:`host.rig.bring_up`), so the nodes notice
when the host is lost; timing: :mod:`bus.cia301.nmt`.  It keeps the longest gap between two of its
beats (this process stopped, or starved of the CPU): a gap longer than the nodes' consumer time means
they have lost the host (:meth:`HostHeartbeat.take_gap`).

Who writes the beats
    On the hub (its C core built) a thread of C writes them on a member of their own
    (:meth:`bus.transports.hub.client.HubBus.periodic_writer`), without the interpreter: a law that
    computes in the host's interpreter between trials, pure Python or one call that holds the GIL,
    cannot delay them.  Why: a Python thread needs the GIL for every beat, and a thread that holds
    the GIL keeps it while the OS does not run it; on a loaded machine a beat came 505 ms late (the
    consumer time is 500 ms) while a pure-Python law ran, and every drive reported the host lost.
    This module's thread then only renews the writer's **lease** every period: the writer writes
    while the lease lasts (:data:`LEASE_CONSUMER_TIMES` consumer times from the last renewal), so a
    host whose interpreter stands still (a call that never lets go of the GIL) still stops beating
    and is lost by the nodes, a lease later.  While the law's code runs, the trial loop holds the
    lease for the law's limit (:meth:`HostHeartbeat.hold`, :mod:`host.experiment.law_watch`).  A
    stopped or dead host process stops the writer with it (it is one of its threads).
    Elsewhere (SocketCAN, UDP multicast, python-can's virtual bus, a hub without its C core) this
    module's thread sends the beats itself with canopen's ``Network.send_message``.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any

import can
import canopen

from bus.cia301.nmt import HOST_NODE_ID, NmtState, heartbeat_cob_id

logger = logging.getLogger(__name__)

__all__ = ["LEASE_CONSUMER_TIMES", "HostHeartbeat"]

#: the writer's lease, in the nodes' consumer times: how long the beats go on without this
#: module's thread running (outside :meth:`HostHeartbeat.hold`)
LEASE_CONSUMER_TIMES = 2.0


class HostHeartbeat(threading.Thread):
    """The host's heartbeat producer: state OPERATIONAL on COB-ID ``0x700 + node_id`` every
    ``period_s`` seconds (module docstring).  A failing send (the bus gone) ends the thread and is
    kept in :attr:`error`.

    :param network: the host's canopen network (sends the beats when there is no writer)
    :param period_s: the producer period, s
    :param node_id: the producer's node id
    :param own_bus: a member of the fieldbus of its own for the beats, opened with
        :data:`bus.transports.hub.client.NOTHING_IN` (None, or a bus without a periodic writer:
        this thread sends); closed by :meth:`stop`
    :param lease_s: the writer's lease, s (module docstring)
    """

    def __init__(
        self,
        network: canopen.Network,
        period_s: float,
        node_id: int = HOST_NODE_ID,
        *,
        own_bus: can.BusABC | None = None,
        lease_s: float = float("inf"),
    ) -> None:
        super().__init__(name="host heartbeat", daemon=True)
        self.network = network
        self.period_s = float(period_s)
        self.cob_id = heartbeat_cob_id(node_id)
        self.lease_s = float(lease_s)
        #: why the producer stopped on its own (the bus failed), else None
        self.error: str | None = None
        #: when that was seen (``time.monotonic()``, s)
        self.error_t: float | None = None
        self._sent = 0
        self._stop_event = threading.Event()
        self._lock = threading.Lock()
        self._last_sent: float | None = None
        #: the longest gap between two beats not taken yet: (gap s, t_mono of the beat that ended it)
        self._gap: tuple[float, float] | None = None
        #: until when (t_mono) the lease is held (:meth:`hold`), else None
        self._held_until: float | None = None
        self._own_bus = own_bus
        self._writer: Any = None
        if own_bus is not None:
            msg = can.Message(arbitration_id=self.cob_id, data=[NmtState.OPERATIONAL], is_extended_id=False)
            try:
                self._writer = own_bus.periodic_writer(msg, self.period_s)  # type: ignore[attr-defined]
                self._writer.lease(self.lease_s)
            except (AttributeError, can.CanOperationError) as exc:
                logger.info("host heartbeat: sent by a Python thread (%s)", exc)
                self._close_own_bus()

    @property
    def in_c(self) -> bool:
        """Whether a thread of C writes the beats (module docstring)."""
        return self._writer is not None

    @property
    def sent(self) -> int:
        """Beats sent so far."""
        return int(self._writer.state()[0]) if self._writer is not None else self._sent

    def run(self) -> None:
        due = time.monotonic()
        while not self._stop_event.is_set():
            if self._writer is not None:
                if not self._renew():
                    return
            else:
                try:
                    self.network.send_message(self.cob_id, bytes([NmtState.OPERATIONAL]))
                    self._sent += 1
                    self._note_beat(time.monotonic())
                except (can.CanError, OSError) as exc:
                    self._failed(f"{type(exc).__name__}: {exc}", time.monotonic())
                    return
            due += self.period_s
            now = time.monotonic()
            if due < now:  # this process was not running (stopped): no burst of late beats
                due = now + self.period_s
            self._stop_event.wait(due - now)

    def _renew(self) -> bool:
        """The writer's lease renewed; False once it has failed (kept in :attr:`error`)."""
        failure = self._writer.state()[3]
        if failure is not None:
            code, t = failure
            self._failed(f"{os.strerror(code)} (errno {code}, the heartbeat's writer)", t)
            return False
        self._writer.lease(self._lease())
        return True

    def _lease(self) -> float:
        """The writer's lease from now, s: :attr:`lease_s`, or longer while :meth:`hold` holds it."""
        with self._lock:
            held = self._held_until
        return self.lease_s if held is None else max(self.lease_s, held - time.monotonic())

    def _failed(self, why: str, t: float) -> None:
        self.error_t = t
        self.error = why
        logger.warning("host heartbeat stopped: %s", self.error)

    def hold(self, seconds: float | None) -> None:
        """Beat on for ``seconds`` from now whether or not this process's interpreter runs (a law's
        code runs meanwhile); None: back to the lease of :attr:`lease_s`.  Without a writer (this
        thread sends) nothing changes."""
        with self._lock:
            self._held_until = None if seconds is None else time.monotonic() + float(seconds)
        if self._writer is not None:
            self._writer.lease(self._lease())

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
        if self._writer is not None:
            _, last_sent, gap, _, _ = self._writer.state(True)
        else:
            with self._lock:
                gap, self._gap = self._gap, None
                last_sent = self._last_sent
        if last_sent is not None and now - last_sent > longer_than_s and (gap is None or now - last_sent > gap[0]):
            gap = (now - last_sent, now)
        if gap is None or gap[0] <= longer_than_s or (since is not None and gap[1] - gap[0] < since):
            return None
        return gap

    def stop(self) -> None:
        """Stop producing (the nodes' consumers notice it unless they are NMT STOPPED)."""
        self._stop_event.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=1.0)
        if self._writer is not None:
            self._writer.stop()
        self._close_own_bus()

    def _close_own_bus(self) -> None:
        bus, self._own_bus = self._own_bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError) as exc:
                logger.debug("host heartbeat's bus: %s", exc)
