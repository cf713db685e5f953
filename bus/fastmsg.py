"""Building :class:`can.Message` objects on the hot path, cheaply.

This module owns :func:`new_message`: the same object ``can.Message(..., check=False)`` builds
(every slot set, ``data`` a bytearray, ``dlc`` given), made without the keyword-argument
processing of ``Message.__init__`` (about ten times faster: it matters at 8–16 frames per
control period in every process of the rig). If a python-can version adds or renames a slot of
``can.Message``, the module notices at import and falls back to the constructor, so the objects
are always complete.
"""

from __future__ import annotations

import logging

import can

logger = logging.getLogger(__name__)

__all__ = ["new_message"]

_EXPECTED_SLOTS = frozenset(
    {
        "arbitration_id",
        "bitrate_switch",
        "channel",
        "data",
        "dlc",
        "error_state_indicator",
        "is_error_frame",
        "is_extended_id",
        "is_fd",
        "is_remote_frame",
        "is_rx",
        "timestamp",
    }
)
#: True when can.Message has exactly the slots set below (checked once, at import)
FAST: bool = frozenset(s for s in getattr(can.Message, "__slots__", ()) if s != "__weakref__") == _EXPECTED_SLOTS
if not FAST:  # pragma: no cover - depends on the installed python-can
    logger.info("can.Message slots changed: building messages with the constructor")

_new = can.Message.__new__
_Message = can.Message


def new_message(
    arbitration_id: int,
    data: bytearray,
    *,
    timestamp: float = 0.0,
    is_extended_id: bool = False,
    is_remote_frame: bool = False,
    is_error_frame: bool = False,
    channel: str | None = None,
    dlc: int | None = None,
    is_fd: bool = False,
    is_rx: bool = True,
    bitrate_switch: bool = False,
    error_state_indicator: bool = False,
) -> can.Message:
    """``can.Message(..., check=False)`` with these fields; ``data`` is kept (not copied) and
    must be a bytearray (empty for a remote frame); ``dlc`` defaults to ``len(data)``."""
    if not FAST:  # pragma: no cover
        return can.Message(
            timestamp=timestamp,
            arbitration_id=arbitration_id,
            is_extended_id=is_extended_id,
            is_remote_frame=is_remote_frame,
            is_error_frame=is_error_frame,
            channel=channel,
            dlc=dlc,
            data=data,
            is_fd=is_fd,
            is_rx=is_rx,
            bitrate_switch=bitrate_switch,
            error_state_indicator=error_state_indicator,
            check=False,
        )
    msg = _new(_Message)
    msg.timestamp = timestamp
    msg.arbitration_id = arbitration_id
    msg.is_extended_id = is_extended_id
    msg.is_remote_frame = is_remote_frame
    msg.is_error_frame = is_error_frame
    msg.channel = channel
    msg.data = data
    msg.dlc = len(data) if dlc is None else dlc
    msg.is_fd = is_fd
    msg.is_rx = is_rx
    msg.bitrate_switch = bitrate_switch
    msg.error_state_indicator = error_state_indicator
    return msg
