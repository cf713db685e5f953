"""Hub records: frames and acceptance filters as the bytes of an ilcrig hub socket.

This module owns the conversion between python-can frames and the hub's records (layout:
:mod:`bus.transports.hub.wire`): :func:`encode_record`, :func:`encode_data_frames` and :func:`encode_filters` (client → hub),
:func:`decode_records` (records → :class:`can.Message`) and :func:`classic_frames` (records → one
numpy array of :data:`bus.bus_features.FRAME_DTYPE`, without a :class:`can.Message` per frame).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import can
import numpy as np

from bus import bus_features as bf
from bus.bus_features import FRAME_DTYPE, check_data_frame, frame_flags, message_of
from bus.fastmsg import FAST
from bus.transports.hub.wire import (
    FILTER_ENTRY,
    FLAG_BRS,
    FLAG_ECHO,
    FLAG_ERR,
    FLAG_ESI,
    FLAG_EXT,
    FLAG_FD,
    FLAG_RTR,
    HEADER,
    HEADER_SIZE,
    KIND_FILTERS,
    KIND_FRAME,
    KIND_GATHER,
    KIND_RELEASE,
    HubProtocolError,
)

_new = can.Message.__new__
_Message = can.Message
#: a classic frame's record (wire.HEADER) as a numpy record
_WIRE_DTYPE = np.dtype(
    [
        ("kind", "u1"),
        ("flags", "u1"),
        ("dlc", "u1"),
        ("length", "u1"),
        ("can_id", "<u4"),
        ("stamp", "<u8"),
        ("inline", "u1", (8,)),
    ]
)
#: the wire's flag bits are the FRAME_* bits (the echo of a sent frame: FRAME_TX)
assert _WIRE_DTYPE.itemsize == HEADER_SIZE
assert [FLAG_EXT, FLAG_RTR, FLAG_ERR, FLAG_FD, FLAG_BRS, FLAG_ESI, FLAG_ECHO] == [
    getattr(bf, f"FRAME_{kind}") for kind in ("EXT", "RTR", "ERR", "FD", "BRS", "ESI", "TX")
]


def encode_record(msg: can.Message) -> bytes:
    """The wire record (24-byte header + FD tail) of one frame, timestamp 0 (the hub stamps it)."""
    data = b"" if msg.is_remote_frame else bytes(msg.data)
    flags = frame_flags(msg)
    n = len(data)
    if n > 64:
        raise ValueError(f"frame data too long ({n} bytes)")
    head = HEADER.pack(KIND_FRAME, flags, msg.dlc & 0xFF, n, msg.arbitration_id & 0xFFFFFFFF, 0, data[:8])
    return head + data[8:] if n > 8 else head


def encode_data_frames(frames: Sequence[tuple[int, bytes]]) -> bytes:
    """The wire records of classic data frames given as (11-bit identifier, data) pairs, timestamp
    0: the bytes :func:`encode_record` gives for their :class:`can.Message` (no flags, DLC = length).

    :raises ValueError: an identifier outside 0..0x7FF or more than 8 data bytes
    """
    pack = HEADER.pack
    out = []
    for can_id, data in frames:
        n = len(data)
        if n > 8 or not 0 <= can_id <= 0x7FF:
            check_data_frame(can_id, data)
        out.append(pack(KIND_FRAME, 0, n, n, can_id, 0, data))
    return b"".join(out)


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


def encode_gather(count: int) -> bytes:
    """The gather record (client → hub): hold this member's frames until ``count`` are held
    (0: deliver at once)."""
    return HEADER.pack(KIND_GATHER, 0, 0, 0, count & 0xFFFFFFFF, 0, b"")


def encode_release() -> bytes:
    """The release record (client → hub): a bulk member's held frames, now."""
    return HEADER.pack(KIND_RELEASE, 0, 0, 0, 0, 0, b"")


def decode_records(data: bytes, channel: str, append: Callable[[can.Message], None]) -> int:
    """Every whole frame record of ``data`` as a :class:`can.Message` (``msg.channel`` =
    ``channel``, ``msg.timestamp`` = the hub's stamp) handed to ``append``, in order.

    :return: the bytes used; a partial record at the end is not
    :raises HubProtocolError: a record of another kind than a frame
    """
    size = len(data)
    off = 0
    unpack = HEADER.unpack_from
    new = _new
    while size - off >= HEADER_SIZE:
        kind, flags, dlc, length, can_id, stamp_ns, inline = unpack(data, off)
        if kind != KIND_FRAME:
            raise HubProtocolError(f"unexpected record kind {kind} from hub")
        end = off + HEADER_SIZE
        if length > 8:
            end += length - 8
            if end > size:
                break
            payload = bytearray(inline + data[off + HEADER_SIZE : end])
        else:
            payload = bytearray(inline[:length])
        if flags or not FAST:
            msg = message_of(can_id, payload, flags, stamp_ns / 1e9, channel, dlc)
        else:  # the common case: a classic data frame with an 11-bit id
            msg = new(_Message)
            msg.timestamp = stamp_ns / 1e9
            msg.arbitration_id = can_id
            msg.is_extended_id = msg.is_remote_frame = msg.is_error_frame = msg.is_fd = False
            msg.bitrate_switch = msg.error_state_indicator = False
            msg.is_rx = True
            msg.channel = channel
            msg.data = payload
            msg.dlc = dlc
        append(msg)
        off = end
    return off


def classic_frames(data: bytes) -> tuple[np.ndarray, int] | None:
    """The whole records of ``data`` as one array of :data:`bus.bus_features.FRAME_DTYPE` and the
    bytes used (a partial record at the end is not); None when a record is not a classic frame
    (CAN FD, or another kind): then :func:`decode_records` reads them one at a time."""
    n = len(data) // HEADER_SIZE
    wire = np.frombuffer(data, dtype=_WIRE_DTYPE, count=n)
    if not ((wire["kind"] == KIND_FRAME) & (wire["length"] <= 8)).all():
        return None
    out = np.zeros(n, dtype=FRAME_DTYPE)
    out["timestamp"] = wire["stamp"] / 1e9
    out["arbitration_id"] = wire["can_id"]
    out["flags"] = wire["flags"]  # the wire's flag bits are FRAME_* (echo = FRAME_TX)
    out["dlc"] = wire["dlc"]
    out["length"] = wire["length"]
    out["data"][:, :8] = wire["inline"]
    return out, n * HEADER_SIZE
