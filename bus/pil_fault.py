"""The fault of a processor-in-the-loop target (``--firmware pil``, docs/firmware.md): what the drive
puts in its EMCY and what the host reads back from it.

Owns :class:`PilFailure` (what happened, EMCY byte 1), :data:`PIL_EMCY_CODE`, :data:`PIL_NO_TICK`
and :func:`pil_target_fault` (the one reader of that EMCY, for the rig's fault record and
``ilcrig sim``'s). The cause byte is :attr:`bus.objects.FaultCause.PIL_TARGET`.

May import: the standard library and :mod:`bus.objects`.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Final

from bus.objects import FaultCause

__all__ = ["PIL_EMCY_CODE", "PIL_NO_TICK", "PilFailure", "pil_target_fault"]


class PilFailure(IntEnum):
    """What happened to a processor-in-the-loop target (``--firmware pil``): byte 1 of the EMCY
    0x6100 manufacturer field (byte 0 :attr:`FaultCause.PIL_TARGET`, bytes 2..4 the trial tick,
    U24 LE, 0xFFFFFF outside a trial)."""

    EXITED = 1  #: the emulator exited (it closed the serial line, or took no more requests)
    NO_ANSWER = 2  #: no reply within the bounded answer time (the emulator hangs or was stopped)
    CORE_FAULT = 3  #: the emulated core took a fault exception (HardFault, …)
    PROTOCOL = 4  #: the link broke the protocol (a refused request, a bad or unexpected frame)

    @property
    def text(self) -> str:
        """What happened, in words (the host's fault record: ``PIL target: <text>``)."""
        return _PIL_FAILURE_TEXT[self]


_PIL_FAILURE_TEXT: Final[dict[PilFailure, str]] = {
    PilFailure.EXITED: "the emulator exited",
    PilFailure.NO_ANSWER: "no answer within the reply time",
    PilFailure.CORE_FAULT: "the Cortex-M4 took a fault exception",
    PilFailure.PROTOCOL: "the link broke the protocol",
}
#: bytes 2..4 of a PIL target's EMCY outside a trial
PIL_NO_TICK: Final[int] = 0xFFFFFF
#: the EMCY error code of a failed PIL target (CiA 301 0x6100, internal software)
PIL_EMCY_CODE: Final[int] = 0x6100


def pil_target_fault(code: int, mfr: bytes) -> tuple[str, int | None] | None:
    """A drive's EMCY ``code`` with its manufacturer bytes ``mfr`` read as a failed PIL target:
    (``"PIL target: <what happened>"``, the trial tick or None outside a trial); None when it is
    not one (another code, or byte 0 not :attr:`FaultCause.PIL_TARGET`)."""
    data = bytes(mfr) + bytes(5)
    if code != PIL_EMCY_CODE or data[0] != FaultCause.PIL_TARGET:
        return None
    what = PilFailure(data[1]).text if data[1] in PilFailure._value2member_map_ else f"failure {data[1]}"
    tick = int.from_bytes(data[2:5], "little")
    return f"PIL target: {what}", None if tick == PIL_NO_TICK else tick
