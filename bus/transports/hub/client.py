r"""Hub client: :class:`HubBus`, the python-can interface ``ilcrig_hub``.

This module owns the client side of the zero-privilege CAN hub: one :class:`HubBus` is one
member of one logical bus on a hub (:mod:`bus.transports.hub.server`), speaking the wire
protocol of :mod:`bus.transports.hub.wire` (records: :mod:`bus.transports.hub.records`). It is
registered as the python-can interface ``ilcrig_hub`` (entry point in ``pyproject.toml``), so
``can.Bus(interface="ilcrig_hub", channel=...)`` and python-can's tools (``can.logger``, ``can.player``, ``can.bridge``,
``can.viewer``) reach it, and it behaves as python-can's own interfaces do (python-can's
back-to-back, notifier, listener, filtering and cyclic-send tests run against it:
``tests/test_hub_python_can.py``).

    >>> bus = can.Bus(interface="ilcrig_hub", channel="unix:/tmp/x.sock#io")  # doctest: +SKIP

Forwarding
    Every frame a client sends is forwarded to every other client of the same logical bus,
    never back to the sender (unless the sender asked for ``receive_own_messages``; it then
    gets its own frames back with ``is_rx=False``).

Timestamps
    ``msg.timestamp`` is the time (``time.time()`` scale, s since the epoch) at which the
    hub received the frame, not the time the application read it: frames read late keep
    their true spacing, as with SocketCAN's kernel timestamps. The hub process takes it
    when it reads the frame, typically ~0.1 ms after the send (later when the machine is
    busy and the hub waits for a core).

Channel
    ``msg.channel`` is the channel string the receiving bus was opened with (e.g.
    ``unix:/tmp/rig/hub.sock#io``), as with python-can's own interfaces (socketcan gives
    ``vcan0``, virtual its channel id): a received frame names the bus it came from and can
    be sent on again, and two buses opened on the same channel agree on it.
    Candump logs: the project's own logs (:class:`bus.canlog.ChannelLog`, the run folder's
    ``fieldbus.log``/``io.log``) keep writing the short logical name (``fieldbus``, ``io``):
    ChannelLog replaces every frame's channel by its fixed ``channel_name``
    (``bus.canlog._with_channel``), so they stay short, stable across runs (the hub socket
    path is a fresh temp dir each run) and comparable to SocketCAN runs. python-can's
    ``can.logger`` writes ``msg.channel`` as it is, i.e. the full channel string (it has
    no whitespace, so ``can.LogReader`` reads it back).

CAN FD, classic CAN and bitrates
    ``fd=True`` (the default, as before: the hub carries FD frames) makes a CAN FD
    controller (:attr:`protocol` ``CAN_FD``). ``fd=False`` makes a classic CAN controller
    (``CAN_20``): :meth:`send` refuses FD frames and frames longer than 8 bytes with
    :class:`can.CanOperationError` (as SocketCAN does, ``EINVAL``), and the hub forwards no
    FD frames to it (as a non-FD SocketCAN raw socket never sees them). ``bitrate`` and
    ``data_bitrate`` (bit/s, the latter only with ``fd=True``; also taken from a ``timing``
    :class:`can.BitTiming` / :class:`can.BitTimingFd`) are kept: the first member of an
    empty logical bus sets the bus's bitrates, a member asking for different ones is
    refused (like a node at the wrong bitrate), a member giving none adopts the bus's.
    They are exposed as :attr:`HubBus.bitrate` / :attr:`HubBus.data_bitrate` (None =
    unknown), in :attr:`channel_info` and in the hub stats
    (:class:`~bus.transports.hub.stats.HubChannelStats`).

Acceptance filters
    ``can_filters`` / :meth:`can.BusABC.set_filters` are pushed to the hub, which then only forwards matching
    frames (like SocketCAN's kernel filters); the client still checks them in software, so frames in flight
    while filters change are filtered too (as one set lookup when each filter is one standard identifier,
    :func:`bus.bus_features.exact_standard_ids`). Bus error frames pass whatever the filters, as on
    python-can's SocketcanBus (its error mask takes every error class).

Reading
    A client reads as many records as are there (up to :attr:`HubBus.RECV_CHUNK` bytes) per
    system call into a local queue, and :meth:`recv` returns from that queue first. So a frame
    may be waiting although :meth:`HubBus.fileno` is not readable: a caller that waits with
    ``select()`` over several buses must first ask :meth:`HubBus.frames_pending` (the documented extra of
    :class:`bus.bus_features.BufferedReceiver`; :func:`bus.bus_features.pending_check`).
    :meth:`HubBus.recv_batch` (:class:`bus.bus_features.BatchReceiver`) returns every frame
    waiting after at most one non-blocking read; :meth:`HubBus.recv_frames`
    (:class:`bus.bus_features.FrameArrayReceiver`) returns them as one numpy array
    (:data:`bus.bus_features.FRAME_DTYPE`), classic frames straight from the records, without a
    :class:`can.Message` each. Blocking client sockets + ``select``, no sleeps.

Sending several frames
    :meth:`HubBus.send_batch` (:class:`bus.bus_features.BatchSender`) writes several frames
    in one system call; the hub forwards them as if sent one by one.

A frame without the interpreter
    :meth:`HubBus.periodic_writer` hands one frame to a thread of C that writes it every period
    without taking the GIL (the host's heartbeat, :mod:`host.rig.host_heartbeat`), on a member of
    its own opened with the filter :data:`NOTHING_IN`.

After :meth:`shutdown`
    ``recv``, ``send``, ``set_filters``, ``flush_tx_buffer`` and ``send_periodic`` raise
    :class:`can.CanOperationError` ("Cannot operate on a closed bus", python-can's virtual
    interface's words), also in a thread that was blocked in ``recv`` when another thread
    shut the bus down; ``shutdown`` again does nothing; ``fileno`` returns -1 (as a closed
    SocketCAN bus does).
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import select
import socket
import threading
import time
from collections.abc import Sequence
from types import ModuleType
from typing import Any

import can
import numpy as np
from can import CanProtocol

from bus.bus_features import FRAME_DTYPE, AnswerEnd, FrameAnswer, exact_standard_ids, frames_from_messages, recv_waiting
from bus.transports.hub.addresses import HubAddress, connect, parse_channel
from bus.transports.hub.core import member_core
from bus.transports.hub.owner import HubOwnerError
from bus.transports.hub.records import (
    classic_frames,
    decode_records,
    encode_data_frames,
    encode_filters,
    encode_gather,
    encode_record,
    encode_release,
)
from bus.transports.hub.wire import (
    PROTOCOL_VERSION,
    ROLE_MEMBER,
    HubAddressError,
    HubProtocolError,
    hello,
    read_member_reply,
)

logger = logging.getLogger(__name__)

_CLOSED = "Cannot operate on a closed bus"
#: an acceptance filter that lets no frame in (the fieldbus and io carry 11-bit identifiers only):
#: for a member that only writes (:meth:`HubBus.periodic_writer`)
NOTHING_IN: can.typechecking.CanFilters = [{"can_id": 0x1FFFFFFF, "can_mask": 0x1FFFFFFF, "extended": True}]


def _refuse_fd(msgs: Sequence[can.Message]) -> None:
    """A classic CAN controller's refusal of FD frames and of more than 8 data bytes (as SocketCAN's).

    :raises can.CanOperationError: ``EINVAL``
    """
    for msg in msgs:
        if msg.is_fd or (not msg.is_remote_frame and len(msg.data) > 8):
            raise can.CanOperationError(
                "Failed to transmit: CAN FD frame on a classic CAN bus (opened with fd=False)", errno.EINVAL
            )


def _bitrate_arg(name: str, value: object) -> int:
    """A bitrate keyword as int bit/s; 0 for None.

    :raises ValueError: not a positive integer below 2**32
    """
    if value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value) or not 0 < value < 1 << 32:
        raise ValueError(f"{name} must be a positive integer in bit/s, got {value!r}")
    return int(value)


def _join(addr: HubAddress, greeting: bytes, timeout_s: float) -> tuple[socket.socket, tuple[int, int]]:
    """A member's socket to the hub at ``addr``, its ``greeting`` (a hello) answered, blocking from
    then on; and the bus's (bitrate, data bitrate) from the answer.

    :raises can.CanInitializationError: no hub there, or it refused
    """
    try:
        sock = connect(addr, timeout_s)
    except HubOwnerError:
        raise  # the hub runs as another user: said as it is, not as an unreachable bus
    except OSError as err:
        raise can.CanInitializationError(f"cannot reach ilcrig hub at {addr}: {err}") from err
    try:
        sock.sendall(greeting)
        rates = read_member_reply(sock)
        sock.settimeout(None)  # blocking from now on
    except (OSError, HubProtocolError) as err:
        sock.close()
        old_hub = "bad hello" in str(err)  # a version-1 hub's words for any other version
        hint = f" (this client speaks hub protocol version {PROTOCOL_VERSION}: an older hub?)" if old_hub else ""
        raise can.CanInitializationError(f"hub handshake with {addr} failed: {err}{hint}") from err
    return sock, rates


class HubBus(can.BusABC):
    """python-can interface ``ilcrig_hub``: one logical bus on an ilcrig hub.

    :param channel: ``<address>#<bus name>`` (see :mod:`bus.transports.hub.addresses`)
    :param can_filters: acceptance filters, applied in the hub and again in software
    :param receive_own_messages: the hub echoes this client's frames back (``is_rx=False``)
    :param fd: True (default): CAN FD controller; False: classic CAN controller (see the
        module docstring)
    :param bitrate: nominal bitrate, bit/s (None: adopt the bus's)
    :param data_bitrate: CAN FD data-phase bitrate, bit/s (None: adopt the bus's)
    :param timing: :class:`can.BitTiming` or :class:`can.BitTimingFd`; gives the bitrates
        (a BitTimingFd also means ``fd=True``) when they are not given
    :param connect_timeout_s: connect + handshake timeout, s
    :param allow_remote: connect to a hub on a non-loopback TCP address (explicit opt-in)
    :param bulk_delivery: a passive member (a logger, a monitor): the hub may hold this
        client's frames up to :data:`~bus.transports.hub.wire.BULK_HOLD_S` and deliver them in
        fewer, larger writes (timestamps stay the hub's receive times)
    :raises can.CanInitializationError: no hub at the address, or the hub refused (e.g.
        another bitrate on that bus, another protocol version)
    :raises HubAddressError: malformed channel string (a ValueError)
    :raises ValueError: a bitrate that is not a positive integer

    :ivar channel: the channel string as given
    :ivar bus_name: the logical bus name (after ``#``)
    :ivar bitrate: the logical bus's nominal bitrate, bit/s, None if unknown
    :ivar data_bitrate: its data-phase bitrate, bit/s, None if unknown
    :ivar fd: whether this is a CAN FD controller
    """

    #: connect + handshake timeout, s
    CONNECT_TIMEOUT_S: float = 5.0
    #: most bytes read from the hub socket at once (many records per system call), bytes
    RECV_CHUNK: int = 1 << 16

    def __init__(
        self,
        channel: str | None = None,
        can_filters: can.typechecking.CanFilters | None = None,
        receive_own_messages: bool = False,
        fd: bool | None = True,
        bitrate: int | None = None,
        data_bitrate: int | None = None,
        timing: can.BitTiming | can.BitTimingFd | None = None,
        connect_timeout_s: float | None = None,
        allow_remote: bool = False,
        bulk_delivery: bool = False,
        **kwargs: Any,
    ) -> None:
        self._closed = True  # until connected: nothing to operate on
        self._writer: Any = None  # the member's PeriodicWriter (periodic_writer), if any
        self._exact_ids: frozenset[int] | None = None
        self._rxq: collections.deque[can.Message] = collections.deque()
        self._rxbuf = bytearray()
        if channel is None:
            raise HubAddressError("HubBus needs a channel such as 'unix:/tmp/hub.sock#io'")
        addr, name = parse_channel(str(channel), bool(allow_remote))
        if isinstance(timing, can.BitTimingFd):
            bitrate = timing.nom_bitrate if bitrate is None else bitrate
            data_bitrate = timing.data_bitrate if data_bitrate is None else data_bitrate
            fd = True
        elif isinstance(timing, can.BitTiming):
            bitrate = timing.bitrate if bitrate is None else bitrate
        self.fd = fd is None or bool(fd)
        asked = _bitrate_arg("bitrate", bitrate), _bitrate_arg("data_bitrate", data_bitrate) if self.fd else 0
        timeout = self.CONNECT_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
        greeting = hello(
            ROLE_MEMBER,
            name,
            echo=receive_own_messages,
            classic=not self.fd,
            bitrate=asked[0],
            data_bitrate=asked[1],
            bulk=bulk_delivery,
        )
        sock, (bus_bitrate, bus_data_bitrate) = _join(addr, greeting, timeout)
        self._sock = sock
        self._closed = False
        self._send_lock = threading.Lock()
        #: the C side of answer_frames (None: not built, or ILCRIG_HUB_CORE=python)
        self._core: ModuleType | None = member_core()
        self._address = addr
        self.bus_name = name
        self.receive_own_messages = receive_own_messages
        self.bulk_delivery = bool(bulk_delivery)
        self.channel = str(channel)
        self.bitrate: int | None = bus_bitrate or None
        self.data_bitrate: int | None = bus_data_bitrate or None
        self._can_protocol = CanProtocol.CAN_FD if self.fd else CanProtocol.CAN_20
        rates = f", {self.bitrate} bit/s" if self.bitrate else ""
        if self.fd and self.data_bitrate:
            rates += f", data {self.data_bitrate} bit/s"
        self.channel_info = f"ilcrig hub {addr} bus {name!r}, {'CAN FD' if self.fd else 'classic CAN'}{rates}"
        try:
            super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        except BaseException:
            self._closed = True
            sock.close()
            raise
        logger.debug("connected to %s", self.channel_info)

    # -- receiving ------------------------------------------------------------------------

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        rxq = self._rxq
        if rxq:
            return self._passed(rxq.popleft())
        try:
            if timeout is None:
                while not rxq:
                    self._fill(block=True)
            elif timeout <= 0:
                self._fill(block=False)
            else:
                deadline = time.monotonic() + timeout
                while not rxq:
                    left = deadline - time.monotonic()
                    if left < 0 or not select.select((self._sock,), (), (), left)[0]:
                        return None, False
                    self._fill(block=False)
        except (OSError, ValueError) as err:  # ValueError: select() on a socket closed meanwhile
            if self._closed:
                raise can.CanOperationError(_CLOSED) from err
            raise can.CanOperationError(f"hub receive failed: {err}") from err
        return self._passed(rxq.popleft()) if rxq else (None, False)

    def _passed(self, msg: can.Message) -> tuple[can.Message, bool]:
        """``msg``, True when :attr:`_exact_ids` passes it or it is a bus error frame (which passes
        every filter), else ``BusABC.recv`` tests it."""
        if msg.is_error_frame:
            return msg, True
        exact = self._exact_ids
        return msg, exact is not None and not msg.is_extended_id and msg.arbitration_id & 0x7FF in exact

    def _fill(self, block: bool) -> None:
        """One read of up to :attr:`RECV_CHUNK` bytes; every whole record read goes to the local
        queue, a partial one waits in the buffer for its rest. Non-blocking reads return at once
        when nothing is there.

        :raises can.CanOperationError: the hub closed the connection
        :raises HubProtocolError: a record of another kind than a frame
        """
        data = self._read(block)
        if data:
            self._parse(data)

    def _read(self, block: bool) -> bytes:
        """One read of up to :attr:`RECV_CHUNK` bytes, after what the buffer holds of a partial
        record (empty when a non-blocking read finds nothing).

        :raises can.CanOperationError: the hub closed the connection
        """
        try:
            data = self._sock.recv(self.RECV_CHUNK) if block else self._sock.recv(self.RECV_CHUNK, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return b""
        if not data:
            if self._closed:
                raise can.CanOperationError(_CLOSED)
            raise can.CanOperationError(f"ilcrig hub closed the connection ({self.channel_info})")
        buf = self._rxbuf
        if buf:
            buf += data
            self._rxbuf = bytearray()
            return bytes(buf)
        return data

    def _parse(self, data: bytes) -> None:
        """Every whole record of ``data`` to the local queue; a partial one waits in the buffer.

        :raises HubProtocolError: a record of another kind than a frame
        """
        used = decode_records(data, self.channel, self._rxq.append)
        self._rxbuf = bytearray(data[used:]) if used < len(data) else bytearray()

    def recv_batch(self) -> list[can.Message]:
        """Every frame waiting now, in order (:class:`bus.bus_features.BatchReceiver`): the local
        queue, or what one non-blocking read of the socket brings; never waits.

        :raises can.CanOperationError: as :meth:`recv`
        """
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        rxq = self._rxq
        if not rxq:
            try:
                self._fill(block=False)
            except (OSError, ValueError) as err:
                if self._closed:
                    raise can.CanOperationError(_CLOSED) from err
                raise can.CanOperationError(f"hub receive failed: {err}") from err
            if not rxq:
                return []
        msgs = list(rxq)
        rxq.clear()
        if self._filters is not None:  # the hub filtered too, but maybe with filters set before
            exact, matches = self._exact_ids, self._matches_filters
            if exact is not None:  # standard ids only: python-can's test as a set lookup
                msgs = [m for m in msgs if (not m.is_extended_id and m.arbitration_id & 0x7FF in exact) or m.is_error_frame]
            else:
                msgs = [m for m in msgs if m.is_error_frame or matches(m)]
        return msgs

    def recv_frames(self, timeout: float | None = None) -> np.ndarray:
        """Every frame waiting, as one array of :data:`bus.bus_features.FRAME_DTYPE`
        (:class:`bus.bus_features.FrameArrayReceiver`): the frames already in the local queue, then
        everything one read of the socket brings, without a :class:`can.Message` per frame (when
        the read holds classic frames only; else through the queue). Waits up to ``timeout`` s
        (None: forever) when nothing is waiting; an empty array when nothing came.

        :raises can.CanOperationError: as :meth:`recv`
        """
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        if self._filters:  # software filtering as recv() does it
            return frames_from_messages(recv_waiting(self, timeout))
        parts = []
        if self._rxq:
            parts.append(frames_from_messages(list(self._rxq)))
            self._rxq.clear()
        try:
            if not parts and timeout != 0 and not select.select((self._sock,), (), (), timeout)[0]:
                return np.zeros(0, dtype=FRAME_DTYPE)
            data = self._read(block=False)
        except (OSError, ValueError) as err:  # ValueError: select() on a socket closed meanwhile
            if self._closed:
                raise can.CanOperationError(_CLOSED) from err
            raise can.CanOperationError(f"hub receive failed: {err}") from err
        if data:
            parts.append(self._frames_of(data))
        if not parts:
            return np.zeros(0, dtype=FRAME_DTYPE)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _frames_of(self, data: bytes) -> np.ndarray:
        """The whole records of ``data`` as frames (a partial one waits in the buffer)."""
        found = classic_frames(data)
        if found is None:  # CAN FD records (or garbage): one at a time
            self._parse(data)
            msgs = list(self._rxq)
            self._rxq.clear()
            return frames_from_messages(msgs)
        frames, used = found
        if used < len(data):
            self._rxbuf = bytearray(data[used:])
        return frames

    def frames_pending(self) -> bool:
        """True when frames wait in the local queue (:class:`bus.bus_features.BufferedReceiver`): :meth:`recv`
        returns one without reading the socket, although :meth:`fileno` may not be readable."""
        return bool(self._rxq)

    def fileno(self) -> int:
        """The socket's descriptor, -1 after :meth:`shutdown`. Readable ⇒ bytes from the hub are waiting;
        frames already read may also wait in the local queue: a frame is waiting ⇔ readable or :meth:`frames_pending`."""
        return self._sock.fileno()

    # -- sending --------------------------------------------------------------------------

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to every other client of this bus.

        Blocking (the hub always reads); ``timeout`` is accepted for the BusABC signature and not used.
        Thread-safe (python-can's periodic tasks send from threads).

        :raises can.CanOperationError: the bus is shut down or the hub gone; on a classic bus
            (``fd=False``) an FD frame or more than 8 data bytes (``EINVAL``)
        """
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        if not self.fd:
            _refuse_fd((msg,))
        self._sock_send(encode_record(msg))

    def send_batch(self, msgs: Sequence[can.Message]) -> None:
        """Send ``msgs`` in order in one socket write (:class:`bus.bus_features.BatchSender`):
        the hub forwards them exactly as if each had been sent with :meth:`send`.

        :raises can.CanOperationError: as :meth:`send` (nothing is sent if a frame is refused)
        """
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        if not self.fd:
            _refuse_fd(msgs)
        self._sock_send(b"".join([encode_record(msg) for msg in msgs]))

    def send_data_frames(self, frames: Sequence[tuple[int, bytes]]) -> None:
        """Send classic data frames given as (11-bit identifier, data) pairs in order in one socket
        write, without a :class:`can.Message` each (:class:`bus.bus_features.DataFrameSender`): the
        hub forwards them exactly as if each had been sent with :meth:`send`.

        :raises ValueError: an identifier outside 0..0x7FF or more than 8 data bytes (nothing is sent)
        :raises can.CanOperationError: as :meth:`send`
        """
        self._sock_send(encode_data_frames(frames))

    def periodic_writer(self, msg: can.Message, period_s: float) -> Any:
        """``msg`` written every ``period_s`` by a thread of C without the interpreter (``_hubcore.PeriodicWriter``,
        stopped by :meth:`shutdown`); the member's frames are then its alone (:meth:`send` refused), so open it
        with the filter :data:`NOTHING_IN`. :raises can.CanOperationError: no C core, shut down, a writer already"""
        if self._core is None or self._closed or self._writer is not None:
            why = "no C core (ILCRIG_HUB_CORE=python?)" if self._core is None else _CLOSED if self._closed else "one already"
            raise can.CanOperationError(f"no periodic writer: {why}")
        self._writer = self._core.PeriodicWriter(self._sock.fileno(), encode_record(msg), float(period_s))
        return self._writer

    def _sock_send(self, data: bytes) -> None:
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        if self._writer is not None:
            raise can.CanOperationError("this member's frames are its periodic writer's (HubBus.periodic_writer)")
        try:
            with self._send_lock:
                self._sock.sendall(data)
        except OSError as err:
            if self._closed:
                raise can.CanOperationError(_CLOSED) from err
            raise can.CanOperationError(f"hub send failed: {err}") from err

    def send_periodic(self, *args: Any, **kwargs: Any) -> can.broadcastmanager.CyclicSendTaskABC:
        """:meth:`can.BusABC.send_periodic`; raises :class:`can.CanOperationError` once shut down."""
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        return super().send_periodic(*args, **kwargs)

    @property
    def answers_in_c(self) -> bool:
        """:meth:`answer_frames` answers (the C core is built, ``ILCRIG_HUB_CORE`` is not ``python``)."""
        return self._core is not None

    def answer_frames(
        self, rx_id: int, rx_count: int, rx_len: int, on_frame: FrameAnswer, deadline_s: float, other_fd: int = -1
    ) -> tuple[int, AnswerEnd]:
        """:class:`bus.bus_features.FrameAnswerer` in C (``_hubcore.answer_frames``; answers written as by
        :meth:`send_data_frames`, records not handled left for :meth:`recv`); :raises: as :meth:`send`."""
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        core, rest = self._core, bytearray()
        if core is None or self._rxq or self._rxbuf:  # (0, PYTHON) at once: what was read waits here
            return 0, AnswerEnd.PYTHON
        try:
            args = (self._sock.fileno(), other_fd, deadline_s, rx_id, rx_count, rx_len, on_frame, rest, self._send_lock)
            n, why, err = core.answer_frames(*args)
        finally:
            self._parse(bytes(rest))
        if why == core.BURST_SENDFAIL:
            raise can.CanOperationError(_CLOSED if self._closed else f"hub send failed: {os.strerror(err)}", err)
        return n, AnswerEnd(why)

    def release_held(self) -> None:
        """Ask the hub for the frames it holds for this bulk member now (the release record of :mod:`bus.transports.hub.wire`;
        :class:`bus.bus_features.HeldReleaser`): a reader waiting for a marker does not wait out ``BULK_HOLD_S``.
        Nothing is held for a member that is not bulk; the request then does nothing."""
        if self._closed:
            raise can.CanOperationError(_CLOSED)
        self._sock_send(encode_release())

    def gather_frames(self, count: int) -> None:
        """From now on have the hub deliver this member's frames ``count`` at a time (the gather record of
        :mod:`bus.transports.hub.wire`; :class:`bus.bus_features.FrameGatherer`): a lockstep master waiting for
        ``count`` answers wakes once for them, not once per answer; fewer are delivered after ``BULK_HOLD_S``.
        0: every frame at once again."""
        if not 0 <= int(count) <= 0xFFFFFFFF:
            raise ValueError(f"gather count must be 0..2**32-1, got {count!r}")
        self._sock_send(encode_gather(int(count)))

    def flush_tx_buffer(self) -> None:
        """Nothing to discard: :meth:`send` returns when the kernel holds the frame."""
        if self._closed:
            raise can.CanOperationError(_CLOSED)

    def _apply_filters(self, filters: can.typechecking.CanFilters | None) -> None:
        self._exact_ids = exact_standard_ids(filters)
        self._sock_send(encode_filters(filters))

    # -- lifetime -------------------------------------------------------------------------

    def shutdown(self) -> None:
        """Leave the hub. Idempotent; wakes a thread blocked in :meth:`recv` (it then raises
        :class:`can.CanOperationError`)."""
        if self._is_shutdown:
            return
        super().shutdown()  # stops the periodic tasks while the socket still works
        if self._writer is not None:
            self._writer.stop()  # before the descriptor closes (its number could be another's next)
        if self._closed:
            return
        self._closed = True
        for close in (lambda: self._sock.shutdown(socket.SHUT_RDWR), self._sock.close):
            try:
                close()
            except OSError as err:
                logger.debug("closing %s: %s", self.channel_info, err)

    @staticmethod
    def _detect_available_configs() -> list[can.typechecking.AutoDetectedConfig]:
        return []
