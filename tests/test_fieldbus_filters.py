"""Fieldbus acceptance filters of the slave nodes (bus/cia301/slave.py, firmware_model/drive_node.py).

A node accepts on the fieldbus only what it consumes — NMT, its SDO requests, the heartbeats it
watches (0x1016), and for a drive SYNC (0x1005) and its valid RPDOs — as a drive's CAN controller
filters in hardware. The transport applies the filters (the hub in either data plane, before the
frame reaches the process). They follow every SDO write and NMT reset, and are set before the SDO
response goes out: a master that moves an RPDO to a new COB-ID and uses it at once is never
filtered away. Waits are for SDO answers and frames, never sleeps.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from drive402_util import canopen_view
from hub_util import serving_in
from test_hub_extras import wait_until

from bus.cia301.nmt import NmtCommand
from bus.transports.hub.server import HubServer
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode

NODE = 2
HOST = 0x7F
PDO_NOT_VALID = 0x8000_0000


class RecordingDriveNode(DriveNode):
    """A drive node that notes the identifier of every fieldbus frame reaching its application
    hook (everything but NMT, its own SDO requests and heartbeats)."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        self.seen: list[int] = []
        super().__init__(*args, **kwargs)

    def on_fieldbus(self, msg: can.Message) -> None:
        self.seen.append(msg.arbitration_id)
        super().on_fieldbus(msg)


def test_a_drive_accepts_nmt_its_sdo_sync_its_valid_rpdos_and_watched_heartbeats() -> None:
    prefix = f"filters-{time.monotonic_ns()}"
    fb, io = can.Bus(interface="virtual", channel=f"{prefix}-fb"), can.Bus(interface="virtual", channel=f"{prefix}-io")
    try:
        drive = Drive(NODE)
        node = DriveNode(drive, fb, io)
        node.start()
        # the EDS defaults: every RPDO invalid, SYNC 0x080, no heartbeat consumed
        assert node.fieldbus_ids() == {0x000, 0x600 + NODE, 0x080}
        assert fb.filters == [{"can_id": c, "can_mask": 0x7FF, "extended": False} for c in (0x000, 0x080, 0x600 + NODE)]
        # what the SDO server writes is what the next filters hold
        drive.write_object(0x1400, 1, (0x200 + NODE).to_bytes(4, "little"))
        drive.write_object(0x1401, 1, (0x3A0).to_bytes(4, "little"))
        drive.write_object(0x1005, 0, (0x081).to_bytes(4, "little"))
        drive.write_object(0x1016, 1, ((HOST << 16) | 500).to_bytes(4, "little"))
        node._reload_consumers()
        assert node.fieldbus_ids() == {0x000, 0x600 + NODE, 0x081, 0x200 + NODE, 0x3A0, 0x700 + HOST}
        # an NMT reset communication restores the defaults, and the filters with them
        node._on_nmt(bytes([NmtCommand.RESET_COMMUNICATION, NODE]))
        assert fb.filters is not None
        assert {f["can_id"] for f in fb.filters} == set(node.fieldbus_ids()) == {0x000, 0x600 + NODE, 0x080}
    finally:
        fb.shutdown()
        io.shutdown()


def test_the_filters_change_before_the_sdo_response_goes_out() -> None:
    """The order on the bus: the new filters, then the response (on the hub both travel on the
    node's one stream, so the hub filters with the new set before the master has its answer)."""
    prefix = f"filters-order-{time.monotonic_ns()}"
    fb, io = can.Bus(interface="virtual", channel=f"{prefix}-fb"), can.Bus(interface="virtual", channel=f"{prefix}-io")
    try:
        node = DriveNode(Drive(NODE), fb, io)
        node.start()
        events: list[str] = []
        send, set_filters = fb.send, fb.set_filters
        fb.send = lambda msg, timeout=None: (
            events.append(f"send 0x{msg.arbitration_id:03X}"),  # type: ignore[method-assign]
            send(msg, timeout),
        )
        fb.set_filters = lambda filters=None: (events.append("filters"), set_filters(filters))  # type: ignore[method-assign]
        for value in (PDO_NOT_VALID | (0x300 + NODE), 0x3A0):  # expedited download of 0x1401:1
            request = bytes([0x23, 0x01, 0x14, 0x01]) + value.to_bytes(4, "little")
            node._on_fieldbus(can.Message(arbitration_id=0x600 + NODE, is_extended_id=False, data=request))
        assert events == [f"send 0x{0x580 + NODE:03X}", "filters", f"send 0x{0x580 + NODE:03X}"]
        assert 0x3A0 in node.fieldbus_ids()
    finally:
        fb.shutdown()
        io.shutdown()


@pytest.fixture
def hub(hub_data_plane: str, tmp_path: Path) -> Iterator[HubServer]:
    with serving_in(tmp_path, hub_data_plane) as server:
        yield server


def test_over_the_hub_other_nodes_frames_never_reach_the_drive_and_a_moved_rpdo_is_heard_at_once(hub: HubServer) -> None:
    address = hub.addresses[0]
    fb = can.Bus(interface="ilcrig_hub", channel=f"{address}#fieldbus")
    io = can.Bus(interface="ilcrig_hub", channel=f"{address}#io")
    node = RecordingDriveNode(Drive(NODE), fb, io)
    try:
        with canopen_view(node, NODE, interface="ilcrig_hub", channel=f"{address}#fieldbus") as (network, remote):
            assert remote.sdo[0x1000].raw == 0x0002_0192  # the node is up (a CiA 402 drive), its filters set
            other = [0x600 + NODE + 1, 0x580 + NODE + 1, 0x180 + NODE, 0x200 + NODE + 1, 0x3A0, 0x701]
            for cob in other:  # SDO of another node, TPDOs, RPDOs not (yet) ours, a heartbeat
                network.send_message(cob, bytes(8))
            assert remote.sdo[0x1000].raw == 0x0002_0192  # answered after the frames above: they were all routed
            assert node.seen == []
            # move RPDO2 to 0x3A0 (invalidate, set, valid) and use it as soon as the answer is in
            remote.sdo[0x1401][1].raw = PDO_NOT_VALID | (0x300 + NODE)
            remote.sdo[0x1401][1].raw = 0x3A0
            network.send_message(0x3A0, bytes(8))
            network.send_message(0x300 + NODE, bytes(8))  # the old identifier is not ours any more
            network.send_message(0x080, b"")  # SYNC
            assert wait_until(lambda: 0x080 in node.seen)
            assert node.seen == [0x3A0, 0x080]
    finally:
        fb.shutdown()
        io.shutdown()
