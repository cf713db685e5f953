"""Hub server: the zero-privilege CAN hub's event loop and its connections.

This module owns :class:`HubServer`: one process (no root, no kernel module) that listens on a
Unix domain socket (the default) or on loopback TCP, accepts clients, runs their handshake
(members of a logical bus, or stats queries), reads their records and writes what is routed to
them, in one loop without sleeps. What happens to a frame between the read and the write is
:mod:`bus.transports.hub.routing`'s (forwarding, filters, bulk delivery, frame faults) or, on a
bus with a bit rate, :mod:`bus.transports.hub.bus_time`'s; where the C extension is built, the
members' frames move in C (:mod:`bus.transports.hub.core`). The counters are
:mod:`bus.transports.hub.stats`'s, the wire protocol :mod:`bus.transports.hub.wire`'s, the
addresses :mod:`bus.transports.hub.addresses`'; the client is
:class:`bus.transports.hub.client.HubBus`.

Listen addresses
    A listen address that is not loopback is refused
    (:class:`~bus.transports.hub.wire.NonLoopbackAddressError`) unless ``allow_remote``; a stale
    Unix socket file (nobody listening) of this user is removed, a live one refused
    (:class:`~bus.transports.hub.wire.HubAddressInUseError`), anyone else's refused
    (:class:`~bus.transports.hub.owner.HubOwnerError`); the socket file has mode 0600:
    :func:`bus.transports.hub.addresses.listen_socket`.

Who may connect
    Only processes of the hub's own user and root (:func:`bus.transports.hub.owner.check_peer`:
    ``SO_PEERCRED`` on a Unix socket, ``/proc/net/tcp`` on loopback TCP); anyone else is refused
    in the handshake (``ILNO`` and the reason) and logged.  A member on another machine
    (``--allow-remote``) cannot be checked: remote TCP is unauthenticated.

Timestamps
    Every frame is stamped with the hub's receive time (``time.time_ns()`` taken right after the
    read that completed it) in the record it forwards; clients deliver it as ``msg.timestamp``.
    On a bus-time bus the stamp is the end of the frame's transmission.

Latency and cost
    Non-blocking sockets in one ``epoll`` loop (``select()`` when a bus runs in bus time: epoll
    rounds its timeout up to whole milliseconds, bus time waits for frame ends tens of µs apart),
    ``TCP_NODELAY`` for TCP. A client that stops reading is dropped once more than
    :attr:`HubServer.MAX_OUTBUF_BYTES` are queued for it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import socket
import time
from collections.abc import Mapping, Sequence
from typing import Any, Self

from bus.timer_slack import fine_timer_slack
from bus.transports.hub.addresses import HubAddress, listen_socket, parse_address
from bus.transports.hub.bus_time import BusTime
from bus.transports.hub.core import CoreSelector, hub_core_available, new_core_selector
from bus.transports.hub.owner import HubOwnerError, check_peer
from bus.transports.hub.routing import Client, Router
from bus.transports.hub.stats import HubChannelStats, encode_stats
from bus.transports.hub.wire import (
    BITRATES,
    HELLO_FIXED,
    HELLO_FLAG_BULK,
    HELLO_FLAG_CLASSIC,
    HELLO_FLAG_ECHO,
    MAGIC_HELLO,
    MAGIC_NO,
    MAGIC_OK,
    PROTOCOL_VERSION,
    ROLE_MEMBER,
    ROLE_STATS,
    ROLE_STATS_RESET,
    HubAddressError,
    version_refusal,
)

logger = logging.getLogger(__name__)


class HubServer:
    """The hub: binds its listen addresses at construction, serves in :meth:`serve_forever`.

    :param listen: addresses (strings or :class:`HubAddress`); TCP port 0 picks a free port
    :param allow_remote: accept non-loopback TCP addresses (explicit opt-in: the hub then serves
        other machines)
    :param frame_hook: frame faults (:class:`bus.transports.fault_inject.FrameFaultInjector`, see
        :mod:`bus.transports.hub.routing`)
    :param bus_time: logical bus name → bit rate [bit/s]: these buses deliver frames in bus time
        (:mod:`bus.transports.hub.bus_time`)
    :raises NonLoopbackAddressError: a TCP address is not loopback (without ``allow_remote``)
    :raises HubAddressInUseError: a live hub already owns a Unix path
    :raises ValueError: a bus-time bit rate that is not positive

    :ivar bus_time: the bus-time buses (:class:`BusTime`), None when no bus runs in bus time
    """

    #: a client with more than this many unsent bytes queued is dropped (it stopped reading)
    MAX_OUTBUF_BYTES: int = 8 << 20
    #: most bytes read from a client at once
    RECV_CHUNK: int = 1 << 16

    def __init__(
        self,
        listen: Sequence[str | HubAddress],
        allow_remote: bool = False,
        frame_hook: Any = None,
        bus_time: Mapping[str, int] | None = None,
    ) -> None:
        if not listen:
            raise HubAddressError("the hub needs at least one listen address")
        self.bus_time: BusTime[Client] | None = BusTime(bus_time) if bus_time else None
        if self.bus_time is not None:
            fine_timer_slack()
        self._router = Router(self._send_to, self._update_events, self.bus_time, frame_hook)
        #: the C data plane, when built and nothing needs the per-frame Python path (faults, bus time)
        self._core: CoreSelector | None = None
        self._sel: selectors.BaseSelector
        if frame_hook is None and self.bus_time is None and hub_core_available():
            self._core = self._sel = new_core_selector(self._core_dropped, self.RECV_CHUNK, self.MAX_OUTBUF_BYTES)
        else:
            self._sel = selectors.SelectSelector() if self.bus_time is not None else selectors.DefaultSelector()
        #: logical bus name -> index in the C core
        self._bus_index: dict[str, int] = {}
        self._listeners: dict[socket.socket, HubAddress] = {}
        self._unix_paths: list[str] = []
        self._clients: dict[socket.socket, Client] = {}
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
        sock, bound = listen_socket(addr)
        if addr.kind == "unix":
            self._unix_paths.append(addr.path)
        self._listeners[sock] = bound
        self._sel.register(sock, selectors.EVENT_READ, "listen")
        logger.info("hub listening on %s", bound)
        return bound

    # -- public ---------------------------------------------------------------------------

    def stats(self, reset: bool = False) -> dict[str, HubChannelStats]:
        """Per-bus counters (copies); ``reset`` zeroes frame and bit counts afterwards."""
        out: dict[str, HubChannelStats] = {}
        for name, st in self._router.stats.items():
            st.clients = len(self._router.buses.get(name, ()))
            out[name] = copy = HubChannelStats(**vars(st))
            if self._core is not None and name in self._bus_index:
                copy.add_core_counts(self._core.stats(self._bus_index[name], reset))
            if reset:
                st.reset_counts()
        return out

    @property
    def data_plane(self) -> str:
        """``"c"`` when members' frames move in the C core, ``"python"`` otherwise."""
        return "c" if self._core is not None else "python"

    def wake(self) -> None:
        """Ask :meth:`serve_forever` to return (thread-safe, signal-safe)."""
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def serve_forever(self, watch_fd: int | None = None) -> None:
        """Serve until :meth:`wake` is called or ``watch_fd`` reaches EOF (parent gone)."""
        if watch_fd is not None:
            self._sel.register(watch_fd, selectors.EVENT_READ, "watch")
        router = self._router
        bus_time = self.bus_time
        try:
            while True:
                for key, events in self._sel.select(self._timeout_s()):
                    tag = key.data
                    if isinstance(tag, Client):
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
                router.release_delayed()
                if bus_time is not None:
                    bus_time.run(time.monotonic_ns(), router.fan_out, self._update_events)
                router.send_round()
                router.release_held()
        finally:
            if watch_fd is not None:
                with contextlib.suppress(KeyError, ValueError):
                    self._sel.unregister(watch_fd)

    def _timeout_s(self) -> float | None:
        """How long the loop may wait for events, s: until the next held, delayed or bus-time frame
        is due (None: no frame is)."""
        held, delayed = self._router.held_due_s(), self._router.delayed_due_s()
        end_ns = self.bus_time.next_end_ns() if self.bus_time is not None else None
        if held is None and delayed is None and end_ns is None:
            return None
        now = time.monotonic()
        dues = [d for d in (held, delayed) if d is not None]
        if end_ns is not None:
            dues.append(now + (end_ns - time.monotonic_ns()) / 1e9)
        return max(0.0, min(dues) - now)

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

    # -- connections ----------------------------------------------------------------------

    def _accept(self, lsock: socket.socket) -> None:
        try:
            sock, peer = lsock.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        if sock.family != socket.AF_UNIX:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = Client(sock=sock, peer=str(peer) or "unix")
        try:
            check_peer(sock, "a client")
        except HubOwnerError as err:
            client.refusal = str(err)  # told at its hello, so the client reads why
        self._clients[sock] = client
        self._sel.register(sock, selectors.EVENT_READ, client)

    def _drop(self, client: Client, reason: str) -> None:
        if self._clients.pop(client.sock, None) is None:
            return
        if self._core is not None:
            self._core.release(client)
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(client.sock)
        client.sock.close()
        if self._router.leave(client):
            logger.info("hub: client left bus %r (%s)", client.bus, reason)

    def _core_dropped(self, client: Client, refuse: bool, reason: str) -> None:
        """The core dropped member ``client`` (it already forgot it): the Python side's part."""
        if reason == "output buffer overflow":
            logger.warning("hub: dropping client %s on bus %r: it stopped reading", client.peer, client.bus)
        if refuse:
            self._refuse(client, reason)
        else:
            self._drop(client, reason)

    def _refuse(self, client: Client, text: str) -> None:
        logger.warning("hub: refusing client %s: %s", client.peer, text)
        raw = text.encode()[:255]
        with contextlib.suppress(OSError):
            client.sock.send(MAGIC_NO + bytes([len(raw)]) + raw)
        self._drop(client, text)

    def _on_readable(self, client: Client) -> None:
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
        refusal = self._router.route(client, stamp_ns)
        if refusal is not None:
            self._refuse(client, refusal)

    def _handshake(self, client: Client, stamp_ns: int) -> None:
        buf = client.inbuf
        if client.refusal is not None:
            self._refuse(client, client.refusal)
            return
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
            self._send_to(client, encode_stats(self.stats(reset=role == ROLE_STATS_RESET)))
            client.role = role
            return
        client.echo = bool(flags & HELLO_FLAG_ECHO)
        client.classic = bool(flags & HELLO_FLAG_CLASSIC)
        client.bulk = bool(flags & HELLO_FLAG_BULK)
        refusal = self._router.join(client, name, bitrate, data_bitrate)
        if refusal is not None:
            self._refuse(client, refusal)
            return
        st = self._router.stats[name]
        logger.info("hub: client %s joined bus %r%s", client.peer, name, " (classic CAN)" if client.classic else "")
        self._send_to(client, MAGIC_OK + BITRATES.pack(st.bitrate, st.data_bitrate))
        if self._core is not None and client.sock in self._clients:
            self._core.adopt(client, self._bus_index.setdefault(name, len(self._bus_index)), stamp_ns)

    # -- output ---------------------------------------------------------------------------

    def _update_events(self, client: Client) -> None:
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

    def _send_to(self, client: Client, data: bytes) -> None:
        """Write ``data`` to ``client`` now, or queue what the socket does not take (and drop the
        client once more than :attr:`MAX_OUTBUF_BYTES` wait)."""
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
            st = self._router.stats.get(client.bus)
            if st is not None:
                st.dropped_clients += 1
            logger.warning("hub: dropping client %s on bus %r: it stopped reading", client.peer, client.bus)
            self._drop(client, "output buffer overflow")
            return
        if not client.writing:
            client.writing = True
            self._update_events(client)

    def _flush(self, client: Client) -> None:
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
