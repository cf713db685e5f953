"""bus.transports.hub: exact forwarding between processes, no echo, entry point, loopback-only,
disconnects, stats, filters, and that the hub child process is always reaped."""

from __future__ import annotations

import errno
import multiprocessing as mp
import os
import select
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import can
import pytest
from cli_util import pid_alive
from clock_util import wait_for

from bus.bus_features import FRAME_ERR
from bus.busload import frame_bits, frame_bits_worst_case
from bus.can_errors import CAN_ERR_CRTL, overflow_error_frame
from bus.transports.hub.addresses import parse_address, parse_channel
from bus.transports.hub.client import HubBus
from bus.transports.hub.process import HubHandle, start_hub
from bus.transports.hub.records import encode_record
from bus.transports.hub.server import HubServer
from bus.transports.hub.stats import query_hub_stats
from bus.transports.hub.wire import (
    PROTOCOL_VERSION,
    HubAddressError,
    HubAddressInUseError,
    HubStartError,
    NonLoopbackAddressError,
)

pytestmark = [pytest.mark.multiprocess, pytest.mark.usefixtures("hub_data_plane")]
CTX = mp.get_context("fork")
Frame = tuple[int, bool, bool, int, bytes]  # id, extended, remote, dlc, data


def _child_pids() -> list[int]:
    """PIDs (zombies included) whose parent is this process."""
    me, out = os.getpid(), []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            if ppid == me:
                out.append(int(entry))
    return out


@pytest.fixture(autouse=True)
def no_process_left() -> Any:
    before = set(_child_pids())
    yield
    left = set(_child_pids()) - before
    assert not left, f"test left child processes {sorted(left)}"


def _frames_of(sender: int, k: int) -> list[can.Message]:
    out = []
    for i in range(k):
        ext = i % 3 == 0
        n = i % 9
        if i % 10 == 7:
            out.append(can.Message(arbitration_id=0x700 + sender, is_extended_id=False, is_remote_frame=True, dlc=n))
            continue
        can_id = (0x1000000 * sender + i) if ext else (0x100 * sender + i % 0x100)
        out.append(can.Message(arbitration_id=can_id, is_extended_id=ext, data=bytes((sender, i, *range(n)))[:n]))
    return out


def _key(m: can.Message) -> Frame:
    return (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc, bytes(m.data))


def _sender_of(m: can.Message) -> int:
    if m.is_remote_frame:
        return m.arbitration_id - 0x700
    return m.arbitration_id // (0x1000000 if m.is_extended_id else 0x100)


def _client(channel: str, me: int, n_clients: int, k: int, barrier: Any, q: Any) -> None:
    bus = can.Bus(interface="ilcrig_hub", channel=channel)  # via the entry point
    try:
        assert isinstance(bus, HubBus)
        barrier.wait(10)
        for m in _frames_of(me, k):
            bus.send(m)
        got: list[Frame] = []
        deadline = time.monotonic() + 10
        while len(got) < (n_clients - 1) * k and time.monotonic() < deadline:
            m = bus.recv(0.5)
            if m is not None:
                assert m.is_rx and m.channel == channel  # the channel string the bus was opened with
                got.append(_key(m))
        barrier.wait(10)  # everybody sent and received: anything else now is an extra
        while (m := bus.recv(0.1)) is not None:
            got.append(_key(m))
        q.put((me, got))
    finally:
        bus.shutdown()


def _run_clients(channel: str, n: int, k: int) -> dict[int, list[Frame]]:
    barrier = CTX.Barrier(n)
    q = CTX.Queue()
    procs = [CTX.Process(target=_client, args=(channel, i, n, k, barrier, q)) for i in range(n)]
    try:
        for p in procs:
            p.start()
        results = dict(q.get(timeout=30) for _ in range(n))
    finally:
        for p in procs:
            p.join(5)
            if p.is_alive():
                p.kill()
                p.join()
    assert [p.exitcode for p in procs] == [0] * n
    return results


def _check_exact(results: dict[int, list[Frame]], n: int, k: int) -> None:
    for me, got in results.items():
        assert len(got) == (n - 1) * k, f"client {me} got {len(got)} frames"
        for s in range(n):
            from_s = [
                f for f in got if _sender_of(can.Message(arbitration_id=f[0], is_extended_id=f[1], is_remote_frame=f[2])) == s
            ]
            if s == me:
                assert from_s == [], "a client received its own frames (echo)"
            else:
                assert from_s == [_key(m) for m in _frames_of(s, k)]  # exact and in order


@pytest.mark.parametrize("kind", ["unix", "tcp"])
def test_two_clients_exchange_exactly(kind: str) -> None:
    listen = None if kind == "unix" else "tcp:127.0.0.1:0"
    with start_hub(listen) as hub:
        results = _run_clients(hub.channel("rig"), 2, 60)
        stats = hub.stats()
    _check_exact(results, 2, 60)
    frames = _frames_of(0, 60) + _frames_of(1, 60)
    n_bytes = [0 if m.is_remote_frame else len(m.data) for m in frames]
    assert stats["rig"].frames == 120
    assert stats["rig"].bits == sum(frame_bits(n, m.is_extended_id) for n, m in zip(n_bytes, frames))
    assert stats["rig"].bits_worst_case == sum(frame_bits_worst_case(n, m.is_extended_id) for n, m in zip(n_bytes, frames))
    assert stats["rig"].connections == 2
    assert not hub.alive


def test_five_clients_exchange_exactly() -> None:
    with start_hub() as hub:
        results = _run_clients(hub.channel("rig"), 5, 40)
    _check_exact(results, 5, 40)
    assert not hub.alive and mp.active_children() == []


def test_logical_buses_are_separate_and_echo_on_request() -> None:
    with start_hub() as hub:
        with (
            HubBus(hub.channel("io")) as a,
            HubBus(hub.channel("io"), receive_own_messages=True) as b,
            HubBus(hub.channel("fieldbus")) as c,
        ):
            b.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01"))
            got_a, own_b = a.recv(2.0), b.recv(2.0)
            assert got_a is not None and got_a.is_rx and bytes(got_a.data) == b"\x01"
            assert own_b is not None and not own_b.is_rx and own_b.arbitration_id == 0x181
            assert c.recv(0.05) is None and a.recv(0.05) is None
            fd = can.Message(arbitration_id=0x1ABCDEF, data=bytes(range(48)), is_fd=True, bitrate_switch=True)
            a.send(fd)
            got = b.recv(2.0)
            assert got is not None and got.is_fd and got.bitrate_switch and bytes(got.data) == bytes(range(48))
        assert hub.stats()["io"].fd_frames == 1


def test_fileno_select_over_two_buses_and_hub_side_filters() -> None:
    with start_hub() as hub:
        with (
            HubBus(hub.channel("io")) as io_tx,
            HubBus(hub.channel("fieldbus")) as fb_tx,
            HubBus(hub.channel("io"), can_filters=[{"can_id": 0x101, "can_mask": 0x7FF, "extended": False}]) as io_rx,
            HubBus(hub.channel("fieldbus")) as fb_rx,
        ):
            # the hub handles one client's records in order: once io_rx's next frame reached
            # io_tx, the hub has applied io_rx's filter record (sent right after the handshake)
            io_rx.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))
            assert io_tx.recv(2.0) is not None
            io_tx.send(can.Message(arbitration_id=0x102, is_extended_id=False, data=b"x"))  # filtered in the hub
            assert select.select([io_rx, fb_rx], [], [], 0.1)[0] == []  # nothing reached the socket
            fb_tx.send(can.Message(arbitration_id=0x601, is_extended_id=False, data=b"f"))
            io_tx.send(can.Message(arbitration_id=0x101, is_extended_id=False, data=b"e"))
            seen = {}
            while len(seen) < 2:
                ready, _, _ = select.select([io_rx, fb_rx], [], [], 2.0)
                assert ready
                for b in ready:
                    m = b.recv(0)
                    assert m is not None
                    seen[b.bus_name] = (m.arbitration_id, bytes(m.data))
            assert seen == {"io": (0x101, b"e"), "fieldbus": (0x601, b"f")}
            assert select.select([io_rx, fb_rx], [], [], 0.05)[0] == []


def test_bus_error_frames_reach_every_member_whatever_its_filters() -> None:
    """A bus error frame (a receive overflow, a CRC error) reaches a member that accepts only 0x101,
    as SocketCAN delivers error frames by the socket's error mask, which python-can's SocketcanBus
    opens to all: a node hears that frames were lost or damaged whatever it accepts. Its other
    frames are still filtered, by the hub and by the client (recv, recv_batch, recv_frames)."""
    overflow = overflow_error_frame(0.0)
    crc = can.Message(is_error_frame=True, arbitration_id=0x008, is_extended_id=False, data=bytes([0, 0, 0, 8, 0, 0, 0, 0]))
    only = [{"can_id": 0x101, "can_mask": 0x7FF, "extended": False}]
    with start_hub() as hub, HubBus(hub.channel("io")) as tx:
        for read in ("recv", "recv_batch", "recv_frames"):
            with HubBus(hub.channel("io"), can_filters=only) as rx:
                rx.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))  # its filters are in force once this came
                assert tx.recv(2.0) is not None
                for msg in (can.Message(arbitration_id=0x102, is_extended_id=False), overflow, crc):
                    tx.send(msg)
                tx.send(can.Message(arbitration_id=0x101, is_extended_id=False, data=b"e"))
                got: list[tuple[bool, int]] = []
                while len(got) < 3:
                    assert select.select([rx], [], [], 2.0)[0] or rx.frames_pending(), (read, got)
                    if read == "recv":
                        m = rx.recv(0)
                        got += [] if m is None else [(m.is_error_frame, m.arbitration_id)]
                    elif read == "recv_batch":
                        got += [(m.is_error_frame, m.arbitration_id) for m in rx.recv_batch()]
                    else:
                        frames = rx.recv_frames(0)
                        got += [
                            (bool(f & FRAME_ERR), int(i)) for f, i in zip(frames["flags"], frames["arbitration_id"], strict=True)
                        ]
                assert got == [(True, CAN_ERR_CRTL), (True, 0x008), (False, 0x101)], read


def _stay_then_die(channel: str, q: Any) -> None:
    bus = HubBus(channel)
    q.put("up")
    signal.pause()  # until the test's SIGKILL
    bus.shutdown()


def test_client_disconnect_does_not_disturb_others() -> None:
    with start_hub() as hub:
        q = CTX.Queue()
        victim = CTX.Process(target=_stay_then_die, args=(hub.channel("rig"), q))
        try:
            victim.start()
            assert q.get(timeout=10) == "up"
            with HubBus(hub.channel("rig")) as a, HubBus(hub.channel("rig")) as b:
                a.send(can.Message(arbitration_id=1, is_extended_id=False, data=b"1"))
                assert b.recv(2.0) is not None
                os.kill(victim.pid, signal.SIGKILL)  # abrupt: no shutdown, socket reset
                victim.join(5)
                for i in range(200):  # traffic keeps flowing both ways
                    a.send(can.Message(arbitration_id=2, is_extended_id=False, data=bytes([i % 256])))
                    m = b.recv(2.0)
                    assert m is not None and m.data[0] == i % 256
                    b.send(can.Message(arbitration_id=3, is_extended_id=False, data=b""))
                    assert a.recv(2.0) is not None
                assert wait_for(lambda: hub.stats()["rig"].clients == 2, 5.0)
        finally:
            if victim.is_alive():
                victim.kill()
            victim.join()


def test_recv_raises_when_hub_goes_away() -> None:
    hub = start_hub()
    try:
        bus = HubBus(hub.channel("x"))
    finally:
        hub.stop()
    try:
        with pytest.raises(can.CanOperationError, match="closed"):
            bus.recv(2.0)
    finally:
        bus.shutdown()


# -- addresses ------------------------------------------------------------------------------


@pytest.mark.parametrize("addr", ["tcp:0.0.0.0:0", "tcp:8.8.8.8:1234", "tcp::0", "tcp:[::]:0"])
def test_non_loopback_listen_refused(addr: str) -> None:
    with pytest.raises(NonLoopbackAddressError):
        HubServer([addr])
    with pytest.raises(NonLoopbackAddressError):
        start_hub(addr)  # refused before any process starts


def test_cli_refuses_non_loopback() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "host.cli", "hub", "--listen", "tcp:0.0.0.0:0"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert res.returncode != 0 and "non-loopback" in res.stderr


def test_address_parsing() -> None:
    assert str(parse_address("tcp:localhost:5")) in ("tcp:127.0.0.1:5", "tcp:[::1]:5")
    assert str(parse_address("tcp:[::1]:7")) == "tcp:[::1]:7"
    assert parse_channel("/tmp/a.sock") == (parse_address("unix:/tmp/a.sock"), "default")
    assert parse_channel("unix:/tmp/a#b.sock#io")[1] == "io"
    for bad in ["", "unix:", "tcp:127.0.0.1", "tcp:127.0.0.1:x", "tcp:127.0.0.1:70000", "foo", "unix:/a#"]:
        with pytest.raises(HubAddressError):
            parse_channel(bad)
    with pytest.raises(ValueError):
        HubBus(None)


def test_unix_path_in_use_and_stale(tmp_path: Path) -> None:
    path = tmp_path / "hub.sock"
    with start_hub(f"unix:{path}") as hub:
        with pytest.raises(HubAddressInUseError):
            HubServer([f"unix:{path}"])
        assert hub.alive
    stale = socket.socket(socket.AF_UNIX)
    stale.bind(str(path))  # a socket file nobody listens on
    stale.close()
    with start_hub(f"unix:{path}") as hub, HubBus(hub.channel("x")):
        pass
    assert not path.exists()


# -- process lifecycle -------------------------------------------------------------------------


def test_hub_child_always_reaped() -> None:
    hub = start_hub()
    pid = hub.pid
    assert hub.alive and query_hub_stats(hub.address) == {}
    assert hub.stop() == 0
    assert hub.stop() == 0  # idempotent
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)  # already reaped: no zombie left
    assert not pid_alive(pid)
    # leaving the context manager reaps it too
    with start_hub() as hub2:
        pid2 = hub2.pid
    assert not pid_alive(pid2)


def test_start_failure_is_reaped(tmp_path: Path) -> None:
    with pytest.raises(HubStartError, match="exited"):
        start_hub(f"unix:{tmp_path}/no/such/dir/hub.sock")
    assert mp.active_children() == []


def test_hub_exits_when_parent_dies(tmp_path: Path) -> None:
    script = tmp_path / "parent.py"
    script.write_text(
        textwrap.dedent(
            """
            import signal
            from bus.transports.hub.process import start_hub
            h = start_hub()
            print(h.pid, flush=True)
            signal.pause()  # until the test's SIGKILL
            """
        )
    )
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        hub_pid = int(parent.stdout.readline())
        assert pid_alive(hub_pid)
        pidfd = os.pidfd_open(hub_pid)  # readable when the hub process ends
        try:
            parent.kill()
            parent.wait()
            assert select.select([pidfd], [], [], 10)[0], "hub still running 10 s after its parent died"
        finally:
            os.close(pidfd)
        assert not pid_alive(hub_pid)
    finally:
        if parent.poll() is None:
            parent.kill()
        parent.wait()
        if parent.stdout is not None:
            parent.stdout.close()


def test_stats_reset_and_record_encoding() -> None:
    with start_hub() as hub, HubBus(hub.channel("a")) as x, HubBus(hub.channel("a")) as y:
        x.send(can.Message(arbitration_id=0x80, is_extended_id=False, data=b""))
        assert y.recv(2.0) is not None
        first = hub.stats(reset=True)["a"]
        assert (first.frames, first.bits, first.bits_worst_case, first.clients) == (1, 47, 55, 2)
        assert hub.stats()["a"].frames == 0
    rec = encode_record(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"))
    assert rec == bytes.fromhex("01 00 02 02 23010000 0000000000000000 0102000000000000")  # stamp 0: the hub's


def _raw_reply(hub: HubHandle, data: bytes) -> bytes:
    """What the hub answers ``data`` sent on a plain socket to its address (first 256 bytes)."""
    raw = socket.socket(socket.AF_UNIX)
    try:
        raw.settimeout(5)
        raw.connect(parse_address(hub.address).path)
        raw.sendall(data)
        return raw.recv(256)
    finally:
        raw.close()


def test_hub_refuses_bad_hello_and_keeps_serving() -> None:
    with start_hub() as hub:
        reply = _raw_reply(hub, b"GET / HTTP/1.0\r\n\r\n")
        assert reply.startswith(b"ILNO") and b"bad hello" in reply
        with HubBus(hub.channel("a")) as x, HubBus(hub.channel("a")) as y:
            x.send(can.Message(arbitration_id=5, is_extended_id=False, data=b"ok"))
            m = y.recv(2.0)
            assert m is not None and bytes(m.data) == b"ok"


# -- a first-class python-can interface ------------------------------------------------


def _stamping_run(hub: HubHandle, bus_name: str) -> tuple[list[float], list[float], list[float], float]:
    """Send six frames, each after the hub has stamped the one before, then read them all:
    (send times, times the hub had stamped each, timestamps, read time)."""
    with HubBus(hub.channel(bus_name)) as tx, HubBus(hub.channel(bus_name)) as rx:
        sent: list[float] = []
        stamped: list[float] = []
        for i in range(6):
            sent.append(time.time())
            tx.send(can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes([i])))
            assert wait_for(lambda n=i + 1: hub.stats()[bus_name].frames == n, 5.0)  # the hub has it
            stamped.append(time.time())
        got = [rx.recv(2.0) for _ in range(6)]
        read_at = time.time()
    assert [m.data[0] if m is not None else None for m in got] == list(range(6))
    return sent, stamped, [m.timestamp for m in got if m is not None], read_at


def test_timestamps_are_the_hubs_receive_time() -> None:
    """msg.timestamp is when the hub received the frame: each of six frames, read together at
    the end, carries a time between its send and the moment the hub had counted it, so before
    the next frame was sent. Stamping at read time (or at send time of a later frame) would put
    every stamp after the last send. Ordering only: no bound on how fast anything runs."""
    with start_hub() as hub:
        sent, stamped, stamps, read_at = _stamping_run(hub, "ts")
    for i in range(6):
        assert sent[i] <= stamps[i] <= stamped[i], (i, sent[i], stamps[i], stamped[i])
        if i + 1 < 6:
            assert stamps[i] < sent[i + 1]
    assert stamps == sorted(stamps) and stamps[-1] <= read_at


@pytest.mark.parametrize("kind", ["unix", "tcp"])
def test_received_channel_is_the_channel_string(kind: str) -> None:
    """msg.channel is the channel string the receiving bus was opened with (python-can's rule)."""
    with start_hub(None if kind == "unix" else "tcp:127.0.0.1:0") as hub:
        channel = hub.channel("io")
        with can.Bus(interface="ilcrig_hub", channel=channel, receive_own_messages=True) as a, HubBus(channel) as b:
            a.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01"))
            got, own = b.recv(2.0), a.recv(2.0)
            assert got is not None and own is not None
            assert (got.channel, own.channel, own.is_rx, a.channel) == (channel, channel, False, channel)


def test_notifier_over_two_hub_buses_keeps_each_channel() -> None:
    """python-can's notifier_test.test_multiple_bus with the hub's channel strings."""
    with start_hub() as hub:
        c0, c1 = hub.channel("n0"), hub.channel("n1")
        with HubBus(c0, receive_own_messages=True) as bus0, HubBus(c1, receive_own_messages=True) as bus1:
            reader = can.BufferedReader()
            notifier = can.Notifier([bus0, bus1], [reader], 0.1)
            try:
                bus0.send(can.Message())
                first = reader.get_message(2.0)
                bus1.send(can.Message())
                second = reader.get_message(2.0)
            finally:
                notifier.stop()
    assert first is not None and first.channel == c0
    assert second is not None and second.channel == c1


def test_after_shutdown_every_method_raises_can_operation_error() -> None:
    closed = "closed bus"
    with start_hub() as hub:
        bus = HubBus(hub.channel("x"))
        bus.shutdown()
        bus.shutdown()  # again: nothing
        for call in (
            lambda: bus.recv(0),
            lambda: bus.recv(0.2),
            lambda: bus.recv(),
            lambda: bus.send(can.Message()),
            lambda: bus.set_filters([{"can_id": 1, "can_mask": 0x7FF}]),
            lambda: bus.flush_tx_buffer(),
            lambda: bus.send_periodic(can.Message(), 0.01),
        ):
            with pytest.raises(can.CanOperationError, match=closed):
                call()
        assert bus.fileno() == -1  # as a closed SocketCAN bus
        safe = can.ThreadSafeBus(interface="ilcrig_hub", channel=hub.channel("x"))
        safe.shutdown()
        for call in (lambda: safe.recv(0.1), lambda: safe.send(can.Message())):
            with pytest.raises(can.CanOperationError, match=closed):
                call()


@pytest.mark.parametrize("timeout", [None, 30.0])
def test_shutdown_wakes_a_thread_blocked_in_recv(timeout: float | None) -> None:
    with start_hub() as hub:
        bus = HubBus(hub.channel("x"))
        entering = threading.Event()
        outcome: list[BaseException | can.Message | None] = []

        def reader() -> None:
            entering.set()
            try:
                outcome.append(bus.recv(timeout))
            except BaseException as err:  # recorded for the assertion below
                outcome.append(err)

        t = threading.Thread(target=reader)
        t.start()
        assert entering.wait(5.0)
        bus.shutdown()  # whether the reader is already blocked in recv or about to enter it
        t.join(10.0)
        assert not t.is_alive()
    assert len(outcome) == 1 and isinstance(outcome[0], can.CanOperationError), outcome
    assert "closed bus" in str(outcome[0])


def test_classic_bus_refuses_fd_frames_and_reports_can20() -> None:
    with start_hub() as hub:
        ch = hub.channel("c")
        with can.Bus(interface="ilcrig_hub", channel=ch, fd=False) as classic, HubBus(ch) as fd_rx, HubBus(ch) as fd_tx:
            assert classic.protocol is can.CanProtocol.CAN_20 and "classic CAN" in classic.channel_info
            assert fd_rx.protocol is can.CanProtocol.CAN_FD
            for bad in (
                can.Message(arbitration_id=1, is_fd=True, data=b"\x01"),
                can.Message(arbitration_id=1, is_fd=True, data=bytes(64)),
                can.Message(arbitration_id=1, data=bytes(12), check=False),
            ):
                with pytest.raises(can.CanOperationError, match="classic CAN") as exc:
                    classic.send(bad)
                assert exc.value.error_code == errno.EINVAL  # as SocketCAN's "Invalid argument"
            classic.send(can.Message(arbitration_id=2, is_extended_id=False, data=b"ok"))
            for member in (fd_rx, fd_tx):
                got = member.recv(2.0)
                assert got is not None and bytes(got.data) == b"ok"
            fd_tx.send(can.Message(arbitration_id=3, is_fd=True, data=bytes(20)))
            fd_tx.send(can.Message(arbitration_id=4, is_extended_id=False, data=b"after"))
            # one sender's frames arrive in order: the classic member's first frame is the
            # classic one, so the FD frame was not delivered to it (a non-FD controller never sees it)
            first = classic.recv(2.0)
            assert first is not None and first.arbitration_id == 4
            assert [m.arbitration_id for m in (fd_rx.recv(2.0), fd_rx.recv(2.0)) if m is not None] == [3, 4]


def test_bitrates_are_kept_reported_and_enforced_per_bus() -> None:
    with start_hub() as hub:
        ch = hub.channel("b")
        with HubBus(ch, bitrate=500_000, data_bitrate=2_000_000) as a:
            assert (a.bitrate, a.data_bitrate, a.protocol) == (500_000, 2_000_000, can.CanProtocol.CAN_FD)
            assert "500000 bit/s" in a.channel_info and "data 2000000 bit/s" in a.channel_info
            with can.Bus(interface="ilcrig_hub", channel=ch) as b:  # gives none: adopts the bus's
                assert (b.bitrate, b.data_bitrate) == (500_000, 2_000_000)
            with pytest.raises(can.CanInitializationError, match="bitrate 500000 bit/s.*asked for 250000"):
                HubBus(ch, bitrate=250_000)
            st = hub.stats()["b"]
            assert (st.bitrate, st.data_bitrate) == (500_000, 2_000_000)
        assert wait_for(lambda: hub.stats()["b"].clients == 0, 5.0)
        # an empty bus takes the next first member's bitrates; a BitTiming gives them too
        timing = can.BitTiming(f_clock=8_000_000, brp=1, tseg1=5, tseg2=2, sjw=1)
        with HubBus(ch, timing=timing, fd=False) as c:
            assert (c.bitrate, c.data_bitrate, c.protocol) == (1_000_000, None, can.CanProtocol.CAN_20)
            assert hub.stats()["b"].bitrate == 1_000_000
        with HubBus(hub.channel("none")) as d:
            assert (d.bitrate, d.data_bitrate) == (None, None)
        with pytest.raises(ValueError, match="bitrate"):
            HubBus(hub.channel("x"), bitrate=-5)


def test_old_protocol_version_is_refused_with_a_clear_message() -> None:
    with start_hub() as hub:
        reply = _raw_reply(hub, b"ILCH" + bytes([1, 1, 0, 2]) + b"io")  # a version-1 member hello
        assert reply.startswith(b"ILNO")
        text = reply[5:].decode()
        assert f"protocol version 1 not supported: this hub speaks version {PROTOCOL_VERSION}" in text
        with HubBus(hub.channel("io")) as x, HubBus(hub.channel("io")) as y:  # and it keeps serving
            x.send(can.Message(arbitration_id=5, is_extended_id=False, data=b"ok"))
            assert y.recv(2.0) is not None


def test_every_frame_kind_is_carried() -> None:
    frames = [
        can.Message(arbitration_id=0x7FF, is_extended_id=False, is_fd=True, bitrate_switch=True, data=bytes(range(64))),
        can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, is_fd=True, error_state_indicator=True, data=bytes(7)),
        can.Message(arbitration_id=0x123, is_extended_id=False, is_remote_frame=True, dlc=5),
        can.Message(arbitration_id=0x20000004, is_error_frame=True, dlc=8, data=bytes([0, 0, 0x04, 0, 0, 0, 0, 0])),
        can.Message(arbitration_id=0x100, is_extended_id=False, data=b""),
        can.Message(arbitration_id=0x18DAF110, is_extended_id=True, is_fd=True, data=b""),
    ]
    with start_hub() as hub, HubBus(hub.channel("k")) as tx, HubBus(hub.channel("k")) as rx:
        for m in frames:
            tx.send(m)
        got = [rx.recv(2.0) for _ in frames]
    for g, m in zip(got, frames, strict=True):
        assert g is not None and g.equals(m, timestamp_delta=None, check_channel=False), (g, m)
