"""bus.io_frames: codec round trips, exact bytes, tick-counter logic."""

from __future__ import annotations

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus.io_frames import (
    TICK_MODULUS,
    ControlFrame,
    EncoderFrame,
    IoControlCommand,
    IoFrameError,
    TickError,
    TickErrorKind,
    TickTracker,
    TorqueFrame,
    TorqueStatus,
    check_tick,
    decode_control,
    decode_encoder,
    decode_io,
    decode_torque,
    encode_control,
    encode_encoder,
    encode_torque,
    encoder_cob_id,
    tick_diff,
    torque_cob_id,
    wire_tick,
)

joints = st.integers(0, 3)
ticks = st.integers(0, 10**9)
i32 = st.integers(-(2**31), 2**31 - 1)


def test_encoder_frame_bytes() -> None:
    msg = encode_encoder(2, 0x1_2345, -2)
    assert msg.arbitration_id == 0x103 and not msg.is_extended_id
    assert msg.dlc == 6
    assert bytes(msg.data) == bytes.fromhex("feffffff4523")


def test_torque_frame_bytes() -> None:
    msg = encode_torque(0, 7, 1_500_000, TorqueStatus.ENABLED | TorqueStatus.SATURATED)
    assert msg.arbitration_id == 0x181 and msg.dlc == 7
    assert bytes(msg.data) == bytes.fromhex("60e31600070005")


def test_control_frame_bytes() -> None:
    msg = encode_control(IoControlCommand.TRIAL_START, 0, 3001)
    assert msg.arbitration_id == 0x010 and msg.dlc == 7
    assert bytes(msg.data) == bytes.fromhex("010000b90b0000")


def test_cob_ids() -> None:
    assert [encoder_cob_id(j) for j in range(4)] == [0x101, 0x102, 0x103, 0x104]
    assert [torque_cob_id(j) for j in range(4)] == [0x181, 0x182, 0x183, 0x184]
    with pytest.raises(IoFrameError):
        encoder_cob_id(4)


@given(joints, ticks, i32)
def test_encoder_round_trip(joint: int, tick: int, count: int) -> None:
    msg = encode_encoder(joint, tick, count)
    assert len(msg.data) <= 8
    assert decode_encoder(msg) == EncoderFrame(joint, tick % TICK_MODULUS, count)
    assert decode_io(msg) == decode_encoder(msg)


@given(joints, ticks, i32, st.integers(0, 15))
def test_torque_round_trip(joint: int, tick: int, torque: int, status: int) -> None:
    msg = encode_torque(joint, tick, torque, status)
    frame = decode_io(msg)
    assert frame == TorqueFrame(joint, tick % TICK_MODULUS, torque, TorqueStatus(status))
    assert isinstance(frame, TorqueFrame) and frame.status & TorqueStatus.FAULT == status & 2


@given(st.sampled_from(list(IoControlCommand)), ticks, st.integers(0, 2**32 - 1))
def test_control_round_trip(cmd: IoControlCommand, tick: int, n: int) -> None:
    assert decode_io(encode_control(cmd, tick, n)) == ControlFrame(cmd, tick % TICK_MODULUS, n)


@pytest.mark.parametrize(
    "call",
    [
        lambda: encode_encoder(0, 0, 2**31),
        lambda: encode_encoder(-1, 0, 0),
        lambda: encode_torque(0, 0, -(2**31) - 1, 0),
        lambda: encode_torque(0, 0, 0, 256),
        lambda: encode_control(9, 0, 0),
        lambda: encode_control(1, 0, -1),
    ],
)
def test_encode_rejects_bad_values(call) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(IoFrameError):
        call()


@pytest.mark.parametrize(
    "msg",
    [
        can.Message(arbitration_id=0x105, is_extended_id=False, data=bytes(6)),  # joint 4
        can.Message(arbitration_id=0x101, is_extended_id=False, data=bytes(5)),  # short
        can.Message(arbitration_id=0x101, is_extended_id=True, data=bytes(6)),  # 29-bit
        can.Message(arbitration_id=0x011, is_extended_id=False, data=bytes(7)),  # not control
        can.Message(arbitration_id=0x010, is_extended_id=False, data=b"\x07" + bytes(6)),  # cmd 7
        can.Message(arbitration_id=0x700, is_extended_id=False, data=b"\x05"),  # heartbeat
    ],
)
def test_decode_rejects_foreign_frames(msg: can.Message) -> None:
    with pytest.raises(IoFrameError):
        decode_io(msg)


def test_decoders_check_their_own_id() -> None:
    enc = encode_encoder(0, 0, 0)
    with pytest.raises(IoFrameError):
        decode_torque(enc)
    with pytest.raises(IoFrameError):
        decode_control(enc)


# -- tick counter -------------------------------------------------------------------------


@given(ticks, st.integers(-(2**15), 2**15 - 1))
def test_tick_diff_is_modular_signed_difference(expected: int, d: int) -> None:
    received = wire_tick(expected + d)
    assert tick_diff(received, expected) == d
    assert tick_diff(received, wire_tick(expected)) == d


def test_tick_diff_wraps_at_16_bits() -> None:
    assert tick_diff(0, 0xFFFF) == 1
    assert tick_diff(0xFFFF, 0) == -1
    assert tick_diff(0x8000, 0) == -0x8000


@given(st.integers(0, 2**20), st.integers(1, 300))
def test_tracker_accepts_consecutive_ticks_across_wrap(start: int, n: int) -> None:
    tr = TickTracker(start)
    for k in range(n):
        assert tr.accept(wire_tick(start + k)) == start + k
    assert tr.next_tick == start + n


@given(st.integers(0, 2**20), st.integers(1, 1000))
def test_tracker_detects_missing(start: int, skipped: int) -> None:
    tr = TickTracker(start, source="torque joint 1")
    with pytest.raises(TickError) as info:
        tr.accept(wire_tick(start + skipped))
    err = info.value
    assert err.kind is TickErrorKind.MISSING and err.diff == skipped
    assert err.expected == start and "torque joint 1" in str(err)
    assert tr.next_tick == start  # state unchanged; the stream is still usable
    assert tr.accept(wire_tick(start)) == start


@given(st.integers(1, 2**20))
def test_tracker_detects_duplicate(start: int) -> None:
    tr = TickTracker(start - 1)
    tr.accept(wire_tick(start - 1))
    with pytest.raises(TickError) as info:
        tr.accept(wire_tick(start - 1))
    assert info.value.kind is TickErrorKind.DUPLICATE


@given(st.integers(2**16, 2**20), st.integers(2, 2**15))
def test_tracker_detects_stale(start: int, age: int) -> None:
    tr = TickTracker(start)
    with pytest.raises(TickError) as info:
        tr.accept(wire_tick(start - age))
    assert info.value.kind is TickErrorKind.STALE and info.value.diff == -age


def test_tracker_reset_for_new_trial() -> None:
    tr = TickTracker()
    for k in range(5):
        tr.accept(k)
    tr.reset(0)
    assert tr.accept(0) == 0


@given(ticks, st.integers(-(2**15), 2**15 - 1))
def test_check_tick(expected: int, d: int) -> None:
    if d == 0:
        check_tick(wire_tick(expected), expected)
        return
    with pytest.raises(TickError) as info:
        check_tick(wire_tick(expected + d), expected)
    assert info.value.kind is (TickErrorKind.MISSING if d > 0 else TickErrorKind.STALE)
    assert isinstance(info.value, ValueError)


@given(
    st.integers(0, TICK_MODULUS - 1),
    st.lists(st.integers(1, 300), min_size=1, max_size=4),
    st.integers(0, 3),
    st.integers(0, 2**32 - 1),
)
def test_follower_on_arrays_equals_frame_by_frame(origin: int, trial_lengths: list[int], cut: int, seed: int) -> None:
    """The host's io monitor reads frames as arrays: TrialTickFollower.on_frame_array ends in the
    same state as on_frame per frame, however the stream is cut into rounds (an error frame and a
    trial stopped early included)."""
    import random

    from bus.bus_features import FRAME_ERR, frames_from_messages
    from bus.io_frames import TrialTickFollower

    rng = random.Random(seed)
    msgs: list[can.Message] = []
    wire = origin
    for n in trial_lengths:
        msgs.append(encode_control(IoControlCommand.TRIAL_START, wire, n))
        ran = rng.randint(1, n)  # a fault may stop it early
        for k in range(ran):
            for j in range(4):
                msgs.append(encode_encoder(j, wire + k, 1000 * j + k))
            if k == ran // 2:
                msgs.append(can.Message(is_error_frame=True, arbitration_id=0, data=b""))
            for j in range(4):
                msgs.append(encode_torque(j, wire + k, -k, TorqueStatus.ENABLED))
        msgs.append(encode_control(IoControlCommand.TRIAL_STOP, wire + ran))
        wire = (wire + n + 7) % TICK_MODULUS
        if rng.random() < 0.5:
            break
    one = TrialTickFollower()
    for m in msgs:
        if not m.is_error_frame:
            one.on_frame(m.arbitration_id, m.data)
    frames = frames_from_messages(msgs)
    bounds = sorted({0, len(frames), *(rng.randrange(len(frames) + 1) for _ in range(cut))})
    arr = TrialTickFollower()
    for a, b in zip(bounds, bounds[1:]):
        f = frames[a:b]
        arr.on_frame_array(f["arbitration_id"], f["data"], f["length"], (f["flags"] & FRAME_ERR) == 0)
    assert (arr.trial, arr.ended, arr.in_trial, arr.tick, arr.origin) == (
        one.trial,
        one.ended,
        one.in_trial,
        one.tick,
        one.origin,
    )
