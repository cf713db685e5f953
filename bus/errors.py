"""Error types shared by drive firmware, CANopen subset and host.

:class:`SdoAbort` carries a CiA 301 SDO abort code.  The drive's object-dictionary
access raises it (unknown object, read-only, wrong length, value range); the SDO server
turns it into an abort frame; the in-process host link sees it directly.
"""

from __future__ import annotations

from enum import IntEnum


class AbortCode(IntEnum):
    """CiA 301 SDO abort codes used by the drive (subset)."""

    TOGGLE_BIT = 0x05030000
    TIMEOUT = 0x05040000
    INVALID_COMMAND = 0x05040001
    INVALID_BLOCK_SIZE = 0x05040002
    INVALID_SEQUENCE = 0x05040003
    CRC_ERROR = 0x05040004
    OUT_OF_MEMORY = 0x05040005
    UNSUPPORTED_ACCESS = 0x06010000
    WRITE_ONLY = 0x06010001
    READ_ONLY = 0x06010002
    NO_OBJECT = 0x06020000
    NOT_MAPPABLE = 0x06040041
    PDO_LENGTH = 0x06040042
    HARDWARE_ERROR = 0x06060000
    LENGTH_MISMATCH = 0x06070010
    LENGTH_TOO_HIGH = 0x06070012
    LENGTH_TOO_LOW = 0x06070013
    NO_SUBINDEX = 0x06090011
    VALUE_RANGE = 0x06090030
    VALUE_TOO_HIGH = 0x06090031
    VALUE_TOO_LOW = 0x06090032
    GENERAL = 0x08000000
    CANNOT_STORE = 0x08000020
    DEVICE_STATE = 0x08000022


class IlcrigError(Exception):
    """Root of the project's own exceptions."""


class InputError(IlcrigError, ValueError):
    """Bad input (an option, a configuration key or value, a path file, a law, the run folder …):
    ``str(exc)`` is the one line ``ilcrig`` prints after ``ilcrig: error:`` (exit code 2), raised
    before any process starts.  The one input-error type of the project: the command line turns this
    (and only this) into exit code 2; the public API re-exports it as ``ilcrig.InputError``."""


class SdoAbort(IlcrigError):
    """An object-dictionary access was refused with a CiA 301 abort code."""

    def __init__(self, code: int, message: str = "") -> None:
        self.code = int(code)
        try:
            name = AbortCode(self.code).name
        except ValueError:
            name = "UNKNOWN"
        text = f"SDO abort 0x{self.code:08X} ({name})"
        if message:
            text += f": {message}"
        super().__init__(text)
