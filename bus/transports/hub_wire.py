"""Hub wire format: what goes over an ilcrig hub socket, and where a hub may listen.

This module owns everything the hub client (:mod:`bus.transports.hub_client`) and the hub
server (:mod:`bus.transports.hub_server`) must agree on: the protocol constants, the
handshake (:func:`hello`, :func:`read_reply`), the frame and filter records
(:func:`encode_record`), the hub errors, and the addresses: :func:`parse_address`,
:func:`parse_channel`, :func:`default_hub_address` and the loopback rule (a TCP address
that is not loopback is refused, :class:`NonLoopbackAddressError`, unless the caller passes
``allow_remote=True`` — ``ilcrig hub --allow-remote``, ``--allow-remote`` of the roles — to span
machines; a wildcard address (all interfaces) is refused even then).

Channels
    One hub serves several logical buses. The channel string is
    ``<address>#<bus name>``, e.g. ``unix:/tmp/rig/hub.sock#io`` or
    ``tcp:127.0.0.1:29536#fieldbus``; without ``#`` the bus is ``default``. A bare path
    (``/tmp/x.sock``) means ``unix:``.

Wire format (all little-endian), protocol version 2
    Handshake, client → hub: ``b"ILCH"``, u8 version (2), u8 role (1 member, 2 stats,
    3 stats and reset), u8 flags (bit 0 receive own messages, bit 1 classic CAN: the client
    was opened with ``fd=False`` and gets no CAN FD frames, bit 2 bulk delivery: a passive
    member that accepts its frames up to ``BULK_HOLD_S`` late, in fewer writes; a hub that
    does not know a bit ignores it), u8 n, n bytes bus name (UTF-8),
    then u32 bitrate, u32 data bitrate (bit/s; 0 = not given). The first five fields keep
    version 1's layout, so a hub reads any client's version before anything else and
    refuses another version with a message naming both (:func:`version_refusal`).

    Hub → member: ``b"ILOK"``, u32 bitrate, u32 data bitrate of the logical bus (0 =
    unknown) once registered (frames flow only after it). Hub → stats query: ``b"ILOK"``,
    u32 n, n bytes JSON. Refusal: ``b"ILNO"``, u8 n, text.

    Then records of a 24-byte header ``<BBBBIQ8s``: kind, flags, dlc, length, can_id,
    timestamp, the first 8 data bytes (zero padded); ``length − 8`` more data bytes follow
    when length > 8 (CAN FD). The timestamp is the hub's receive time of the frame in
    nanoseconds since the epoch (``time.time_ns()``), written by the hub into every record
    it forwards (clients send 0). kind 1 = frame; kind 2 = acceptance filters (client →
    hub): the ``can_id`` field holds the payload size, followed by that many bytes of
    ``<IIb`` entries (can_id, can_mask, extended: −1 any, 0 standard, 1 extended); no
    entries = accept all. Frame flags: 0x01 extended, 0x02 remote, 0x04 error, 0x08 FD,
    0x10 BRS, 0x20 ESI, 0x40 own message echoed back.

    Version history: 1 = 16-byte records without timestamp, no bitrates in the handshake;
    2 = hub receive timestamps, bitrates and the classic-CAN flag.
"""

from __future__ import annotations

import ipaddress
import os
import socket
import struct
import tempfile
from dataclasses import dataclass
from typing import Any

import can

from bus.errors import IlcrigError

MAGIC_HELLO = b"ILCH"
MAGIC_OK = b"ILOK"
MAGIC_NO = b"ILNO"
#: wire protocol version; hub and clients must speak the same one (see the module docstring)
PROTOCOL_VERSION = 2

ROLE_MEMBER = 1
ROLE_STATS = 2
ROLE_STATS_RESET = 3
HELLO_FLAG_ECHO = 0x01
HELLO_FLAG_CLASSIC = 0x02
HELLO_FLAG_BULK = 0x04
#: bulk delivery: longest a hub holds a bulk member's frames, s, and most bytes it holds
BULK_HOLD_S = 0.02
BULK_MAX_BYTES = 32 << 10

KIND_FRAME = 1
KIND_FILTERS = 2

FLAG_EXT = 0x01
FLAG_RTR = 0x02
FLAG_ERR = 0x04
FLAG_FD = 0x08
FLAG_BRS = 0x10
FLAG_ESI = 0x20
FLAG_ECHO = 0x40

HEADER = struct.Struct("<BBBBIQ8s")
HEADER_SIZE = HEADER.size  # 24
#: offset of the u64 timestamp in a record header
STAMP_OFFSET = 8
STAMP = struct.Struct("<Q")
HELLO_FIXED = struct.Struct("<4sBBBB")
#: bitrate, data bitrate (after the bus name of a hello; after ``ILOK`` to a member)
BITRATES = struct.Struct("<II")
FILTER_ENTRY = struct.Struct("<IIb")
U32 = struct.Struct("<I")

DEFAULT_BUS_NAME = "default"
MAX_BUS_NAME_BYTES = 64

#: environment variable naming the hub address used when none is given
HUB_ENV: str = "ILCRIG_HUB"


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


def _require_loopback(host: str, port: int, allow_remote: bool = False) -> str:
    """Resolve ``host`` and return a numeric loopback address (any one address when
    ``allow_remote``, but never a wildcard).

    :raises NonLoopbackAddressError: empty or wildcard host, or (without ``allow_remote``) any
        resolved address not loopback
    """
    if not host:
        raise NonLoopbackAddressError("the hub listens on loopback only; an empty host means all interfaces")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as err:
        raise HubAddressError(f"cannot resolve hub host {host!r}: {err}") from err
    addrs = [str(info[4][0]) for info in infos]
    if allow_remote and addrs:
        if any(ipaddress.ip_address(a.split("%")[0]).is_unspecified for a in addrs):
            raise NonLoopbackAddressError(
                f"refusing the non-loopback wildcard hub address {host!r} (all interfaces): name one interface's address"
            )
        return addrs[0]
    bad = [a for a in addrs if not ipaddress.ip_address(a.split("%")[0]).is_loopback]
    if bad or not addrs:
        raise NonLoopbackAddressError(
            f"refusing non-loopback hub address {host!r} (resolves to {', '.join(addrs)}); "
            "use 127.0.0.1, ::1, localhost or a unix: path (or --allow-remote to span machines)"
        )
    return addrs[0]


def parse_address(text: str, allow_remote: bool = False) -> HubAddress:
    """Parse ``unix:/path``, a bare path, ``tcp:HOST:PORT`` or ``tcp:[v6]:PORT``.

    :param allow_remote: accept a TCP host that is not loopback (explicit opt-in)
    :raises NonLoopbackAddressError: a TCP host that is not loopback (without ``allow_remote``)
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
        return HubAddress("tcp", host=_require_loopback(host, port, allow_remote), port=port)
    if "/" in text or text.endswith(".sock"):
        return HubAddress("unix", path=text)
    raise HubAddressError(f"unknown hub address {text!r}; use unix:/path or tcp:127.0.0.1:PORT")


def parse_channel(channel: str, allow_remote: bool = False) -> tuple[HubAddress, str]:
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
    return parse_address(addr_text, allow_remote), name


def default_hub_address() -> str:
    """``$ILCRIG_HUB`` if set, else a per-user Unix socket in the temp directory,
    e.g. ``unix:/tmp/ilcrig-hub-1000.sock``."""
    env = os.environ.get(HUB_ENV, "").strip()
    if env:
        return env
    return f"unix:{os.path.join(tempfile.gettempdir(), f'ilcrig-hub-{os.getuid()}.sock')}"


# ---------------------------------------------------------------------------------------
# connection and handshake
# ---------------------------------------------------------------------------------------


def connect(addr: HubAddress, timeout_s: float) -> socket.socket:
    """A stream socket connected to the hub at ``addr`` (``TCP_NODELAY`` for TCP).

    :raises OSError: nobody listens there
    """
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


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes of the handshake.

    :raises HubProtocolError: the hub closed the connection first
    """
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise HubProtocolError("hub closed the connection during the handshake")
        buf += chunk
    return buf


def hello(
    role: int,
    name: str,
    *,
    echo: bool = False,
    classic: bool = False,
    bitrate: int = 0,
    data_bitrate: int = 0,
    bulk: bool = False,
) -> bytes:
    """The client's handshake message (bitrates in bit/s, 0 = not given)."""
    raw = name.encode()
    flags = (HELLO_FLAG_ECHO if echo else 0) | (HELLO_FLAG_CLASSIC if classic else 0) | (HELLO_FLAG_BULK if bulk else 0)
    return HELLO_FIXED.pack(MAGIC_HELLO, PROTOCOL_VERSION, role, flags, len(raw)) + raw + BITRATES.pack(bitrate, data_bitrate)


def version_refusal(version: int) -> str:
    """The hub's refusal text for a client speaking protocol ``version``."""
    return (
        f"protocol version {version} not supported: this hub speaks version {PROTOCOL_VERSION}; "
        "hub and clients must come from the same ilcrig version"
    )


def read_reply(sock: socket.socket) -> None:
    """Read the hub's handshake answer up to and including ``ILOK``.

    :raises HubProtocolError: the hub refused (its reason in the message) or answered garbage
    """
    magic = recv_exact(sock, 4)
    if magic == MAGIC_OK:
        return
    if magic == MAGIC_NO:
        n = recv_exact(sock, 1)[0]
        raise HubProtocolError(f"hub refused: {recv_exact(sock, n).decode(errors='replace')}")
    raise HubProtocolError(f"unexpected hub reply {magic!r}")


def read_member_reply(sock: socket.socket) -> tuple[int, int]:
    """Read a member's handshake answer: the logical bus's (bitrate, data bitrate), 0 = unknown.

    :raises HubProtocolError: the hub refused (its reason in the message) or answered garbage
    """
    read_reply(sock)
    bitrate, data_bitrate = BITRATES.unpack(recv_exact(sock, BITRATES.size))
    return int(bitrate), int(data_bitrate)


# ---------------------------------------------------------------------------------------
# records
# ---------------------------------------------------------------------------------------


def encode_record(msg: can.Message) -> bytes:
    """The wire record (24-byte header + FD tail) of one frame, timestamp 0 (the hub stamps it)."""
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
    head = HEADER.pack(KIND_FRAME, flags, msg.dlc & 0xFF, n, msg.arbitration_id & 0xFFFFFFFF, 0, data[:8])
    return head + data[8:] if n > 8 else head


def encode_filters(filters: can.typechecking.CanFilters | None) -> bytes:
    """The acceptance-filter record (client → hub) of ``filters`` (None or empty: accept all)."""
    entries = b"".join(
        FILTER_ENTRY.pack(
            f["can_id"] & 0xFFFFFFFF,
            f["can_mask"] & 0xFFFFFFFF,
            -1 if "extended" not in f else int(bool(f["extended"])),
        )
        for f in (filters or ())
    )
    return HEADER.pack(KIND_FILTERS, 0, 0, 0, len(entries), 0, b"") + entries
