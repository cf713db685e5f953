"""Optional capabilities of a python-can bus beyond :class:`can.BusABC`, and how callers use them.

This module owns the two documented extras a transport may offer on top of python-can's
``BusABC`` (which stays the interface of every transport); callers use an extra only when the
bus declares it — an ``isinstance`` check against the :class:`typing.Protocol` below, done once
when the caller is built — and fall back to plain ``BusABC`` calls otherwise:

* :class:`BatchSender` — ``send_batch(msgs)``: several frames in one write (the ilcrig hub
  client, :class:`bus.transports.hub_client.HubBus`, sends them as one socket write; the
  frames reach the bus in order, exactly as with one :meth:`can.BusABC.send` each).
  :func:`batch_sender` returns ``send_batch`` or a loop over ``send``.
* :class:`BufferedReceiver` — ``frames_pending()``: the bus reads several frames per system
  call into a local queue, so a frame may be waiting although ``fileno()`` is not readable. A
  ``select()``-based caller must not wait while ``frames_pending()`` is true
  (:func:`pending_check` gives it a cheap callable, always False for a bus without a queue).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import can

logger = logging.getLogger(__name__)

__all__ = ["BatchSender", "BufferedReceiver", "batch_sender", "pending_check"]


@runtime_checkable
class BatchSender(Protocol):
    """A bus that sends several frames in one operation, in order."""

    def send_batch(self, msgs: Sequence[can.Message]) -> None:
        """Send ``msgs`` in order, as :meth:`can.BusABC.send` would one by one.

        :raises can.CanOperationError: as :meth:`can.BusABC.send`
        """
        ...


@runtime_checkable
class BufferedReceiver(Protocol):
    """A bus that may hold received frames in a local queue (not visible to ``select()``)."""

    def frames_pending(self) -> bool:
        """True when :meth:`can.BusABC.recv` would return a frame without reading the socket."""
        ...


def batch_sender(bus: can.BusABC) -> Callable[[Sequence[can.Message]], None]:
    """``bus.send_batch`` when ``bus`` is a :class:`BatchSender`, else one ``bus.send`` per frame."""
    if isinstance(bus, BatchSender):
        return bus.send_batch

    def send_each(msgs: Sequence[can.Message]) -> None:
        for msg in msgs:
            bus.send(msg)

    return send_each


def _never() -> bool:
    return False


def pending_check(bus: can.BusABC) -> Callable[[], bool]:
    """``bus.frames_pending`` when ``bus`` is a :class:`BufferedReceiver`, else a callable that
    is always False (the bus's ``fileno()`` readiness tells everything)."""
    if isinstance(bus, BufferedReceiver):
        return bus.frames_pending
    return _never
