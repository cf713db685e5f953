"""The hub's bus-time delivery (``--bus-time BUS=BIT_S``): frames wait in their sender's transmit
queue, win the free bus in arbitration order and are delivered after their bit time, stamped with
the end of their transmission on a virtual clock.  The order and the stamps are exact, whatever the
machine's speed: the tests read them from the received frames (they wait for frames, never sleep)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus.busload import bits_lookup
from bus.transports.hub.bus_time import arbitration_key, bit_time_ns, parse_bus_time
from bus.transports.hub.client import HubBus
from bus.transports.hub.process import start_hub
from bus.transports.hub.server import HubServer
from bus.transports.hub.wire import FLAG_EXT, FLAG_FD, FLAG_RTR

pytestmark = pytest.mark.multiprocess


def std(can_id: int, n: int = 2, remote: bool = False) -> can.Message:
    return can.Message(
        arbitration_id=can_id, is_extended_id=False, data=b"" if remote else bytes(range(n)), is_remote_frame=remote, dlc=n
    )


def bit_s(msg: can.Message, bitrate: int) -> float:
    """Bit time of ``msg`` at ``bitrate`` (worst-case stuffing, intermission included), s."""
    n = 0 if msg.is_remote_frame else len(msg.data)
    return bits_lookup(n, msg.is_extended_id)[1] / bitrate


def recv_n(bus: can.BusABC, n: int, timeout_s: float = 10.0) -> list[can.Message]:
    out = []
    for _ in range(n):
        m = bus.recv(timeout_s)
        assert m is not None, f"only {len(out)} of {n} frames arrived"
        out.append(m)
    return out


@given(st.integers(0, 0x7FF), st.integers(0, 0x7FF), st.booleans(), st.booleans())
def test_arbitration_key_orders_like_the_wire(a: int, b: int, a_rtr: bool, b_rtr: bool) -> None:
    """Lower base identifier wins; with the same base, a standard frame beats an extended one and a
    data frame beats a remote one (a dominant bit wins the first place the frames differ)."""
    fa = FLAG_RTR if a_rtr else 0
    fb = FLAG_RTR if b_rtr else 0
    assert (arbitration_key(a, fa) < arbitration_key(b, fb)) == ((a, a_rtr) < (b, b_rtr))
    assert arbitration_key(a, fa) < arbitration_key((a << 18) | 0x3FFFF, FLAG_EXT)
    assert arbitration_key((a << 18) | 5, FLAG_EXT) < arbitration_key((a << 18) | 6, FLAG_EXT)


@given(st.integers(0, 8), st.booleans(), st.sampled_from([10_000, 125_000, 500_000, 1_000_000, 833_333]))
def test_bit_time_is_the_worst_case_frame_length_at_the_rate(n: int, ext: bool, rate: int) -> None:
    bits = bits_lookup(n, ext)[1]
    assert abs(bit_time_ns(n, FLAG_EXT if ext else 0, rate) - bits * 1e9 / rate) <= 0.5
    assert bit_time_ns(n, FLAG_RTR, rate) == bit_time_ns(0, 0, rate)  # a remote frame carries no data
    assert bit_time_ns(n, FLAG_FD, rate) == 0  # CAN FD: not modelled


def test_bus_time_option_parsing() -> None:
    assert parse_bus_time(["io=500000", "fieldbus=1000000"]) == {"io": 500_000, "fieldbus": 1_000_000}
    for bad in ("io", "io=", "=5", "io=0", "io=-5", "io=1e6"):
        with pytest.raises(ValueError, match="BUS=BIT_S"):
            parse_bus_time([bad])
    with pytest.raises(ValueError, match="must be > 0"):
        HubServer(["unix:/nonexistent/x.sock"], bus_time={"io": 0})


def test_frames_waiting_for_a_busy_bus_go_in_arbitration_order_back_to_back() -> None:
    """While a long frame occupies a slow bus, three nodes queue 0x300, 0x100 and 0x200: the bus
    carries them lowest identifier first, each starting the moment the previous one ended."""
    rate = 500  # bit/s: the first frame occupies the bus for 270 ms, time enough for the others to queue
    with start_hub(bus_time={"b": rate}) as hub:
        buses = [HubBus(hub.channel("b")) for _ in range(5)]
        rx, a, b, c, d = buses
        try:
            a.send(std(0x700, 8))
            # the hub has read it (and put it on the free bus) before the others are sent
            deadline = time.monotonic() + 10.0
            while hub.stats()["b"].frames < 1 and time.monotonic() < deadline:
                pass
            for bus, cid in ((b, 0x300), (c, 0x100), (d, 0x200)):
                bus.send(std(cid))
            got = recv_n(rx, 4)
            assert [m.arbitration_id for m in got] == [0x700, 0x100, 0x200, 0x300]
            for prev, m in zip(got, got[1:]):
                assert m.timestamp - prev.timestamp == pytest.approx(bit_s(m, rate), abs=1e-6)
        finally:
            for bus in buses:
                bus.shutdown()


def test_one_nodes_frames_keep_their_order_and_the_bus_counts_them_as_sent() -> None:
    """A node's transmit queue is first in, first out: its 0x300 goes before its 0x100 (while
    another node's 0x200, queued later, waits for its turn by arbitration)."""
    rate = 1_000_000
    with start_hub(bus_time={"b": rate}) as hub, HubBus(hub.channel("b")) as rx, HubBus(hub.channel("b")) as a:
        a.send_batch([std(0x300, 8), std(0x100, 8), std(0x050, 0, remote=True)])
        got = recv_n(rx, 3)
        assert [(m.arbitration_id, m.is_remote_frame) for m in got] == [(0x300, False), (0x100, False), (0x050, True)]
        for prev, m in zip(got, got[1:]):
            assert m.timestamp - prev.timestamp == pytest.approx(bit_s(m, rate), abs=1e-6)
        assert hub.stats()["b"].frames == 3


def test_buses_without_a_rate_are_not_timed_and_echo_comes_when_the_frame_is_sent() -> None:
    with (
        start_hub(bus_time={"slow": 500}) as hub,
        HubBus(hub.channel("fast")) as f_rx,
        HubBus(hub.channel("fast")) as f_tx,
        HubBus(hub.channel("slow"), receive_own_messages=True) as s_tx,
    ):
        s_tx.send(std(0x123, 8))  # 270 ms on the slow bus
        f_tx.send(std(0x456))
        assert f_rx.recv(5.0).arbitration_id == 0x456  # type: ignore[union-attr]
        echo = s_tx.recv(5.0)
        assert echo is not None and echo.arbitration_id == 0x123 and not echo.is_rx


@pytest.fixture
def small_queue_hub(tmp_path: Path) -> Iterator[str]:
    """A hub in a thread of this process with a transmit queue of 8 frames per sender."""
    server = HubServer([f"unix:{tmp_path}/hub.sock"], bus_time={"b": 1_000_000})
    assert server.bus_time is not None
    server.bus_time.queue_frames = 8
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"{server.addresses[0]}#b"
    finally:
        server.wake()
        thread.join(5.0)
        server.close()


def test_a_sender_far_ahead_of_the_bus_is_held_back_and_loses_nothing(small_queue_hub: str) -> None:
    """200 frames in one write, 25 times the queue: the hub stops reading the sender until the bus
    has caught up; every frame arrives, in order, exactly one bit time after the previous one."""
    with HubBus(small_queue_hub) as rx, HubBus(small_queue_hub) as tx:
        sent = [std(0x100 + i % 0x600, i % 9) for i in range(200)]
        tx.send_batch(sent)
        got = recv_n(rx, 200)
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(m.arbitration_id, bytes(m.data)) for m in sent]
        for prev, m in zip(got, got[1:]):
            assert m.timestamp - prev.timestamp == pytest.approx(bit_s(m, 1_000_000), abs=1e-6)
