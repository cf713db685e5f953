"""CiA 301 SDO server, drive side: pure protocol logic (no threads, no I/O, no clock).

:class:`SdoServer` owns one server SDO channel of one node.  Feed it the 8 data bytes of
every frame received on COB-ID ``0x600 + node_id`` (:func:`sdo_request_cob_id`) with
:meth:`SdoServer.handle`; send whatever it returns on COB-ID ``0x580 + node_id``
(:func:`sdo_response_cob_id`).  Objects are reached through an :class:`ObjectAccess`
(``read_object`` / ``write_object`` on raw little-endian bytes, raising
:class:`bus.errors.SdoAbort`), so the server works with the drive firmware or with a small
dict-backed store in tests.

Supported services:

* expedited download (with and without size indicated) and expedited upload (size always
  indicated);
* segmented download and upload, with toggle-bit checking (abort 0x05030000);
* block download and block upload (CiA 301 §7.2.4.3.9 ff.), CRC-CCITT (XModem, the CRC the
  standard specifies) or no CRC; the server advertises CRC support only when the client
  indicates it, so CRC is used exactly when both sides asked for it.  Block upload honours the
  protocol-switch threshold (falls back to a normal upload when ``0 < size <= pst``);
* client abort (the transfer is dropped, nothing is sent);
* a transfer timeout driven by the caller's clock: :meth:`SdoServer.tick` (abort 0x05040000).

One transfer at a time: a new initiate request abandons the transfer in progress.
A download reaches the object only when complete: segmented and block downloads hand the whole
payload to ``write_object`` once, after the last segment.  An upload reads the object once,
at initiation, and serves that snapshot.

Expedited download *without* size indicated hands all 4 data bytes to the object (the server
does not know object sizes); the object may refuse with 0x06070010.
"""

from __future__ import annotations

import binascii
import logging
import struct
from enum import Enum, auto
from typing import Protocol

from bus.errors import AbortCode, SdoAbort
from bus.units import timeout_scale

logger = logging.getLogger(__name__)

_TIMEOUT_SCALE = timeout_scale()  # ILCRIG_TIMEOUT_SCALE, read once

#: COB-ID base of SDO requests (client → server), CiA 301 predefined connection set.
SDO_REQUEST_BASE = 0x600
#: COB-ID base of SDO responses (server → client).
SDO_RESPONSE_BASE = 0x580

# Client command specifiers (bits 7..5 of byte 0 of a request).
CCS_DOWNLOAD_SEGMENT = 0
CCS_DOWNLOAD_INITIATE = 1
CCS_UPLOAD_INITIATE = 2
CCS_UPLOAD_SEGMENT = 3
CCS_ABORT = 4
CCS_BLOCK_UPLOAD = 5
CCS_BLOCK_DOWNLOAD = 6

# Server command specifiers (bits 7..5 of byte 0 of a response).
SCS_UPLOAD_SEGMENT = 0
SCS_DOWNLOAD_SEGMENT = 1
SCS_UPLOAD_INITIATE = 2
SCS_DOWNLOAD_INITIATE = 3
SCS_ABORT = 4
SCS_BLOCK_DOWNLOAD = 5
SCS_BLOCK_UPLOAD = 6

# Block sub-commands (cs / ss, low bits of byte 0).
BLOCK_INITIATE = 0
BLOCK_END = 1
BLOCK_ACK = 2
BLOCK_UPLOAD_START = 3

#: Largest block size (segments per sub-block) allowed by CiA 301.
MAX_BLOCK_SIZE = 127

_HEADER = struct.Struct("<BHB")
_ABORT = struct.Struct("<BHBL")


def sdo_request_cob_id(node_id: int) -> int:
    """COB-ID the server listens on (``0x600 + node_id``).

    :raises ValueError: node id outside 1..127.
    """
    _check_node_id(node_id)
    return SDO_REQUEST_BASE + node_id


def sdo_response_cob_id(node_id: int) -> int:
    """COB-ID the server answers on (``0x580 + node_id``).

    :raises ValueError: node id outside 1..127.
    """
    _check_node_id(node_id)
    return SDO_RESPONSE_BASE + node_id


def _check_node_id(node_id: int) -> None:
    if not 1 <= node_id <= 127:
        raise ValueError(f"CANopen node id must be 1..127, got {node_id}")


def abort_frame(index: int, subindex: int, code: int) -> bytes:
    """Encode an SDO abort transfer frame (8 bytes): 0x80, index LE, subindex, code U32 LE."""
    return _ABORT.pack(SCS_ABORT << 5, index & 0xFFFF, subindex & 0xFF, code & 0xFFFFFFFF)


def crc16_ccitt(data: bytes, crc: int = 0) -> int:
    """CRC-16-CCITT as used by SDO block transfer (poly 0x1021, init 0, no reflection)."""
    return binascii.crc_hqx(data, crc)


class ObjectAccess(Protocol):
    """Object-dictionary access by raw bytes (little-endian, as on the bus)."""

    def read_object(self, index: int, sub: int) -> bytes:
        """Return the object's value; raise :class:`SdoAbort` to refuse."""
        ...

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        """Store ``data``; raise :class:`SdoAbort` to refuse."""
        ...


class _State(Enum):
    IDLE = auto()
    DOWNLOAD_SEGMENTED = auto()
    UPLOAD_SEGMENTED = auto()
    BLOCK_DOWNLOAD = auto()  # receiving sub-block segments
    BLOCK_DOWNLOAD_END = auto()  # last segment acknowledged, waiting for the end request
    BLOCK_UPLOAD_WAIT_START = auto()
    BLOCK_UPLOAD = auto()  # sub-block sent, waiting for the acknowledgement
    BLOCK_UPLOAD_END = auto()  # end frame sent, waiting for the client's end response


class _Abort(Exception):
    """Internal: abort the current transfer with ``code``."""

    def __init__(self, code: int) -> None:
        super().__init__(f"0x{code:08X}")
        self.code = int(code)


Response = bytes | list[bytes] | None


class SdoServer:
    """One SDO server channel of node ``node_id`` (pure; feed frames in, get frames out).

    :param node_id: CANopen node id 1..127.
    :param access: the object store (see :class:`ObjectAccess`).
    """

    #: Seconds of silence after which a transfer in progress is aborted by :meth:`tick`.
    TIMEOUT_S: float = 1.0
    #: Sub-block size (segments) the server asks for in block download, 1..127.
    BLOCK_SIZE: int = MAX_BLOCK_SIZE
    #: Largest download the server accepts, bytes (larger: abort 0x05040005).
    MAX_DOWNLOAD_BYTES: int = 1 << 20

    #: Clock time [s] of the last request of the transfer in progress (None: not yet known).
    _last_activity_s: float | None

    def __init__(self, node_id: int, access: ObjectAccess) -> None:
        _check_node_id(node_id)
        if not 1 <= self.BLOCK_SIZE <= MAX_BLOCK_SIZE:
            raise ValueError(f"BLOCK_SIZE must be 1..127, got {self.BLOCK_SIZE}")
        self.node_id = node_id
        self.request_cob_id = sdo_request_cob_id(node_id)
        self.response_cob_id = sdo_response_cob_id(node_id)
        self._access = access
        self._now_s: float | None = None
        self._reset()

    # ------------------------------------------------------------------ public API

    @property
    def busy(self) -> bool:
        """True while a segmented or block transfer is in progress."""
        return self._state is not _State.IDLE

    def handle(self, data: bytes, now_s: float | None = None) -> Response:
        """Process one request frame (the data bytes of a 0x600+id frame).

        :param data: request data bytes (normally 8; shorter frames are zero-padded).
        :param now_s: optional current time [s], same clock as :meth:`tick`.
        :return: one response frame (8 bytes), a list of frames (block upload sub-block, to be
            sent in order), or None when no response is due.
        """
        if now_s is not None:
            self._now_s = now_s
        frame = bytes(data[:8]).ljust(8, b"\x00")
        try:
            response = self._dispatch(frame)
        except _Abort as err:
            logger.info("node %d: SDO abort 0x%08X on 0x%04X:%02X", self.node_id, err.code, self._index, self._sub)
            response = abort_frame(self._index, self._sub, err.code)
            self._reset()
        if self._state is not _State.IDLE:
            self._last_activity_s = self._now_s
        return response

    def next_deadline(self) -> float | None:
        """When a transfer in progress times out [s of the caller's clock] (None: none is)."""
        if self._state is _State.IDLE or self._last_activity_s is None:
            return None
        return self._last_activity_s + self.TIMEOUT_S * _TIMEOUT_SCALE

    def grace(self, now_s: float) -> None:
        """A transfer in progress counts as active at ``now_s``: the node itself did not run before
        (:meth:`bus.cia301.slave.SlaveNode.after_stall`), its client may not have either."""
        if self._state is not _State.IDLE:
            self._last_activity_s = now_s

    def tick(self, now_s: float) -> bytes | None:
        """Report the time [s]; abort a transfer that has been silent for over TIMEOUT_S.

        :return: the abort frame (0x05040000) to send, or None.
        """
        self._now_s = now_s
        if self._state is _State.IDLE:
            return None
        if self._last_activity_s is None:
            self._last_activity_s = now_s
            return None
        if now_s - self._last_activity_s <= self.TIMEOUT_S * _TIMEOUT_SCALE:
            return None
        logger.warning("node %d: SDO transfer 0x%04X:%02X timed out", self.node_id, self._index, self._sub)
        frame = abort_frame(self._index, self._sub, AbortCode.TIMEOUT)
        self._reset()
        return frame

    # ------------------------------------------------------------------ state

    def _reset(self) -> None:
        self._state = _State.IDLE
        self._index = 0
        self._sub = 0
        self._toggle = 0
        self._size: int | None = None
        self._buffer = bytearray()
        self._payload = b""
        self._pos = 0
        self._crc = False
        self._blksize = 0
        self._expected_seq = 1
        self._block_data = bytearray()
        self._last_segment_seen = False
        self._sent = 0
        self._last_activity_s = None

    def _begin(self, state: _State, index: int, sub: int) -> None:
        if self._state is not _State.IDLE:
            logger.info("node %d: new SDO request abandons transfer 0x%04X:%02X", self.node_id, self._index, self._sub)
        self._reset()
        self._state = state
        self._index = index
        self._sub = sub

    # ------------------------------------------------------------------ dispatch

    def _dispatch(self, frame: bytes) -> Response:
        b0 = frame[0]
        if self._state is _State.BLOCK_DOWNLOAD:
            # In the sub-block phase every frame is a segment (seqno | c); 0x80 (seqno 0) can
            # only be the client's abort.
            if b0 == SCS_ABORT << 5:
                self._client_abort(frame)
                return None
            return self._block_download_segment(frame)
        ccs = b0 >> 5
        if ccs == CCS_ABORT:
            self._client_abort(frame)
            return None
        if ccs == CCS_DOWNLOAD_INITIATE:
            return self._download_initiate(frame)
        if ccs == CCS_UPLOAD_INITIATE:
            return self._upload_initiate(frame)
        if ccs == CCS_DOWNLOAD_SEGMENT:
            if self._state is not _State.DOWNLOAD_SEGMENTED:
                raise _Abort(AbortCode.INVALID_COMMAND)
            return self._download_segment(frame)
        if ccs == CCS_UPLOAD_SEGMENT:
            if self._state is not _State.UPLOAD_SEGMENTED:
                raise _Abort(AbortCode.INVALID_COMMAND)
            return self._upload_segment(frame)
        if ccs == CCS_BLOCK_DOWNLOAD:
            if b0 & 0x01 == BLOCK_INITIATE:
                return self._block_download_initiate(frame)
            if self._state is not _State.BLOCK_DOWNLOAD_END:
                raise _Abort(AbortCode.INVALID_COMMAND)
            return self._block_download_end(frame)
        if ccs == CCS_BLOCK_UPLOAD:
            cs = b0 & 0x03
            if cs == BLOCK_INITIATE:
                return self._block_upload_initiate(frame)
            if cs == BLOCK_UPLOAD_START and self._state is _State.BLOCK_UPLOAD_WAIT_START:
                self._state = _State.BLOCK_UPLOAD
                return self._block_upload_subblock()
            if cs == BLOCK_ACK and self._state is _State.BLOCK_UPLOAD:
                return self._block_upload_ack(frame)
            if cs == BLOCK_END and self._state is _State.BLOCK_UPLOAD_END:
                self._reset()
                return None
            raise _Abort(AbortCode.INVALID_COMMAND)
        # ccs 7: not a client command specifier.  Echo the multiplexer of the frame.
        self._reset()
        _, self._index, self._sub = _HEADER.unpack_from(frame)
        raise _Abort(AbortCode.INVALID_COMMAND)

    def _client_abort(self, frame: bytes) -> None:
        code = struct.unpack_from("<L", frame, 4)[0]
        logger.info("node %d: client aborted SDO transfer 0x%04X:%02X with 0x%08X", self.node_id, self._index, self._sub, code)
        self._reset()
        return None

    # ------------------------------------------------------------------ access

    def _read(self) -> bytes:
        try:
            return bytes(self._access.read_object(self._index, self._sub))
        except SdoAbort as err:
            raise _Abort(err.code) from err

    def _write(self, data: bytes) -> None:
        try:
            self._access.write_object(self._index, self._sub, bytes(data))
        except SdoAbort as err:
            raise _Abort(err.code) from err

    # ------------------------------------------------------------------ download

    def _download_initiate(self, frame: bytes) -> bytes:
        b0, index, sub = _HEADER.unpack_from(frame)
        self._begin(_State.IDLE, index, sub)
        expedited = bool(b0 & 0x02)
        size_indicated = bool(b0 & 0x01)
        if expedited:
            n = 4 - ((b0 >> 2) & 0x03) if size_indicated else 4
            self._write(frame[4 : 4 + n])
            self._reset()
            return _HEADER.pack(SCS_DOWNLOAD_INITIATE << 5, index, sub) + bytes(4)
        if size_indicated:
            self._size = struct.unpack_from("<L", frame, 4)[0]
            if self._size > self.MAX_DOWNLOAD_BYTES:
                raise _Abort(AbortCode.OUT_OF_MEMORY)
        self._state = _State.DOWNLOAD_SEGMENTED
        self._toggle = 0
        return _HEADER.pack(SCS_DOWNLOAD_INITIATE << 5, index, sub) + bytes(4)

    def _download_segment(self, frame: bytes) -> bytes:
        b0 = frame[0]
        toggle = (b0 >> 4) & 0x01
        if toggle != self._toggle:
            raise _Abort(AbortCode.TOGGLE_BIT)
        n = 7 - ((b0 >> 1) & 0x07)
        self._buffer += frame[1 : 1 + n]
        limit = self._size if self._size is not None else self.MAX_DOWNLOAD_BYTES
        if len(self._buffer) > limit:
            raise _Abort(AbortCode.LENGTH_MISMATCH if self._size is not None else AbortCode.OUT_OF_MEMORY)
        response = bytes([(SCS_DOWNLOAD_SEGMENT << 5) | (toggle << 4)]) + bytes(7)
        self._toggle ^= 1
        if b0 & 0x01:  # c: no more segments
            if self._size is not None and len(self._buffer) != self._size:
                raise _Abort(AbortCode.LENGTH_MISMATCH)
            self._write(bytes(self._buffer))
            self._reset()
        return response

    # ------------------------------------------------------------------ upload

    def _upload_initiate(self, frame: bytes) -> bytes:
        _, index, sub = _HEADER.unpack_from(frame)
        self._begin(_State.IDLE, index, sub)
        return self._upload_response(self._read())

    def _upload_response(self, value: bytes) -> bytes:
        """Initiate-upload response for ``value``: expedited for 1..4 bytes, else segmented."""
        index, sub = self._index, self._sub
        if 1 <= len(value) <= 4:
            b0 = (SCS_UPLOAD_INITIATE << 5) | ((4 - len(value)) << 2) | 0x03
            self._reset()
            return _HEADER.pack(b0, index, sub) + value.ljust(4, b"\x00")
        self._state = _State.UPLOAD_SEGMENTED
        self._payload = value
        self._pos = 0
        self._toggle = 0
        return _HEADER.pack((SCS_UPLOAD_INITIATE << 5) | 0x01, index, sub) + struct.pack("<L", len(value))

    def _upload_segment(self, frame: bytes) -> bytes:
        toggle = (frame[0] >> 4) & 0x01
        if toggle != self._toggle:
            raise _Abort(AbortCode.TOGGLE_BIT)
        chunk = self._payload[self._pos : self._pos + 7]
        self._pos += len(chunk)
        last = self._pos >= len(self._payload)
        b0 = (SCS_UPLOAD_SEGMENT << 5) | (toggle << 4) | ((7 - len(chunk)) << 1) | int(last)
        self._toggle ^= 1
        if last:
            self._reset()
        return bytes([b0]) + chunk.ljust(7, b"\x00")

    # ------------------------------------------------------------------ block download

    def _block_download_initiate(self, frame: bytes) -> bytes:
        b0, index, sub = _HEADER.unpack_from(frame)
        self._begin(_State.BLOCK_DOWNLOAD, index, sub)
        self._crc = bool(b0 & 0x04)
        if b0 & 0x02:
            self._size = struct.unpack_from("<L", frame, 4)[0]
            if self._size > self.MAX_DOWNLOAD_BYTES:
                raise _Abort(AbortCode.OUT_OF_MEMORY)
        self._blksize = self.BLOCK_SIZE
        self._expected_seq = 1
        b0_resp = (SCS_BLOCK_DOWNLOAD << 5) | (0x04 if self._crc else 0) | BLOCK_INITIATE
        return _HEADER.pack(b0_resp, index, sub) + bytes([self._blksize, 0, 0, 0])

    def _block_download_segment(self, frame: bytes) -> bytes | None:
        seqno = frame[0] & 0x7F
        last = bool(frame[0] & 0x80)
        if seqno == self._expected_seq:
            self._block_data += frame[1:8]
            self._expected_seq += 1
            if last:
                self._last_segment_seen = True
            if len(self._buffer) + len(self._block_data) > self.MAX_DOWNLOAD_BYTES + 7:
                raise _Abort(AbortCode.OUT_OF_MEMORY)
        elif seqno == 0:
            raise _Abort(AbortCode.INVALID_SEQUENCE)
        # else: out of order: ignore the data, acknowledge the last good one below.
        if not (last or seqno >= self._blksize):
            return None
        ackseq = self._expected_seq - 1
        self._buffer += self._block_data
        self._block_data = bytearray()
        self._expected_seq = 1
        if self._last_segment_seen:
            self._state = _State.BLOCK_DOWNLOAD_END
        elif ackseq != seqno:
            logger.info("node %d: block download sub-block broke after %d segments", self.node_id, ackseq)
        return bytes([(SCS_BLOCK_DOWNLOAD << 5) | BLOCK_ACK, ackseq, self._blksize]) + bytes(5)

    def _block_download_end(self, frame: bytes) -> bytes:
        n = (frame[0] >> 2) & 0x07
        data = bytes(self._buffer[: len(self._buffer) - n])
        if self._size is not None and len(data) != self._size:
            raise _Abort(AbortCode.LENGTH_MISMATCH)
        if self._crc:
            crc = struct.unpack_from("<H", frame, 1)[0]
            if crc != crc16_ccitt(data):
                raise _Abort(AbortCode.CRC_ERROR)
        self._write(data)
        self._reset()
        return bytes([(SCS_BLOCK_DOWNLOAD << 5) | BLOCK_END]) + bytes(7)

    # ------------------------------------------------------------------ block upload

    def _block_upload_initiate(self, frame: bytes) -> bytes:
        b0, index, sub, blksize, pst = struct.unpack_from("<BHBBB", frame)
        self._begin(_State.IDLE, index, sub)
        if not 1 <= blksize <= MAX_BLOCK_SIZE:
            raise _Abort(AbortCode.INVALID_BLOCK_SIZE)
        value = self._read()
        if 0 < len(value) <= pst:
            # Protocol switch: the client accepts a normal upload for small objects.
            return self._upload_response(value)
        self._state = _State.BLOCK_UPLOAD_WAIT_START
        self._crc = bool(b0 & 0x04)
        self._payload = value
        self._blksize = blksize
        self._pos = 0  # index of the first unacknowledged segment
        b0_resp = (SCS_BLOCK_UPLOAD << 5) | (0x04 if self._crc else 0) | 0x02 | BLOCK_INITIATE
        return _HEADER.pack(b0_resp, index, sub) + struct.pack("<L", len(value))

    def _n_segments(self) -> int:
        return max(1, -(-len(self._payload) // 7))

    def _block_upload_subblock(self) -> list[bytes]:
        total = self._n_segments()
        stop = min(self._pos + self._blksize, total)
        frames = []
        for k in range(self._pos, stop):
            seqno = k - self._pos + 1
            chunk = self._payload[7 * k : 7 * k + 7]
            flag = 0x80 if k == total - 1 else 0
            frames.append(bytes([flag | seqno]) + chunk.ljust(7, b"\x00"))
        self._sent = stop - self._pos
        return frames

    def _block_upload_ack(self, frame: bytes) -> bytes | list[bytes]:
        ackseq, blksize = frame[1], frame[2]
        if ackseq > self._sent:
            raise _Abort(AbortCode.INVALID_SEQUENCE)
        if not 1 <= blksize <= MAX_BLOCK_SIZE:
            raise _Abort(AbortCode.INVALID_BLOCK_SIZE)
        self._pos += ackseq
        self._blksize = blksize
        total = self._n_segments()
        if self._pos < total:
            return self._block_upload_subblock()
        n = 7 * total - len(self._payload)
        crc = crc16_ccitt(self._payload) if self._crc else 0
        self._state = _State.BLOCK_UPLOAD_END
        return struct.pack("<BH", (SCS_BLOCK_UPLOAD << 5) | (n << 2) | BLOCK_END, crc) + bytes(5)
