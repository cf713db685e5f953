"""python-can's udp_multicast bus as the project opens it: no frame is lost silently.

This module owns :class:`CheckedUdpMulticastBus`, the python-can interface ``ilcrig_udp_multicast``
(entry point in ``pyproject.toml``; :mod:`bus.transports.config` resolves python-can's
``udp_multicast`` to it): python-can's :class:`can.interfaces.udp_multicast.UdpMulticastBus` with a
large receive buffer and the kernel's drop counter read with every datagram; and
:func:`enlarge_receive_buffer` (any kernel socket: UDP, SocketCAN).

What udp_multicast guarantees, and what it does not
    A CAN bus never loses a frame silently: a frame is received by every node or, when a receiver's
    controller overflows, that node sees an error (SocketCAN: an error frame of class
    ``CAN_ERR_CRTL`` with ``CAN_ERR_CRTL_RX_OVERFLOW``).  UDP multicast carries one datagram per
    frame through one kernel socket per receiver; the kernel drops a datagram when that socket's
    receive buffer is full, i.e. when its process did not read for as long as the buffer lasts (a
    process waiting for a core on a busy machine; python-can leaves the buffer at
    ``net.core.rmem_default``, 208 KiB, about 250 datagrams of 832 bytes each as the kernel counts
    them).  Every frame goes to every socket of the group, the sender's own included, so a drive
    reads all the fieldbus traffic, the other drives' SDO blocks too.  Hence:

    * the receive buffer is raised to :data:`UDP_RCVBUF_BYTES` (``SO_RCVBUFFORCE`` where the
      process may, else ``SO_RCVBUF``, which the kernel caps at ``net.core.rmem_max``; a buffer
      left smaller is logged as a warning naming that sysctl) — lossless in practice;
    * every datagram the kernel still drops on this socket is counted by the kernel
      (``SO_RXQ_OVFL``: the socket's drop count comes with each datagram; ``SO_MEMINFO`` when
      nothing arrives) and reported, in order, as a bus error frame before the first frame
      received after the loss (:func:`overflow_error_frame`, SocketCAN's form of a controller
      receive overflow, :mod:`bus.can_errors`), logged as a warning and counted
      (:attr:`CheckedUdpMulticastBus.frames_lost`).  The host's channel monitors and the plant
      turn a bus error frame into a fault of the run; a drive reports a loss on its fieldbus as
      EMCY 0x8110 "CAN overrun" and reacts as its 0x1029 says (:mod:`bus.cia301.slave`,
      :mod:`firmware_model.power_stage`).

    Not detected: a datagram lost before it reaches the socket (the per-CPU input backlog,
    ``net.core.netdev_max_backlog``; on loopback the sender's own CPU delivers its datagram at
    once, counted in ``/proc/net/softnet_stat``).  Not provided: arbitration (frames of two senders
    arrive in the order the kernel queued them) and bus time.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import time
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import unpack_message

from bus.can_errors import CAN_ERR_CRTL, CAN_ERR_CRTL_RX_OVERFLOW, overflow_error_frame  # noqa: F401 - re-exported

logger = logging.getLogger(__name__)

#: receive buffer wanted for every udp_multicast socket (as the kernel counts it, so twice what is
#: asked of SO_RCVBUF): about 10 000 datagrams, a few seconds of the rig's traffic
UDP_RCVBUF_BYTES: int = 8 << 20

# Linux socket options python's socket module does not name (asm-generic/socket.h)
SO_RCVBUFFORCE: int = getattr(socket, "SO_RCVBUFFORCE", 33)
SO_TIMESTAMPNS: int = getattr(socket, "SO_TIMESTAMPNS", 35)
SO_RXQ_OVFL: int = getattr(socket, "SO_RXQ_OVFL", 40)
SO_MEMINFO: int = getattr(socket, "SO_MEMINFO", 55)
#: SO_MEMINFO answers SK_MEMINFO_VARS u32 counters; the socket's drops are the one at SK_MEMINFO_DROPS
_MEMINFO = struct.Struct("=9I")
_SK_MEMINFO_DROPS = 8
_TIMESPEC = struct.Struct("@ll")
_DROPS = struct.Struct("@I")


def enlarge_receive_buffer(sock: socket.socket, size_bytes: int) -> int:
    """Ask for a receive buffer of ``size_bytes`` on ``sock`` (``SO_RCVBUFFORCE`` where the process
    has CAP_NET_ADMIN, else ``SO_RCVBUF``, which the kernel caps at ``net.core.rmem_max``).

    :return: the buffer the socket has now, bytes as the kernel counts them (twice what was granted)
    """
    for option in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size_bytes)
            break
        except OSError as err:
            logger.debug("receive buffer option %d refused: %s", option, err)
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


class CheckedUdpMulticastBus(UdpMulticastBus):
    """python-can's udp_multicast bus whose losses are errors (see the module docstring).

    Takes python-can's arguments (``channel`` = the group, ``port``, ``hop_limit``, ``fd``,
    ``can_filters``) and ``receive_buffer_bytes``, the receive buffer wanted (bytes as the kernel
    counts them, default :data:`UDP_RCVBUF_BYTES`).  A loss is reported by :meth:`recv` as one bus error frame
    (:func:`overflow_error_frame`), whatever the acceptance filters, before the frame that
    revealed it; that frame then waits in the bus (:meth:`frames_pending`).

    :ivar rcvbuf_bytes: the socket's receive buffer, bytes as the kernel counts them
    :ivar frames_lost: datagrams the kernel dropped on this socket since it was opened
    """

    def __init__(
        self, channel: str = UdpMulticastBus.DEFAULT_GROUP_IPv6, receive_buffer_bytes: int = UDP_RCVBUF_BYTES, **kwargs: Any
    ) -> None:
        super().__init__(channel, **kwargs)
        self._group = f"{channel}:{self._multicast.port}"
        self._sock: socket.socket = self._multicast._socket
        self.rcvbuf_bytes = enlarge_receive_buffer(self._sock, receive_buffer_bytes // 2)
        if self.rcvbuf_bytes < receive_buffer_bytes:
            logger.warning(
                "udp_multicast %s: receive buffer %d bytes, fewer than the %d wanted (net.core.rmem_max caps it; "
                "raise it with sysctl -w net.core.rmem_max=%d): a busy machine may overflow it (reported as bus errors)",
                self._group,
                self.rcvbuf_bytes,
                receive_buffer_bytes,
                receive_buffer_bytes // 2,
            )
        self._sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        self._ancillary_bytes = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_DROPS.size)
        self._max_datagram = self._multicast.max_buffer
        self._drops_seen = self._kernel_drops()
        self.frames_lost = 0
        #: a frame received after a loss, delivered after the loss's error frame
        self._held: can.Message | None = None
        self.channel_info = f"udp_multicast {self._group}, receive buffer {self.rcvbuf_bytes} bytes, losses reported"

    def _kernel_drops(self) -> int:
        """The socket's drop count now (``SO_MEMINFO``)."""
        raw = self._sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, _MEMINFO.size)
        return int(_MEMINFO.unpack_from(raw)[_SK_MEMINFO_DROPS])

    def _lost(self, drops: int) -> int:
        """How many datagrams were lost since the last report, given the socket's drop count
        ``drops`` (a u32 that may wrap); counts and logs them."""
        lost = (drops - self._drops_seen) & 0xFFFFFFFF
        if lost == 0 or lost >= 1 << 31:  # none, or an older count than one already reported
            return 0
        self._drops_seen = drops
        self.frames_lost += lost
        logger.warning(
            "udp_multicast %s: %d datagram(s) lost (receive buffer of %d bytes full; %d lost since open): "
            "reported as a bus error frame",
            self._group,
            lost,
            self.rcvbuf_bytes,
            self.frames_lost,
        )
        return lost

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        held = self._held
        if held is not None:
            self._held = None
            return held, False
        try:
            ready = select.select((self._sock,), (), (), timeout)[0]
            if not ready:
                if self._lost(self._kernel_drops()):
                    return overflow_error_frame(time.time(), self._group), True
                return None, False
            data, ancillary, _, _ = self._sock.recvmsg(self._max_datagram, self._ancillary_bytes)
        except (OSError, ValueError) as err:  # ValueError: the socket was closed meanwhile
            raise can.CanOperationError(f"udp_multicast {self._group}: receive failed: {err}") from err
        stamp = None
        drops = None
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
                stamp = seconds + nanoseconds * 1e-9
            elif level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL:
                drops = _DROPS.unpack_from(payload)[0]
        if stamp is None:
            stamp = time.time()
        try:
            msg: can.Message | None = unpack_message(data, replace={"timestamp": stamp}, check=True)
        except Exception as err:  # python-can's own words: whatever msgpack or can.Message raise
            raise can.CanOperationError(f"udp_multicast {self._group}: could not unpack a datagram") from err
        if msg is not None and msg.is_fd and self.protocol is not can.CanProtocol.CAN_FD:
            msg = None  # a classic CAN bus ignores FD frames (as python-can's bus does)
        if drops is not None and self._lost(drops):
            self._held = msg
            return overflow_error_frame(stamp, self._group), True
        return msg, False

    def frames_pending(self) -> bool:
        """True when a frame waits in the bus although the socket may not be readable (the frame
        that revealed a loss; :class:`bus.bus_features.BufferedReceiver`)."""
        return self._held is not None
