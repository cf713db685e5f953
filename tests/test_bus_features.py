"""bus.bus_features on python-can's own buses: every waiting frame the filters pass is taken, past
the frames the filters drop (python-can's software filtering, ``virtual`` and ``udp_multicast``)."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import pytest

from bus.bus_features import BatchReceiver, batch_receiver, exact_standard_ids, recv_waiting

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
