"""bus.bus_features on python-can's own buses: every waiting frame the filters pass is taken, past
the frames the filters drop (python-can's software filtering, ``virtual`` and ``udp_multicast``);
data frames sent as (identifier, data) pairs arrive as sent frames would, on a virtual bus and on
the hub."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bus.bus_features import (
    BatchReceiver,
    DataFrameSender,
    batch_receiver,
    data_frame_sender,
    exact_standard_ids,
    recv_waiting,
)
from bus.transports.hub.client import HubBus
from bus.transports.hub.process import start_hub
from bus.transports.hub.records import encode_data_frames, encode_record

_channels = itertools.count()


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """A sender and a receiver on a fresh virtual channel; the receiver accepts 0x100..0x10F."""
    channel = f"bus-features-{next(_channels)}"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel, can_filters=[{"can_id": 0x100, "can_mask": 0x7F0, "extended": False}])
    try:
        yield tx, rx
    finally:
        tx.shutdown()
        rx.shutdown()


def _send(bus: can.BusABC, ids: list[int]) -> None:
    for n, can_id in enumerate(ids):
        bus.send(can.Message(arbitration_id=can_id, is_extended_id=False, data=bytes([n])))


#: accepted and dropped frames interleaved, a dropped one first and last
_IDS = [0x200, 0x101, 0x300, 0x301, 0x102, 0x080, 0x103, 0x7FF]


def test_python_can_recv_gives_up_behind_a_dropped_frame(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """What recv_waiting must not do: python-can's recv(0) answers None at a dropped frame."""
    tx, rx = buses
    _send(tx, [0x200, 0x101])
    assert rx.recv(0) is None  # 0x101 is waiting
    assert rx.recv(0).arbitration_id == 0x101  # type: ignore[union-attr]


def test_recv_waiting_without_waiting_takes_every_accepted_frame(buses: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = buses
    _send(tx, _IDS)
    got = recv_waiting(rx, 0)
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x101, b"\x01"), (0x102, b"\x04"), (0x103, b"\x06")]
    assert recv_waiting(rx, 0) == []  # the dropped frames are gone too


def test_recv_waiting_waits_for_the_first_then_takes_the_rest(buses: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = buses
    _send(tx, _IDS)
    assert [m.arbitration_id for m in recv_waiting(rx, 5.0)] == [0x101, 0x102, 0x103]
    assert recv_waiting(rx, 0.01) == []


def test_batch_receiver_of_a_filtered_virtual_bus_drains_past_dropped_frames(buses: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = buses
    assert not isinstance(rx, BatchReceiver)
    take = batch_receiver(rx)
    _send(tx, _IDS)
    assert [m.arbitration_id for m in take()] == [0x101, 0x102, 0x103]
    _send(tx, [0x300] * 5 + [0x10F])
    assert [m.arbitration_id for m in take()] == [0x10F]
    assert take() == []


def test_recv_waiting_keeps_a_bus_with_its_own_recv() -> None:
    """A bus whose recv is not python-can's is asked through its recv."""

    class OwnRecv(can.BusABC):
        def __init__(self) -> None:
            super().__init__(channel="own")
            self.frames = [can.Message(arbitration_id=n) for n in (1, 2)]

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            raise NotImplementedError

        def recv(self, timeout: float | None = None) -> can.Message | None:
            return self.frames.pop(0) if self.frames else None

    bus = OwnRecv()
    assert [m.arbitration_id for m in recv_waiting(bus, 0)] == [1, 2]
    bus.shutdown()


@pytest.mark.parametrize(
    "filters",
    [
        [{"can_id": 0x080, "can_mask": 0x7FF, "extended": False}, {"can_id": 0x201, "can_mask": 0x7FF, "extended": False}],
        [{"can_id": 0x880, "can_mask": 0x7FF, "extended": False}],  # bits above the mask: compared under it
    ],
)
def test_exact_standard_ids_pass_what_python_can_passes(filters: can.typechecking.CanFilters) -> None:
    """The set of :func:`exact_standard_ids` passes exactly the frames python-can's own test passes."""
    ids = exact_standard_ids(filters)
    assert ids is not None
    bus = can.Bus(interface="virtual", channel=f"bus-features-{next(_channels)}", can_filters=filters)
    try:
        for arb, ext in itertools.product((0x000, 0x080, 0x880, 0x201, 0x202, 0x7FF, 0x10080, 0x1FFFFFFF), (False, True)):
            if not ext and arb > 0x7FF:
                continue
            msg = can.Message(arbitration_id=arb, is_extended_id=ext)
            assert (not ext and arb & 0x7FF in ids) == bus._matches_filters(msg), (hex(arb), ext)
    finally:
        bus.shutdown()


@pytest.mark.parametrize(
    "filters",
    [
        None,
        [],
        [{"can_id": 0x080, "can_mask": 0x7F0, "extended": False}],
        [{"can_id": 0x080, "can_mask": 0x7FF}],
        [{"can_id": 0x080, "can_mask": 0x7FF, "extended": True}],
        [{"can_id": 0x080, "can_mask": 0x7FF, "extended": False}, {"can_id": 0x100, "can_mask": 0x1FFFFFFF, "extended": False}],
    ],
)
def test_exact_standard_ids_none_for_other_filters(filters: can.typechecking.CanFilters | None) -> None:
    assert exact_standard_ids(filters) is None


_DATA_FRAMES = st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)), max_size=6)


@given(frames=_DATA_FRAMES)
@settings(max_examples=200, deadline=None)
def test_hub_data_frame_records_are_the_records_of_their_messages(frames: list[tuple[int, bytes]]) -> None:
    """DataFrameSender on the hub: the records packed from (identifier, data) are byte for byte the
    records of the same frames sent as can.Message."""
    msgs = [can.Message(arbitration_id=cob, data=data, is_extended_id=False) for cob, data in frames]
    assert encode_data_frames(frames) == b"".join(encode_record(m) for m in msgs)


@pytest.mark.parametrize("frame", [(0x800, b""), (-1, b"\x01"), (0x123, bytes(9))])
def test_a_frame_outside_the_contract_is_refused_and_nothing_is_sent(
    buses: tuple[can.BusABC, can.BusABC], frame: tuple[int, bytes]
) -> None:
    """Not a classic data frame with a standard identifier: ValueError, from the hub's packing and
    from the fallback of a bus without the extra, before anything goes out."""
    tx, rx = buses
    with pytest.raises(ValueError, match="not a classic data frame"):
        encode_data_frames([(0x101, b"\x01"), frame])
    with pytest.raises(ValueError, match="not a classic data frame"):
        data_frame_sender(tx)([(0x101, b"\x01"), frame])
    assert rx.recv(0) is None


def test_data_frames_reach_the_other_members_as_sent_frames_would(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """The fallback of a bus without the extra (python-can's virtual bus) and the hub client's own
    send_data_frames: the receivers get the frames in order, exactly as from send()."""
    frames = [(0x101, bytes([1, 2, 3, 4, 5, 6])), (0x102, b""), (0x103, bytes(range(8)))]
    tx, rx = buses
    assert not isinstance(tx, DataFrameSender)
    data_frame_sender(tx)(frames)
    got = [rx.recv(1.0) for _ in frames]
    assert [(m.arbitration_id, bytes(m.data), m.dlc, m.is_extended_id) for m in got if m is not None] == [
        (cob, data, len(data), False) for cob, data in frames
    ]
    with start_hub() as hub, HubBus(hub.channel("io")) as a, HubBus(hub.channel("io")) as b:
        assert isinstance(a, DataFrameSender) and data_frame_sender(a) == a.send_data_frames
        data_frame_sender(a)(frames)
        for cob, data in frames:
            a.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
        got = [b.recv(5.0) for _ in range(2 * len(frames))]
        keys = [(m.arbitration_id, bytes(m.data), m.dlc, m.is_extended_id, m.is_remote_frame) for m in got if m is not None]
        assert keys[: len(frames)] == keys[len(frames) :] == [(cob, data, len(data), False, False) for cob, data in frames]
