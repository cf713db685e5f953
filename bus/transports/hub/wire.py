"""Hub wire protocol: the constants, the handshake and the errors of an ilcrig hub socket.

This module owns what the hub client (:mod:`bus.transports.hub.client`) and the hub server
(:mod:`bus.transports.hub.server`) must agree on: the protocol constants, the handshake
(:func:`hello`, :func:`read_reply`, :func:`read_member_reply`) and the hub errors. The frame and
filter records are built and read by :mod:`bus.transports.hub.records`; where a hub listens is
:mod:`bus.transports.hub.addresses`'s.

Wire format (all little-endian), protocol version 3
    Handshake, client → hub: ``b"ILCH"``, u8 version (3), u8 role (1 member, 2 stats,
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
    entries = accept all; kind 3 = release (client → hub, a header alone): a bulk member asks
    for the frames the hub holds for it now, not at the end of ``BULK_HOLD_S`` (a reader that
    waits for a marker; a member that is not bulk has nothing held); kind 4 = gather (client →
    hub, a header whose ``can_id`` field is a count n): from now on the hub holds the frames it
    routes to this member until n of them are held (or ``BULK_HOLD_S`` passed) and delivers them
    in one write — a lockstep master that waits for n answers wakes once, not per answer; n = 0
    delivers at once again (and sends what is held). Frame flags: 0x01 extended, 0x02 remote, 0x04 error, 0x08 FD,
    0x10 BRS, 0x20 ESI, 0x40 own message echoed back.

    Version history: 1 = 16-byte records without timestamp, no bitrates in the handshake;
    2 = hub receive timestamps, bitrates and the classic-CAN flag; 3 = the release and gather records.
"""

from __future__ import annotations

import socket
import struct

import can

from bus.errors import IlcrigError, InputError

MAGIC_HELLO = b"ILCH"
MAGIC_OK = b"ILOK"
MAGIC_NO = b"ILNO"
#: wire protocol version; hub and clients must speak the same one (see the module docstring)
PROTOCOL_VERSION = 3

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
KIND_RELEASE = 3
KIND_GATHER = 4

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


class HubError(IlcrigError):
    """Root of hub errors."""


class HubAddressError(HubError, InputError):
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
# handshake
# ---------------------------------------------------------------------------------------


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
