"""Optional capabilities of a python-can bus beyond :class:`can.BusABC`, and how callers use them.

This module owns the eight documented extras a transport may offer on top of python-can's
``BusABC`` (which stays the interface of every transport); callers use an extra only when the
bus declares it — an ``isinstance`` check against the :class:`typing.Protocol` below, done once
when the caller is built — and fall back to plain ``BusABC`` calls otherwise:

* :class:`BatchSender` — ``send_batch(msgs)``: several frames in one write (the ilcrig hub
  client, :class:`bus.transports.hub.client.HubBus`, sends them as one socket write; the
  frames reach the bus in order, exactly as with one :meth:`can.BusABC.send` each).
  :func:`batch_sender` returns ``send_batch`` or a loop over ``send``.
* :class:`DataFrameSender` — ``send_data_frames(frames)``: classic data frames given as
  (11-bit identifier, data) pairs, in order, in one write, without a :class:`can.Message` per
  frame (the hub client packs its records directly); for the per-tick frames of the io channel
  (the plant's four encoder frames, a drive's torque frame). :func:`data_frame_sender` returns it,
  or a callable that builds the messages and sends them through :func:`batch_sender`.
* :class:`BufferedReceiver` — ``frames_pending()``: the bus reads several frames per system
  call into a local queue, so a frame may be waiting although ``fileno()`` is not readable. A
  ``select()``-based caller must not wait while ``frames_pending()`` is true
  (:func:`pending_check` gives it a cheap callable, always False for a bus without a queue).
* :class:`BatchReceiver` — ``recv_batch()``: every frame waiting now, at most one read of the
  socket, no waiting: a ``select()``-based caller takes all the frames of one readiness in one
  call instead of one :meth:`can.BusABC.recv` per frame and a last one that finds nothing.
  :func:`batch_receiver` returns ``recv_batch`` or :func:`recv_waiting` (every frame waiting
  that the bus's filters pass, past the ones they drop).
* :class:`FrameArrayReceiver` — ``recv_frames(timeout)``: every frame waiting, as one numpy
  array of :data:`FRAME_DTYPE` (one row per frame, in order), without building a
  :class:`can.Message` per frame; for a reader that looks at every frame of a busy channel (the
  host's io monitor). :func:`frames_from_messages` and :func:`messages_from_frames` convert;
  :func:`frame_bits` and :func:`load_of` give the frames' classic-CAN bit lengths and totals.
* :class:`HeldReleaser` — ``release_held()``: the transport holds a reader's frames a while to
  deliver them in fewer writes (the hub's bulk members) and delivers them at once when asked; for
  a reader that waits for a marker (the host's monitors at the end of a trial).
  :func:`release_held` asks, or does nothing on a bus that holds nothing.
* :class:`FrameGatherer` — ``gather_frames(n)``: the transport delivers a reader's frames n at a
  time (the hub); a lockstep master that waits for the n answers of a tick (the plant: four
  torque frames) wakes once per tick instead of once per answer. :func:`frame_gatherer` returns
  it, or a callable that does nothing.
* :class:`FrameAnswerer` — ``answer_frames(rx_id, rx_count, rx_len, on_frame, deadline_s, other_fd)``:
  the transport waits, reads and writes outside the interpreter and calls ``on_frame(index, data)``
  for each classic data frame of a range of identifiers and one length, writing the frames it
  answers (the hub client, in C): a drive's plain io ticks (encoder frame in, torque frame out),
  the plant's (four torque frames in, the next tick's four encoder frames out), without the
  per-frame Python of the receive loop. It returns (:class:`AnswerEnd`) at a deadline, when another
  descriptor is readable, at any other frame (left waiting for :meth:`can.BusABC.recv`) or when
  ``on_frame`` handled its frame itself. :func:`frame_answerer` returns it, or None (the caller
  reads as usual).
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import can
import numpy as np

from bus.busload import BusLoadCounter, bits_lookup
from bus.fastmsg import new_message

logger = logging.getLogger(__name__)

__all__ = [
    "FRAME_DTYPE",
    "AnswerEnd",
    "BatchReceiver",
    "BatchSender",
    "BufferedReceiver",
    "DataFrameSender",
    "FrameAnswer",
    "FrameAnswerer",
    "FrameArrayReceiver",
    "batch_receiver",
    "batch_sender",
    "data_frame_sender",
    "exact_standard_ids",
    "frame_answerer",
    "frame_bits",
    "frames_from_messages",
    "load_of",
    "messages_from_frames",
    "pending_check",
    "recv_waiting",
]

#: one frame per row (:class:`FrameArrayReceiver`): receive time (s, as ``Message.timestamp``),
#: identifier, flag bits (``FRAME_*``), DLC, number of data bytes, the data (zero padded)
FRAME_DTYPE = np.dtype(
    [("timestamp", "<f8"), ("arbitration_id", "<u4"), ("flags", "u1"), ("dlc", "u1"), ("length", "u1"), ("data", "u1", (64,))]
)
FRAME_EXT = 0x01
FRAME_RTR = 0x02
FRAME_ERR = 0x04
FRAME_FD = 0x08
FRAME_BRS = 0x10
FRAME_ESI = 0x20
#: the frame was sent by this bus (``Message.is_rx`` False)
FRAME_TX = 0x40


@runtime_checkable
class BatchSender(Protocol):
    """A bus that sends several frames in one operation, in order."""

    def send_batch(self, msgs: Sequence[can.Message]) -> None:
        """Send ``msgs`` in order, as :meth:`can.BusABC.send` would one by one.

        :raises can.CanOperationError: as :meth:`can.BusABC.send`
        """
        ...


@runtime_checkable
class DataFrameSender(Protocol):
    """A bus that sends classic data frames given as (identifier, data) pairs, in order."""

    def send_data_frames(self, frames: Sequence[tuple[int, bytes]]) -> None:
        """Send ``frames`` — (11-bit identifier, 0..8 data bytes) each: classic CAN data frames
        with standard identifiers — in order, as :meth:`can.BusABC.send` would one by one.

        :raises ValueError: an identifier outside 0..0x7FF or more than 8 data bytes (nothing is sent)
        :raises can.CanOperationError: as :meth:`can.BusABC.send`
        """
        ...


def data_frame_sender(bus: can.BusABC) -> Callable[[Sequence[tuple[int, bytes]]], None]:
    """``bus.send_data_frames`` when ``bus`` is a :class:`DataFrameSender`, else one
    :class:`can.Message` per frame through :func:`batch_sender` (the same checks)."""
    if isinstance(bus, DataFrameSender):
        return bus.send_data_frames
    send = batch_sender(bus)

    def send_messages(frames: Sequence[tuple[int, bytes]]) -> None:
        msgs = []
        for can_id, data in frames:
            check_data_frame(can_id, data)
            msgs.append(new_message(can_id, bytearray(data)))
        send(msgs)

    return send_messages


def check_data_frame(can_id: int, data: bytes) -> None:
    """The contract of :meth:`DataFrameSender.send_data_frames` for one frame.

    :raises ValueError: an identifier outside 0..0x7FF or more than 8 data bytes
    """
    if not 0 <= can_id <= 0x7FF or len(data) > 8:
        raise ValueError(f"not a classic data frame with a standard identifier: 0x{can_id:X}, {len(data)} bytes")


@runtime_checkable
class BufferedReceiver(Protocol):
    """A bus that may hold received frames in a local queue (not visible to ``select()``)."""

    def frames_pending(self) -> bool:
        """True when :meth:`can.BusABC.recv` would return a frame without reading the socket."""
        ...


def batch_sender(bus: can.BusABC) -> Callable[[Sequence[can.Message]], None]:
    """``bus.send_batch`` when ``bus`` is a :class:`BatchSender`, else one ``bus.send`` per frame."""
    if isinstance(bus, BatchSender):
        return bus.send_batch

    def send_each(msgs: Sequence[can.Message]) -> None:
        for msg in msgs:
            bus.send(msg)

    return send_each


@runtime_checkable
class BatchReceiver(Protocol):
    """A bus that returns every frame waiting at once."""

    def recv_batch(self) -> list[can.Message]:
        """Every frame waiting now (filtered as :meth:`can.BusABC.recv` filters), in order, after
        at most one non-blocking read; an empty list when none is there. Frames that arrive
        later make the bus readable (or :meth:`BufferedReceiver.frames_pending` true) again.

        :raises can.CanOperationError: as :meth:`can.BusABC.recv`
        """
        ...


def batch_receiver(bus: can.BusABC) -> Callable[[], list[can.Message]]:
    """``bus.recv_batch`` when ``bus`` is a :class:`BatchReceiver`, else a callable that returns
    every frame waiting that the bus's filters pass (:func:`recv_waiting` without waiting)."""
    if isinstance(bus, BatchReceiver):
        return bus.recv_batch

    def recv_each() -> list[can.Message]:
        return recv_waiting(bus, 0)

    return recv_each


def _never() -> bool:
    return False


def pending_check(bus: can.BusABC) -> Callable[[], bool]:
    """``bus.frames_pending`` when ``bus`` is a :class:`BufferedReceiver`, else a callable that
    is always False (the bus's ``fileno()`` readiness tells everything)."""
    if isinstance(bus, BufferedReceiver):
        return bus.frames_pending
    return _never


@runtime_checkable
class FrameArrayReceiver(Protocol):
    """A bus that returns every waiting frame at once, as an array of :data:`FRAME_DTYPE`."""

    def recv_frames(self, timeout: float | None = None) -> np.ndarray:
        """Every frame waiting (filtered as :meth:`can.BusABC.recv` filters), in order; waits up to
        ``timeout`` s (None: forever) for the first. An empty array when none came.

        :raises can.CanOperationError: as :meth:`can.BusABC.recv`
        """
        ...


def frame_flags(msg: can.Message) -> int:
    """The kind bits of ``msg``: :data:`FRAME_EXT` … :data:`FRAME_ESI` (the hub's wire flags are the
    same bits); :data:`FRAME_TX` is the caller's."""
    return (
        (FRAME_EXT if msg.is_extended_id else 0)
        | (FRAME_RTR if msg.is_remote_frame else 0)
        | (FRAME_ERR if msg.is_error_frame else 0)
        | (FRAME_FD if msg.is_fd else 0)
        | (FRAME_BRS if msg.bitrate_switch else 0)
        | (FRAME_ESI if msg.error_state_indicator else 0)
    )


def message_of(
    can_id: int, data: bytearray, flags: int, timestamp: float, channel: str | None = None, dlc: int | None = None
) -> can.Message:
    """A frame as a :class:`can.Message`: ``flags`` the bits of :func:`frame_flags` (+ :data:`FRAME_TX`:
    a frame this process sent, ``is_rx`` False)."""
    return new_message(
        can_id,
        data,
        timestamp=timestamp,
        is_extended_id=bool(flags & FRAME_EXT),
        is_remote_frame=bool(flags & FRAME_RTR),
        is_error_frame=bool(flags & FRAME_ERR),
        channel=channel,
        dlc=dlc,
        is_fd=bool(flags & FRAME_FD),
        is_rx=not flags & FRAME_TX,
        bitrate_switch=bool(flags & FRAME_BRS),
        error_state_indicator=bool(flags & FRAME_ESI),
    )


@runtime_checkable
class HeldReleaser(Protocol):
    """A bus whose transport may hold received frames a while to deliver them in fewer writes (the
    hub's bulk members) and can be asked to deliver them now."""

    def release_held(self) -> None:
        """Ask for the frames held for this bus to be delivered now."""
        ...


def release_held(bus: can.BusABC) -> None:
    """``bus.release_held()`` when ``bus`` is a :class:`HeldReleaser`; else nothing (frames are
    never held)."""
    if isinstance(bus, HeldReleaser):
        bus.release_held()


@runtime_checkable
class FrameGatherer(Protocol):
    """A bus whose transport can deliver the frames for it n at a time."""

    def gather_frames(self, count: int) -> None:
        """Deliver this bus's frames ``count`` at a time from now on (0: each at once)."""
        ...


def _gather_nothing(count: int) -> None:
    return None


def frame_gatherer(bus: can.BusABC) -> Callable[[int], None]:
    """``bus.gather_frames`` when ``bus`` is a :class:`FrameGatherer`, else a callable that does
    nothing (every frame comes as it comes)."""
    if isinstance(bus, FrameGatherer):
        return bus.gather_frames
    return _gather_nothing


class AnswerEnd(enum.IntEnum):
    """Why :meth:`FrameAnswerer.answer_frames` returned (the values of the hub's C core)."""

    DEADLINE = 0  #: ``deadline_s`` came, or a signal interrupted the wait (its handler ran: the caller looks)
    OTHER = 1  #: ``other_fd`` is readable
    PYTHON = 2  #: a frame that is not ``rx_id`` of ``rx_len`` bytes (or any frame already read) waits for ``recv``
    STOPPED = 3  #: ``on_frame`` returned None: it handled its frame itself
    CLOSED = 4  #: the connection ended or failed: the next ``recv`` says how


#: ``on_frame(index, data)`` of :meth:`FrameAnswerer.answer_frames`: the frame ``rx_id + index``'s data
#: bytes in; the answers out as (11-bit identifier, 0..8 data bytes) pairs, written at once in one
#: write (none: nothing to answer yet), or None: it handled the frame itself (the loop returns)
FrameAnswer = Callable[[int, bytes], Sequence[tuple[int, bytes]] | None]


@runtime_checkable
class FrameAnswerer(Protocol):
    """A bus that can answer frames outside the interpreter (module docstring)."""

    def answer_frames(
        self, rx_id: int, rx_count: int, rx_len: int, on_frame: FrameAnswer, deadline_s: float, other_fd: int = -1
    ) -> tuple[int, AnswerEnd]:
        """Wait for and read frames; each classic data frame ``rx_id`` .. ``rx_id + rx_count - 1`` of
        ``rx_len`` bytes goes to ``on_frame`` (:data:`FrameAnswer`) and its answers go out at once.
        Returns (frames handed to ``on_frame``, why: :class:`AnswerEnd`) at ``deadline_s``
        (``time.monotonic()``), when ``other_fd`` (-1: none) is readable, at any other frame (it and
        all after it wait for :meth:`can.BusABC.recv`) or when ``on_frame`` returned None. The bus's
        one reader calls it (no other thread receives on the bus meanwhile; sending is safe)."""
        ...


def frame_answerer(bus: can.BusABC) -> Callable[..., tuple[int, AnswerEnd]] | None:
    """``bus.answer_frames`` when ``bus`` is a :class:`FrameAnswerer` that can answer now (the
    hub client with its C core), else None."""
    if isinstance(bus, FrameAnswerer) and getattr(bus, "answers_in_c", False):
        return bus.answer_frames
    return None


def frames_from_messages(msgs: Sequence[can.Message]) -> np.ndarray:
    """``msgs`` as an array of :data:`FRAME_DTYPE`."""
    out = np.zeros(len(msgs), dtype=FRAME_DTYPE)
    for i, msg in enumerate(msgs):
        data = b"" if msg.is_remote_frame else bytes(msg.data)
        row = out[i]
        row["timestamp"] = msg.timestamp
        row["arbitration_id"] = msg.arbitration_id
        row["flags"] = frame_flags(msg) | (0 if msg.is_rx else FRAME_TX)
        row["dlc"] = msg.dlc
        row["length"] = len(data)
        row["data"][: len(data)] = np.frombuffer(data, dtype=np.uint8)
    return out


def messages_from_frames(frames: np.ndarray, channel: str | None = None) -> list[can.Message]:
    """The rows of ``frames`` (:data:`FRAME_DTYPE`) as :class:`can.Message` objects on ``channel``."""
    out = []
    for ts, can_id, flags, dlc, length, data in frames.tolist():
        out.append(message_of(can_id, bytearray(data[:length]), flags, ts, channel, dlc))
    return out


def load_of(frames: np.ndarray) -> BusLoadCounter:
    """The frames and bits of ``frames`` as :meth:`BusLoadCounter.add` counts them one by one
    (error frames ignored, CAN FD frames only counted)."""
    classic, nominal, worst = frame_bits(frames)
    fd = (frames["flags"] & (FRAME_ERR | FRAME_FD)) == FRAME_FD
    return BusLoadCounter(int(classic.sum()), int(nominal.sum()), int(worst.sum()), int(fd.sum()))


def recv_waiting(bus: can.BusABC, timeout: float | None) -> list[can.Message]:
    """:meth:`can.BusABC.recv` waiting up to ``timeout`` s for the first frame, then every frame
    already waiting that the bus's filters pass, in order (none waits: ``timeout`` 0 takes only
    what is there).

    python-can's own ``recv`` filters in software where the transport does not (``virtual``,
    ``udp_multicast``) and, asked not to wait, gives up at the first frame its filters drop, as if
    nothing were left; for a bus with that ``recv`` the waiting frames are taken from its
    ``_recv_internal`` (python-can's interface for implementers) until it has none, each filtered
    as ``recv`` filters it.
    """
    take = _waiting_frame(bus)
    msgs = []
    msg = take() if timeout is not None and timeout <= 0 else bus.recv(timeout)
    while msg is not None:
        msgs.append(msg)
        msg = take()
    return msgs


def _waiting_frame(bus: can.BusABC) -> Callable[[], can.Message | None]:
    """The next frame waiting on ``bus`` that its filters pass, without waiting (None: none)."""
    if getattr(type(bus), "recv", None) is not can.BusABC.recv:
        return lambda: bus.recv(0)  # the bus's own recv decides

    def take() -> can.Message | None:
        while True:
            msg, already_filtered = bus._recv_internal(timeout=0.0)
            if msg is None:
                return None
            if already_filtered or bus._matches_filters(msg):
                return msg

    return take


#: (nominal, worst-case) bits of a classic frame by [extended, data bytes]
_BITS = np.array([[bits_lookup(n, ext) for n in range(9)] for ext in (False, True)], dtype=np.int64)


def frame_bits(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(classic, nominal bits, worst-case bits) of every row of ``frames``: ``classic`` is False for
    error and CAN FD frames, whose bits are 0 (not modelled, as in :mod:`bus.busload`)."""
    flags = frames["flags"]
    classic = (flags & (FRAME_ERR | FRAME_FD)) == 0
    n = np.where(flags & FRAME_RTR, 0, np.minimum(frames["length"], 8))
    bits = _BITS[(flags & FRAME_EXT).astype(bool).astype(np.intp), n]
    nominal = np.where(classic, bits[:, 0], 0)
    worst = np.where(classic, bits[:, 1], 0)
    return classic, nominal, worst


def exact_standard_ids(filters: can.typechecking.CanFilters | None) -> frozenset[int] | None:
    """The identifiers ``filters`` pass when every filter is one standard-frame identifier (mask
    0x7FF, ``extended`` False): a frame passes python-can's test (``BusABC._matches_filters``) iff
    it is a standard frame whose ``arbitration_id & 0x7FF`` is in the set.  None: other filters
    (or none)."""
    if not filters:
        return None
    ids = set()
    for f in filters:
        if f.get("extended", None) is not False or f["can_mask"] != 0x7FF:
            return None
        ids.add(f["can_id"] & 0x7FF)
    return frozenset(ids)
