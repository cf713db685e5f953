"""io-channel frame layouts and codecs (plant ↔ drives), classic CAN, 11-bit IDs.

This module owns the frames of the ``io`` channel, which stands in for the encoder cable
and the power stage (docs/architecture.md §1). Lockstep, the plant is the
clock master; per tick ``n`` (architecture.md "Time and one trial"):

1. plant → drive j: :func:`encode_encoder` (one frame per joint);
2. drive j → plant: :func:`encode_torque`;
3. trial start/stop: :func:`encode_control` (plant → all drives).

==================  ==============  ====  ===============================================
frame               COB-ID          DLC   layout (little-endian)
==================  ==============  ====  ===============================================
control (plant)     0x010           7     u8 command, u16 tick, u32 n_ticks
encoder (plant→j)   0x101 + j       6     i32 position [counts], u16 tick
torque (j→plant)    0x181 + j       7     i32 torque [µN·m], u16 tick, u8 status bits
==================  ==============  ====  ===============================================

``j`` = joint index 0..3 (drive node id j + 1). The control frame has the highest priority.

Tick counter
    Every frame carries the low 16 bits of the tick number (``TICK_MODULUS`` = 2**16).
    :func:`tick_diff` is the signed modular difference in [−2**15, 2**15). A stream of
    frames from one source must carry consecutive ticks; :class:`TickTracker` follows one
    such stream and raises :class:`TickError` with the kind ``MISSING`` (frames skipped),
    ``DUPLICATE`` (the last tick again) or ``STALE`` (an older tick). :func:`check_tick`
    compares one frame with the tick the receiver is waiting for.

Deadlines
    The plant waits at most :data:`TICK_TIMEOUT_S` for the four torque frames of a tick
    (:data:`FIRST_TICK_TIMEOUT_S` for tick 0), both × ``ILCRIG_TIMEOUT_SCALE``: a frame later
    than that is *late* — the trial faults at that tick and the late frame, when it comes, is
    recognised as stale. A frame delayed less is absorbed by the lockstep (no fault, no change
    in the traces).
"""

from __future__ import annotations

import enum
import logging
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import can
import numpy as np

from bus.errors import IlcrigError
from bus.fastmsg import new_message
from bus.units import INT32_MAX, INT32_MIN

logger = logging.getLogger(__name__)

N_JOINTS: int = 4
CONTROL_COB_ID: int = 0x010
ENCODER_COB_BASE: int = 0x101
TORQUE_COB_BASE: int = 0x181

#: longest wait of the plant for the torque frames of one tick, s (× ILCRIG_TIMEOUT_SCALE)
TICK_TIMEOUT_S: float = 1.0
#: the same for tick 0 of a trial, s (× ILCRIG_TIMEOUT_SCALE)
FIRST_TICK_TIMEOUT_S: float = 2.0

TICK_BITS: int = 16
TICK_MODULUS: int = 1 << TICK_BITS
TICK_MASK: int = TICK_MODULUS - 1
_TICK_HALF: int = TICK_MODULUS >> 1

_ENCODER = struct.Struct("<iH")
#: data bytes of an encoder frame (int32 count, uint16 wire tick)
ENCODER_LEN: int = _ENCODER.size
_TORQUE = struct.Struct("<iHB")
_CONTROL = struct.Struct("<BHI")


class IoFrameError(IlcrigError, ValueError):
    """An io frame is malformed (wrong ID, length) or a value does not fit its field."""


class TickErrorKind(enum.Enum):
    MISSING = "missing"
    DUPLICATE = "duplicate"
    STALE = "stale"


class TickError(IoFrameError):
    """A frame's tick counter is not the expected one.

    :ivar kind: :class:`TickErrorKind`
    :ivar expected: the full tick number the receiver expected
    :ivar received: the 16-bit tick counter in the frame
    :ivar diff: ``tick_diff(received, expected)`` (> 0: frames missing, < 0: old frame)
    """

    def __init__(self, kind: TickErrorKind, expected: int, received: int, source: str = "") -> None:
        self.kind = kind
        self.expected = expected
        self.received = received
        self.diff = tick_diff(received, expected)
        what = {
            TickErrorKind.MISSING: f"{self.diff} frame(s) missing",
            TickErrorKind.DUPLICATE: "duplicate frame",
            TickErrorKind.STALE: f"stale frame ({-self.diff} ticks old)",
        }[kind]
        src = f" from {source}" if source else ""
        super().__init__(
            f"tick mismatch{src}: expected tick {expected} (wire {expected & TICK_MASK}), got wire {received}: {what}"
        )


class TorqueStatus(enum.IntFlag):
    """Status bits of the torque frame."""

    ENABLED = 0x01  #: CiA 402 "operation enabled": torque is applied
    FAULT = 0x02  #: drive in Fault / Fault reaction: the plant must apply zero torque
    SATURATED = 0x04  #: the command was clamped to the drive's torque limit this tick
    WARNING = 0x08  #: statusword warning bit


class IoControlCommand(enum.IntEnum):
    """The command of the io channel's control frame (plant → drives); not the CiA 402
    controlword commands (:class:`bus.objects.ControlCommand`)."""

    TRIAL_START = 1  #: a trial of ``n_ticks`` ticks starts at ``tick``
    TRIAL_STOP = 2  #: the trial ended (normally or aborted) at ``tick``


@dataclass(frozen=True)
class EncoderFrame:
    """Plant → drive ``joint``: encoder position at the start of tick ``tick``."""

    joint: int
    tick: int  #: 16-bit wire tick counter
    count: int  #: position, int32 counts


@dataclass(frozen=True)
class TorqueFrame:
    """Drive ``joint`` → plant: torque command for tick ``tick``."""

    joint: int
    tick: int  #: 16-bit wire tick counter
    torque_units: int  #: int32 µN·m
    status: TorqueStatus


@dataclass(frozen=True)
class ControlFrame:
    """Plant → drives: trial start/stop."""

    command: IoControlCommand
    tick: int  #: 16-bit wire tick counter
    n_ticks: int  #: trial length in ticks (u32)


IoFrame = EncoderFrame | TorqueFrame | ControlFrame


# -- tick counter -------------------------------------------------------------------------


def wire_tick(tick: int) -> int:
    """The 16-bit counter carried for full tick number ``tick`` (any int)."""
    return tick & TICK_MASK


def tick_diff(received: int, expected: int) -> int:
    """Signed modular difference ``received − expected`` in [−2**15, 2**15).

    Both arguments may be full tick numbers or wire counters.
    """
    return ((received - expected + _TICK_HALF) & TICK_MASK) - _TICK_HALF


def check_tick(received: int, expected: int, source: str = "") -> None:
    """Raise :class:`TickError` unless wire tick ``received`` is full tick ``expected``.

    ``diff > 0`` → MISSING (the sender is ahead), ``diff < 0`` → STALE (an old frame).
    """
    d = tick_diff(received, expected)
    if d:
        raise TickError(TickErrorKind.MISSING if d > 0 else TickErrorKind.STALE, expected, received, source)


class TickTracker:
    """Follows one frame stream that must carry consecutive ticks.

    :param next_tick: full tick number the first frame must carry
    :param source: name used in error messages (e.g. ``"torque joint 2"``)
    """

    def __init__(self, next_tick: int = 0, source: str = "") -> None:
        self.next_tick = next_tick
        self.source = source

    def reset(self, next_tick: int = 0) -> None:
        """Start over (new trial) expecting ``next_tick``."""
        self.next_tick = next_tick

    def accept(self, received: int) -> int:
        """Accept wire tick ``received`` and return its full tick number.

        :raises TickError: MISSING if ticks were skipped, DUPLICATE for the previous tick
            again, STALE for an older one; the tracker's state is unchanged then
        """
        d = tick_diff(received, self.next_tick)
        if d == 0:
            tick = self.next_tick
            self.next_tick += 1
            return tick
        if d > 0:
            kind = TickErrorKind.MISSING
        elif d == -1:
            kind = TickErrorKind.DUPLICATE
        else:
            kind = TickErrorKind.STALE
        raise TickError(kind, self.next_tick, received, self.source)


# -- codecs -------------------------------------------------------------------------------


def _check_joint(joint: int) -> None:
    if not 0 <= joint < N_JOINTS:
        raise IoFrameError(f"joint index must be 0..{N_JOINTS - 1}, got {joint}")


def _check_i32(value: int, what: str) -> None:
    if not INT32_MIN <= value <= INT32_MAX:
        raise IoFrameError(f"{what} {value} does not fit int32")


def encoder_cob_id(joint: int) -> int:
    """COB-ID of joint ``joint``'s encoder frame (0x101..0x104)."""
    _check_joint(joint)
    return ENCODER_COB_BASE + joint


def torque_cob_id(joint: int) -> int:
    """COB-ID of joint ``joint``'s torque frame (0x181..0x184)."""
    _check_joint(joint)
    return TORQUE_COB_BASE + joint


def encode_encoder(joint: int, tick: int, count: int) -> can.Message:
    """Encoder frame plant → drive ``joint``; ``tick`` is a full tick number (wrapped to 16 bits).

    :raises IoFrameError: bad joint index or count outside int32
    """
    _check_joint(joint)
    _check_i32(count, "encoder count")
    return new_message(ENCODER_COB_BASE + joint, bytearray(_ENCODER.pack(count, tick & TICK_MASK)))


def encoder_frames(tick: int, counts: Sequence[int]) -> list[tuple[int, bytes]]:
    """The encoder frames of one tick, joint 0 first, as (COB-ID, data) pairs
    (:class:`bus.bus_features.DataFrameSender`): the frames :func:`encode_encoder` gives.

    :raises IoFrameError: not one count per joint, or a count outside int32
    """
    if len(counts) != N_JOINTS:
        raise IoFrameError(f"one encoder count per joint expected, got {len(counts)}")
    wire = tick & TICK_MASK
    pack = _ENCODER.pack
    out = []
    for joint, count in enumerate(counts):
        if not INT32_MIN <= count <= INT32_MAX:
            _check_i32(count, "encoder count")
        out.append((ENCODER_COB_BASE + joint, pack(count, wire)))
    return out


def encode_torque(joint: int, tick: int, torque_units: int, status: TorqueStatus | int) -> can.Message:
    """Torque frame drive ``joint`` → plant.

    :raises IoFrameError: bad joint index, torque outside int32, status outside u8
    """
    _check_joint(joint)
    return new_message(TORQUE_COB_BASE + joint, bytearray(torque_data(tick, torque_units, status)))


def torque_data(tick: int, torque_units: int, status: TorqueStatus | int) -> bytes:
    """The data bytes of a torque frame (the frame of :func:`encode_torque` without a
    :class:`can.Message`: (:func:`torque_cob_id`, these) for :class:`bus.bus_features.DataFrameSender`).

    :raises IoFrameError: torque outside int32, status outside u8
    """
    _check_i32(torque_units, "torque")
    if not 0 <= int(status) <= 0xFF:
        raise IoFrameError(f"status {status} does not fit u8")
    return _TORQUE.pack(torque_units, tick & TICK_MASK, int(status))


def encode_control(command: IoControlCommand | int, tick: int, n_ticks: int = 0) -> can.Message:
    """Trial start/stop frame plant → all drives.

    :raises IoFrameError: unknown command or ``n_ticks`` outside u32
    """
    try:
        cmd = IoControlCommand(command)
    except ValueError as err:
        raise IoFrameError(f"unknown control command {command}") from err
    if not 0 <= n_ticks <= 0xFFFFFFFF:
        raise IoFrameError(f"n_ticks {n_ticks} does not fit u32")
    return new_message(CONTROL_COB_ID, bytearray(_CONTROL.pack(cmd, tick & TICK_MASK, n_ticks)))


def _payload(msg: can.Message, cob_base: int, n_ids: int, size: int, what: str) -> tuple[int, bytes]:
    joint = msg.arbitration_id - cob_base
    if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd or not 0 <= joint < n_ids:
        raise IoFrameError(f"not an {what} frame: {msg}")
    if len(msg.data) != size:
        raise IoFrameError(f"{what} frame must have {size} data bytes, got {len(msg.data)}")
    return joint, bytes(msg.data)


def _is_joint_frame(msg: can.Message, base: int, size: int) -> bool:
    """The per-tick paths' quick check: a classic standard data frame of ``size`` bytes from one of
    the joints' COB-IDs ``base`` … ``base + 3`` (when not, the full decoder says what is wrong)."""
    return (
        len(msg.data) == size
        and not (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd)
        and 0 <= msg.arbitration_id - base < N_JOINTS
    )


def decode_encoder(msg: can.Message) -> EncoderFrame:
    """:raises IoFrameError: not an encoder frame (ID, flags, length)"""
    joint, data = _payload(msg, ENCODER_COB_BASE, N_JOINTS, _ENCODER.size, "encoder")
    count, tick = _ENCODER.unpack(data)
    return EncoderFrame(joint, tick, count)


def encoder_fields(msg: can.Message) -> tuple[int, int]:
    """(count, wire tick) of an encoder frame: :func:`decode_encoder` without building a
    dataclass (the drives' per-tick path); the joint is the caller's (it filtered the COB-ID).

    :raises IoFrameError: not an encoder frame (ID, flags, length)
    """
    data = msg.data
    if not _is_joint_frame(msg, ENCODER_COB_BASE, 6):
        decode_encoder(msg)  # raises with the precise reason
    count, tick = _ENCODER.unpack(data)
    return count, tick


#: data bytes of a torque frame (int32 torque, uint16 wire tick, uint8 status)
TORQUE_LEN: int = _TORQUE.size
#: (torque µN·m, wire tick, status bits) of a torque frame's TORQUE_LEN data bytes (a frame the
#: caller checked: identifier and length, e.g. the transport that read it)
torque_data_fields: Callable[[bytes], tuple[int, int, int]] = _TORQUE.unpack
#: (count, wire tick) of an encoder frame's ENCODER_LEN data bytes (a frame the caller checked:
#: identifier and length, e.g. the transport that read it, :class:`bus.bus_features.FrameAnswerer`)
encoder_data_fields: Callable[[bytes], tuple[int, int]] = _ENCODER.unpack


def torque_fields(msg: can.Message) -> tuple[int, int, int]:
    """(torque µN·m, wire tick, status bits) of a torque frame: :func:`decode_torque` without
    building a dataclass (the plant's per-tick path).

    :raises IoFrameError: not a torque frame (ID, flags, length)
    """
    data = msg.data
    if not _is_joint_frame(msg, TORQUE_COB_BASE, 7):
        decode_torque(msg)  # raises with the precise reason
    torque, tick, status = _TORQUE.unpack(data)
    return torque, tick, status


def decode_torque(msg: can.Message) -> TorqueFrame:
    """:raises IoFrameError: not a torque frame (ID, flags, length)"""
    joint, data = _payload(msg, TORQUE_COB_BASE, N_JOINTS, _TORQUE.size, "torque")
    torque, tick, status = _TORQUE.unpack(data)
    return TorqueFrame(joint, tick, torque, TorqueStatus(status))


def decode_control(msg: can.Message) -> ControlFrame:
    """:raises IoFrameError: not a control frame or unknown command"""
    _, data = _payload(msg, CONTROL_COB_ID, 1, _CONTROL.size, "control")
    cmd, tick, n_ticks = _CONTROL.unpack(data)
    try:
        command = IoControlCommand(cmd)
    except ValueError as err:
        raise IoFrameError(f"unknown control command {cmd}") from err
    return ControlFrame(command, tick, n_ticks)


def decode_io(msg: can.Message) -> IoFrame:
    """Decode any io frame by its COB-ID.

    :raises IoFrameError: unknown COB-ID or malformed frame
    """
    cob = msg.arbitration_id
    if ENCODER_COB_BASE <= cob < ENCODER_COB_BASE + N_JOINTS:
        return decode_encoder(msg)
    if TORQUE_COB_BASE <= cob < TORQUE_COB_BASE + N_JOINTS:
        return decode_torque(msg)
    if cob == CONTROL_COB_ID:
        return decode_control(msg)
    raise IoFrameError(f"unknown io COB-ID 0x{cob:03X}")


class TrialTickFollower:
    """Follows the trials and ticks of the io channel from the plant's frames, for observers of
    the channel (the host's monitor, the hub's fault injector, the launcher's injector).

    :ivar trial: index of the current (or last) trial, counted from its TRIAL_START frames
        (−1 before the first)
    :ivar in_trial: between a TRIAL_START and its TRIAL_STOP
    :ivar ended: index of the last trial whose TRIAL_STOP was seen (−1 before the first): the
        explicit end-of-trial marker an observer waits for (every frame of trial ``k`` has been
        seen once ``ended >= k``)
    :ivar tick: the tick of the current trial that the last encoder frame carried (None before it)
    """

    def __init__(self) -> None:
        self.trial = -1
        self.ended = -1
        self.in_trial = False
        self.tick: int | None = None
        self.origin = 0

    def frame_tick(self, wire: int) -> int:
        """The tick within the current trial of a frame carrying wire tick ``wire``."""
        rel = (wire - self.origin) & TICK_MASK
        if self.tick is None:
            return rel
        return self.tick + tick_diff(rel, self.tick & TICK_MASK)

    def on_frame(self, can_id: int, data: bytes | bytearray) -> int | None:
        """Take one io frame into account; returns the tick it carries (None for others)."""
        if can_id == CONTROL_COB_ID and len(data) >= 3:
            wire = data[1] | data[2] << 8
            if data[0] == IoControlCommand.TRIAL_START:
                self.trial += 1
                self.origin, self.in_trial, self.tick = wire, True, None
            elif data[0] == IoControlCommand.TRIAL_STOP:
                self.in_trial = False
                self.ended = self.trial
            return None
        if ENCODER_COB_BASE <= can_id < ENCODER_COB_BASE + N_JOINTS and len(data) >= 6 and self.in_trial:
            self.tick = self.frame_tick(data[4] | data[5] << 8)
            return self.tick
        if TORQUE_COB_BASE <= can_id < TORQUE_COB_BASE + N_JOINTS and len(data) >= 6 and self.in_trial:
            return self.frame_tick(data[4] | data[5] << 8)
        return None

    def on_frame_array(self, can_ids: np.ndarray, data: np.ndarray, lengths: np.ndarray, valid: np.ndarray | None = None) -> None:
        """:meth:`on_frame` for many frames in order (identifiers, data rows, data lengths; rows
        where ``valid`` is False, e.g. error frames, are skipped), looking only at the control
        frames and the last encoder frame before each of them: the state afterwards is the same as
        frame by frame (a tick moves by less than half the 16-bit wire range between two of them)."""
        ids = np.asarray(can_ids)
        ok = np.ones(len(ids), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        control = np.flatnonzero(ok & (ids == CONTROL_COB_ID) & (lengths >= 3))
        encoder = ok & (ids >= ENCODER_COB_BASE) & (ids < ENCODER_COB_BASE + N_JOINTS) & (lengths >= 6)
        start = 0
        for stop in [*control.tolist(), len(ids)]:
            if self.in_trial:
                seg = np.flatnonzero(encoder[start:stop])
                if len(seg):
                    last = start + int(seg[-1])
                    self.on_frame(int(ids[last]), bytes(data[last, :8]))
            if stop < len(ids):
                self.on_frame(CONTROL_COB_ID, bytes(data[stop, : int(lengths[stop])]))
            start = stop + 1
