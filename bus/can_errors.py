"""SocketCAN's bus error frames as the project's transports deliver them (linux/can/error.h): the
frame that reports received frames lost, and how a receiver recognises it.

A CAN controller whose receive buffer overflows loses frames and says so: SocketCAN delivers an
error frame of class ``CAN_ERR_CRTL`` with ``CAN_ERR_CRTL_RX_OVERFLOW`` in data byte 1, whatever
the socket's acceptance filters (the error mask decides).  The project's udp_multicast bus reports
every datagram the kernel dropped the same way (:mod:`bus.transports.udp_multicast`), and a CANopen
node reads it as CiA 301's EMCY 0x8110 "CAN overrun (objects lost)" (:mod:`bus.cia301.slave`).
"""

from __future__ import annotations

import logging
from typing import Any

import can
import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["CAN_ERR_CRTL", "CAN_ERR_CRTL_RX_OVERFLOW", "is_receive_overflow", "overflow_error_frame", "receive_overflows"]

#: SocketCAN's error class of a controller problem and its detail "receive buffer overflow"
#: (linux/can/error.h: CAN_ERR_CRTL in the identifier, data[1] CAN_ERR_CRTL_RX_OVERFLOW)
CAN_ERR_CRTL: int = 0x004
CAN_ERR_CRTL_RX_OVERFLOW: int = 0x01


def overflow_error_frame(timestamp: float, channel: Any = None) -> can.Message:
    """The bus error frame that reports lost frames: a controller receive overflow, as SocketCAN
    delivers it (error class :data:`CAN_ERR_CRTL`, data[1] :data:`CAN_ERR_CRTL_RX_OVERFLOW`)."""
    return can.Message(
        timestamp=timestamp,
        arbitration_id=CAN_ERR_CRTL,
        is_extended_id=False,
        is_error_frame=True,
        dlc=8,
        data=bytes([0, CAN_ERR_CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0]),
        channel=channel,
    )


def is_receive_overflow(msg: can.Message) -> bool:
    """True for an error frame that says the receiver's controller lost frames (receive overflow)."""
    return bool(
        msg.is_error_frame and msg.arbitration_id & CAN_ERR_CRTL and len(msg.data) > 1 and msg.data[1] & CAN_ERR_CRTL_RX_OVERFLOW
    )


def receive_overflows(error_ids: np.ndarray, error_data: np.ndarray) -> int:
    """How many of the error frames with identifiers ``error_ids`` (n,) and data ``error_data``
    (n, >= 2 bytes) say that the receiver's controller lost frames (:func:`is_receive_overflow`,
    on arrays: the channel monitors read frames as :data:`bus.bus_features.FRAME_DTYPE` rows)."""
    if not len(error_ids):
        return 0
    return int(np.count_nonzero((error_ids & CAN_ERR_CRTL != 0) & (error_data[:, 1] & CAN_ERR_CRTL_RX_OVERFLOW != 0)))
