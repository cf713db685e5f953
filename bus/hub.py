"""Zero-privilege CAN hub: a python-can interface over Unix or loopback TCP sockets.

This module owns the hub transport: the wire format, the hub server
(:class:`HubServer`, ``python -m bus.hub``), the client :class:`HubBus` (registered as the
python-can interface ``ilcrig_hub``) and the child-process API :func:`start_hub`.

No root, no kernel module: the hub is one process that accepts clients on a Unix domain
socket (default) or on loopback TCP. A listen address that is not loopback is refused
(:class:`NonLoopbackAddressError`). Every frame a client sends is forwarded to every other
client of the same logical bus, never back to the sender (unless the sender asked for
``receive_own_messages``; it then gets its own frames back with ``is_rx=False``).

Channels
    One hub serves several logical buses. The channel string is
    ``<address>#<bus name>``, e.g. ``unix:/tmp/rig/hub.sock#io`` or
    ``tcp:127.0.0.1:29536#fieldbus``; without ``#`` the bus is ``default``. A bare path
    (``/tmp/x.sock``) means ``unix:``. Received messages carry the bus name as
    ``msg.channel`` (short, candump-friendly).

    >>> bus = can.Bus(interface="ilcrig_hub", channel="unix:/tmp/x.sock#io")  # doctest: +SKIP

Counting
    The hub counts, per logical bus, frames and bits (without and with worst-case
    stuffing, :mod:`bus.busload`), FD and error frames, and clients. Read them with
    :func:`query_hub_stats` or :meth:`HubHandle.stats`.

Acceptance filters
    ``can_filters`` / :meth:`can.BusABC.set_filters` are pushed to the hub, which then only
    forwards matching frames (like SocketCAN's kernel filters); the client still checks
    them in software, so frames in flight while filters change are filtered too.

Wire format (all little-endian)
    Handshake, client → hub: ``b"ILCH"``, u8 version (1), u8 role (1 member, 2 stats,
    3 stats and reset), u8 flags (bit 0 receive own messages), u8 n, n bytes bus name
    (UTF-8). Hub → member: ``b"ILOK"`` once registered (frames flow only after it).
    Hub → stats query: ``b"ILOK"``, u32 n, n bytes JSON. Refusal: ``b"ILNO"``, u8 n, text.

    Then records of a 16-byte header ``<BBBBI8s``: kind, flags, dlc, length, can_id, the
    first 8 data bytes (zero padded); ``length − 8`` more data bytes follow when
    length > 8 (CAN FD). kind 1 = frame; kind 2 = acceptance filters (client → hub): the
    ``can_id`` field holds the payload size, followed by that many bytes of ``<IIb``
    entries (can_id, can_mask, extended: −1 any, 0 standard, 1 extended); no entries =
    accept all. Frame flags: 0x01 extended, 0x02 remote, 0x04 error, 0x08 FD, 0x10 BRS,
    0x20 ESI, 0x40 own message echoed back.

    Clients read exactly one record per ``recv`` (header with ``MSG_WAITALL``), so a
    readable :meth:`HubBus.fileno` always means a frame is waiting: callers may
    ``select()`` over several buses.

Latency
    Blocking client sockets + ``select`` and non-blocking hub sockets in one ``epoll`` loop,
    no sleeps, ``TCP_NODELAY`` on both ends for TCP. A client that stops reading is
    dropped once more than :attr:`HubServer.MAX_OUTBUF_BYTES` are queued for it.
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import json
import logging
import os
import select
import selectors
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import can
from can import CanProtocol

from bus.busload import BusLoadCounter, bits_lookup
from bus.errors import IlcrigError

logger = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------
# wire format
# ---------------------------------------------------------------------------------------

MAGIC_HELLO = b"ILCH"
MAGIC_OK = b"ILOK"
MAGIC_NO = b"ILNO"
PROTOCOL_VERSION = 1

ROLE_MEMBER = 1
ROLE_STATS = 2
ROLE_STATS_RESET = 3
HELLO_FLAG_ECHO = 0x01

KIND_FRAME = 1
KIND_FILTERS = 2

FLAG_EXT = 0x01
FLAG_RTR = 0x02
FLAG_ERR = 0x04
FLAG_FD = 0x08
FLAG_BRS = 0x10
FLAG_ESI = 0x20
FLAG_ECHO = 0x40

HEADER = struct.Struct("<BBBBI8s")
HEADER_SIZE = HEADER.size  # 16
_HELLO_FIXED = struct.Struct("<4sBBBB")
_FILTER_ENTRY = struct.Struct("<IIb")
_U32 = struct.Struct("<I")

DEFAULT_BUS_NAME = "default"
MAX_BUS_NAME_BYTES = 64


class HubError(IlcrigError):
    """Root of hub errors."""


class HubAddressError(HubError, ValueError):
    """A hub address or channel string is malformed."""


class NonLoopbackAddressError(HubAddressError):
    """A TCP address that is not a loopback address (the hub never leaves this machine)."""


class HubAddressInUseError(HubError, OSError):
    """Another live hub already listens on this Unix socket path."""


class HubStartError(HubError, RuntimeError):
    """The hub child process did not become ready."""


class HubProtocolError(HubError, can.CanOperationError):
    """The peer violated the hub wire protocol."""


# ---------------------------------------------------------------------------------------
# addresses
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HubAddress:
    """Where a hub listens: ``unix`` (``path``) or ``tcp`` (loopback ``host``, ``port``)."""

    kind: str
    path: str = ""
    host: str = ""
    port: int = 0

    def __str__(self) -> str:
        if self.kind == "unix":
            return f"unix:{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tcp:{host}:{self.port}"

    @property
    def family(self) -> socket.AddressFamily:
        if self.kind == "unix":
            return socket.AF_UNIX
        return socket.AF_INET6 if ":" in self.host else socket.AF_INET

    @property
    def sockaddr(self) -> Any:
        return self.path if self.kind == "unix" else (self.host, self.port)


def _require_loopback(host: str, port: int) -> str:
    """Resolve ``host`` and return a numeric loopback address.

    :raises NonLoopbackAddressError: empty host, or any resolved address not loopback
    """
    if not host:
        raise NonLoopbackAddressError("the hub listens on loopback only; an empty host means all interfaces")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as err:
        raise HubAddressError(f"cannot resolve hub host {host!r}: {err}") from err
    addrs = [info[4][0] for info in infos]
    bad = [a for a in addrs if not ipaddress.ip_address(a.split("%")[0]).is_loopback]
    if bad or not addrs:
        raise NonLoopbackAddressError(
            f"refusing non-loopback hub address {host!r} (resolves to {', '.join(addrs)}); "
            "use 127.0.0.1, ::1, localhost or a unix: path"
        )
    return addrs[0]


def parse_address(text: str) -> HubAddress:
    """Parse ``unix:/path``, a bare path, ``tcp:HOST:PORT`` or ``tcp:[v6]:PORT``.

    :raises NonLoopbackAddressError: a TCP host that is not loopback
    :raises HubAddressError: anything else malformed
    """
    if not text:
        raise HubAddressError("empty hub address")
    if text.startswith("unix:"):
        path = text[5:]
        if not path:
            raise HubAddressError("unix: address without a path")
        return HubAddress("unix", path=path)
    if text.startswith("tcp:"):
        rest = text[4:]
        if rest.startswith("["):
            host, sep, port_s = rest[1:].partition("]:")
        else:
            host, sep, port_s = rest.rpartition(":")
        if not sep:
            raise HubAddressError(f"tcp address needs HOST:PORT, got {text!r}")
        try:
            port = int(port_s)
        except ValueError as err:
            raise HubAddressError(f"bad TCP port in {text!r}") from err
        if not 0 <= port <= 65535:
            raise HubAddressError(f"TCP port out of range in {text!r}")
        return HubAddress("tcp", host=_require_loopback(host, port), port=port)
    if "/" in text or text.endswith(".sock"):
        return HubAddress("unix", path=text)
    raise HubAddressError(f"unknown hub address {text!r}; use unix:/path or tcp:127.0.0.1:PORT")


def parse_channel(channel: str) -> tuple[HubAddress, str]:
    """Split ``<address>#<bus name>`` into (address, bus name); the name defaults to ``default``.

    :raises HubAddressError: malformed address or bus name
    """
    if not isinstance(channel, str):
        raise HubAddressError(f"hub channel must be a string, got {channel!r}")
    addr_text, sep, name = channel.rpartition("#")
    if not sep:
        addr_text, name = channel, DEFAULT_BUS_NAME
    if not name or len(name.encode()) > MAX_BUS_NAME_BYTES or any(c.isspace() for c in name):
        raise HubAddressError(f"bad bus name {name!r} in channel {channel!r}")
    return parse_address(addr_text), name


#: environment variable naming the hub address used when none is given
HUB_ENV: str = "ILCRIG_HUB"


def default_hub_address() -> str:
    """``$ILCRIG_HUB`` if set, else a per-user Unix socket in the temp directory,
    e.g. ``unix:/tmp/ilcrig-hub-1000.sock``."""
    env = os.environ.get(HUB_ENV, "").strip()
    if env:
        return env
    return f"unix:{os.path.join(tempfile.gettempdir(), f'ilcrig-hub-{os.getuid()}.sock')}"


def _connect(addr: HubAddress, timeout_s: float) -> socket.socket:
    sock = socket.socket(addr.family, socket.SOCK_STREAM)
    try:
        sock.settimeout(timeout_s)
        sock.connect(addr.sockaddr)
        if addr.kind == "tcp":
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except BaseException:
        sock.close()
        raise
    return sock


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise HubProtocolError("hub closed the connection during the handshake")
        buf += chunk
    return buf


def _hello(role: int, name: str, echo: bool = False) -> bytes:
    raw = name.encode()
    return _HELLO_FIXED.pack(MAGIC_HELLO, PROTOCOL_VERSION, role, HELLO_FLAG_ECHO if echo else 0, len(raw)) + raw


def _read_reply(sock: socket.socket) -> None:
    magic = _recv_exact(sock, 4)
    if magic == MAGIC_OK:
        return
    if magic == MAGIC_NO:
        n = _recv_exact(sock, 1)[0]
        raise HubProtocolError(f"hub refused: {_recv_exact(sock, n).decode(errors='replace')}")
    raise HubProtocolError(f"unexpected hub reply {magic!r}")


# ---------------------------------------------------------------------------------------
# client: the python-can interface
# ---------------------------------------------------------------------------------------


class HubBus(can.BusABC):
    """python-can interface ``ilcrig_hub``: one logical bus on an ilcrig hub.

    :param channel: ``<address>#<bus name>`` (see module docstring)
    :param receive_own_messages: the hub echoes this client's frames back (``is_rx=False``)
    :param connect_timeout_s: connect + handshake timeout, s
    :param can_filters: acceptance filters, applied in the hub and again in software
    :raises can.CanInitializationError: no hub at the address, or the handshake failed
    :raises HubAddressError: malformed channel string (a ValueError)
    """

    #: connect + handshake timeout, s
    CONNECT_TIMEOUT_S: float = 5.0

    def __init__(
        self,
        channel: str | None = None,
        can_filters: can.typechecking.CanFilters | None = None,
        receive_own_messages: bool = False,
        connect_timeout_s: float | None = None,
        **kwargs: Any,
    ) -> None:
        if channel is None:
            raise HubAddressError("HubBus needs a channel such as 'unix:/tmp/hub.sock#io'")
        addr, name = parse_channel(str(channel))
        timeout = self.CONNECT_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
        try:
            sock = _connect(addr, timeout)
        except OSError as err:
            raise can.CanInitializationError(f"cannot reach ilcrig hub at {addr}: {err}") from err
        try:
            sock.sendall(_hello(ROLE_MEMBER, name, echo=receive_own_messages))
            _read_reply(sock)
            sock.settimeout(None)  # blocking from now on
        except (OSError, HubProtocolError) as err:
            sock.close()
            raise can.CanInitializationError(f"hub handshake with {addr} failed: {err}") from err
        self._sock = sock
        self._send_lock = threading.Lock()
        self._address = addr
        self.bus_name = name
        self.receive_own_messages = receive_own_messages
        self.channel = channel
        self.channel_info = f"ilcrig hub {addr} bus {name!r}"
        self._can_protocol = CanProtocol.CAN_FD
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        logger.debug("connected to %s", self.channel_info)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        sock = self._sock
        try:
            if timeout is not None:
                ready, _, _ = select.select((sock,), (), (), max(timeout, 0.0))
                if not ready:
                    return None, False
            head = sock.recv(HEADER_SIZE, socket.MSG_WAITALL)
            if len(head) != HEADER_SIZE:
                head = self._complete(head, HEADER_SIZE)
            kind, flags, dlc, length, can_id, inline = HEADER.unpack(head)
            if kind != KIND_FRAME:
                raise HubProtocolError(f"unexpected record kind {kind} from hub")
            if length > 8:
                data = inline + self._complete(b"", length - 8)
            else:
                data = inline[:length]
        except OSError as err:
            raise can.CanOperationError(f"hub receive failed: {err}") from err
        msg = can.Message(
            timestamp=time.time(),
            arbitration_id=can_id,
            is_extended_id=bool(flags & FLAG_EXT),
            is_remote_frame=bool(flags & FLAG_RTR),
            is_error_frame=bool(flags & FLAG_ERR),
            is_fd=bool(flags & FLAG_FD),
            bitrate_switch=bool(flags & FLAG_BRS),
            error_state_indicator=bool(flags & FLAG_ESI),
            dlc=dlc,
            data=data,
            channel=self.bus_name,
            is_rx=not flags & FLAG_ECHO,
            check=False,
        )
        return msg, False

    def _complete(self, part: bytes, n: int) -> bytes:
        """Read until ``n`` bytes (a signal may cut a MSG_WAITALL read short)."""
        while len(part) < n:
            chunk = self._sock.recv(n - len(part), socket.MSG_WAITALL)
            if not chunk:
                raise can.CanOperationError(f"ilcrig hub closed the connection ({self.channel_info})")
            part += chunk
        return part

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to every other client of this bus.

        Blocking (the hub always reads); ``timeout`` is accepted for the BusABC signature
        and not used. Thread-safe (python-can's periodic tasks send from threads).
        """
        self._sock_send(encode_record(msg))

    def _sock_send(self, data: bytes) -> None:
        try:
            with self._send_lock:
                self._sock.sendall(data)
        except OSError as err:
            raise can.CanOperationError(f"hub send failed: {err}") from err

    def _apply_filters(self, filters: can.typechecking.CanFilters | None) -> None:
        entries = b"".join(
            _FILTER_ENTRY.pack(
                f["can_id"] & 0xFFFFFFFF,
                f["can_mask"] & 0xFFFFFFFF,
                -1 if "extended" not in f else int(bool(f["extended"])),  # type: ignore[typeddict-item]
            )
            for f in (filters or ())
        )
        self._sock_send(HEADER.pack(KIND_FILTERS, 0, 0, 0, len(entries), b"") + entries)

    def fileno(self) -> int:
        """The socket's descriptor: readable ⇔ a frame is waiting (one record per recv)."""
        return self._sock.fileno()

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        with contextlib.suppress(OSError):
            self._sock.close()

    @staticmethod
    def _detect_available_configs() -> list[can.typechecking.AutoDetectedConfig]:
        return []


def encode_record(msg: can.Message) -> bytes:
    """The wire record (16-byte header + FD tail) of one frame."""
    data = b"" if msg.is_remote_frame else bytes(msg.data)
    flags = (
        (FLAG_EXT if msg.is_extended_id else 0)
        | (FLAG_RTR if msg.is_remote_frame else 0)
        | (FLAG_ERR if msg.is_error_frame else 0)
        | (FLAG_FD if msg.is_fd else 0)
        | (FLAG_BRS if msg.bitrate_switch else 0)
        | (FLAG_ESI if msg.error_state_indicator else 0)
    )
    n = len(data)
    if n > 64:
        raise ValueError(f"frame data too long ({n} bytes)")
    head = HEADER.pack(KIND_FRAME, flags, msg.dlc & 0xFF, n, msg.arbitration_id & 0xFFFFFFFF, data[:8])
    return head + data[8:] if n > 8 else head


# ---------------------------------------------------------------------------------------
# hub server
# ---------------------------------------------------------------------------------------


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

    def load(self) -> BusLoadCounter:
        """The classic-CAN frame and bit totals as a :class:`BusLoadCounter`."""
        return BusLoadCounter(self.frames, self.bits, self.bits_worst_case, self.fd_frames)


@dataclass(eq=False)
class _Client:
    sock: socket.socket
    peer: str
    bus: str = ""
    role: int = 0
    echo: bool = False
    filters: list[tuple[int, int, int]] | None = None
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    writing: bool = False

    def accepts(self, can_id: int, ext: int) -> bool:
        if not self.filters:
            return True
        for f_id, f_mask, f_ext in self.filters:
            if f_ext >= 0 and f_ext != ext:
                continue
            if (f_id ^ can_id) & f_mask == 0:
                return True
        return False


class HubServer:
    """The hub: binds its listen addresses at construction, serves in :meth:`serve_forever`.

    :param listen: addresses (strings or :class:`HubAddress`); TCP port 0 picks a free port
    :raises NonLoopbackAddressError: a TCP address is not loopback
    :raises HubAddressInUseError: a live hub already owns a Unix path
    """

    #: a client with more than this many unsent bytes queued is dropped (it stopped reading)
    MAX_OUTBUF_BYTES: int = 8 << 20
    RECV_CHUNK: int = 1 << 16

    def __init__(self, listen: Sequence[str | HubAddress]) -> None:
        if not listen:
            raise HubAddressError("the hub needs at least one listen address")
        self._sel = selectors.DefaultSelector()
        self._listeners: dict[socket.socket, HubAddress] = {}
        self._unix_paths: list[str] = []
        self._clients: dict[socket.socket, _Client] = {}
        self._buses: dict[str, list[_Client]] = {}
        self._stats: dict[str, HubChannelStats] = {}
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self.addresses: list[HubAddress] = []
        try:
            for item in listen:
                addr = item if isinstance(item, HubAddress) else parse_address(item)
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
            out[name] = HubChannelStats(**vars(st))
            if reset:
                st.frames = st.bits = st.bits_worst_case = st.fd_frames = st.error_frames = 0
        return out

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
                for key, events in self._sel.select():
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
                    elif tag == "watch":
                        if not os.read(watch_fd, 4096):  # type: ignore[arg-type]
                            logger.info("hub: watched descriptor closed, exiting")
                            return
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

    def __enter__(self) -> HubServer:
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
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(client.sock)
        client.sock.close()
        members = self._buses.get(client.bus)
        if members and client in members:
            members.remove(client)
            logger.info("hub: client left bus %r (%s)", client.bus, reason)

    def _on_readable(self, client: _Client) -> None:
        try:
            data = client.sock.recv(self.RECV_CHUNK)
        except BlockingIOError:
            return
        except OSError as err:
            self._drop(client, f"recv error {err}")
            return
        if not data:
            self._drop(client, "disconnected")
            return
        client.inbuf += data
        if not client.role:
            self._handshake(client)
            if not client.role or client.sock not in self._clients:
                return
        self._route(client)

    def _handshake(self, client: _Client) -> None:
        buf = client.inbuf
        if len(buf) < _HELLO_FIXED.size:
            return
        magic, version, role, flags, n = _HELLO_FIXED.unpack_from(buf)
        if magic != MAGIC_HELLO or version != PROTOCOL_VERSION or role not in (ROLE_MEMBER, ROLE_STATS, ROLE_STATS_RESET):
            self._refuse(client, f"bad hello (magic {magic!r}, version {version}, role {role})")
            return
        if len(buf) < _HELLO_FIXED.size + n:
            return
        name = bytes(buf[_HELLO_FIXED.size : _HELLO_FIXED.size + n]).decode(errors="replace")
        del buf[: _HELLO_FIXED.size + n]
        if role in (ROLE_STATS, ROLE_STATS_RESET):
            stats = self.stats(reset=role == ROLE_STATS_RESET)
            body = json.dumps({k: vars(v) for k, v in stats.items()}).encode()
            self._send_to(client, MAGIC_OK + _U32.pack(len(body)) + body)
            client.role = role
            return
        client.role = role
        client.bus = name
        client.echo = bool(flags & HELLO_FLAG_ECHO)
        self._buses.setdefault(name, []).append(client)
        st = self._stats.setdefault(name, HubChannelStats())
        st.connections += 1
        logger.info("hub: client %s joined bus %r", client.peer, name)
        self._send_to(client, MAGIC_OK)

    def _refuse(self, client: _Client, text: str) -> None:
        logger.warning("hub: refusing client %s: %s", client.peer, text)
        raw = text.encode()[:255]
        with contextlib.suppress(OSError):
            client.sock.send(MAGIC_NO + bytes([len(raw)]) + raw)
        self._drop(client, text)

    def _route(self, sender: _Client) -> None:
        if sender.role != ROLE_MEMBER:
            sender.inbuf.clear()  # a stats connection has nothing more to say
            return
        buf = sender.inbuf
        size = len(buf)
        members = self._buses[sender.bus]
        st = self._stats[sender.bus]
        out: dict[_Client, list[bytes]] = {}
        off = 0
        while size - off >= HEADER_SIZE:
            kind = buf[off]
            flags = buf[off + 1]
            length = buf[off + 3]
            if kind == KIND_FRAME:
                total = HEADER_SIZE + (length - 8 if length > 8 else 0)
                if size - off < total:
                    break
                rec = bytes(buf[off : off + total])
                can_id = _U32.unpack_from(buf, off + 4)[0]
                ext = flags & FLAG_EXT
                if flags & FLAG_ERR:
                    st.error_frames += 1
                elif flags & FLAG_FD:
                    st.fd_frames += 1
                else:
                    nominal, worst = bits_lookup(0 if flags & FLAG_RTR else min(length, 8), bool(ext))
                    st.frames += 1
                    st.bits += nominal
                    st.bits_worst_case += worst
                ext = 1 if ext else 0
                for peer in members:
                    if peer is sender:
                        if peer.echo and peer.accepts(can_id, ext):
                            out.setdefault(peer, []).append(rec[:1] + bytes([flags | FLAG_ECHO]) + rec[2:])
                    elif peer.accepts(can_id, ext):
                        out.setdefault(peer, []).append(rec)
            elif kind == KIND_FILTERS:
                n = _U32.unpack_from(buf, off + 4)[0]
                total = HEADER_SIZE + n
                if size - off < total:
                    break
                body = bytes(buf[off + HEADER_SIZE : off + total])
                sender.filters = [
                    _FILTER_ENTRY.unpack_from(body, i) for i in range(0, n - n % _FILTER_ENTRY.size, _FILTER_ENTRY.size)
                ] or None
            else:
                self._refuse(sender, f"unknown record kind {kind}")
                return
            off += total
        del buf[:off]
        for peer, chunks in out.items():
            self._send_to(peer, b"".join(chunks))

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
            self._sel.modify(client.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, client)

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
            self._sel.modify(client.sock, selectors.EVENT_READ, client)


def query_hub_stats(address: str, reset: bool = False, timeout_s: float = 2.0) -> dict[str, HubChannelStats]:
    """Ask a running hub for its per-bus counters.

    :param address: the hub address (a channel string's ``#bus`` part is ignored)
    :param reset: zero the frame and bit counters after reading them
    :raises HubError: no hub, or a protocol error
    """
    addr = parse_channel(address)[0] if "#" in address else parse_address(address)
    try:
        sock = _connect(addr, timeout_s)
    except OSError as err:
        raise HubError(f"cannot reach hub at {addr}: {err}") from err
    with sock:
        sock.sendall(_hello(ROLE_STATS_RESET if reset else ROLE_STATS, ""))
        _read_reply(sock)
        n = _U32.unpack(_recv_exact(sock, 4))[0]
        raw = json.loads(_recv_exact(sock, n))
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

    def __enter__(self) -> HubHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_hub(
    listen: str | Sequence[str] | None = None, *, timeout_s: float = 10.0, log_level: str = "WARNING"
) -> HubHandle:
    """Start a hub in a child process and wait until it accepts clients.

    :param listen: address(es); default: ``hub.sock`` in a fresh private temp directory
        (removed again by :meth:`HubHandle.stop`)
    :param timeout_s: how long to wait for readiness, s
    :raises NonLoopbackAddressError: checked here already, before any process starts
    :raises HubStartError: the child exited or did not report ready in time (it is reaped)

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
    cmd = [sys.executable, "-m", "bus.hub", "--ready", "--exit-on-stdin-eof", "--log-level", log_level]
    for text in listen_list:
        cmd += ["--listen", text]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
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


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bus.hub --listen unix:/path [--listen tcp:127.0.0.1:0]``."""
    parser = argparse.ArgumentParser(prog="python -m bus.hub", description="ilcrig zero-privilege CAN hub")
    parser.add_argument(
        "--listen",
        action="append",
        help=f"unix:/path or tcp:127.0.0.1:PORT (repeatable; default {default_hub_address()})",
    )
    parser.add_argument("--ready", action="store_true", help=f"print '{READY_PREFIX} <addresses>' when listening")
    parser.add_argument("--exit-on-stdin-eof", action="store_true", help="exit when stdin closes")
    parser.add_argument("--log-level", default="INFO")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s hub %(levelname)s %(message)s")
    try:
        server = HubServer(args.listen or [default_hub_address()])
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
