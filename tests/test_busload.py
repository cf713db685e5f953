"""bus.busload: bit lengths against docs/canopen-objects.md §9, counters, listener."""

from __future__ import annotations

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus.busload import (
    BusLoadCounter,
    BusLoadListener,
    FrameLengthError,
    frame_bits,
    frame_bits_worst_case,
    max_frames_per_s,
    message_bits,
    stuff_bits_worst_case,
)

# docs/canopen-objects.md §9 table: n bytes -> (bits no stuffing, worst case), 11-bit ID; n = 3, 5, 7
# are not in the table and were computed by hand from 47 + 8n and ⌊(34 + 8n − 1)/4⌋.
STD_TABLE = {
    0: (47, 55),
    1: (55, 65),
    2: (63, 75),
    3: (71, 85),
    4: (79, 95),
    5: (87, 105),
    6: (95, 115),
    7: (103, 125),
    8: (111, 135),
}
# docs/canopen-objects.md §9 "max frames/s at 1 Mbit/s" row: (no stuffing, worst case)
MAX_FRAMES = {
    0: (21_276, 18_181),
    1: (18_181, 15_384),
    2: (15_873, 13_333),
    4: (12_658, 10_526),
    6: (10_526, 8_695),
    8: (9_009, 7_407),
}


@pytest.mark.parametrize("n", range(9))
def test_standard_id_bits_match_canopen_table(n: int) -> None:
    assert (frame_bits(n), frame_bits_worst_case(n)) == STD_TABLE[n]


@pytest.mark.parametrize("n", sorted(MAX_FRAMES))
def test_max_frames_per_s_match_canopen_table(n: int) -> None:
    assert (max_frames_per_s(n, worst_case=False), max_frames_per_s(n)) == MAX_FRAMES[n]


def test_extended_id_eight_bytes_is_131_to_160_bits() -> None:
    assert frame_bits(8, extended=True) == 131
    assert frame_bits_worst_case(8, extended=True) == 160
    assert frame_bits(0, extended=True) == 67
    assert stuff_bits_worst_case(0, extended=True) == (54 - 1) // 4


@given(st.integers(0, 8), st.booleans())
def test_formula(n: int, ext: bool) -> None:
    base, g = (67, 54) if ext else (47, 34)
    assert frame_bits(n, ext) == base + 8 * n
    assert frame_bits_worst_case(n, ext) == base + 8 * n + (g + 8 * n - 1) // 4


@pytest.mark.parametrize("n", [-1, 9, 64])
def test_bad_length_rejected(n: int) -> None:
    with pytest.raises(FrameLengthError, match="0..8"):
        frame_bits(n)
    with pytest.raises(ValueError):
        BusLoadCounter().add_frame(n)


def test_remote_frame_has_no_data_field() -> None:
    msg = can.Message(arbitration_id=0x701, is_extended_id=False, is_remote_frame=True, dlc=8)
    assert message_bits(msg) == (47, 55)


def test_counter_and_load_percent() -> None:
    c = BusLoadCounter()
    # one lockstep tick of the paper's cycle: SYNC (0 B) + 4 TPDO (8 B): 491–595 bits
    c.add(can.Message(arbitration_id=0x80, is_extended_id=False, data=b""))
    for j in range(4):
        c.add(can.Message(arbitration_id=0x181 + j, is_extended_id=False, data=bytes(8)))
    assert (c.frames, c.bits, c.bits_worst_case) == (5, 491, 595)
    # 1000 such ticks in 1 s at 1 Mbit/s → 49.1 % / 59.5 % (docs/canopen-objects.md §9: 49–60 %)
    scaled = BusLoadCounter(c.frames * 1000, c.bits * 1000, c.bits_worst_case * 1000)
    assert scaled.load_percent(1.0) == pytest.approx(59.5)
    assert scaled.load_percent(1.0, worst_case=False) == pytest.approx(49.1)
    assert scaled.load_percent(2.0, bitrate=500_000) == pytest.approx(59.5)
    with pytest.raises(ValueError):
        c.load_percent(0.0)


def test_fd_and_error_frames_not_counted_as_bits() -> None:
    c = BusLoadCounter()
    c.add(can.Message(arbitration_id=1, data=bytes(12), is_fd=True))
    c.add(can.Message(is_error_frame=True))
    assert c.as_dict() == {"frames": 0, "bits": 0, "bits_worst_case": 0, "fd_frames": 1}
    with pytest.raises(FrameLengthError):
        message_bits(can.Message(arbitration_id=1, data=bytes(12), is_fd=True))


def test_merge_and_reset() -> None:
    a, b = BusLoadCounter(), BusLoadCounter()
    a.add_frame(8)
    b.add_frame(0, extended=True)
    a.merge(b)
    assert (a.frames, a.bits, a.bits_worst_case) == (2, 111 + 67, 135 + 67 + 13)
    a.reset()
    assert a.as_dict()["frames"] == 0


def test_listener_counts_via_notifier() -> None:
    with can.Bus(interface="virtual", channel="busload-test") as tx, can.Bus(interface="virtual", channel="busload-test") as rx:
        listener = BusLoadListener()
        for i in range(10):
            tx.send(can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes(i % 9)))
        for _ in range(10):
            msg = rx.recv(1.0)
            assert msg is not None
            listener(msg)
    assert listener.counter.frames == 10
    assert listener.counter.bits == sum(frame_bits(i % 9) for i in range(10))
