"""The hub's documented extras beyond python-can's BusABC (bus/bus_features.py) and the transport
behaviour the rig's speed relies on: several frames per write (send_batch) arrive as single frames
in order; frames read ahead wait in the client's queue and a select()-based caller finds them with
frames_pending; a bulk (passive) member gets every frame, later and in fewer writes, with the hub's
receive timestamps; a drive's io bus filters out the other joints' frames. Waits are for events
(frames, the hub's counters), never sleeps."""

from __future__ import annotations

import select
import time
from collections.abc import Callable

import can
import numpy as np
import pytest
from clock_util import wait_for

from bus import io_frames
from bus.bus_features import (
    FRAME_DTYPE,
    BatchReceiver,
    BatchSender,
    BufferedReceiver,
    FrameArrayReceiver,
    batch_receiver,
    batch_sender,
    frames_from_messages,
    load_of,
    messages_from_frames,
    pending_check,
)
from bus.busload import BusLoadCounter
from bus.transports.config import hub_transport
from bus.transports.hub.client import HubBus
from bus.transports.hub.process import start_hub

pytestmark = pytest.mark.usefixtures("hub_data_plane")


def wait_until(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """:func:`clock_util.wait_for`, by default for 5 s."""
    return wait_for(condition, timeout_s)


def frames(n: int, base: int = 0x100) -> list[can.Message]:
    return [can.Message(arbitration_id=base + i, is_extended_id=False, data=bytes([i, 0xAA])) for i in range(n)]


def test_send_batch_arrives_as_single_frames_in_order() -> None:
    with start_hub() as hub, HubBus(hub.channel("b")) as tx, HubBus(hub.channel("b")) as rx:
        assert isinstance(tx, BatchSender) and batch_sender(tx) == tx.send_batch
        tx.send_batch(frames(5))
        got = [rx.recv(2.0) for _ in range(5)]
        assert [(m.arbitration_id, bytes(m.data)) for m in got if m is not None] == [
            (0x100 + i, bytes([i, 0xAA])) for i in range(5)
        ]
        assert hub.stats()["b"].frames == 5


def test_send_batch_refuses_fd_frames_on_a_classic_bus_and_sends_nothing() -> None:
    with start_hub() as hub, HubBus(hub.channel("c"), fd=False) as tx, HubBus(hub.channel("c")) as rx:
        fd = can.Message(arbitration_id=1, is_extended_id=False, is_fd=True, data=bytes(12))
        with pytest.raises(can.CanOperationError):
            tx.send_batch([*frames(2), fd])
        tx.send(frames(1, 0x200)[0])
        msg = rx.recv(2.0)
        assert msg is not None and msg.arbitration_id == 0x200  # the refused batch sent nothing


def test_frames_read_ahead_are_pending_although_the_socket_is_not_readable() -> None:
    with start_hub() as hub, HubBus(hub.channel("p")) as tx, HubBus(hub.channel("p")) as rx:
        assert isinstance(rx, BufferedReceiver) and pending_check(rx) == rx.frames_pending
        tx.send_batch(frames(3))
        assert wait_until(lambda: bool(select.select([rx.fileno()], [], [], 0)[0]))
        first = rx.recv(0)  # one read takes all three records
        assert first is not None and first.arbitration_id == 0x100
        assert rx.frames_pending()
        assert not select.select([rx.fileno()], [], [], 0)[0]  # what select() cannot see
        rest = [rx.recv(0), rx.recv(0)]
        assert [m.arbitration_id for m in rest if m is not None] == [0x101, 0x102]
        assert not rx.frames_pending() and rx.recv(0) is None


def test_a_bus_without_the_extras_gets_the_plain_fallbacks() -> None:
    bus = can.Bus(interface="virtual", channel="extras-fallback")
    peer = can.Bus(interface="virtual", channel="extras-fallback")
    try:
        assert not isinstance(bus, BatchSender) and not isinstance(bus, BufferedReceiver)
        batch_sender(bus)(frames(2))
        assert [peer.recv(1.0).arbitration_id for _ in range(2)] == [0x100, 0x101]  # type: ignore[union-attr]
        assert pending_check(bus)() is False
    finally:
        bus.shutdown()
        peer.shutdown()


def test_bulk_member_gets_every_frame_with_the_hubs_timestamps() -> None:
    with (
        start_hub() as hub,
        HubBus(hub.channel("m")) as tx,
        HubBus(hub.channel("m"), bulk_delivery=True) as bulk,
        HubBus(hub.channel("m")) as live,
    ):
        assert bulk.bulk_delivery
        sent_at = []
        for msg in frames(40):
            sent_at.append(time.time())
            tx.send(msg)
        got_live = [live.recv(2.0) for _ in range(40)]
        got_bulk = [bulk.recv(2.0) for _ in range(40)]
        assert [m.arbitration_id for m in got_bulk if m is not None] == [0x100 + i for i in range(40)]
        assert [m.timestamp for m in got_bulk if m is not None] == [m.timestamp for m in got_live if m is not None]
        assert all(m is not None and m.timestamp >= t for m, t in zip(got_bulk, sent_at, strict=True))


def test_passive_open_asks_the_hub_for_bulk_delivery() -> None:
    with start_hub() as hub:
        t = hub_transport(hub.address)
        passive, active = t.open("io", passive=True), t.open("io")
        try:
            assert isinstance(passive, HubBus) and passive.bulk_delivery
            assert isinstance(active, HubBus) and not active.bulk_delivery
        finally:
            passive.shutdown()
            active.shutdown()


def test_drive_io_bus_gets_only_its_encoder_and_the_control_frames() -> None:
    """A DriveNode sets acceptance filters on its io bus: the hub forwards it this joint's encoder
    frame and the control frame only."""
    from firmware_model.drive import Drive
    from firmware_model.drive_node import DriveNode

    with start_hub() as hub:
        t = hub_transport(hub.address)
        fb, io, plant = t.open("fieldbus"), t.open("io"), t.open("io")
        try:
            DriveNode(Drive(2), fb, io, node_id=2)
            assert wait_until(lambda: hub.stats()["io"].clients == 2)
            plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 0, 5))
            plant.send_batch([io_frames.encode_encoder(j, 0, 10 * j) for j in range(4)])  # type: ignore[attr-defined]
            plant.send(io_frames.encode_torque(0, 0, 1, 0))
            plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, 1, 5))
            got = []
            while len(got) < 3 and (msg := io.recv(2.0)) is not None:
                got.append(msg.arbitration_id)
            assert got == [io_frames.CONTROL_COB_ID, io_frames.encoder_cob_id(1), io_frames.CONTROL_COB_ID]
            assert io.recv(0) is None  # the torque frame, sent before TRIAL_STOP, never came
        finally:
            for bus in (fb, io, plant):
                bus.shutdown()


def _mixed_frames() -> list[can.Message]:
    """Classic standard and extended data frames of every length, a remote frame and an FD frame."""
    out = [can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes(range(i % 9))) for i in range(20)]
    out.append(can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"\x01\x02"))
    out.append(can.Message(arbitration_id=0x123, is_extended_id=False, is_remote_frame=True, dlc=3))
    return out


def test_recv_frames_gives_the_same_frames_as_recv_without_messages() -> None:
    fd = can.Message(arbitration_id=0x55, is_extended_id=False, is_fd=True, bitrate_switch=True, data=bytes(range(20)))
    with start_hub() as hub, HubBus(hub.channel("f")) as tx, HubBus(hub.channel("f")) as rx, HubBus(hub.channel("f")) as ref:
        assert isinstance(rx, FrameArrayReceiver)
        for sent in (_mixed_frames(), [*_mixed_frames()[:3], fd, *_mixed_frames()[3:6]]):
            tx.send_batch(sent)
            want = [ref.recv(2.0) for _ in sent]
            got = rx.recv_frames(2.0)
            while len(got) < len(sent):
                more = rx.recv_frames(2.0)
                assert len(more)
                got = np.concatenate((got, more))
            expected = frames_from_messages([m for m in want if m is not None])
            assert expected.dtype == got.dtype == FRAME_DTYPE
            for name in FRAME_DTYPE.names or ():
                assert (got[name] == expected[name]).all(), name
            back = messages_from_frames(got, "x")
            assert [(m.arbitration_id, bytes(m.data), m.is_fd, m.is_remote_frame, m.dlc) for m in back] == [
                (m.arbitration_id, bytes(m.data), m.is_fd, m.is_remote_frame, m.dlc) for m in sent
            ]
        assert len(rx.recv_frames(0)) == 0


def test_recv_frames_takes_the_frames_already_read_ahead_first() -> None:
    with start_hub() as hub, HubBus(hub.channel("q")) as tx, HubBus(hub.channel("q")) as rx:
        tx.send_batch(frames(3))
        first = rx.recv(2.0)
        assert first is not None and rx.frames_pending()
        tx.send_batch(frames(2, 0x200))
        got = rx.recv_frames(2.0)
        while len(got) < 4:
            got = np.concatenate((got, rx.recv_frames(2.0)))
        assert got["arbitration_id"].tolist() == [0x101, 0x102, 0x200, 0x201]


def test_load_of_counts_as_the_counter_does_one_by_one() -> None:
    msgs = [
        *_mixed_frames(),
        can.Message(arbitration_id=1, is_fd=True, data=bytes(12)),
        can.Message(arbitration_id=2, is_error_frame=True),
    ]
    one_by_one = BusLoadCounter()
    for m in msgs:
        one_by_one.add(m)
    assert load_of(frames_from_messages(msgs)) == one_by_one


def test_recv_batch_takes_every_frame_of_one_read_and_filters_in_software_too() -> None:
    with start_hub() as hub, HubBus(hub.channel("r")) as tx, HubBus(hub.channel("r")) as rx:
        assert isinstance(rx, BatchReceiver) and batch_receiver(rx) == rx.recv_batch
        assert rx.recv_batch() == []  # nothing waiting: no wait
        tx.send_batch(frames(3))
        assert wait_until(lambda: bool(select.select([rx.fileno()], [], [], 0)[0]))
        assert [m.arbitration_id for m in rx.recv_batch()] == [0x100, 0x101, 0x102]
        assert not rx.frames_pending() and rx.recv_batch() == []
        tx.send_batch(frames(3))
        first = rx.recv(2.0)  # the rest waits in the queue, read before the new filters
        assert first is not None
        rx.set_filters([{"can_id": 0x102, "can_mask": 0x7FF, "extended": False}])
        assert [m.arbitration_id for m in rx.recv_batch()] == [0x102]


def test_batch_receiver_of_a_plain_bus_reads_until_nothing_is_left() -> None:
    bus = can.Bus(interface="virtual", channel="batch-fallback")
    peer = can.Bus(interface="virtual", channel="batch-fallback")
    try:
        assert not isinstance(bus, BatchReceiver)
        for msg in frames(2):
            peer.send(msg)
        assert [m.arbitration_id for m in batch_receiver(bus)()] == [0x100, 0x101]
        assert batch_receiver(bus)() == []
    finally:
        bus.shutdown()
        peer.shutdown()
