"""Bus time: how long the frames of a channel would occupy a real classic CAN bus at its bit rate.

This module owns the emulated-time accounting of the two channels (docs/canopen-objects.md §9,
docs/timing.md §4): frames are counted by what they are — decided from the COB-ID and, for SDO,
from the protocol's own multiplexer, never from when they were seen — and their bits
(:mod:`bus.busload`, worst-case stuffing by default) are turned into time at a bit rate. So two
runs of the same configuration give the same figures on any machine at any load, for the
traffic the experiment defines.

* :class:`IoTickCounter` — the io channel: bits per control period, binned by the tick counter
  every encoder and torque frame carries (:mod:`bus.io_frames`); control frames (trial
  start/stop) are counted apart, per trial. Frames come one by one (``add``) or many at once
  as an array (``add_frames``, :data:`bus.bus_features.FRAME_DTYPE`), with the same result.
* :class:`SdoTransferCounter` — the fieldbus: every frame on a node's SDO COB-IDs belongs to the
  transfer (node, index, sub-index, upload/download) opened by the last initiate request on that
  node's request COB-ID (block-download data segments are recognised as such), and the transfers
  of each object are counted, so the bits of one transfer of an object follow from its size
  alone; the other frames by COB-ID range: NMT, SYNC, EMCY, PDO, heartbeat / boot-up, other.
* :func:`bits_to_s`, :class:`TickBudget` — bits at a bit rate; one control period's capacity
  and whether (by how much) a number of bits per period does not fit. A load figure is never
  above the capacity: what does not fit is reported as not fitting.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from bus.bus_features import FRAME_EXT, frame_bits
from bus.busload import DEFAULT_BITRATE_BPS, bits_lookup
from bus.io_frames import CONTROL_COB_ID, ENCODER_COB_BASE, N_JOINTS, TORQUE_COB_BASE, tick_diff

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_BITRATE", "IoTickCounter", "SdoKey", "SdoTransferCounter", "TickBudget", "bits_to_s", "frame_bits_of"]

#: the default bit rate of both channels, bit/s
DEFAULT_BITRATE: int = DEFAULT_BITRATE_BPS  # one definition: bus.busload


def frame_bits_of(msg: can.Message, worst_case: bool = True) -> int:
    """Bits of one classic frame (0 for error and CAN FD frames, which are not modelled)."""
    if msg.is_error_frame or msg.is_fd:
        return 0
    nominal, worst = bits_lookup(0 if msg.is_remote_frame else min(len(msg.data), 8), bool(msg.is_extended_id))
    return worst if worst_case else nominal


def bits_to_s(bits: float, bitrate: int) -> float:
    """Time ``bits`` occupy a bus of ``bitrate`` bit/s, s.

    :raises ValueError: non-positive bit rate
    """
    if bitrate <= 0:
        raise ValueError(f"bitrate must be > 0, got {bitrate}")
    return bits / bitrate


@dataclass(frozen=True)
class TickBudget:
    """One control period of ``period_s`` s on a bus of ``bitrate`` bit/s."""

    bitrate: int
    period_s: float

    @property
    def capacity_bits(self) -> float:
        """Bits the bus can carry in one period."""
        return self.bitrate * self.period_s

    def fit(self, bits: float) -> dict[str, Any]:
        """How ``bits`` per period fit: utilisation (≤ 100 %), whether it fits, and if not by how
        much (bits over, and the period it would need)."""
        cap = self.capacity_bits
        fits = bits <= cap
        return {
            "bits": bits,
            "fits": fits,
            "utilisation_percent": 100.0 * min(bits, cap) / cap,
            "excess_bits": max(0.0, bits - cap),
            "excess_percent_of_capacity": 100.0 * max(0.0, bits - cap) / cap,
            "time_needed_s": bits_to_s(bits, self.bitrate),
        }


class IoTickCounter:
    """Bits per control period on the io channel, binned by the frames' tick counter.

    Feed every frame of the channel to :meth:`add` in the order seen. Encoder and torque frames
    of wire tick t add to tick t's bin; a bin is closed once frames of a tick more than
    :attr:`WINDOW` ticks later arrive (or at :meth:`close`). Control frames go to
    ``control_bits``; frames with other COB-IDs to ``other_bits``.
    """

    #: ticks a bin stays open for late frames
    WINDOW: int = 16

    def __init__(self, worst_case: bool = True) -> None:
        self.worst_case = worst_case
        self._open: dict[int, int] = {}
        self.ticks = 0
        self.bits_total = 0
        self.bits_max = 0
        self.frames = 0
        self.control_frames = 0
        self.control_bits = 0
        self.other_frames = 0
        self.other_bits = 0

    def add(self, msg: can.Message) -> None:
        """Count one frame of the io channel."""
        bits = frame_bits_of(msg, self.worst_case)
        cob = msg.arbitration_id
        data = msg.data
        if (
            not msg.is_extended_id
            and len(data) >= 6
            and (0 <= cob - ENCODER_COB_BASE < N_JOINTS or 0 <= cob - TORQUE_COB_BASE < N_JOINTS)
        ):
            self.frames += 1
            self._add_tick(data[4] | data[5] << 8, bits)
        elif cob == CONTROL_COB_ID and not msg.is_extended_id:
            self.control_frames += 1
            self.control_bits += bits
        else:
            self.other_frames += 1
            self.other_bits += bits

    def add_frames(self, frames: np.ndarray) -> None:
        """Count the rows of ``frames`` (:data:`bus.bus_features.FRAME_DTYPE`, in the order seen)
        exactly as :meth:`add` counts them one by one, with numpy: the frames of one tick that
        follow each other are added to its bin at once."""
        if not len(frames):
            return
        _, nominal, worst = frame_bits(frames)
        bits = worst if self.worst_case else nominal
        cob = frames["arbitration_id"].astype(np.int64)
        std = (frames["flags"] & FRAME_EXT) == 0
        in_tick = (
            std
            & (frames["length"] >= 6)
            & (
                ((cob >= ENCODER_COB_BASE) & (cob < ENCODER_COB_BASE + N_JOINTS))
                | ((cob >= TORQUE_COB_BASE) & (cob < TORQUE_COB_BASE + N_JOINTS))
            )
        )
        control = ~in_tick & std & (cob == CONTROL_COB_ID)
        other = ~(in_tick | control)
        self.control_frames += int(control.sum())
        self.control_bits += int(bits[control].sum())
        self.other_frames += int(other.sum())
        self.other_bits += int(bits[other].sum())
        idx = np.flatnonzero(in_tick)
        if not len(idx):
            return
        self.frames += len(idx)
        data = frames["data"][idx]
        ticks = data[:, 4].astype(np.int64) | data[:, 5].astype(np.int64) << 8
        change = np.empty(len(ticks), dtype=bool)
        change[0] = True
        np.not_equal(ticks[1:], ticks[:-1], out=change[1:])
        starts = np.flatnonzero(change)
        for tick, run_bits in zip(ticks[starts].tolist(), np.add.reduceat(bits[idx], starts).tolist(), strict=True):
            self._add_tick(tick, run_bits)

    def _add_tick(self, tick: int, bits: int) -> None:
        """Add ``bits`` of frames of wire tick ``tick`` to its bin (opened if needed; bins more
        than :attr:`WINDOW` ticks older are closed)."""
        if tick in self._open:
            self._open[tick] += bits
            return
        self._open[tick] = bits
        stale = [t for t in self._open if tick_diff(tick, t) > self.WINDOW]
        for t in stale:
            self._close_bin(t)

    def _close_bin(self, tick: int) -> None:
        bits = self._open.pop(tick)
        self.ticks += 1
        self.bits_total += bits
        self.bits_max = max(self.bits_max, bits)

    def close(self) -> None:
        """Close every open bin (end of the run)."""
        for t in list(self._open):
            self._close_bin(t)

    @property
    def bits_mean(self) -> float:
        """Mean bits per tick over the closed bins."""
        return self.bits_total / self.ticks if self.ticks else 0.0


#: an SDO transfer's identity: (node id, index, sub-index, "upload" | "download")
SdoKey = tuple[int, int, int, str]


@dataclass
class _Tally:
    frames: int = 0
    bits: int = 0
    #: SDO transfers (initiate requests) counted; 0 for classes that are not SDO
    transfers: int = 0

    def add(self, bits: int) -> None:
        self.frames += 1
        self.bits += bits


@dataclass
class SdoTransferCounter:
    """Fieldbus frames by what they are (see the module docstring): SDO frames by transfer
    (:data:`SdoKey`), the rest by COB-ID class (``nmt``, ``sync``, ``emcy``, ``pdo``,
    ``heartbeat``, ``sdo_unattributed``, ``other``)."""

    worst_case: bool = True
    sdo: dict[SdoKey, _Tally] = field(default_factory=dict)
    classes: dict[str, _Tally] = field(default_factory=dict)
    _current: dict[int, SdoKey] = field(default_factory=dict)
    _block_download: set[int] = field(default_factory=set)

    def add(self, msg: can.Message) -> None:
        """Count one frame of the fieldbus."""
        bits = frame_bits_of(msg, self.worst_case)
        if msg.is_extended_id or msg.is_error_frame or msg.is_fd:
            self._class("other", bits)
            return
        cob = msg.arbitration_id
        data = msg.data
        if 0x601 <= cob <= 0x67F:  # SDO request (client → server)
            node = cob - 0x600
            b0 = data[0] if data else 0
            if node in self._block_download:
                if b0 == 0x80:  # abort
                    self._block_download.discard(node)
            elif len(data) >= 4:
                ccs = b0 >> 5
                if ccs in (1, 2) or (ccs == 5 and b0 & 0x03 == 0) or (ccs == 6 and b0 & 0x01 == 0):
                    direction = "download" if ccs in (1, 6) else "upload"
                    key = (node, data[1] | data[2] << 8, data[3], direction)
                    self._current[node] = key
                    tally = self.sdo.get(key)
                    if tally is None:
                        tally = self.sdo[key] = _Tally()
                    tally.transfers += 1
                    if ccs == 6:
                        self._block_download.add(node)
            self._sdo(node, bits)
        elif 0x581 <= cob <= 0x5FF:  # SDO response (server → client)
            node = cob - 0x580
            b0 = data[0] if data else 0
            if node in self._block_download and b0 in (0xA1, 0x80):  # block download end response, abort
                self._block_download.discard(node)
            self._sdo(node, bits)
        elif cob == 0:
            self._class("nmt", bits)
        elif cob == 0x080:
            self._class("sync", bits)
        elif 0x081 <= cob <= 0x0FF:
            self._class("emcy", bits)
        elif 0x180 <= cob <= 0x57F:
            self._class("pdo", bits)
        elif 0x701 <= cob <= 0x77F:
            self._class("heartbeat", bits)
        else:
            self._class("other", bits)

    def _sdo(self, node: int, bits: int) -> None:
        key = self._current.get(node)
        if key is None:
            self._class("sdo_unattributed", bits)
            return
        tally = self.sdo.get(key)
        if tally is None:
            tally = self.sdo[key] = _Tally()
        tally.add(bits)

    def _class(self, name: str, bits: int) -> None:
        tally = self.classes.get(name)
        if tally is None:
            tally = self.classes[name] = _Tally()
        tally.add(bits)
