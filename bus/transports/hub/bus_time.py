"""Hub bus time: logical buses delivered as a real CAN bus at its bit rate would carry them.

This module owns the arbitration order (:func:`arbitration_key`), the bit time of a frame record
(:func:`bit_time_ns`), the virtual bus clock of one logical bus (:class:`BusClock`), the bus-time
buses of a hub (:class:`BusTime`) and the ``--bus-time BUS=BIT_S`` option's parsing
(:func:`parse_bus_time`).

Bus time (``--bus-time BUS=BIT_S``, :class:`bus.transports.hub.server.HubServer` ``bus_time``)
    Every frame waits in its sender's transmit queue (first in, first out, like one controller's
    queue), and whenever the bus is free the waiting frames compete in arbitration — the lowest
    identifier wins (an 11-bit data frame before a remote frame or a 29-bit frame with the same
    base identifier) among the frames that had arrived by then.  The winner occupies the bus for
    its classic-CAN bit length with worst-case stuffing (:func:`bus.busload.bits_lookup`, the
    3-bit intermission included) at the bus's bit rate, on a virtual clock (monotonic ns) that
    runs back to back while frames wait and never drifts: each frame starts when the previous one
    ended, or when it arrived if the bus was idle.  It is delivered when its transmission ends,
    stamped with that end time, so a receiver's timestamps show the bus time (two frames sent back
    to back are exactly one bit time apart).  A damaged frame (a bus error frame from the fault
    hook) occupies the bus like the frame it replaced; CAN FD frames are not modelled (as in the
    bus-load counts) and pass at once.  A sender more than :attr:`BusTime.queue_frames` frames
    ahead of the bus is not read until the bus has caught up (its ``send`` then blocks, like a
    full transmit queue).  Buses without a bit rate here forward at once.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar

from bus.busload import bits_lookup
from bus.transports.hub.wire import FLAG_EXT, FLAG_FD, FLAG_RTR, STAMP, STAMP_OFFSET, U32


class Sender(Protocol):
    """A member whose frames wait for the bus (the hub's :class:`bus.transports.hub.routing.Client`)."""

    #: not read for now: too many of its frames wait for the bus
    paused: bool


S = TypeVar("S", bound=Sender)


def arbitration_key(can_id: int, flags: int) -> tuple[int, int, int, int]:
    """The order in which CAN arbitration lets frames win (lower first): the 11 base identifier
    bits, then an 11-bit frame before a 29-bit one (IDE), then the 18 extension bits, then a data
    frame before a remote frame (RTR)."""
    rtr = 1 if flags & FLAG_RTR else 0
    if flags & FLAG_EXT:
        return (can_id >> 18) & 0x7FF, 1, can_id & 0x3FFFF, rtr
    return can_id & 0x7FF, 0, 0, rtr


def bit_time_ns(length: int, flags: int, bitrate: int) -> int:
    """How long a frame record (data ``length`` bytes, wire ``flags``) occupies a classic CAN bus
    at ``bitrate`` bit/s, ns: worst-case stuffed bit length incl. the intermission (a remote
    frame carries no data; an FD frame is not modelled: 0)."""
    if flags & FLAG_FD:
        return 0
    bits = bits_lookup(0 if flags & FLAG_RTR else min(length, 8), bool(flags & FLAG_EXT))[1]
    return (bits * 1_000_000_000 + bitrate // 2) // bitrate


def checked_bus_time(bus_time: Mapping[str, int] | None) -> dict[str, int]:
    """``bus_time`` (logical bus → bit rate, bit/s) as ints.

    :raises ValueError: a bit rate that is not positive
    """
    out = {name: int(rate) for name, rate in (bus_time or {}).items()}
    for name, rate in out.items():
        if rate <= 0:
            raise ValueError(f"bus time of {name!r}: the bit rate must be > 0 bit/s, got {rate}")
    return out


def parse_bus_time(items: Sequence[str]) -> dict[str, int]:
    """``["io=500000", "fieldbus=1000000"]`` → ``{"io": 500000, "fieldbus": 1000000}``.

    :raises ValueError: not ``BUS=BIT_S`` with a positive integer bit rate
    """
    out: dict[str, int] = {}
    for item in items:
        name, sep, rate = item.partition("=")
        if not sep or not name or not rate.isdigit() or int(rate) <= 0:
            raise ValueError(f"--bus-time {item!r}: expected BUS=BIT_S with a bit rate > 0, e.g. io=1000000")
        out[name] = int(rate)
    return out


@dataclass(eq=False)
class BusClock(Generic[S]):
    """Bus-time delivery of one logical bus: the transmit queue of every sender, the frame on the
    bus and the virtual clock (monotonic ns)."""

    bitrate: int
    #: per sender: (arrival [monotonic ns], arbitration key, bit time [ns], record), oldest first
    queues: dict[S, deque[tuple[int, tuple[int, int, int, int], int, bytes]]] = field(default_factory=dict)
    #: the frame on the bus: (end of its transmission [monotonic ns], sender, record)
    current: tuple[int, S, bytes] | None = None
    #: when the bus became free (the end of the last frame), monotonic ns
    free_ns: int = 0

    def enqueue(self, sender: S, rec: bytes, arrival_ns: int) -> bool:
        """``rec`` (a frame record that arrived at ``arrival_ns``, monotonic ns) joins its sender's
        transmit queue. Returns False for a CAN FD frame (not modelled: the caller delivers it at
        once)."""
        flags = rec[1]
        if flags & FLAG_FD:
            return False
        queue = self.queues.get(sender)
        if queue is None:
            queue = self.queues[sender] = deque()
        queue.append(
            (arrival_ns, arbitration_key(U32.unpack_from(rec, 4)[0], flags), bit_time_ns(rec[3], flags, self.bitrate), rec)
        )
        return True

    def backlog(self, sender: S) -> int:
        """How many frames of ``sender`` wait for the bus."""
        return len(self.queues.get(sender, ()))


class BusTime(Generic[S]):
    """The bus-time buses of one hub (see the module docstring).

    :param rates: logical bus name → bit rate, bit/s (each > 0)
    :raises ValueError: a bit rate that is not positive
    """

    #: default of :attr:`queue_frames`
    QUEUE_FRAMES: int = 4096

    def __init__(self, rates: Mapping[str, int]) -> None:
        self.clocks: dict[str, BusClock[S]] = {name: BusClock(rate) for name, rate in checked_bus_time(rates).items()}
        #: a sender with this many frames waiting for the bus is not read until they are sent
        self.queue_frames = self.QUEUE_FRAMES
        #: wall-clock ns minus monotonic ns: bus-time stamps are monotonic times shown as wall-clock ones
        self._epoch_offset_ns = time.time_ns() - time.monotonic_ns()

    def clock(self, bus: str) -> BusClock[S] | None:
        """The clock of logical bus ``bus``, None if it is not delivered in bus time."""
        return self.clocks.get(bus)

    def forget(self, sender: S) -> None:
        """Drop the frames of a member that left."""
        for clock in self.clocks.values():
            clock.queues.pop(sender, None)

    def next_end_ns(self) -> int | None:
        """When the next frame on a bus ends its transmission (monotonic ns), None if every bus is idle."""
        ends = [c.current[0] for c in self.clocks.values() if c.current is not None]
        return min(ends) if ends else None

    def run(self, now_ns: int, deliver: Callable[[S, bytes], None], resume: Callable[[S], None]) -> None:
        """Every bus-time bus: ``deliver`` the frames whose transmission ended by ``now_ns``
        (monotonic ns; the record stamped with that end), start the next ones (arbitration among
        the frames that had arrived when the bus became free), and ``resume`` a paused sender
        once half of its queue has gone."""
        for clock in self.clocks.values():
            while True:
                if clock.current is not None:
                    end_ns, sender, rec = clock.current
                    if end_ns > now_ns:
                        break
                    clock.current = None
                    clock.free_ns = end_ns
                    stamped = bytearray(rec)
                    STAMP.pack_into(stamped, STAMP_OFFSET, end_ns + self._epoch_offset_ns)
                    deliver(sender, bytes(stamped))
                    if sender.paused and clock.backlog(sender) < self.queue_frames // 2:
                        sender.paused = False
                        resume(sender)
                heads = [(q[0][0], q[0][1], s) for s, q in clock.queues.items() if q]
                if not heads:
                    break
                start_ns = max(clock.free_ns, min(h[0] for h in heads))
                winner = min((h for h in heads if h[0] <= start_ns), key=lambda h: h[1])[2]
                _, _, bit_ns, rec = clock.queues[winner].popleft()
                clock.current = (start_ns + bit_ns, winner, rec)
