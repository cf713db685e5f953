"""Bus-load accounting for classic CAN frames.

This module owns the bit length of a classic CAN frame (docs/canopen-objects.md §9) and the counters
built on it: :class:`BusLoadCounter` (frames and bits, load in percent of a bit rate) and
:class:`BusLoadListener` (a :class:`can.Listener` feeding a counter).

Bit lengths, ``n`` = data bytes (0 for a remote frame, whatever its DLC):

* 11-bit ID: ``47 + 8n`` bits without stuffing (SOF, ID, RTR, IDE, r0, DLC, data, CRC15,
  CRC delimiter, ACK 2, EOF 7, IFS 3). The stuffed region SOF…CRC is ``g + 8n`` bits with
  ``g = 34``.
* 29-bit ID: ``67 + 8n`` bits (adds SRR, IDE, 18 ID bits, r1), ``g = 54``.
* Worst-case stuffing adds ``⌊(g + 8n − 1) / 4⌋`` bits.

So an 8-byte 11-bit frame takes 111–135 bits, an 8-byte 29-bit frame 131–160 bits.
CAN FD frames are not modelled: they are counted in ``fd_frames`` and add no bits.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import can

logger = logging.getLogger(__name__)

#: the fieldbus bit rate assumed when none is given, bit/s (classic CAN's highest)
DEFAULT_BITRATE_BPS: int = 1_000_000

#: bits outside the stuffed region plus the stuffed region without data, 11-bit ID
_BASE_BITS_STD = 47
#: same for a 29-bit ID
_BASE_BITS_EXT = 67
#: stuffed region (SOF … CRC) without data, 11-bit ID
_STUFF_REGION_STD = 34
#: stuffed region without data, 29-bit ID
_STUFF_REGION_EXT = 54


class FrameLengthError(ValueError):
    """A classic CAN frame cannot carry this many data bytes."""


def _check_n_bytes(n_bytes: int) -> None:
    if not 0 <= n_bytes <= 8:
        raise FrameLengthError(f"classic CAN carries 0..8 data bytes, got {n_bytes}")


def frame_bits(n_bytes: int, extended: bool = False) -> int:
    """Bits of a classic CAN frame without stuff bits.

    :param n_bytes: data bytes 0..8 (0 for a remote frame)
    :param extended: 29-bit identifier
    :return: bit count including the 3-bit inter-frame space
    :raises FrameLengthError: ``n_bytes`` outside 0..8
    """
    _check_n_bytes(n_bytes)
    return (_BASE_BITS_EXT if extended else _BASE_BITS_STD) + 8 * n_bytes


def stuff_bits_worst_case(n_bytes: int, extended: bool = False) -> int:
    """Maximum number of stuff bits, ``⌊(g + 8n − 1)/4⌋`` (g = 34 or 54).

    :raises FrameLengthError: ``n_bytes`` outside 0..8
    """
    _check_n_bytes(n_bytes)
    g = _STUFF_REGION_EXT if extended else _STUFF_REGION_STD
    return (g + 8 * n_bytes - 1) // 4


def frame_bits_worst_case(n_bytes: int, extended: bool = False) -> int:
    """Bits of a classic CAN frame with worst-case stuffing.

    :raises FrameLengthError: ``n_bytes`` outside 0..8
    """
    return frame_bits(n_bytes, extended) + stuff_bits_worst_case(n_bytes, extended)


def max_frames_per_s(n_bytes: int, extended: bool = False, bitrate: int = 1_000_000, worst_case: bool = True) -> int:
    """Whole frames per second a saturated bus of ``bitrate`` bit/s can carry."""
    bits = frame_bits_worst_case(n_bytes, extended) if worst_case else frame_bits(n_bytes, extended)
    return bitrate // bits


def message_bits(msg: can.Message) -> tuple[int, int]:
    """(bits without stuffing, bits with worst-case stuffing) of a classic frame.

    Remote frames carry no data field whatever their DLC.

    :raises FrameLengthError: the message is a CAN FD frame
    """
    if msg.is_fd:
        raise FrameLengthError("CAN FD frames are not modelled by bus.busload")
    n = 0 if msg.is_remote_frame else len(msg.data)
    ext = bool(msg.is_extended_id)
    return _TABLE[ext][n]


#: precomputed (nominal, worst) per [extended][n_bytes]; used on the hot path (hub)
_TABLE: tuple[tuple[tuple[int, int], ...], ...] = tuple(
    tuple((frame_bits(n, ext), frame_bits_worst_case(n, ext)) for n in range(9)) for ext in (False, True)
)


def bits_lookup(n_bytes: int, extended: bool) -> tuple[int, int]:
    """Fast (nominal, worst-case) bits for 0 ≤ ``n_bytes`` ≤ 8, no validation."""
    return _TABLE[extended][n_bytes]


@dataclass
class BusLoadCounter:
    """Frames and bits seen on one channel.

    ``bits`` counts without stuffing, ``bits_worst_case`` with worst-case stuffing.
    CAN FD frames are only counted in ``fd_frames``.
    """

    frames: int = 0
    bits: int = 0
    bits_worst_case: int = 0
    fd_frames: int = 0

    def add_frame(self, n_bytes: int, extended: bool = False) -> None:
        """Count one classic frame with ``n_bytes`` data bytes (0 for remote).

        :raises FrameLengthError: ``n_bytes`` outside 0..8
        """
        _check_n_bytes(n_bytes)
        nominal, worst = _TABLE[bool(extended)][n_bytes]
        self.frames += 1
        self.bits += nominal
        self.bits_worst_case += worst

    def add(self, msg: can.Message) -> None:
        """Count one message (error frames are ignored, FD frames only counted)."""
        if msg.is_error_frame:
            return
        if msg.is_fd:
            self.fd_frames += 1
            return
        nominal, worst = message_bits(msg)
        self.frames += 1
        self.bits += nominal
        self.bits_worst_case += worst

    def merge(self, other: BusLoadCounter) -> None:
        """Add another counter's totals into this one."""
        self.frames += other.frames
        self.bits += other.bits
        self.bits_worst_case += other.bits_worst_case
        self.fd_frames += other.fd_frames

    def reset(self) -> None:
        """Zero all totals."""
        self.frames = self.bits = self.bits_worst_case = self.fd_frames = 0

    def load_percent(self, duration_s: float, bitrate: int = 1_000_000, worst_case: bool = True) -> float:
        """Bus load in percent: counted bits / (``bitrate`` bit/s × ``duration_s`` s) × 100.

        :raises ValueError: non-positive duration or bit rate
        """
        if duration_s <= 0 or bitrate <= 0:
            raise ValueError(f"duration_s and bitrate must be > 0 (got {duration_s}, {bitrate})")
        bits = self.bits_worst_case if worst_case else self.bits
        return 100.0 * bits / (bitrate * duration_s)

    def as_dict(self) -> dict[str, int]:
        """Totals as a plain dict (for summary.json)."""
        return asdict(self)


class BusLoadListener(can.Listener):
    """A :class:`can.Listener` that counts every received message into ``counter``.

    Attach it to a :class:`can.Notifier`, or call it from a receive loop. A process only
    receives other nodes' frames (unless ``receive_own_messages``); the hub's counters
    (:func:`bus.transports.hub.stats.query_hub_stats`) see every frame of a channel.
    """

    def __init__(self, counter: BusLoadCounter | None = None) -> None:
        self.counter = counter if counter is not None else BusLoadCounter()

    def on_message_received(self, msg: can.Message) -> None:
        self.counter.add(msg)

    def stop(self) -> None:  # nothing to release
        pass
