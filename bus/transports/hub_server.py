"""Hub server: the hub process, its counters, and starting it as a child process.

This module owns the server side of the zero-privilege CAN hub (no root, no kernel module):
:class:`HubServer` (one process that accepts clients on a Unix domain socket, the default,
or on loopback TCP, and forwards frames between the members of each logical bus), its
per-bus counters (:class:`HubChannelStats`, :func:`query_hub_stats`), the child-process API
(:func:`start_hub`, :class:`HubHandle`) and the command line :func:`main`
(``ilcrig hub`` / ``python -m bus.transports.hub_server``). The wire format and the
addresses are :mod:`bus.transports.hub_wire`'s; the client is
:class:`bus.transports.hub_client.HubBus`.

Forwarding
    Every frame a member sends is forwarded to every other member of the same logical bus,
    never back to the sender (unless the sender asked for ``receive_own_messages``; it then
    gets its own frames back flagged as echo). A listen address that is not loopback is
    refused (:class:`~bus.transports.hub_wire.NonLoopbackAddressError`).

Timestamps
    Every frame is stamped with the hub's receive time (``time.time_ns()`` taken right after
    the read that completed it) in the record it forwards; clients deliver it as
    ``msg.timestamp``.

Classic CAN members and bitrates
    A member that joined with the classic-CAN flag (``fd=False``) gets no FD frames. The
    first member of an empty logical bus sets the bus's bitrate and data bitrate (0 = not
    given); a later member asking for a different non-zero one is refused, one giving none
    adopts the bus's (sent back in the handshake answer).

Counting
    The hub counts, per logical bus, frames and bits (without and with worst-case
    stuffing, :mod:`bus.busload`), FD and error frames, and clients, and reports the bus's
    bitrates. Read them with :func:`query_hub_stats` or :meth:`HubHandle.stats`.

Acceptance filters
    A member's filters (a filter record, see :mod:`bus.transports.hub_wire`) are applied
    here: only matching frames are forwarded to it (like SocketCAN's kernel filters).

Latency and cost
    Non-blocking hub sockets in one ``epoll`` loop, no sleeps, ``TCP_NODELAY`` for TCP. The
    frames read in one round of the loop (all ready members) are queued per destination and
    written with one ``send`` per destination at the end of the round (a member that joined
    for bulk delivery, e.g. a monitor, gets them held up to ``BULK_HOLD_S``, in fewer
    writes); who gets a frame of a
    given sender and identifier is cached per logical bus until a member joins, leaves or
    changes its filters. A client that stops reading is dropped once more than
    :attr:`HubServer.MAX_OUTBUF_BYTES` are queued for it.

Data planes
    Where the C extension :mod:`bus.transports._hubcore` is built (``setup.py``; it needs a C
    compiler at install), a hub moves its members' frames in C: once a member's handshake is done,
    the core reads its records, counts them, routes them by the rules above and writes them out,
    in one epoll loop that also reports the descriptors this module still serves (listen sockets,
    handshakes, stats queries, the wake pipe) to :meth:`HubServer.serve_forever`. Profiling the rig
    showed about two thirds of the Python hub's CPU in the interpreter, moving 24-byte records. A
    hub with frame faults or bus time, or started with ``ILCRIG_HUB_CORE=python``
    (:data:`HUB_CORE_ENV`), uses the pure-Python path described here; both behave the same
    (``tests/test_hub*.py`` run on both), :attr:`HubServer.data_plane` says which one a hub uses.

Bus time (``--bus-time BUS=BIT_S``, :class:`HubServer` ``bus_time``)
    A logical bus given a bit rate this way is delivered as a real CAN bus would carry it: every
    frame waits in its sender's transmit queue (first in, first out, like one controller's queue),
    and whenever the bus is free the waiting frames compete in arbitration — the lowest identifier
    wins (an 11-bit data frame before a remote frame or a 29-bit frame with the same base
    identifier) among the frames that had arrived by then.  The winner occupies the bus for its
    classic-CAN bit length with worst-case stuffing (:func:`bus.busload.bits_lookup`, the 3-bit
    intermission included) at the bus's bit rate, on a virtual clock (monotonic ns) that runs
    back to back while frames wait and never drifts: each frame starts when the previous one
    ended, or when it arrived if the bus was idle.  It is delivered when its transmission ends,
    stamped with that end time, so a receiver's timestamps show the bus time (two frames sent
    back to back are exactly one bit time apart).  A damaged frame (a bus error frame from the fault
    hook) occupies the bus like the frame it replaced; CAN FD frames are not modelled (as in the
    bus-load counts) and pass at once.  A sender more than :attr:`HubServer.BUS_TIME_QUEUE`
    frames ahead of the bus is not read until the bus has caught up (its ``send`` then blocks,
    like a full transmit queue).  Buses without a bit rate here forward at once, as before.

Fault injection
    An optional ``frame_hook`` (:class:`bus.transports.fault_inject.FrameFaultInjector`, from
    ``--inject JSON``) decides for every frame what is delivered and when: nothing (lost), twice,
    a bus error frame instead (damaged), or later (the loop wakes for delayed frames). Counting is
    unchanged (the frames as sent). Without a hook the forwarding path is the plain one.
"""

from __future__ import annotations

import argparse
import contextlib
import heapq
import json
import logging
import os
import select
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Self

from bus.busload import BusLoadCounter, bits_lookup
from bus.timer_slack import fine_timer_slack
from bus.transports.hub_wire import (
    BITRATES,
    BULK_HOLD_S,
    BULK_MAX_BYTES,
    FILTER_ENTRY,
    FLAG_ECHO,
    FLAG_ERR,
    FLAG_EXT,
    FLAG_FD,
    FLAG_RTR,
    HEADER_SIZE,
    HELLO_FIXED,
    HELLO_FLAG_BULK,
    HELLO_FLAG_CLASSIC,
    HELLO_FLAG_ECHO,
    KIND_FILTERS,
    KIND_FRAME,
    MAGIC_HELLO,
    MAGIC_NO,
    MAGIC_OK,
    PROTOCOL_VERSION,
    ROLE_MEMBER,
    ROLE_STATS,
    ROLE_STATS_RESET,
    STAMP,
    STAMP_OFFSET,
    U32,
    HubAddress,
    HubAddressError,
    HubAddressInUseError,
    HubError,
    HubStartError,
    connect,
    default_hub_address,
    hello,
    parse_address,
    parse_channel,
    read_reply,
    recv_exact,
    version_refusal,
)

_hubcore: ModuleType | None
try:  # the hub's data plane in C, built at install when a C compiler is there (setup.py)
    from bus.transports import _hubcore
except ImportError:  # pragma: no cover - depends on the installation
    _hubcore = None

logger = logging.getLogger(__name__)


@dataclass
class HubChannelStats:
    """What the hub counted on one logical bus since start (or the last reset)."""

    frames: int = 0
    bits: int = 0
    bits_worst_case: int = 0
    fd_frames: int = 0
    error_frames: int = 0
    clients: int = 0
    connections: int = 0
    dropped_clients: int = 0
    #: the logical bus's bitrates, bit/s (0 = no member gave one), set by the first member
    #: that joins the empty bus; a member asking for another one is refused
    bitrate: int = 0
    data_bitrate: int = 0

    def load(self) -> BusLoadCounter:
        """The classic-CAN frame and bit totals as a :class:`BusLoadCounter`."""
        return BusLoadCounter(self.frames, self.bits, self.bits_worst_case, self.fd_frames)


@dataclass(eq=False)
class _BusClock:
    """Bus-time delivery of one logical bus (see the module docstring): the transmit queue of every
    sender, the frame on the bus and the virtual clock (monotonic ns)."""

    bitrate: int
    #: per sender: (arrival [monotonic ns], arbitration key, bit time [ns], record), oldest first
    queues: dict[_Client, deque[tuple[int, tuple[int, int, int, int], int, bytes]]] = field(default_factory=dict)
    #: the frame on the bus: (end of its transmission [monotonic ns], sender, record)
    current: tuple[int, _Client, bytes] | None = None
    #: when the bus became free (the end of the last frame), monotonic ns
    free_ns: int = 0


def _checked_bus_time(bus_time: Mapping[str, int] | None) -> dict[str, int]:
    """``bus_time`` (logical bus → bit rate) as ints.

    :raises ValueError: a bit rate that is not positive
    """
    out = {name: int(rate) for name, rate in (bus_time or {}).items()}
    for name, rate in out.items():
        if rate <= 0:
            raise ValueError(f"bus time of {name!r}: the bit rate must be > 0 bit/s, got {rate}")
    return out


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


@dataclass(eq=False)
class _Client:
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
    #: not read for now: too many of its frames wait for bus time (see HubServer.BUS_TIME_QUEUE)
    paused: bool = False

    def accepts(self, can_id: int, ext: int) -> bool:
        if not self.filters:
            return True
        for f_id, f_mask, f_ext in self.filters:
            if f_ext >= 0 and f_ext != ext:
                continue
            if (f_id ^ can_id) & f_mask == 0:
                return True
        return False


#: environment variable: ``python`` makes every hub of this process and its children use the pure-Python
#: data plane even where the C one (:mod:`bus.transports._hubcore`) is built (comparisons, debugging)
HUB_CORE_ENV: str = "ILCRIG_HUB_CORE"


def hub_core_available() -> bool:
    """A hub started now (without frame faults or bus time) would move frames in C."""
    return _hubcore is not None and os.environ.get(HUB_CORE_ENV, "c").strip().lower() != "python"


class _CoreSelector(selectors.BaseSelector):
    """The selector of a hub whose members the C core serves (:mod:`bus.transports._hubcore`).

    The descriptors the Python side registers (listen sockets, the wake pipe, the watched
    descriptor, clients before and outside membership) are watched by the core's epoll and come
    back from :meth:`select` as usual; a member handed over with :meth:`adopt` is read, routed and
    written by the core, and only comes back when the core dropped it (``on_drop(client, refuse,
    reason)``, called from :meth:`select`).
    """

    def __init__(self, module: ModuleType, on_drop: Any, **core_args: Any) -> None:
        self._core = module.Core(**core_args)
        self._report_events: int = module.REPORT_EVENTS
        self._report_refuse: int = module.REPORT_REFUSE
        self._on_drop = on_drop
        self._keys: dict[int, selectors.SelectorKey] = {}
        self._members: dict[int, _Client] = {}

    @staticmethod
    def _mask(events: int) -> int:
        return (select.EPOLLIN if events & selectors.EVENT_READ else 0) | (
            select.EPOLLOUT if events & selectors.EVENT_WRITE else 0
        )

    def register(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        fd = selectors._fileobj_to_fd(fileobj)  # type: ignore[attr-defined]
        if fd in self._keys or fd in self._members:
            raise KeyError(f"{fileobj!r} (fd {fd}) is already registered")
        key = selectors.SelectorKey(fileobj, fd, events, data)
        self._core.watch(fd, self._mask(events))
        self._keys[fd] = key
        return key

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        fd = selectors._fileobj_to_fd(fileobj)  # type: ignore[attr-defined]
        key = self._keys.pop(fd)
        with contextlib.suppress(OSError, ValueError):
            self._core.unwatch(fd)
        return key

    def modify(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        fd = selectors._fileobj_to_fd(fileobj)  # type: ignore[attr-defined]
        old = self._keys[fd]
        key = selectors.SelectorKey(old.fileobj, fd, events, data)
        self._core.watch(fd, self._mask(events))
        self._keys[fd] = key
        return key

    def adopt(self, client: _Client, bus: int, stamp_ns: int) -> None:
        """The core serves ``client`` (a member after its handshake) from now on, starting with the
        bytes it already sent (read at ``stamp_ns``) and the bytes still to be sent to it."""
        fd = client.sock.fileno()
        self._keys.pop(fd, None)
        self._core.add_member(
            fd, bus, client.echo, client.classic, client.bulk, bytes(client.inbuf), bytes(client.outbuf), stamp_ns
        )
        client.inbuf.clear()
        client.outbuf.clear()
        client.writing = False
        self._members[fd] = client

    def release(self, client: _Client) -> None:
        """Take ``client`` back from the core (before its socket closes)."""
        with contextlib.suppress(OSError):
            fd = client.sock.fileno()
            if self._members.get(fd) is client:
                del self._members[fd]
                self._core.remove(fd)

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready: list[tuple[selectors.SelectorKey, int]] = []
        for fd, kind, value in self._core.poll(-1.0 if timeout is None else max(0.0, timeout)):
            if kind == self._report_events:
                key = self._keys.get(fd)
                if key is None:
                    continue
                events = 0
                if value & ~select.EPOLLIN:
                    events |= selectors.EVENT_WRITE
                if value & ~select.EPOLLOUT:
                    events |= selectors.EVENT_READ
                if key.events & events:
                    ready.append((key, key.events & events))
            else:
                client = self._members.pop(fd, None)
                if client is not None:
                    self._on_drop(client, kind == self._report_refuse, value)
        return ready

    def stats(self, bus: int, reset: bool) -> tuple[int, int, int, int, int, int]:
        """The core's counters of logical bus ``bus`` (index): frames, bits, bits worst case, FD frames,
        error frames, dropped members; ``reset`` zeroes the frame and bit counts afterwards."""
        counts: tuple[int, int, int, int, int, int] = self._core.stats(bus, reset)
        return counts

    def get_map(self) -> Mapping[Any, selectors.SelectorKey]:
        return {key.fileobj: key for key in self._keys.values()}

    def close(self) -> None:
        self._keys.clear()
        self._members.clear()
        self._core.close()


class HubServer:
    """The hub: binds its listen addresses at construction, serves in :meth:`serve_forever`.

    :param listen: addresses (strings or :class:`HubAddress`); TCP port 0 picks a free port
    :param allow_remote: accept non-loopback TCP addresses (explicit opt-in: the hub then serves
        other machines)
    :param frame_hook: frame faults (see the module docstring)
    :param bus_time: logical bus name → bit rate [bit/s]: these buses deliver frames in bus time
        (see the module docstring)
    :raises NonLoopbackAddressError: a TCP address is not loopback (without ``allow_remote``)
    :raises HubAddressInUseError: a live hub already owns a Unix path
    :raises ValueError: a bus-time bit rate that is not positive
    """

    #: a client with more than this many unsent bytes queued is dropped (it stopped reading)
    MAX_OUTBUF_BYTES: int = 8 << 20
    RECV_CHUNK: int = 1 << 16
    #: bus time: a sender with this many frames waiting for the bus is not read until they are sent
    BUS_TIME_QUEUE: int = 4096

    def __init__(
        self,
        listen: Sequence[str | HubAddress],
        allow_remote: bool = False,
        frame_hook: Any = None,
        bus_time: Mapping[str, int] | None = None,
    ) -> None:
        if not listen:
            raise HubAddressError("the hub needs at least one listen address")
        self._clocks = {name: _BusClock(rate) for name, rate in _checked_bus_time(bus_time).items()}
        #: wall-clock ns minus monotonic ns: bus-time stamps are monotonic times shown as wall-clock ones
        self._epoch_offset_ns = time.time_ns() - time.monotonic_ns()
        self._hook = frame_hook
        if self._clocks:
            fine_timer_slack()
        #: frames the hook delays: (due [s, monotonic], sequence, sender, record), a heap
        self._delayed: list[tuple[float, int, _Client, bytes]] = []
        self._delayed_seq = 0
        # epoll rounds its timeout up to whole milliseconds; bus time waits for frame ends that are
        # tens of µs apart, so it uses select(), which waits to the µs (the hub has a few clients)
        self._sel: selectors.BaseSelector = selectors.SelectSelector() if self._clocks else selectors.DefaultSelector()
        #: the C data plane, when built and nothing needs the per-frame Python path (faults, bus time)
        self._core: _CoreSelector | None = None
        if frame_hook is None and not self._clocks and _hubcore is not None and hub_core_available():
            self._sel.close()
            self._core = _CoreSelector(
                _hubcore,
                self._core_dropped,
                bits=[bits_lookup(n, ext)[k] for ext in (False, True) for n in range(9) for k in (0, 1)],
                recv_chunk=self.RECV_CHUNK,
                max_outbuf=self.MAX_OUTBUF_BYTES,
                bulk_hold_s=BULK_HOLD_S,
                bulk_max_bytes=BULK_MAX_BYTES,
            )
            self._sel = self._core
        #: logical bus name -> index in the C core
        self._bus_index: dict[str, int] = {}
        self._listeners: dict[socket.socket, HubAddress] = {}
        self._unix_paths: list[str] = []
        self._clients: dict[socket.socket, _Client] = {}
        self._buses: dict[str, list[_Client]] = {}
        self._stats: dict[str, HubChannelStats] = {}
        #: per bus: (sender, can_id, extended, fd) -> [(member, as echo)], see _recipients
        self._route_cache: dict[str, dict[tuple[_Client, int, int, int], list[tuple[_Client, bool]]]] = {}
        #: frames routed in the current select round, per destination (see _send_pending)
        self._pending: dict[_Client, list[bytes]] = {}
        #: bulk members holding frames (see _send_pending, _send_held)
        self._held: dict[_Client, None] = {}
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self.addresses: list[HubAddress] = []
        try:
            for item in listen:
                addr = item if isinstance(item, HubAddress) else parse_address(item, allow_remote)
                self.addresses.append(self._bind(addr))
        except BaseException:
            self.close()
            raise

    def _bind(self, addr: HubAddress) -> HubAddress:
        if addr.kind == "unix":
            self._clear_stale_unix_path(addr.path)
        sock = socket.socket(addr.family, socket.SOCK_STREAM)
        try:
            if addr.kind == "tcp":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(addr.sockaddr)
            sock.listen(64)
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        if addr.kind == "unix":
            self._unix_paths.append(addr.path)
            bound = addr
        else:
            host, port = sock.getsockname()[:2]
            bound = HubAddress("tcp", host=host, port=port)
        self._listeners[sock] = bound
        self._sel.register(sock, selectors.EVENT_READ, "listen")
        logger.info("hub listening on %s", bound)
        return bound

    @staticmethod
    def _clear_stale_unix_path(path: str) -> None:
        if not os.path.exists(path):
            return
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(path)
        except (ConnectionRefusedError, FileNotFoundError):
            logger.info("removing stale hub socket %s", path)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            return
        except OSError as err:
            raise HubAddressInUseError(f"cannot use {path}: {err}") from err
        finally:
            probe.close()
        raise HubAddressInUseError(f"a hub already listens on {path}")

    # -- public ---------------------------------------------------------------------------

    def stats(self, reset: bool = False) -> dict[str, HubChannelStats]:
        """Per-bus counters (copies); ``reset`` zeroes frame and bit counts afterwards."""
        out: dict[str, HubChannelStats] = {}
        for name, st in self._stats.items():
            st.clients = len(self._buses.get(name, ()))
            out[name] = copy = HubChannelStats(**vars(st))
            if self._core is not None and name in self._bus_index:
                counts = self._core.stats(self._bus_index[name], reset)
                copy.frames += counts[0]
                copy.bits += counts[1]
                copy.bits_worst_case += counts[2]
                copy.fd_frames += counts[3]
                copy.error_frames += counts[4]
                copy.dropped_clients += counts[5]
            if reset:
                st.frames = st.bits = st.bits_worst_case = st.fd_frames = st.error_frames = 0
        return out

    @property
    def data_plane(self) -> str:
        """``"c"`` when members' frames move in the C core, ``"python"`` otherwise."""
        return "c" if self._core is not None else "python"

    def _core_dropped(self, client: _Client, refuse: bool, reason: str) -> None:
        """The core dropped member ``client`` (it already forgot it): the Python side's part."""
        if reason == "output buffer overflow":
            logger.warning("hub: dropping client %s on bus %r: it stopped reading", client.peer, client.bus)
        if refuse:
            self._refuse(client, reason)
        else:
            self._drop(client, reason)

    def wake(self) -> None:
        """Ask :meth:`serve_forever` to return (thread-safe, signal-safe)."""
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def serve_forever(self, watch_fd: int | None = None) -> None:
        """Serve until :meth:`wake` is called or ``watch_fd`` reaches EOF (parent gone)."""
        if watch_fd is not None:
            self._sel.register(watch_fd, selectors.EVENT_READ, "watch")
        try:
            while True:
                timeout = None
                if self._held:
                    timeout = max(0.0, min(c.held_since_s for c in self._held) + BULK_HOLD_S - time.monotonic())
                if self._delayed:
                    due = max(0.0, self._delayed[0][0] - time.monotonic())
                    timeout = due if timeout is None else min(timeout, due)
                if self._clocks:
                    ends = [c.current[0] for c in self._clocks.values() if c.current is not None]
                    if ends:
                        due = max(0.0, (min(ends) - time.monotonic_ns()) / 1e9)
                        timeout = due if timeout is None else min(timeout, due)
                for key, events in self._sel.select(timeout):
                    tag = key.data
                    if isinstance(tag, _Client):
                        if events & selectors.EVENT_READ:
                            self._on_readable(tag)
                        if events & selectors.EVENT_WRITE and tag.sock in self._clients:
                            self._flush(tag)
                    elif tag == "listen":
                        self._accept(key.fileobj)  # type: ignore[arg-type]
                    elif tag == "wake":
                        return
                    elif tag == "watch" and not os.read(watch_fd, 4096):  # type: ignore[arg-type]
                        logger.info("hub: watched descriptor closed, exiting")
                        return
                if self._delayed:
                    self._release_delayed()
                if self._clocks:
                    self._run_bus_time(time.monotonic_ns())
                self._send_pending()
                if self._held:
                    self._send_held(time.monotonic())
        finally:
            if watch_fd is not None:
                with contextlib.suppress(KeyError, ValueError):
                    self._sel.unregister(watch_fd)

    def close(self) -> None:
        """Close every socket and remove the Unix socket files."""
        for client in list(self._clients.values()):
            self._drop(client, "hub closing")
        for sock in list(self._listeners):
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(sock)
            sock.close()
        self._listeners.clear()
        for path in self._unix_paths:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        self._unix_paths.clear()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1
        self._sel.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals ------------------------------------------------------------------------

    def _accept(self, lsock: socket.socket) -> None:
        try:
            sock, peer = lsock.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        if sock.family != socket.AF_UNIX:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock=sock, peer=str(peer) or "unix")
        self._clients[sock] = client
        self._sel.register(sock, selectors.EVENT_READ, client)

    def _drop(self, client: _Client, reason: str) -> None:
        if self._clients.pop(client.sock, None) is None:
            return
        if self._core is not None:
            self._core.release(client)
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(client.sock)
        client.sock.close()
        members = self._buses.get(client.bus)
        self._pending.pop(client, None)
        self._held.pop(client, None)
        clock = self._clocks.get(client.bus)
        if clock is not None:
            clock.queues.pop(client, None)
        if members and client in members:
            members.remove(client)
            self._route_cache.pop(client.bus, None)
            logger.info("hub: client left bus %r (%s)", client.bus, reason)

    def _on_readable(self, client: _Client) -> None:
        try:
            data = client.sock.recv(self.RECV_CHUNK)
        except BlockingIOError:
            return
        except OSError as err:
            self._drop(client, f"recv error {err}")
            return
        stamp_ns = time.time_ns()  # the receive time of every frame completed by this read
        if not data:
            self._drop(client, "disconnected")
            return
        client.inbuf += data
        if not client.role:
            self._handshake(client, stamp_ns)
            if not client.role or client.sock not in self._clients:
                return
        self._route(client, stamp_ns)

    def _handshake(self, client: _Client, stamp_ns: int) -> None:
        buf = client.inbuf
        if len(buf) < HELLO_FIXED.size:
            return
        magic, version, role, flags, n = HELLO_FIXED.unpack_from(buf)
        if magic != MAGIC_HELLO or role not in (ROLE_MEMBER, ROLE_STATS, ROLE_STATS_RESET):
            self._refuse(client, f"bad hello (magic {magic!r}, version {version}, role {role})")
            return
        if version != PROTOCOL_VERSION:
            self._refuse(client, version_refusal(version))
            return
        end = HELLO_FIXED.size + n
        if len(buf) < end + BITRATES.size:
            return
        name = bytes(buf[HELLO_FIXED.size : end]).decode(errors="replace")
        bitrate, data_bitrate = BITRATES.unpack_from(buf, end)
        del buf[: end + BITRATES.size]
        if role in (ROLE_STATS, ROLE_STATS_RESET):
            stats = self.stats(reset=role == ROLE_STATS_RESET)
            body = json.dumps({k: vars(v) for k, v in stats.items()}).encode()
            self._send_to(client, MAGIC_OK + U32.pack(len(body)) + body)
            client.role = role
            return
        members = self._buses.setdefault(name, [])
        st = self._stats.setdefault(name, HubChannelStats())
        if not members:  # the first member of an empty bus sets its bitrates
            st.bitrate, st.data_bitrate = bitrate, data_bitrate
        else:
            for what, have, asked in (("bitrate", st.bitrate, bitrate), ("data bitrate", st.data_bitrate, data_bitrate)):
                if have and asked and have != asked:
                    self._refuse(client, f"bus {name!r} runs at {what} {have} bit/s, the client asked for {asked} bit/s")
                    return
            st.bitrate = st.bitrate or bitrate
            st.data_bitrate = st.data_bitrate or data_bitrate
        client.role = role
        client.bus = name
        client.echo = bool(flags & HELLO_FLAG_ECHO)
        client.classic = bool(flags & HELLO_FLAG_CLASSIC)
        client.bulk = bool(flags & HELLO_FLAG_BULK)
        members.append(client)
        self._route_cache.pop(name, None)
        st.connections += 1
        logger.info("hub: client %s joined bus %r%s", client.peer, name, " (classic CAN)" if client.classic else "")
        self._send_to(client, MAGIC_OK + BITRATES.pack(st.bitrate, st.data_bitrate))
        if self._core is not None and client.sock in self._clients:
            self._core.adopt(client, self._bus_index.setdefault(name, len(self._bus_index)), stamp_ns)

    def _refuse(self, client: _Client, text: str) -> None:
        logger.warning("hub: refusing client %s: %s", client.peer, text)
        raw = text.encode()[:255]
        with contextlib.suppress(OSError):
            client.sock.send(MAGIC_NO + bytes([len(raw)]) + raw)
        self._drop(client, text)

    def _recipients(self, sender: _Client, can_id: int, ext: int, fd: int) -> list[tuple[_Client, bool]]:
        """(member, as echo) pairs that get a frame of ``sender`` (cached per bus until a member
        joins, leaves or changes its filters)."""
        cache = self._route_cache.setdefault(sender.bus, {})
        key = (sender, can_id, ext, fd)
        found = cache.get(key)
        if found is None:
            found = []
            for peer in self._buses[sender.bus]:
                if fd and peer.classic:
                    continue  # a classic CAN member never sees FD frames (like a non-FD raw socket)
                if peer is sender:
                    if peer.echo and peer.accepts(can_id, ext):
                        found.append((peer, True))
                elif peer.accepts(can_id, ext):
                    found.append((peer, False))
            cache[key] = found
        return found

    def _route(self, sender: _Client, stamp_ns: int) -> None:
        """Forward every whole record of ``sender``'s input buffer: frames are stamped in place
        and queued per destination (:meth:`_send_pending` writes each destination's queue with
        one send after the whole select round)."""
        if sender.role != ROLE_MEMBER:
            sender.inbuf.clear()  # a stats connection has nothing more to say
            return
        buf = sender.inbuf
        size = len(buf)
        st = self._stats[sender.bus]
        pending = self._pending
        clock = self._clocks.get(sender.bus)
        arrival_ns = time.monotonic_ns() if clock is not None else 0
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
                if self._hook is None and clock is not None:
                    self._enqueue(clock, sender, rec, arrival_ns)
                elif self._hook is None:  # the plain path
                    for peer, echo in self._recipients(sender, can_id, ext, fd):
                        chunk = rec[:1] + bytes([flags | FLAG_ECHO]) + rec[2:] if echo else rec
                        queue = pending.get(peer)
                        if queue is None:
                            pending[peer] = [chunk]
                        else:
                            queue.append(chunk)
                else:
                    data = rec[HEADER_SIZE - 8 : HEADER_SIZE - 8 + min(length, 8)]
                    for delay, r in self._hook.deliveries(sender.bus, rec, can_id, data, bool(flags & FLAG_ERR)):
                        if delay > 0:
                            self._delayed_seq += 1
                            heapq.heappush(self._delayed, (time.monotonic() + delay, self._delayed_seq, sender, bytes(r)))
                        elif clock is not None:
                            self._enqueue(clock, sender, bytes(r), arrival_ns)
                        else:
                            self._fan_out(sender, bytes(r))
            elif kind == KIND_FILTERS:
                n = U32.unpack_from(buf, off + 4)[0]
                total = HEADER_SIZE + n
                if size - off < total:
                    break
                body = bytes(buf[off + HEADER_SIZE : off + total])
                sender.filters = [
                    FILTER_ENTRY.unpack_from(body, i) for i in range(0, n - n % FILTER_ENTRY.size, FILTER_ENTRY.size)
                ] or None
                self._route_cache.pop(sender.bus, None)
            else:
                self._refuse(sender, f"unknown record kind {kind}")
                return
            off += total
        del buf[:off]
        if clock is not None and len(clock.queues.get(sender, ())) >= self.BUS_TIME_QUEUE:
            sender.paused = True  # its socket fills up: its send() blocks like a full transmit queue
            self._update_events(sender)

    def _send_pending(self) -> None:
        """One send per destination of everything routed in this select round; a bulk member's
        frames are held instead (see :meth:`_send_held`)."""
        pending = self._pending
        if pending:
            self._pending = {}
            for peer, chunks in pending.items():
                if peer.bulk:
                    if not peer.held:
                        peer.held_since_s = time.monotonic()
                        self._held[peer] = None
                    peer.held += chunks
                    peer.held_bytes += sum(map(len, chunks))
                    if peer.held_bytes >= BULK_MAX_BYTES:
                        self._release(peer)
                else:
                    self._send_to(peer, chunks[0] if len(chunks) == 1 else b"".join(chunks))

    def _send_held(self, now_s: float) -> None:
        """Send what bulk members held for :data:`BULK_HOLD_S` or longer."""
        for peer in [c for c in self._held if now_s - c.held_since_s >= BULK_HOLD_S]:
            self._release(peer)

    def _release(self, peer: _Client) -> None:
        data = b"".join(peer.held)
        peer.held = []
        peer.held_bytes = 0
        self._held.pop(peer, None)
        self._send_to(peer, data)

    def _fan_out(self, sender: _Client, rec: bytes) -> None:
        """Queue ``rec`` (a frame record of ``sender``) for every member of its bus that takes it
        (the frame-fault path; the same rules as the plain path in :meth:`_route`)."""
        if sender.bus not in self._buses:
            return
        flags = rec[1]
        can_id = U32.unpack_from(rec, 4)[0]
        ext = 1 if flags & FLAG_EXT else 0
        fd = flags & FLAG_FD
        pending = self._pending
        for peer, echo in self._recipients(sender, can_id, ext, fd):
            pending.setdefault(peer, []).append(rec[:1] + bytes([flags | FLAG_ECHO]) + rec[2:] if echo else rec)

    def _release_delayed(self) -> None:
        """Queue the delayed frames that are due (sent with the round's other frames; on a bus-time
        bus they wait for the bus from now)."""
        now = time.monotonic()
        while self._delayed and self._delayed[0][0] <= now:
            _, _, sender, rec = heapq.heappop(self._delayed)
            clock = self._clocks.get(sender.bus)
            if clock is not None:
                self._enqueue(clock, sender, rec, time.monotonic_ns())
            else:
                self._fan_out(sender, rec)

    # -- bus time --------------------------------------------------------------------------

    def _enqueue(self, clock: _BusClock, sender: _Client, rec: bytes, arrival_ns: int) -> None:
        """``rec`` joins its sender's transmit queue (an FD frame, not modelled, goes at once)."""
        flags = rec[1]
        if flags & FLAG_FD:
            self._fan_out(sender, rec)
            return
        queue = clock.queues.get(sender)
        if queue is None:
            queue = clock.queues[sender] = deque()
        queue.append(
            (arrival_ns, arbitration_key(U32.unpack_from(rec, 4)[0], flags), bit_time_ns(rec[3], flags, clock.bitrate), rec)
        )

    def _run_bus_time(self, now_ns: int) -> None:
        """Every bus-time bus: deliver the frames whose transmission ended by ``now_ns`` and start
        the next ones (arbitration among the frames that had arrived when the bus became free)."""
        for clock in self._clocks.values():
            while True:
                if clock.current is not None:
                    end_ns, sender, rec = clock.current
                    if end_ns > now_ns:
                        break
                    clock.current = None
                    clock.free_ns = end_ns
                    stamped = bytearray(rec)
                    STAMP.pack_into(stamped, STAMP_OFFSET, end_ns + self._epoch_offset_ns)
                    self._fan_out(sender, bytes(stamped))
                    if sender.paused and len(clock.queues.get(sender, ())) < self.BUS_TIME_QUEUE // 2:
                        sender.paused = False
                        self._update_events(sender)
                heads = [(q[0][0], q[0][1], s) for s, q in clock.queues.items() if q]
                if not heads:
                    break
                start_ns = max(clock.free_ns, min(h[0] for h in heads))
                winner = min((h for h in heads if h[0] <= start_ns), key=lambda h: h[1])[2]
                _, _, bit_ns, rec = clock.queues[winner].popleft()
                clock.current = (start_ns + bit_ns, winner, rec)

    def _update_events(self, client: _Client) -> None:
        """(Re)register ``client``'s socket for what it waits for: reading unless paused, writing
        while output is queued."""
        if client.sock not in self._clients:
            return
        events = (0 if client.paused else selectors.EVENT_READ) | (selectors.EVENT_WRITE if client.writing else 0)
        try:
            if events:
                try:
                    self._sel.modify(client.sock, events, client)
                except KeyError:
                    self._sel.register(client.sock, events, client)
            else:
                self._sel.unregister(client.sock)
        except (KeyError, ValueError, OSError) as err:
            logger.debug("hub: cannot update the events of %s: %s", client.peer, err)

    def _send_to(self, client: _Client, data: bytes) -> None:
        if client.sock not in self._clients:
            return
        if client.outbuf:
            client.outbuf += data
        else:
            try:
                sent = client.sock.send(data)
            except BlockingIOError:
                sent = 0
            except OSError as err:
                self._drop(client, f"send error {err}")
                return
            if sent == len(data):
                return
            client.outbuf += data[sent:]
        if len(client.outbuf) > self.MAX_OUTBUF_BYTES:
            st = self._stats.get(client.bus)
            if st is not None:
                st.dropped_clients += 1
            logger.warning("hub: dropping client %s on bus %r: it stopped reading", client.peer, client.bus)
            self._drop(client, "output buffer overflow")
            return
        if not client.writing:
            client.writing = True
            self._update_events(client)

    def _flush(self, client: _Client) -> None:
        try:
            sent = client.sock.send(client.outbuf)
        except BlockingIOError:
            return
        except OSError as err:
            self._drop(client, f"send error {err}")
            return
        del client.outbuf[:sent]
        if not client.outbuf and client.writing:
            client.writing = False
            self._update_events(client)


def query_hub_stats(address: str, reset: bool = False, timeout_s: float = 2.0) -> dict[str, HubChannelStats]:
    """Ask a running hub for its per-bus counters.

    :param address: the hub address (a channel string's ``#bus`` part is ignored)
    :param reset: zero the frame and bit counters after reading them
    :raises HubError: no hub, or a protocol error
    """
    addr = parse_channel(address)[0] if "#" in address else parse_address(address)
    try:
        sock = connect(addr, timeout_s)
    except OSError as err:
        raise HubError(f"cannot reach hub at {addr}: {err}") from err
    with sock:
        sock.sendall(hello(ROLE_STATS_RESET if reset else ROLE_STATS, ""))
        read_reply(sock)
        n = U32.unpack(recv_exact(sock, 4))[0]
        raw = json.loads(recv_exact(sock, n))
    return {name: HubChannelStats(**values) for name, values in raw.items()}


# ---------------------------------------------------------------------------------------
# child-process API
# ---------------------------------------------------------------------------------------

READY_PREFIX = "ILCRIG-HUB-READY"


def _reap(proc: subprocess.Popen[bytes], timeout_s: float) -> int:
    """Terminate (then kill) and wait for ``proc``; always reaps. Returns the exit code."""
    if proc.poll() is None:
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()  # the hub exits on stdin EOF
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    for stream in (proc.stdin, proc.stdout):
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()
    return int(proc.returncode)


class HubHandle:
    """A hub running in a child process (from :func:`start_hub`). Use as a context manager.

    :ivar addresses: the resolved listen addresses (TCP port 0 replaced by the real port)
    """

    def __init__(self, proc: subprocess.Popen[bytes], addresses: list[str], tmpdir: str | None) -> None:
        self.process = proc
        self.addresses = addresses
        self._tmpdir = tmpdir
        self._finalizer = weakref.finalize(self, HubHandle._cleanup, proc, tmpdir)

    @staticmethod
    def _cleanup(proc: subprocess.Popen[bytes], tmpdir: str | None) -> None:
        _reap(proc, 2.0)
        if tmpdir is not None:
            with contextlib.suppress(OSError):
                for name in os.listdir(tmpdir):
                    os.unlink(os.path.join(tmpdir, name))
                os.rmdir(tmpdir)

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def address(self) -> str:
        """The first listen address, e.g. ``unix:/tmp/ilcrig-hub-x/hub.sock``."""
        return self.addresses[0]

    def channel(self, bus_name: str, address_index: int = 0) -> str:
        """The python-can channel string of logical bus ``bus_name`` on this hub."""
        return f"{self.addresses[address_index]}#{bus_name}"

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def stats(self, reset: bool = False) -> dict[str, HubChannelStats]:
        """Per-bus counters of this hub (see :func:`query_hub_stats`)."""
        return query_hub_stats(self.address, reset=reset)

    def stop(self) -> int:
        """Stop the hub and reap the child process (idempotent). Returns its exit code."""
        self._finalizer()
        return int(self.process.returncode)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_hub(
    listen: str | Sequence[str] | None = None,
    *,
    timeout_s: float = 10.0,
    log_level: str = "WARNING",
    inject: str | None = None,
    stderr: Any = None,
    bus_time: Mapping[str, int] | None = None,
) -> HubHandle:
    """Start a hub in a child process and wait until it accepts clients.

    :param listen: address(es); default: ``hub.sock`` in a fresh private temp directory
        (removed again by :meth:`HubHandle.stop`)
    :param timeout_s: how long to wait for readiness, s
    :raises NonLoopbackAddressError: checked here already, before any process starts
    :raises HubStartError: the child exited or did not report ready in time (it is reaped)
    :param inject: frame faults for the hub (``--inject``, JSON of
        :meth:`bus.transports.fault_inject.FrameFaultInjector.from_json`)
    :param stderr: where the hub's stderr goes (default: inherited)
    :param bus_time: logical bus → bit rate, bit/s: deliver these buses in bus time (``--bus-time``)

    The child exits when :meth:`HubHandle.stop` closes its stdin, and also when this
    process dies (its stdin reaches EOF), so no hub outlives its parent.
    """
    tmpdir = None
    if listen is None:
        tmpdir = tempfile.mkdtemp(prefix="ilcrig-hub-")
        listen_list = [f"unix:{os.path.join(tmpdir, 'hub.sock')}"]
    else:
        listen_list = [listen] if isinstance(listen, str) else list(listen)
    for text in listen_list:
        parse_address(text)  # fail fast on a bad or non-loopback address
    cmd = [sys.executable, "-m", "bus.transports.hub_server", "--ready", "--exit-on-stdin-eof", "--log-level", log_level]
    for text in listen_list:
        cmd += ["--listen", text]
    if inject:
        cmd += ["--inject", inject]
    for name, rate in _checked_bus_time(bus_time).items():
        cmd += ["--bus-time", f"{name}={rate}"]
    if tmpdir is not None:
        cmd += ["--remove-dir", tmpdir]  # the hub removes it when it exits, even if this process was killed
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=stderr)
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    line = b""
    try:
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([proc.stdout], [], [], left)[0]:
                raise HubStartError(f"hub did not become ready within {timeout_s} s")
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                raise HubStartError(f"hub exited during start-up (exit code {proc.wait()})")
            line += chunk
    except BaseException:
        HubHandle._cleanup(proc, tmpdir)
        raise
    parts = line.decode().split()
    if not parts or parts[0] != READY_PREFIX:
        HubHandle._cleanup(proc, tmpdir)
        raise HubStartError(f"unexpected hub start-up output {line!r}")
    handle = HubHandle(proc, parts[1:], tmpdir)
    logger.info("hub pid %d ready on %s", proc.pid, " ".join(parts[1:]))
    return handle


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


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bus.transports.hub_server --listen unix:/path [--listen tcp:127.0.0.1:0]``."""
    parser = argparse.ArgumentParser(prog="python -m bus.transports.hub_server", description="ilcrig zero-privilege CAN hub")
    parser.add_argument(
        "--listen",
        action="append",
        help=f"unix:/path or tcp:127.0.0.1:PORT (repeatable; default {default_hub_address()})",
    )
    parser.add_argument("--ready", action="store_true", help=f"print '{READY_PREFIX} <addresses>' when listening")
    parser.add_argument("--exit-on-stdin-eof", action="store_true", help="exit when stdin closes")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="accept non-loopback TCP listen addresses (the hub then serves other machines)",
    )
    parser.add_argument("--inject", default=None, help='frame faults (JSON: {"specs": [...], "log": path})')
    parser.add_argument("--remove-dir", default=None, help="a private folder to remove on exit")
    parser.add_argument(
        "--bus-time",
        action="append",
        default=[],
        metavar="BUS=BIT_S",
        help="deliver logical bus BUS in bus time at BIT_S bit/s: arbitration order, each frame after its bit time (repeatable)",
    )
    args = parser.parse_args(argv)
    try:
        bus_time = parse_bus_time(args.bus_time)
    except ValueError as err:
        parser.error(str(err))
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s hub %(levelname)s %(message)s")
    hook = None
    if args.inject:
        from bus.transports.fault_inject import FrameFaultInjector

        hook = FrameFaultInjector.from_json(args.inject)
    try:
        server = HubServer(
            args.listen or [default_hub_address()], allow_remote=args.allow_remote, frame_hook=hook, bus_time=bus_time
        )
        if args.allow_remote:
            logger.warning("hub accepts remote members on %s", ", ".join(map(str, server.addresses)))
    except (HubAddressError, HubAddressInUseError, OSError) as err:
        sys.exit(f"error: {err}")
    signal.signal(signal.SIGTERM, lambda *_: server.wake())
    signal.signal(signal.SIGINT, lambda *_: server.wake())
    try:
        if args.ready:
            print(READY_PREFIX, *map(str, server.addresses), flush=True)
        server.serve_forever(watch_fd=sys.stdin.fileno() if args.exit_on_stdin_eof else None)
    finally:
        server.close()
        if args.remove_dir:
            with contextlib.suppress(OSError):
                os.rmdir(args.remove_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
