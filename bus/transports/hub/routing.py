"""Hub routing: the members of each logical bus and who gets which frame.

This module owns :class:`Client` (one connection to the hub: a member of a logical bus, or a stats
query) and :class:`Router`: the logical buses and their members, the bitrate rule, acceptance
filters, fan-out, the per-round delivery queues and the frame-fault hook. It is the pure-Python
data plane; the C core (:mod:`bus.transports.hub.core`) follows the same rules.

Forwarding
    Every frame a member sends is forwarded to every other member of the same logical bus, never
    back to the sender (unless the sender asked for ``receive_own_messages``; it then gets its own
    frames back flagged as echo). Every record is stamped with the hub's receive time of the read
    that completed it.

Classic CAN members and bitrates
    A member that joined with the classic-CAN flag (``fd=False``) gets no FD frames. The first
    member of an empty logical bus sets the bus's bitrate and data bitrate (0 = not given); a later
    member asking for a different non-zero one is refused, one giving none adopts the bus's (sent
    back in the handshake answer).

Acceptance filters
    A member's filters (a filter record, see :mod:`bus.transports.hub.wire`) are applied here: only
    matching frames are forwarded to it (like SocketCAN's kernel filters). Bus error frames reach
    every member whatever its filters, as SocketCAN delivers them by the socket's error mask, which
    python-can's SocketcanBus opens to every error class: a node hears that frames were damaged or
    lost whatever it accepts.

Delivery
    The frames routed in one round of the hub's loop (all ready members) are queued per
    destination and written with one ``send`` per destination at the end of the round (a member
    that joined for bulk delivery, e.g. a monitor, gets them held up to ``BULK_HOLD_S`` or
    ``BULK_MAX_BYTES``, in fewer writes; a release record of its own has them sent at once). Who
    gets a frame of a given sender and identifier is cached per logical bus until a member joins,
    leaves or changes its filters.

Counting
    Every frame record is counted on its logical bus as sent (:mod:`bus.transports.hub.stats`),
    before faults or bus time act on it.

Frame faults
    An optional ``hook`` (:class:`bus.transports.fault_inject.FrameFaultInjector`, from
    ``--inject JSON``) decides for every frame what is delivered and when: nothing (lost), twice, a
    bus error frame instead (damaged), or later (the hub's loop wakes for delayed frames). Without
    a hook the forwarding path is the plain one.

Bus time
    On a logical bus with a bit rate (:mod:`bus.transports.hub.bus_time`) a frame joins its
    sender's transmit queue instead of being fanned out at once; a sender too far ahead of its bus
    is paused (not read) until the bus has caught up.
"""

from __future__ import annotations

import heapq
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bus.busload import bits_lookup
from bus.transports.hub.bus_time import BusClock, BusTime
from bus.transports.hub.stats import HubChannelStats
from bus.transports.hub.wire import (
    BULK_HOLD_S,
    BULK_MAX_BYTES,
    FILTER_ENTRY,
    FLAG_ECHO,
    FLAG_ERR,
    FLAG_EXT,
    FLAG_FD,
    FLAG_RTR,
    HEADER_SIZE,
    KIND_FILTERS,
    KIND_FRAME,
    KIND_GATHER,
    KIND_RELEASE,
    ROLE_MEMBER,
    STAMP,
    STAMP_OFFSET,
    U32,
)


@dataclass(eq=False)
class Client:
    """One connection to the hub: a member of logical bus :attr:`bus` once its handshake is done
    (``role`` = member), or a stats query."""

    sock: socket.socket
    peer: str
    bus: str = ""
    role: int = 0
    echo: bool = False
    classic: bool = False
    filters: list[tuple[int, int, int]] | None = None
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    writing: bool = False
    bulk: bool = False
    held: list[bytes] = field(default_factory=list)
    held_bytes: int = 0
    held_since_s: float = 0.0
    #: > 0: its frames are held until this many are (a gather record; see send_round)
    gather: int = 0
    #: not read for now: too many of its frames wait for bus time (see BusTime.queue_frames)
    paused: bool = False
    #: refused at its handshake: why (it runs as another user; :mod:`bus.transports.hub.owner`)
    refusal: str | None = None

    def accepts(self, can_id: int, ext: int) -> bool:
        """Whether this member's acceptance filters let a frame with ``can_id`` (``ext`` 1 =
        29-bit) through (no filters: every frame)."""
        if not self.filters:
            return True
        for f_id, f_mask, f_ext in self.filters:
            if f_ext >= 0 and f_ext != ext:
                continue
            if (f_id ^ can_id) & f_mask == 0:
                return True
        return False


#: hands ``data`` to a client's socket (the server's output path)
Send = Callable[[Client, bytes], None]


class Router:
    """The logical buses of a hub and the routing of their frames (see the module docstring).

    :param send: writes bytes to a client (the server's output path, which drops a client that
        stopped reading)
    :param pause: called when a client's paused state changed (the server re-registers its socket)
    :param bus_time: the buses delivered in bus time, or None
    :param hook: the frame-fault hook, or None
    """

    def __init__(self, send: Send, pause: Callable[[Client], None], bus_time: BusTime[Client] | None, hook: Any) -> None:
        self._send = send
        self._pause = pause
        self.bus_time = bus_time
        self._hook = hook
        #: logical bus name -> its members, in joining order
        self.buses: dict[str, list[Client]] = {}
        #: logical bus name -> its counters (what the Python path counted)
        self.stats: dict[str, HubChannelStats] = {}
        #: per bus: (sender, can_id, extended, fd, error frame) -> [(member, as echo)], see recipients
        self._cache: dict[str, dict[tuple[Client, int, int, int, int], list[tuple[Client, bool]]]] = {}
        #: frames routed in the current round, per destination (see send_round)
        self._pending: dict[Client, list[bytes]] = {}
        #: bulk members holding frames (see send_round, release_held)
        self._held: dict[Client, None] = {}
        #: frames the hook delays: (due [s, monotonic], sequence, sender, record), a heap
        self._delayed: list[tuple[float, int, Client, bytes]] = []
        self._delayed_seq = 0

    # -- members ----------------------------------------------------------------------------

    def join(self, client: Client, name: str, bitrate: int, data_bitrate: int) -> str | None:
        """Make ``client`` a member of logical bus ``name`` (bitrates in bit/s, 0 = not given).

        :return: None, or why it is refused (another bitrate than the bus's)
        """
        members = self.buses.setdefault(name, [])
        st = self.stats.setdefault(name, HubChannelStats())
        if not members:  # the first member of an empty bus sets its bitrates
            st.bitrate, st.data_bitrate = bitrate, data_bitrate
        else:
            for what, have, asked in (("bitrate", st.bitrate, bitrate), ("data bitrate", st.data_bitrate, data_bitrate)):
                if have and asked and have != asked:
                    return f"bus {name!r} runs at {what} {have} bit/s, the client asked for {asked} bit/s"
            st.bitrate = st.bitrate or bitrate
            st.data_bitrate = st.data_bitrate or data_bitrate
        client.role = ROLE_MEMBER
        client.bus = name
        members.append(client)
        self._cache.pop(name, None)
        st.connections += 1
        return None

    def leave(self, client: Client) -> bool:
        """Forget ``client`` (its queued frames too). Returns whether it was a member."""
        self._pending.pop(client, None)
        self._held.pop(client, None)
        if self.bus_time is not None:
            self.bus_time.forget(client)
        members = self.buses.get(client.bus)
        if members and client in members:
            members.remove(client)
            self._cache.pop(client.bus, None)
            return True
        return False

    def recipients(self, sender: Client, can_id: int, ext: int, fd: int, err: int = 0) -> list[tuple[Client, bool]]:
        """(member, as echo) pairs that get a frame of ``sender`` (cached per bus until a member
        joins, leaves or changes its filters); a bus error frame (``err``) reaches every member
        whatever its filters, as SocketCAN delivers error frames by the socket's error mask
        (python-can's SocketcanBus opens it to all)."""
        cache = self._cache.setdefault(sender.bus, {})
        key = (sender, can_id, ext, fd, err)
        found = cache.get(key)
        if found is None:
            found = []
            for peer in self.buses[sender.bus]:
                if fd and peer.classic:
                    continue  # a classic CAN member never sees FD frames (like a non-FD raw socket)
                if peer is sender:
                    if peer.echo and (err or peer.accepts(can_id, ext)):
                        found.append((peer, True))
                elif err or peer.accepts(can_id, ext):
                    found.append((peer, False))
            cache[key] = found
        return found

    # -- records ----------------------------------------------------------------------------

    def route(self, sender: Client, stamp_ns: int) -> str | None:
        """Route every whole record of ``sender``'s input buffer: frames are stamped with
        ``stamp_ns`` (wall-clock ns) in place, counted, and queued per destination (or for bus
        time, or handed to the fault hook); filter records replace the sender's filters.

        :return: None, or why the sender must be refused (an unknown record kind)
        """
        if sender.role != ROLE_MEMBER:
            sender.inbuf.clear()  # a stats connection has nothing more to say
            return None
        buf = sender.inbuf
        size = len(buf)
        st = self.stats[sender.bus]
        pending = self._pending
        bus_time = self.bus_time
        clock = bus_time.clock(sender.bus) if bus_time is not None else None
        queue_frames = bus_time.queue_frames if bus_time is not None else 0
        arrival_ns = time.monotonic_ns() if clock is not None else 0
        hook = self._hook
        off = 0
        while size - off >= HEADER_SIZE:
            kind = buf[off]
            flags = buf[off + 1]
            length = buf[off + 3]
            if kind == KIND_FRAME:
                total = HEADER_SIZE + (length - 8 if length > 8 else 0)
                if size - off < total:
                    break
                STAMP.pack_into(buf, off + STAMP_OFFSET, stamp_ns)
                rec = bytes(buf[off : off + total])
                can_id = U32.unpack_from(buf, off + 4)[0]
                ext = 1 if flags & FLAG_EXT else 0
                fd = flags & FLAG_FD
                if flags & FLAG_ERR:
                    st.error_frames += 1
                elif fd:
                    st.fd_frames += 1
                else:
                    nominal, worst = bits_lookup(0 if flags & FLAG_RTR else min(length, 8), bool(ext))
                    st.frames += 1
                    st.bits += nominal
                    st.bits_worst_case += worst
                if hook is not None:
                    self._faults(sender, rec, can_id, flags, length, clock, arrival_ns)
                elif clock is not None:
                    if not clock.enqueue(sender, rec, arrival_ns):
                        self.fan_out(sender, rec)
                else:  # the plain path
                    for peer, echo in self.recipients(sender, can_id, ext, fd, flags & FLAG_ERR):
                        chunk = rec[:1] + bytes([flags | FLAG_ECHO]) + rec[2:] if echo else rec
                        queue = pending.get(peer)
                        if queue is None:
                            pending[peer] = [chunk]
                        else:
                            queue.append(chunk)
            elif kind == KIND_FILTERS:
                n = U32.unpack_from(buf, off + 4)[0]
                total = HEADER_SIZE + n
                if size - off < total:
                    break
                body = bytes(buf[off + HEADER_SIZE : off + total])
                sender.filters = [
                    FILTER_ENTRY.unpack_from(body, i) for i in range(0, n - n % FILTER_ENTRY.size, FILTER_ENTRY.size)
                ] or None
                self._cache.pop(sender.bus, None)
            elif kind == KIND_GATHER:
                total = HEADER_SIZE
                sender.gather = U32.unpack_from(buf, off + 4)[0]
                self.gather_changed(sender)
            elif kind == KIND_RELEASE:
                total = HEADER_SIZE
                if sender.bulk:
                    self.release_now(sender)
            else:
                return f"unknown record kind {kind}"
            off += total
        del buf[:off]
        if clock is not None and clock.backlog(sender) >= queue_frames:
            sender.paused = True  # its socket fills up: its send() blocks like a full transmit queue
            self._pause(sender)
        return None

    def _faults(
        self, sender: Client, rec: bytes, can_id: int, flags: int, length: int, clock: BusClock[Client] | None, arrival_ns: int
    ) -> None:
        """What the fault hook makes of one frame: delivered now (or into bus time), later, twice,
        damaged, or not at all."""
        data = rec[HEADER_SIZE - 8 : HEADER_SIZE - 8 + min(length, 8)]
        for delay, r in self._hook.deliveries(sender.bus, rec, can_id, data, bool(flags & FLAG_ERR)):
            if delay > 0:
                self._delayed_seq += 1
                heapq.heappush(self._delayed, (time.monotonic() + delay, self._delayed_seq, sender, bytes(r)))
            elif clock is None or not clock.enqueue(sender, bytes(r), arrival_ns):
                self.fan_out(sender, bytes(r))

    def delayed_due_s(self) -> float | None:
        """When the next delayed frame is due (monotonic s), None if none waits."""
        return self._delayed[0][0] if self._delayed else None

    def release_delayed(self) -> None:
        """Queue the delayed frames that are due (sent with the round's other frames; on a bus-time
        bus they wait for the bus from now)."""
        if not self._delayed:
            return
        now = time.monotonic()
        while self._delayed and self._delayed[0][0] <= now:
            _, _, sender, rec = heapq.heappop(self._delayed)
            clock = self.bus_time.clock(sender.bus) if self.bus_time is not None else None
            if clock is None or not clock.enqueue(sender, rec, time.monotonic_ns()):
                self.fan_out(sender, rec)

    def fan_out(self, sender: Client, rec: bytes) -> None:
        """Queue ``rec`` (a frame record of ``sender``) for every member of its bus that takes it
        (the path of faults and bus time; the same rules as the plain path of :meth:`route`)."""
        if sender.bus not in self.buses:
            return
        flags = rec[1]
        can_id = U32.unpack_from(rec, 4)[0]
        ext = 1 if flags & FLAG_EXT else 0
        fd = flags & FLAG_FD
        pending = self._pending
        for peer, echo in self.recipients(sender, can_id, ext, fd, flags & FLAG_ERR):
            pending.setdefault(peer, []).append(rec[:1] + bytes([flags | FLAG_ECHO]) + rec[2:] if echo else rec)

    # -- delivery ---------------------------------------------------------------------------

    def send_round(self) -> None:
        """One send per destination of everything routed in this round; a bulk member's frames
        are held instead (see :meth:`release_held`)."""
        pending = self._pending
        if not pending:
            return
        self._pending = {}
        for peer, chunks in pending.items():
            if peer.bulk or peer.gather:
                if not peer.held:
                    peer.held_since_s = time.monotonic()
                    self._held[peer] = None
                peer.held += chunks
                peer.held_bytes += sum(map(len, chunks))
                if peer.held_bytes >= BULK_MAX_BYTES or (peer.gather and len(peer.held) >= peer.gather):
                    self._release(peer)
            else:
                self._send(peer, chunks[0] if len(chunks) == 1 else b"".join(chunks))

    def held_due_s(self) -> float | None:
        """When the oldest held frames of a bulk member are due (monotonic s), None if none are held."""
        if not self._held:
            return None
        return min(c.held_since_s for c in self._held) + BULK_HOLD_S

    def release_held(self) -> None:
        """Send what bulk members held for :data:`BULK_HOLD_S` or longer."""
        if not self._held:
            return
        now_s = time.monotonic()
        for peer in [c for c in self._held if now_s - c.held_since_s >= BULK_HOLD_S]:
            self._release(peer)

    def release_now(self, peer: Client) -> None:
        """A bulk member's release record: what it holds and what this round routed to it so far,
        sent now."""
        chunks = self._pending.pop(peer, None)
        if chunks:
            peer.held += chunks
        if peer.held:
            self._release(peer)

    def gather_changed(self, peer: Client) -> None:
        """A member's gather record: what it holds (and this round routed to it so far) is sent
        now when that is the new count already, or when it gathers no more."""
        chunks = self._pending.pop(peer, None)
        if chunks:
            if not peer.held:
                peer.held_since_s = time.monotonic()
                self._held[peer] = None
            peer.held += chunks
            peer.held_bytes += sum(map(len, chunks))
        if peer.held and (not peer.gather or len(peer.held) >= peer.gather):
            self._release(peer)

    def _release(self, peer: Client) -> None:
        data = b"".join(peer.held)
        peer.held = []
        peer.held_bytes = 0
        self._held.pop(peer, None)
        self._send(peer, data)
