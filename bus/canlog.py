"""candump-format logs of a CAN channel, written and read with python-can's own io classes.

This module owns how a run folder's channel logs are made (docs/architecture.md §7:
candump-format logs of both channels): :func:`open_log` returns a :class:`ChannelLog`, a
:class:`can.Listener` that writes every frame with :class:`can.CanutilsLogWriter` under a
fixed channel name (``fieldbus``, ``io``), and :func:`read_log` reads a log back with
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

from bus.fastmsg import new_message

logger = logging.getLogger(__name__)


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

    def on_message_received(self, msg: can.Message) -> None:
        """Write one frame (its own channel attribute is replaced by ``channel_name``)."""
        if msg.channel != self.channel_name:
            msg = _with_channel(msg, self.channel_name)
        self._writer.on_message_received(msg)
        self.frames += 1

    def log_sent(self, msg: can.Message, timestamp: float) -> None:
        """Write a frame this process sent, with ``timestamp`` s (sent frames carry none)."""
        copy = _with_channel(msg, self.channel_name)
        copy.timestamp = timestamp
        copy.is_rx = False
        self._writer.on_message_received(copy)
        self.frames += 1

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
    return new_message(msg.arbitration_id, bytearray(msg.data), timestamp=msg.timestamp,
                       is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                       is_error_frame=msg.is_error_frame, channel=channel, dlc=msg.dlc, is_fd=msg.is_fd,
                       is_rx=msg.is_rx, bitrate_switch=msg.bitrate_switch,
                       error_state_indicator=msg.error_state_indicator)


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
