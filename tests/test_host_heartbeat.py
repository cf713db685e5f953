"""The host's heartbeat goes on while the host's interpreter is held (host/rig/host_heartbeat.py): on
the hub a thread of C writes it on a member of its own, under a lease the host's Python thread renews
every period; a held interpreter stops it only past the lease, and the trial loop holds the lease
while a law's code runs.  Each test holds the interpreter with one C call (``sum(range(n))``, the GIL
never let go) while a hub in a process of its own stamps every frame as it comes: the stamps say
what was written while this process's Python stood still.  A hub process per test (fast tier)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import can
import canopen
import pytest

from bus.cia301.nmt import HOST_NODE_ID, heartbeat_cob_id
from bus.transports.hub.client import NOTHING_IN, HubBus
from bus.transports.hub.core import HUB_CORE_ENV, core_built
from bus.transports.hub.process import HubHandle, start_hub
from host.rig.host_heartbeat import HostHeartbeat

pytestmark = [pytest.mark.multiprocess, pytest.mark.fast]

PERIOD_S = 0.1
HOST_BEAT = heartbeat_cob_id(HOST_NODE_ID)


@pytest.fixture
def hub(monkeypatch: pytest.MonkeyPatch) -> Iterator[HubHandle]:
    if not core_built():
        pytest.skip("the hub's C core is not built here (no C compiler at install): the heartbeat has no writer")
    monkeypatch.delenv(HUB_CORE_ENV, raising=False)
    with start_hub() as handle:
        yield handle


def _hold_interpreter(seconds: float) -> tuple[float, float]:
    """This process's interpreter held (the GIL never let go) in one call for at least ``seconds``;
    the wall times (``time.time()``, the hub's stamps' scale) before and after that call. The call is
    sized on the last one that was too short (a calibration on a busy machine can be too fast)."""
    n = 1_000_000
    while True:
        before = time.time()
        sum(range(n))  # one C call: no other thread of this process runs Python
        after = time.time()
        if after - before >= seconds:
            return before, after
        n = int(n * 1.3 * seconds / max(after - before, 1e-3))


def _beats_stamped(rx: HubBus, until_wall: float) -> list[float]:
    """The hub's stamps of the host's beats received on ``rx`` up to the first one after ``until_wall``."""
    stamps: list[float] = []
    while True:
        msg = rx.recv(timeout=10.0)
        assert msg is not None, "no heartbeat for 10 s"
        if msg.arbitration_id == HOST_BEAT:
            stamps.append(msg.timestamp)
            if msg.timestamp > until_wall:
                return stamps


@pytest.fixture
def producer(hub: HubHandle) -> Iterator[tuple[HostHeartbeat, HubBus]]:
    """A host heartbeat on the hub's ``fieldbus`` (lease 0.3 s) and a member that hears it."""
    network = canopen.Network(HubBus(hub.channel("fieldbus")))
    rx = HubBus(hub.channel("fieldbus"))
    beat = HostHeartbeat(network, PERIOD_S, own_bus=HubBus(hub.channel("fieldbus"), can_filters=NOTHING_IN), lease_s=0.3)
    beat.start()
    try:
        assert beat.in_c
        _beats_stamped(rx, 0.0)  # it beats
        yield beat, rx
    finally:
        beat.stop()
        rx.shutdown()
        network.bus.shutdown()


def test_the_beats_go_on_while_the_interpreter_is_held_within_the_lease(producer: tuple[HostHeartbeat, HubBus]) -> None:
    beat, rx = producer
    beat.hold(5.0)  # as the trial loop does while a law's code runs
    before, after = _hold_interpreter(1.5)
    inside = [t for t in _beats_stamped(rx, after) if before < t < after]
    assert len(inside) >= 5  # about 15 came; a Python thread would have sent none
    assert beat.take_gap(0.5) is None
    assert beat.error is None


def test_past_the_lease_a_held_interpreter_stops_the_beats(producer: tuple[HostHeartbeat, HubBus]) -> None:
    beat, rx = producer
    before, after = _hold_interpreter(1.5)
    gap = beat.take_gap(1.0)  # the lease (0.3 s) ran out while nothing renewed it: no beat until it was
    assert gap is not None and gap[0] > 1.0
    beat.hold(None)
    assert _beats_stamped(rx, time.time())  # and it beats again once renewed


def test_a_hub_gone_ends_the_writer_and_says_why(hub: HubHandle) -> None:
    network = canopen.Network(HubBus(hub.channel("fieldbus")))
    beat = HostHeartbeat(network, PERIOD_S, own_bus=HubBus(hub.channel("fieldbus"), can_filters=NOTHING_IN), lease_s=0.3)
    beat.start()
    try:
        hub.stop()
        beat.join(timeout=10.0)  # the thread ends once the writer has failed
        assert not beat.is_alive()
        assert beat.error is not None and "the heartbeat's writer" in beat.error
        assert beat.error_t is not None
    finally:
        beat.stop()
        network.bus.shutdown()


def test_a_member_with_a_writer_sends_nothing_else_and_stops_it_when_shut_down(hub: HubHandle) -> None:
    rx = HubBus(hub.channel("fieldbus"))
    bus = HubBus(hub.channel("fieldbus"), can_filters=NOTHING_IN)
    writer = bus.periodic_writer(can.Message(arbitration_id=HOST_BEAT, data=[5], is_extended_id=False), PERIOD_S)
    _beats_stamped(rx, 0.0)
    with pytest.raises(can.CanOperationError, match="periodic writer"):
        bus.send(can.Message(arbitration_id=0x123, data=[1], is_extended_id=False))
    with pytest.raises(can.CanOperationError, match="no periodic writer: one already"):
        bus.periodic_writer(can.Message(arbitration_id=HOST_BEAT, data=[5], is_extended_id=False), PERIOD_S)
    bus.shutdown()
    sent, _, _, failure, running = writer.state()
    assert sent >= 1 and failure is None and not running
    rx.shutdown()
