"""candump-format logs of a CAN channel, written and read with python-can's own io classes.

This module owns how a run folder's channel logs are made (docs/architecture.md §7:
candump-format logs of both channels): :func:`open_log` returns a :class:`ChannelLog`, a
:class:`can.Listener` that writes every frame with :class:`can.CanutilsLogWriter` under a
fixed channel name (``fieldbus``, ``io``) — one by one, or many frames of an array at once
(:meth:`ChannelLog.write_frames`, same lines) — and :func:`read_log` reads a log back with
:class:`can.LogReader`.

Line format (``candump -L`` plus python-can's direction column):
``(1716900000.123456) io 101#A086010000002A R`` (``T`` for frames this process sent).
python-can's candump writer does not keep a remote frame's DLC (it writes ``#R``).

A process only receives the other nodes' frames; to log a whole channel, join it as one
more client (``can.Bus(interface="ilcrig_hub", channel=...)`` sees every frame of that
logical bus) or log both the frames a process sends (:meth:`ChannelLog.log_sent`) and the
ones it receives.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np

from bus.bus_features import FRAME_ERR, FRAME_EXT, FRAME_FD, FRAME_RTR, FRAME_TX, messages_from_frames
from bus.fastmsg import new_message

logger = logging.getLogger(__name__)

#: most digits of the seconds in a line written with numpy (:meth:`ChannelLog.write_frames`)
_SEC_DIGITS = 12
_HEX = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)
_SEC_POW = 10 ** np.arange(_SEC_DIGITS - 1, -1, -1, dtype=np.int64)
_SEC_LAST = np.arange(_SEC_DIGITS) == _SEC_DIGITS - 1
_USEC_POW = 10 ** np.arange(5, -1, -1, dtype=np.int64)
_ID_SHIFT = np.array([8, 4, 0], dtype=np.uint32)
_BYTE_INDEX = np.arange(8)


class CanLogError(ValueError):
    """A log path or channel name is not usable for a candump log."""


class ChannelLog(can.Listener):
    """Writes frames of one logical channel to a candump ``.log`` file.

    :param path: file name ending in ``.log``
    :param channel_name: channel column written for every frame (no whitespace)
    :param append: append to an existing log instead of truncating it
    """

    def __init__(self, path: str | os.PathLike[str], channel_name: str, append: bool = False) -> None:
        self.path = Path(path)
        if self.path.suffix != ".log":
            raise CanLogError(f"candump logs end in .log, got {self.path.name!r}")
        if not channel_name or any(c.isspace() for c in channel_name):
            raise CanLogError(f"bad channel name {channel_name!r}")
        self.channel_name = channel_name
        self.frames = 0
        self._stopped = False
        self._writer = can.CanutilsLogWriter(self.path, channel=channel_name, append=append)
        #: the channel column as the writer prints it (a number n becomes canN)
        self._log_channel = f"can{channel_name}" if channel_name.isdigit() else channel_name

    def on_message_received(self, msg: can.Message) -> None:
        """Write one frame (its own channel attribute is replaced by ``channel_name``)."""
        if msg.channel != self.channel_name:
            msg = _with_channel(msg, self.channel_name)
        self._writer.on_message_received(msg)
        self.frames += 1

    def write_frames(self, frames: np.ndarray) -> None:
        """Write the rows of ``frames`` (:data:`bus.bus_features.FRAME_DTYPE`, in order): the same
        lines as :meth:`on_message_received` one by one, formatted with numpy for classic data
        frames with 11-bit identifiers (the io channel), one by one otherwise."""
        n = len(frames)
        if not n:
            return
        writer = self._writer
        ts = frames["timestamp"]
        if writer.last_timestamp is None:
            writer.last_timestamp = float(ts[0]) or 0.0
        ts = np.maximum(ts, writer.last_timestamp)  # as the writer: never before the first frame
        flags = frames["flags"]
        if (
            (flags & (FRAME_EXT | FRAME_RTR | FRAME_ERR | FRAME_FD)).any()
            or (frames["length"] > 8).any()
            or (frames["arbitration_id"] > 0x7FF).any()
            or not 0 <= ts.min() <= ts.max() < 1e12
        ):
            for msg in messages_from_frames(frames, self.channel_name):
                self.on_message_received(msg)
            return
        # one padded row of bytes per line, zeros where a line is shorter; the zeros are dropped
        sec = np.floor(ts)
        usec = np.rint((ts - sec) * 1e6).astype(np.int64)
        sec_i = sec.astype(np.int64) + (usec // 1_000_000)
        usec %= 1_000_000
        head = f") {self._log_channel} ".encode()
        rows = np.empty((n, _SEC_DIGITS + 8 + len(head) + 4 + 16 + 3), dtype=np.uint8)
        rows[:, 0] = ord("(")
        col = 1 + _SEC_DIGITS  # the seconds without leading zeros (at least one digit)
        sec_col = sec_i[:, None]
        rows[:, 1:col] = np.where((sec_col >= _SEC_POW) | _SEC_LAST, 48 + sec_col // _SEC_POW % 10, 0)
        rows[:, col] = ord(".")
        rows[:, col + 1 : col + 7] = 48 + usec[:, None] // _USEC_POW % 10
        col += 7
        rows[:, col : col + len(head)] = np.frombuffer(head, dtype=np.uint8)
        col += len(head)
        rows[:, col : col + 3] = _HEX[frames["arbitration_id"][:, None] >> _ID_SHIFT & 0xF]
        rows[:, col + 3] = ord("#")
        col += 4
        data = frames["data"][:, :8]
        shown = _BYTE_INDEX < frames["length"][:, None]
        rows[:, col : col + 16 : 2] = np.where(shown, _HEX[data >> 4], 0)
        rows[:, col + 1 : col + 16 : 2] = np.where(shown, _HEX[data & 0xF], 0)
        col += 16
        rows[:, col] = ord(" ")
        rows[:, col + 1] = np.where(flags & FRAME_TX, ord("T"), ord("R"))
        rows[:, col + 2] = ord("\n")
        writer.file.write(rows[rows != 0].tobytes().decode("ascii"))
        self.frames += n

    def log_sent(self, msg: can.Message, timestamp: float) -> None:
        """Write a frame this process sent, with ``timestamp`` s (sent frames carry none)."""
        copy = _with_channel(msg, self.channel_name)
        copy.timestamp = timestamp
        copy.is_rx = False
        self._writer.on_message_received(copy)
        self.frames += 1

    def flush(self) -> None:
        """Hand what is written so far to the kernel (a writer killed afterwards loses none of it).

        :raises OSError: the write failed (e.g. a full disk)
        """
        if not self._stopped:
            self._writer.file.flush()

    def stop(self) -> None:
        """Flush and close the file (idempotent)."""
        if not self._stopped:
            self._stopped = True
            self._writer.stop()

    def __enter__(self) -> ChannelLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _with_channel(msg: can.Message, channel: str) -> can.Message:
    return new_message(
        msg.arbitration_id,
        bytearray(msg.data),
        timestamp=msg.timestamp,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame,
        channel=channel,
        dlc=msg.dlc,
        is_fd=msg.is_fd,
        is_rx=msg.is_rx,
        bitrate_switch=msg.bitrate_switch,
        error_state_indicator=msg.error_state_indicator,
    )


def open_log(path: str | os.PathLike[str], channel_name: str, append: bool = False) -> ChannelLog:
    """Open a candump log for channel ``channel_name`` (see :class:`ChannelLog`)."""
    return ChannelLog(path, channel_name, append=append)


def read_log(path: str | os.PathLike[str]) -> Iterator[can.Message]:
    """Yield the frames of a candump log in file order (python-can's :class:`can.LogReader`)."""
    p = Path(path)
    if p.suffix != ".log":
        raise CanLogError(f"candump logs end in .log, got {p.name!r}")
    reader = can.LogReader(p)
    try:
        yield from reader
    finally:
        reader.stop()
