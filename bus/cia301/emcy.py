"""CiA 301 emergency (EMCY) frames: codec, COB-ID and the common error codes, and the
pre-defined error field (object 0x1003).

EMCY frame on COB-ID ``0x080 + node_id`` (object 0x1014 default), 8 data bytes:
error code U16 little-endian, error register U8 (object 0x1001), 5 manufacturer-specific
bytes.  Error code 0x0000 means "error reset / no error".

Object 0x1014 (COB-ID EMCY, U32): bit 31 = 1 the EMCY is not valid (not sent), bit 29 = 1 a
29-bit identifier (not supported), bits 0–10 the identifier; the identifier can change only while
bit 31 is set, and a valid EMCY cannot take a restricted CAN-ID of CiA 301 (Table 3: 0x000,
0x001–0x07F, 0x101–0x180, 0x581–0x5FF, 0x601–0x67F, 0x6E0–0x6FF, 0x701–0x77F, 0x780–0x7FF;
:func:`check_emcy_cob_id`).  Object 0x1003 (:class:`ErrorHistory`): sub 0 the number
of errors recorded, subs 1.. the errors, newest first, each ``additional info << 16 | error code``;
writing 0 to sub 0 clears it, any other value is refused.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from bus.pdo_objects import is_restricted_can_id

logger = logging.getLogger(__name__)

#: COB-ID base of EMCY frames.
EMCY_BASE = 0x080

_EMCY = struct.Struct("<HB5s")


class EmcyFrameError(ValueError):
    """A frame or field is not a valid EMCY message."""


class EmcyCode(IntEnum):
    """Common emergency error codes (CiA 301 table 21, CiA 402)."""

    ERROR_RESET = 0x0000
    GENERIC = 0x1000
    CURRENT = 0x2000
    OVER_CURRENT = 0x2310  # continuous over-current, device output side
    SHORT_CIRCUIT = 0x2320
    VOLTAGE = 0x3000
    DC_LINK_OVER_VOLTAGE = 0x3210
    DC_LINK_UNDER_VOLTAGE = 0x3220
    TEMPERATURE = 0x4000
    DRIVE_TEMPERATURE = 0x4310
    DEVICE_HARDWARE = 0x5000
    DEVICE_SOFTWARE = 0x6000
    INTERNAL_SOFTWARE = 0x6100
    ADDITIONAL_MODULES = 0x7000
    MONITORING = 0x8000
    COMMUNICATION = 0x8100
    CAN_OVERRUN = 0x8110
    CAN_ERROR_PASSIVE = 0x8120
    HEARTBEAT_ERROR = 0x8130  # life guard / heartbeat consumer error
    CAN_BUS_OFF_RECOVERED = 0x8140
    PROTOCOL_ERROR = 0x8200
    PDO_LENGTH = 0x8210
    PDO_LENGTH_EXCEEDED = 0x8220
    SYNC_LENGTH = 0x8240  # unexpected SYNC data length (0x1019)
    RPDO_TIMEOUT = 0x8250  # an RPDO missed its deadline (0x1400+k:5)
    CONTROL = 0x8600  # CiA 402 positioning controller
    FOLLOWING_ERROR = 0x8611
    REFERENCE_LIMIT = 0x8612
    SYNC_CONTROLLER = 0x8700
    EXTERNAL_ERROR = 0x9000
    ADDITIONAL_FUNCTIONS = 0xF000
    DEVICE_SPECIFIC = 0xFF00


class ErrorRegister(IntFlag):
    """Bits of the error register, object 0x1001 (byte 2 of an EMCY frame)."""

    NONE = 0x00
    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08
    COMMUNICATION = 0x10
    DEVICE_PROFILE = 0x20
    MANUFACTURER = 0x80


def emcy_cob_id(node_id: int) -> int:
    """COB-ID of node ``node_id``'s EMCY frames (``0x080 + node_id``).

    :raises EmcyFrameError: node id outside 1..127.
    """
    if not 1 <= node_id <= 127:
        raise EmcyFrameError(f"node id must be 1..127, got {node_id}")
    return EMCY_BASE + node_id


#: 0x1014 bits: not valid, 29-bit identifier
EMCY_NOT_VALID = 1 << 31
EMCY_EXTENDED = 1 << 29


def check_emcy_cob_id(old: int, new: int) -> None:
    """Refuse a 0x1014 write (CiA 301 §7.5.2.13).

    :raises ValueError: a 29-bit identifier, bits other than 31, 29 and 0–10, a restricted CAN-ID
        of CiA 301 (Table 3, :func:`bus.pdo_objects.is_restricted_can_id`) in a valid COB-ID, or a
        new identifier while the EMCY is valid (set bit 31 first).
    """
    if new & EMCY_EXTENDED or new & 0x5FFFF800:
        raise ValueError(f"COB-ID EMCY 0x{new:08X}: only an 11-bit identifier and bit 31 are supported")
    if not new & EMCY_NOT_VALID and is_restricted_can_id(new & 0x7FF):
        raise ValueError(f"COB-ID EMCY 0x{new:08X}: CAN-ID 0x{new & 0x7FF:03X} is restricted (CiA 301 Table 3)")
    if not old & EMCY_NOT_VALID and not new & EMCY_NOT_VALID and (new & 0x7FF) != (old & 0x7FF):
        raise ValueError("the EMCY is valid: set bit 31 of 0x1014 before changing its identifier")


class ErrorHistory:
    """The pre-defined error field, object 0x1003 (see the module docstring).

    :param size: entries kept (subs 1..size); the oldest falls out.
    """

    def __init__(self, size: int = 8) -> None:
        self.size = int(size)
        self._entries: list[int] = []

    def __len__(self) -> int:
        return len(self._entries)

    def push(self, code: int, info: int = 0) -> None:
        """Record error ``code`` (U16) with ``info`` (U16, manufacturer) as the newest entry."""
        self._entries.insert(0, ((int(info) & 0xFFFF) << 16) | (int(code) & 0xFFFF))
        del self._entries[self.size :]

    def entry(self, sub: int) -> int:
        """Sub ``sub`` (1 = newest); 0 where nothing is recorded."""
        return self._entries[sub - 1] if 1 <= sub <= len(self._entries) else 0

    def clear(self) -> None:
        self._entries.clear()


def emcy_node_id(cob_id: int) -> int | None:
    """Node id if ``cob_id`` is an EMCY COB-ID (0x081..0x0FF), else None (0x080 is SYNC)."""
    node_id = cob_id - EMCY_BASE
    return node_id if 1 <= node_id <= 127 else None


@dataclass(frozen=True)
class EmcyMessage:
    """One emergency message.

    :ivar code: error code U16 (:class:`EmcyCode` or any 0..0xFFFF).
    :ivar register: error register U8 (:class:`ErrorRegister` bits).
    :ivar manufacturer: 5 manufacturer-specific bytes (shorter input is zero-padded).
    """

    code: int
    register: int = 0
    manufacturer: bytes = bytes(5)

    def __post_init__(self) -> None:
        if not 0 <= self.code <= 0xFFFF:
            raise EmcyFrameError(f"EMCY error code must be a U16, got {self.code}")
        if not 0 <= self.register <= 0xFF:
            raise EmcyFrameError(f"error register must be a U8, got {self.register}")
        data = bytes(self.manufacturer)
        if len(data) > 5:
            raise EmcyFrameError(f"manufacturer field is at most 5 bytes, got {len(data)}")
        object.__setattr__(self, "manufacturer", data.ljust(5, b"\x00"))

    @property
    def is_reset(self) -> bool:
        """True for the "error reset / no error" message (code 0x0000)."""
        return self.code == EmcyCode.ERROR_RESET

    def encode(self) -> bytes:
        """The 8 data bytes of the frame."""
        return _EMCY.pack(self.code, self.register, self.manufacturer)

    @classmethod
    def decode(cls, data: bytes) -> EmcyMessage:
        """Decode the data bytes of an EMCY frame.

        :raises EmcyFrameError: data is not 8 bytes.
        """
        if len(data) != 8:
            raise EmcyFrameError(f"EMCY frame must have 8 data bytes, got {len(data)}")
        code, register, manufacturer = _EMCY.unpack(bytes(data))
        return cls(code, register, manufacturer)

    def __str__(self) -> str:
        try:
            name = EmcyCode(self.code).name
        except ValueError:
            name = "UNKNOWN"
        return f"EMCY 0x{self.code:04X} ({name}) register 0x{self.register:02X} data {self.manufacturer.hex(' ')}"


def encode_emcy(code: int, register: int = 0, manufacturer: bytes = b"") -> bytes:
    """Data bytes of an EMCY frame (see :class:`EmcyMessage`)."""
    return EmcyMessage(code, register, manufacturer).encode()


def decode_emcy(data: bytes) -> EmcyMessage:
    """Decode EMCY frame data (see :meth:`EmcyMessage.decode`)."""
    return EmcyMessage.decode(data)
