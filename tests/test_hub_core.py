"""The hub's two data planes (bus/transports/hub/_hubcore.c and the pure-Python path, bus/transports/hub/routing.py):
which one a hub uses, and the byte-level behaviour both must share — records split over reads,
records sent in the handshake's read, filter records, an unknown record kind refused, a member that
stops reading dropped and counted, a member leaving in the middle. Every test runs on both planes
(the ``hub_data_plane`` fixture); waits are for frames or the hub's counters, never sleeps."""

from __future__ import annotations

import shutil
import socket
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from hub_util import serving_in
from test_hub_extras import wait_until

from bus.transports.fault_inject import FrameFaultInjector
from bus.transports.hub.client import HubBus
from bus.transports.hub.core import HUB_CORE_ENV, core_built
from bus.transports.hub.records import encode_record
from bus.transports.hub.server import HubServer
from bus.transports.hub.wire import (
    BITRATES,
    FILTER_ENTRY,
    HEADER,
    KIND_FILTERS,
    ROLE_MEMBER,
    hello,
    read_reply,
    recv_exact,
)


class _SmallBuffers(HubServer):
    MAX_OUTBUF_BYTES = 64 << 10


@pytest.fixture
def served(hub_data_plane: str, tmp_path: Path) -> Iterator[HubServer]:
    """A hub serving in a thread of this process (so a test can read its state)."""
    with serving_in(tmp_path, hub_data_plane, _SmallBuffers) as server:
        yield server


def _channel(server: HubServer, bus: str) -> str:
    return f"{server.addresses[0]}#{bus}"


def _raw_member(server: HubServer, bus: str, first: bytes = b"") -> socket.socket:
    """A member speaking the wire protocol by hand; ``first`` goes in the same write as its hello."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(5)
    sock.connect(server.addresses[0].path)
    sock.sendall(hello(ROLE_MEMBER, bus) + first)
    read_reply(sock)
    assert BITRATES.unpack(recv_exact(sock, BITRATES.size)) == (0, 0)
    return sock


def _frame(can_id: int, data: bytes) -> bytes:
    return encode_record(can.Message(arbitration_id=can_id, is_extended_id=False, data=data))


def test_the_c_core_is_built_where_a_compiler_is() -> None:
    """setup.py builds the core when a C compiler is there (CI has gcc): the fast path is not
    silently lost."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler here: the hub uses its Python path")
    assert core_built()


def test_which_plane_a_hub_uses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    if not core_built():
        pytest.skip("the C core is not built here")
    monkeypatch.delenv(HUB_CORE_ENV, raising=False)
    cases = [({}, "c"), ({"bus_time": {"io": 1_000_000}}, "python"), ({"frame_hook": FrameFaultInjector([], None)}, "python")]
    for i, (kwargs, plane) in enumerate(cases):
        with HubServer([f"unix:{tmp_path}/h{i}.sock"], **kwargs) as server:  # type: ignore[arg-type]
            assert server.data_plane == plane, kwargs
    monkeypatch.setenv(HUB_CORE_ENV, "python")
    with HubServer([f"unix:{tmp_path}/p.sock"]) as server:
        assert server.data_plane == "python"


def test_records_split_over_reads_and_sent_with_the_hello_arrive_whole(served: HubServer) -> None:
    with HubBus(_channel(served, "s")) as rx:
        first = _frame(0x10, b"hello")  # in the handshake's read: routed when the member joins
        tx = _raw_member(served, "s", first)
        try:
            two = _frame(0x11, b"\x01\x02\x03") + _frame(0x12, bytes(8))
            for i in range(len(two)):  # byte by byte: every read ends inside a record
                tx.send(two[i : i + 1])
                if i % 7 == 0:
                    assert wait_until(lambda n=1 + (i + 1) // HEADER.size: served.stats()["s"].frames >= n)
            got = [rx.recv(5.0) for _ in range(3)]
        finally:
            tx.close()
    assert [(m.arbitration_id, bytes(m.data)) for m in got if m is not None] == [
        (0x10, b"hello"),
        (0x11, b"\x01\x02\x03"),
        (0x12, bytes(8)),
    ]
    st = served.stats()["s"]
    assert (st.frames, st.bits) == (3, (47 + 40) + (47 + 24) + (47 + 64))


def test_a_filter_record_changes_what_a_member_gets(served: HubServer) -> None:
    body = FILTER_ENTRY.pack(0x200, 0x7F0, 0)  # 0x200..0x20F, standard ids only
    with HubBus(_channel(served, "f")) as tx:
        # the filter record in the hello's write: applied before the member's answer is read
        rx = _raw_member(served, "f", HEADER.pack(KIND_FILTERS, 0, 0, 0, len(body), 0, bytes(8)) + body)
        try:
            for can_id, ext in ((0x205, False), (0x305, False), (0x205, True), (0x20F, False)):
                tx.send(can.Message(arbitration_id=can_id, is_extended_id=ext, data=b"b"))
            assert wait_until(lambda: served.stats()["f"].frames == 4)
            data = b""
            while len(data) < 2 * HEADER.size:
                data += rx.recv(4096)
        finally:
            rx.close()
    ids = [HEADER.unpack_from(data, off)[4] for off in range(0, len(data), HEADER.size)]
    assert ids == [0x205, 0x20F]


def test_an_unknown_record_kind_is_refused_and_the_hub_keeps_serving(served: HubServer) -> None:
    bad = _raw_member(served, "k")
    try:
        bad.sendall(HEADER.pack(9, 0, 0, 0, 0, 0, bytes(8)))
        reply = bad.recv(256)
    finally:
        bad.close()
    assert reply.startswith(b"ILNO") and b"unknown record kind 9" in reply
    with HubBus(_channel(served, "k")) as a, HubBus(_channel(served, "k")) as b:
        assert wait_until(lambda: served.stats()["k"].clients == 2)
        a.send(can.Message(arbitration_id=1, is_extended_id=False, data=b"ok"))
        m = b.recv(5.0)
        assert m is not None and bytes(m.data) == b"ok"


def test_a_member_that_stops_reading_is_dropped_and_counted(served: HubServer) -> None:
    stuck = _raw_member(served, "d")
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    with HubBus(_channel(served, "d")) as tx, HubBus(_channel(served, "d")) as rx:
        assert wait_until(lambda: served.stats()["d"].clients == 3)
        n = 0
        while served.stats()["d"].dropped_clients == 0:
            tx.send_batch([can.Message(arbitration_id=0x100, is_extended_id=False, data=bytes(8))] * 64)
            n += 64
            assert n < 200_000, "the stuck member was never dropped"
            while rx.recv(0) is not None:
                pass
        assert wait_until(lambda: served.stats()["d"].clients == 2)  # (the hub's thread may be mid-drop)
        assert served.stats()["d"].dropped_clients == 1
        tx.send(can.Message(arbitration_id=0x7, is_extended_id=False, data=b"after"))
        while (m := rx.recv(5.0)) is not None and m.arbitration_id != 0x7:
            pass
        assert m is not None and bytes(m.data) == b"after"
    stuck.close()


def test_a_member_leaving_mid_stream_disturbs_nobody(served: HubServer) -> None:
    with HubBus(_channel(served, "l")) as tx, HubBus(_channel(served, "l")) as rx:
        leaver = _raw_member(served, "l")
        tx.send(can.Message(arbitration_id=0x1, is_extended_id=False, data=b"1"))
        assert rx.recv(5.0) is not None
        leaver.close()
        assert wait_until(lambda: served.stats()["l"].clients == 2)
        for i in range(50):
            tx.send(can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes([i])))
        got = [rx.recv(5.0) for _ in range(50)]
    assert [m.arbitration_id for m in got if m is not None] == [0x100 + i for i in range(50)]


def test_a_bulk_member_gets_its_held_frames_when_it_asks(
    hub_data_plane: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The release record (wire protocol 3): a bulk member's held frames come at once when it asks,
    not after the hold (made 60 s here, so only the release can deliver them); a member that
    is not bulk asking changes nothing."""
    import bus.transports.hub.core as core
    import bus.transports.hub.routing as routing

    monkeypatch.setattr(routing, "BULK_HOLD_S", 60.0)
    monkeypatch.setattr(core, "BULK_HOLD_S", 60.0)
    with serving_in(tmp_path, hub_data_plane) as server, HubBus(_channel(server, "r")) as tx:
        with HubBus(_channel(server, "r"), bulk_delivery=True) as bulk, HubBus(_channel(server, "r")) as live:
            assert wait_until(lambda: server.stats()["r"].clients == 3)
            for i in range(3):
                tx.send(can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes([i])))
            assert [m.arbitration_id for m in (live.recv(5.0) for _ in range(3)) if m is not None] == [0x100, 0x101, 0x102]
            assert bulk.recv(0.2) is None  # held
            bulk.release_held()
            live.release_held()
            got = [bulk.recv(5.0) for _ in range(3)]
            assert [m.arbitration_id for m in got if m is not None] == [0x100, 0x101, 0x102]
            tx.send(can.Message(arbitration_id=0x200, is_extended_id=False, data=b"x"))
            m = live.recv(5.0)
            assert m is not None and m.arbitration_id == 0x200
            bulk.release_held()
            m = bulk.recv(5.0)
            assert m is not None and m.arbitration_id == 0x200


def test_a_gathering_member_gets_its_frames_n_at_a_time(
    hub_data_plane: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The gather record (wire protocol 3): the hub holds a member's frames until the count is held
    and delivers them in one write (a hold of 60 s here: only the count releases them); count 0
    delivers what is held and every frame at once again."""
    import bus.transports.hub.core as core
    import bus.transports.hub.routing as routing

    monkeypatch.setattr(routing, "BULK_HOLD_S", 60.0)
    monkeypatch.setattr(core, "BULK_HOLD_S", 60.0)
    with serving_in(tmp_path, hub_data_plane) as server:
        with HubBus(_channel(server, "g")) as master, HubBus(_channel(server, "g")) as a, HubBus(_channel(server, "g")) as b:
            assert wait_until(lambda: server.stats()["g"].clients == 3)
            master.gather_frames(4)
            master.send(can.Message(arbitration_id=0x10, is_extended_id=False, data=b"s"))  # after the record: in order
            assert a.recv(5.0) is not None and b.recv(5.0) is not None
            for i in range(3):  # two senders: each frame counted by the hub before the next is sent (their order)
                (a if i % 2 else b).send(can.Message(arbitration_id=0x180 + i, is_extended_id=False, data=bytes([i])))
                assert wait_until(lambda n=2 + i: server.stats()["g"].frames == n)
            assert master.recv(0.2) is None  # three of four: held
            a.send(can.Message(arbitration_id=0x183, is_extended_id=False, data=b"\x03"))
            got = [master.recv(5.0) for _ in range(4)]
            assert [m.arbitration_id for m in got if m is not None] == [0x180, 0x181, 0x182, 0x183]
            b.send(can.Message(arbitration_id=0x184, is_extended_id=False, data=b"\x04"))
            assert wait_until(lambda: server.stats()["g"].frames == 6)
            assert master.recv(0.2) is None
            master.gather_frames(0)  # what is held goes out, and from now on every frame at once
            m = master.recv(5.0)
            assert m is not None and m.arbitration_id == 0x184
            a.send(can.Message(arbitration_id=0x185, is_extended_id=False, data=b"\x05"))
            m = master.recv(5.0)
            assert m is not None and m.arbitration_id == 0x185
