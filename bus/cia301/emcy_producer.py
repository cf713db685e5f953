"""A node's EMCY producer on the fieldbus: the COB-ID of 0x1014 and the inhibit time of 0x1015,
the EMCYs of the application queued and sent one per inhibit time, none in NMT STOPPED.

This module owns :class:`EmcyProducer`, the part of :class:`bus.cia301.slave.SlaveNode` that sends
EMCY frames: every entry of the app's ``pop_emcy()`` on the COB-ID of 0x1014 (default 0x080 + id;
bit 31 set: the EMCY is not valid and nothing is sent), at most one per 0x1015 inhibit time
(100 µs units; EMCYs within it wait in order), both re-read by :meth:`EmcyProducer.reload` after
every completed SDO transfer and NMT reset.  The frames go out through the node's send function.

May import: :mod:`bus.cia301.emcy`, :mod:`bus.cia301.nmt`, :mod:`bus.errors`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from bus.cia301.emcy import EMCY_NOT_VALID, emcy_cob_id, encode_emcy
from bus.cia301.nmt import NmtState
from bus.errors import SdoAbort

logger = logging.getLogger(__name__)

__all__ = ["COB_ID_EMCY_INDEX", "INHIBIT_TIME_EMCY_INDEX", "EmcyProducer"]

#: Object indices of the EMCY COB-ID (U32) and the EMCY inhibit time (U16, 100 µs).
COB_ID_EMCY_INDEX = 0x1014
INHIBIT_TIME_EMCY_INDEX = 0x1015
_INHIBIT_UNIT_S = 100e-6


class _EmcyApp(Protocol):
    """What the producer needs of the node's application (a part of :class:`bus.cia301.slave.SlaveApp`)."""

    @property
    def nmt_state(self) -> int: ...

    def read_object(self, index: int, sub: int) -> bytes: ...

    def pop_emcy(self) -> Sequence[tuple[int, int, bytes]]: ...


class EmcyProducer:
    """The EMCY frames of one node (see the module docstring).

    :param node_id: CANopen node id 1..127.
    :param app: the node's application (``nmt_state``, ``read_object``, ``pop_emcy``).
    :param send: sends one fieldbus frame ``(cob_id, data)``.
    :ivar cob_id: the EMCY's COB-ID now; None: the EMCY is not valid (0x1014 bit 31).
    """

    def __init__(self, node_id: int, app: _EmcyApp | Any, send: Callable[[int, bytes], None]) -> None:
        self.node_id = node_id
        self.app = app
        self._send = send
        self.cob_id: int | None = emcy_cob_id(node_id)
        self.inhibit_s = 0.0
        self._queue: list[bytes] = []  # EMCY frames waiting for the inhibit time
        self._next_s: float | None = None  # earliest time the next EMCY may go out

    def own_ids(self) -> set[int]:
        """The fieldbus identifiers of this node's EMCYs (the predefined one and the configured one)."""
        return {emcy_cob_id(self.node_id)} | ({self.cob_id} if self.cob_id is not None else set())

    def next_deadline(self) -> float | None:
        """When a waiting EMCY may go out (None: none waits)."""
        return self._next_s if self._queue else None

    def reload(self) -> None:
        """Re-read 0x1014 (COB-ID EMCY) and 0x1015 (inhibit time); an app without them keeps the
        predefined 0x080 + id and no inhibit time."""
        try:
            cob = int.from_bytes(self.app.read_object(COB_ID_EMCY_INDEX, 0)[:4], "little")
            self.cob_id = None if cob & EMCY_NOT_VALID else cob & 0x7FF
        except SdoAbort:
            self.cob_id = emcy_cob_id(self.node_id)
        try:
            self.inhibit_s = int.from_bytes(self.app.read_object(INHIBIT_TIME_EMCY_INDEX, 0)[:2], "little") * _INHIBIT_UNIT_S
        except SdoAbort:
            self.inhibit_s = 0.0

    def flush(self, now: float) -> None:
        """Queue the app's new EMCYs, then send what the inhibit time allows (one per inhibit
        time, in order; without an inhibit time all at once)."""
        for code, register, data in self.app.pop_emcy():
            if self.cob_id is None:
                logger.info("node %d: EMCY 0x%04X not sent: 0x1014 says the EMCY is not valid", self.node_id, int(code))
                continue
            self._queue.append(encode_emcy(int(code), int(register), bytes(data)[:5]))
        if not self._queue:
            return
        if int(self.app.nmt_state) == NmtState.STOPPED:
            return  # no EMCY in STOPPED (CiA 301): what waits goes out once the node leaves it
        while self._queue and (self._next_s is None or now >= self._next_s - 1e-9):
            if self.cob_id is None:
                self._queue.clear()
                break
            self._send(self.cob_id, self._queue.pop(0))
            self._next_s = now + self.inhibit_s if self.inhibit_s > 0 else None

    def send_now(self, code: int, register: int, data: bytes = b"") -> None:
        """Send one EMCY frame now (unless the node is STOPPED or 0x1014 says the EMCY is not valid)."""
        if int(self.app.nmt_state) != NmtState.STOPPED and self.cob_id is not None:
            self._send(self.cob_id, encode_emcy(int(code), int(register), data[:5]))
