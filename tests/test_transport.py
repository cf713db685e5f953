"""bus.transports.config: config precedence, transport choice, multicast policy; udp_multicast in a netns, its losses
reported as bus errors (bus.transports.udp_multicast)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import can
import pytest
from netns_util import NETNS_SETUP, netns_unavailable_reason, script_report_in_netns

import bus.transports.config as tr
from bus.transports.config import (
    ChannelConfig,
    MulticastNotAllowedError,
    TransportConfigError,
    auto_transport,
    can_config_transport,
    hub_transport,
    open_bus,
    resolve_bus_config,
    socketcan_transport,
    transport_from_name,
    udp_multicast_transport,
    virtual_transport,
)
from bus.transports.hub.process import start_hub
from bus.transports.hub.wire import NonLoopbackAddressError

CAN_ENV = [
    "CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG",
    "CAN_INTERFACE_io", "CAN_CHANNEL_io", "CAN_INTERFACE_fieldbus", "CAN_CHANNEL_fieldbus",
    "CAN_CONFIG_io", "CAN_CONFIG_fieldbus", tr.PRIVATE_NETNS_ENV,
]  # fmt: skip


@pytest.fixture(autouse=True)
def clean_can_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """No python-can env vars or ~/.canrc from the developer's machine leak into these tests."""
    for name in CAN_ENV:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setattr(can, "rc", {})


def test_open_bus_explicit_virtual() -> None:
    with open_bus(ChannelConfig("virtual", "tr-a")) as a, open_bus(ChannelConfig("virtual", "tr-a")) as b:
        a.send(can.Message(arbitration_id=0x42, is_extended_id=False, data=b"\x01"))
        msg = b.recv(1.0)
    assert msg is not None and msg.arbitration_id == 0x42 and bytes(msg.data) == b"\x01"


def test_env_vars_honoured_when_nothing_explicit(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"receive_own_messages": True}))
    cfg = resolve_bus_config(ChannelConfig())
    assert (cfg["interface"], cfg["channel"], cfg["receive_own_messages"]) == ("virtual", "from-env", True)
    with open_bus(ChannelConfig()) as bus:
        assert bus.channel_info.endswith("from-env")
        bus.send(can.Message(arbitration_id=1, is_extended_id=False))
        assert bus.recv(1.0) is not None  # receive_own_messages came from CAN_CONFIG


def test_explicit_beats_env_and_context_beats_plain(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "plain")
    monkeypatch.setenv("CAN_CHANNEL_io", "io-ctx")
    assert resolve_bus_config(ChannelConfig(channel="explicit"))["channel"] == "explicit"
    assert resolve_bus_config(ChannelConfig(context="io"))["channel"] == "io-ctx"
    assert resolve_bus_config(ChannelConfig(context="fieldbus"))["channel"] == "plain"


def test_can_config_transport_uses_contexts(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "same")
    t = can_config_transport()
    with pytest.raises(TransportConfigError, match="same bus"):
        t.validate()
    monkeypatch.setenv("CAN_CHANNEL_io", "other")
    t.validate()


def test_config_file_section(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    (tmp_path / ".canrc").write_text("[default]\ninterface = virtual\nchannel = file-default\n[io]\nchannel = file-io\n")
    assert resolve_bus_config(ChannelConfig(context="io"))["channel"] == "file-io"
    assert resolve_bus_config(ChannelConfig())["channel"] == "file-default"


def test_no_interface_anywhere_is_a_clear_error() -> None:
    with pytest.raises(TransportConfigError, match="cannot resolve"):
        resolve_bus_config(ChannelConfig())


def test_auto_transport_prefers_vcan(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tr, "net_interfaces", lambda: {"lo", "eth0", "vcan0", "vcan1"})
    t = auto_transport()
    assert t.name == "socketcan"
    assert (t.fieldbus.interface, t.fieldbus.channel, t.io.channel) == ("socketcan", "vcan0", "vcan1")
    monkeypatch.setattr(tr, "net_interfaces", lambda: {"lo", "vcan0"})
    t = auto_transport("unix:/tmp/rig/hub.sock")
    assert t.name == "hub" and t.needs_hub
    assert (t.fieldbus.interface, t.fieldbus.channel) == ("ilcrig_hub", "unix:/tmp/rig/hub.sock#fieldbus")
    assert t.io.channel == "unix:/tmp/rig/hub.sock#io"


def test_factories() -> None:
    assert socketcan_transport().as_dict()["io"]["channel"] == "vcan1"
    v = virtual_transport("x")
    assert (v.channel("fieldbus").channel, v.channel("io").channel) == ("x-fieldbus", "x-io")
    with pytest.raises(TransportConfigError):
        v.channel("power")
    u = udp_multicast_transport()
    assert u.fieldbus.channel != u.io.channel and u.fieldbus.kwargs["port"] != u.io.kwargs["port"]
    assert u.io.kwargs["hop_limit"] == 1
    assert transport_from_name("virtual").name == "virtual"
    with pytest.raises(TransportConfigError, match="unknown transport") as exc:
        transport_from_name("carrier-pigeon")
    # the names the command line offers, not the in-process one
    assert (
        str(exc.value) == "--bus carrier-pigeon: unknown transport; choose from auto, hub, socketcan, udp_multicast, can_config"
    )


def test_a_transport_this_machine_cannot_carry_is_refused_before_anything_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(tr.PRIVATE_NETNS_ENV, raising=False)
    monkeypatch.setattr(tr, "in_private_netns", lambda: False)
    cases = [
        (virtual_transport(), {}, "--bus virtual: the virtual transport works inside one process only"),
        (socketcan_transport("nocan7", "nocan8"), {}, "--bus socketcan: this machine has no CAN interface nocan7, nocan8"),
        (udp_multicast_transport(), {}, "--bus udp_multicast: only inside a private network namespace"),
        (socketcan_transport("nocan7", "nocan8"), {"hub_given": True}, "--hub applies to --bus hub"),
        (
            hub_transport(f"unix:{tmp_path}/missing/hub.sock"),
            {"hub_given": True},
            f"the folder {tmp_path}/missing does not exist",
        ),
    ]
    for tc, kw, text in cases:
        with pytest.raises(TransportConfigError) as exc:
            tc.check_usable(**kw)
        assert text in str(exc.value) and "\n" not in str(exc.value)
    hub_transport(f"unix:{tmp_path}/hub.sock").check_usable(hub_given=True)  # a folder of this user's: fine
    if os.getuid() == 0:  # another user's folder (root can make one)
        theirs = tmp_path / "theirs"
        theirs.mkdir()
        os.chown(theirs, 65534, 65534)
        with pytest.raises(TransportConfigError, match="is not yours"):
            hub_transport(f"unix:{theirs}/hub.sock").check_usable(hub_given=True)


def test_hub_transport_refuses_non_loopback() -> None:
    with pytest.raises(NonLoopbackAddressError):
        hub_transport("tcp:0.0.0.0:5000")
    with pytest.raises(NonLoopbackAddressError):
        hub_transport("tcp:8.8.8.8:5000")
    assert hub_transport("tcp:localhost:5000").fieldbus.channel == "tcp:localhost:5000#fieldbus"


def test_udp_multicast_resolves_to_the_checked_bus(monkeypatch: pytest.MonkeyPatch) -> None:
    """Whoever opens it (open_bus, or a role calling can.Bus with the resolved config), python-can's
    udp_multicast is the bus that reports its losses."""
    assert resolve_bus_config(udp_multicast_transport().io)["interface"] == tr.UDP_MULTICAST_INTERFACE
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CHANNEL", "239.74.163.12")
    assert resolve_bus_config(ChannelConfig())["interface"] == tr.UDP_MULTICAST_INTERFACE
    from bus.transports.udp_multicast import CheckedUdpMulticastBus

    assert can.interface._get_class_for_interface(tr.UDP_MULTICAST_INTERFACE) is CheckedUdpMulticastBus


def test_udp_multicast_refused_outside_private_netns(monkeypatch: pytest.MonkeyPatch) -> None:
    """Refused before any socket exists (nothing is sent on a real interface)."""
    monkeypatch.setattr(tr, "net_interfaces", lambda: {"lo", "eth0"})

    def no_bus(**kwargs: object) -> None:
        raise AssertionError("can.Bus must not be called")

    monkeypatch.setattr(can, "Bus", no_bus)
    with pytest.raises(MulticastNotAllowedError, match="private network namespace"):
        open_bus(udp_multicast_transport().io)
    # the policy: loopback-only namespace, explicit flag, or env var
    assert tr._multicast_allowed(udp_multicast_transport(private_netns=True).io)
    monkeypatch.setenv(tr.PRIVATE_NETNS_ENV, "1")
    assert tr._multicast_allowed(udp_multicast_transport().io)
    monkeypatch.delenv(tr.PRIVATE_NETNS_ENV)
    monkeypatch.setattr(tr, "net_interfaces", lambda: {"lo"})
    assert tr.in_private_netns() and tr._multicast_allowed(udp_multicast_transport().io)


@pytest.mark.multiprocess
def test_hub_transport_end_to_end() -> None:
    with start_hub() as hub:
        t = hub_transport(hub.address)
        with t.open("io") as io_a, t.open("io") as io_b, t.open("fieldbus") as fb:
            io_a.send(can.Message(arbitration_id=0x101, is_extended_id=False, data=b"\x01\x02"))
            msg = io_b.recv(2.0)
            assert msg is not None and (msg.arbitration_id, bytes(msg.data)) == (0x101, b"\x01\x02")
            assert fb.recv(0.05) is None
        stats = hub.stats()
    assert stats["io"].frames == 1 and stats["fieldbus"].frames == 0
    assert not hub.alive


NETNS_SCRIPT = textwrap.dedent(
    """
    import json, multiprocessing as mp, sys
    import can
    from bus.transports.config import udp_multicast_transport, in_private_netns

    def drive(q):
        t = udp_multicast_transport()
        with t.open("io") as io:
            q.put("ready")
            got = []
            while len(got) < 3:
                m = io.recv(5.0)
                if m is None:
                    break
                if m.arbitration_id == 0x181:  # own frame looped back on lo: ignore
                    continue
                got.append([m.arbitration_id, m.data.hex(), m.dlc, m.is_extended_id])
                io.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=m.data[:2]))
            q.put(got)

    if __name__ == "__main__":
        ctx = mp.get_context("fork")
        q = ctx.Queue()
        p = ctx.Process(target=drive, args=(q,))
        t = udp_multicast_transport()
        with t.open("io") as io, t.open("fieldbus") as fb:
            p.start()
            try:
                assert q.get(timeout=10) == "ready"
                sent = [
                    can.Message(arbitration_id=0x101, is_extended_id=False, data=bytes([1, 2, 3, 4, 5, 6])),
                    can.Message(arbitration_id=0x1234567, is_extended_id=True, data=b"\\xaa"),
                    can.Message(arbitration_id=0x102, is_extended_id=False, data=b""),
                ]
                answers, own = [], 0
                for m in sent:
                    io.send(m)
                    while True:
                        r = io.recv(5.0)
                        if r is None:
                            break
                        if r.arbitration_id == m.arbitration_id:
                            own += 1
                            continue
                        answers.append([r.arbitration_id, r.data.hex()])
                        break
                got = q.get(timeout=10)
                fb_frames = 0
                while fb.recv(0.05) is not None:
                    fb_frames += 1
            finally:
                p.join(5)
                if p.is_alive():
                    p.kill()
                    p.join()
        print(json.dumps({"private": in_private_netns(), "got": got, "answers": answers,
                          "own": own, "fieldbus_frames": fb_frames, "exitcode": p.exitcode}))
    """
)


@pytest.mark.netns
@pytest.mark.multiprocess
def test_udp_multicast_in_private_netns(tmp_path: Path) -> None:
    out = script_report_in_netns(tmp_path, "udp_netns.py", NETNS_SCRIPT, timeout_s=30)
    assert out["private"] is True  # the policy allowed it by detection, no flag set
    assert out["got"] == [
        [0x101, "010203040506", 6, False],
        [0x1234567, "aa", 1, True],
        [0x102, "", 0, False],
    ]
    assert out["answers"] == [[0x181, "0102"], [0x181, "aa"], [0x181, ""]]
    assert out["own"] == 3  # udp_multicast loops a sender's own frames back on lo
    assert out["fieldbus_frames"] == 0  # distinct groups/ports per channel
    assert out["exitcode"] == 0


def test_default_hub_address_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ILCRIG_HUB", "tcp:127.0.0.1:4000")
    assert hub_transport().io.channel == "tcp:127.0.0.1:4000#io"
    monkeypatch.delenv("ILCRIG_HUB")
    assert hub_transport().hub_address.startswith("unix:")  # type: ignore[union-attr]


LOSS_SCRIPT = textwrap.dedent(
    """
    import json
    import can
    from bus.transports.config import ChannelConfig, open_bus, udp_multicast_transport
    from bus.transports.udp_multicast import CAN_ERR_CRTL, CAN_ERR_CRTL_RX_OVERFLOW, UDP_RCVBUF_BYTES

    def udp_errors():
        rows = [l.split() for l in open("/proc/net/snmp") if l.startswith("Udp:")]
        return int(rows[1][rows[0].index("RcvbufErrors")])

    rmem_max = int(open("/proc/sys/net/core/rmem_max").read())
    with udp_multicast_transport().open("io") as default:
        default_rcvbuf = default.rcvbuf_bytes
    cfg = ChannelConfig("udp_multicast", "239.74.163.13", {"port": 43130, "hop_limit": 1}, private_netns=True)
    small = ChannelConfig(cfg.interface, cfg.channel, {**cfg.kwargs, "receive_buffer_bytes": 8192}, private_netns=True)
    with open_bus(small) as rx, open_bus(cfg) as tx:
        def send(first, end):
            for i in range(first, end):
                tx.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=i.to_bytes(2, "big")))
        send(0, 100)  # far more than 8 KiB of receive buffer holds
        got = [int.from_bytes(rx.recv(2.0).data, "big") for _ in range(3)]
        send(100, 103)  # queued after the loss: they carry the socket's drop count
        errors = []
        while (m := rx.recv(0.5)) is not None:
            if m.is_error_frame:
                errors.append([m.arbitration_id, m.dlc, m.data[1], len(got)])
                got.append(-1)
            else:
                got.append(int.from_bytes(m.data, "big"))
        print(json.dumps({"rmem_max": rmem_max, "default_rcvbuf": default_rcvbuf, "wanted": UDP_RCVBUF_BYTES,
                          "got": got, "errors": errors, "frames_lost": rx.frames_lost, "kernel": udp_errors(),
                          "expected_error": [CAN_ERR_CRTL, 8, CAN_ERR_CRTL_RX_OVERFLOW]}))
    """
)


@pytest.mark.netns
@pytest.mark.multiprocess
def test_udp_multicast_reports_every_lost_datagram_as_a_bus_error(tmp_path: Path) -> None:
    """A receiver whose socket overflows gets one bus error frame (a controller receive overflow)
    exactly where the frames are missing, and counts every datagram the kernel dropped; by default
    the receive buffer is as large as the kernel grants, up to UDP_RCVBUF_BYTES."""
    out = script_report_in_netns(tmp_path, "udp_loss.py", LOSS_SCRIPT, timeout_s=60)
    assert out["default_rcvbuf"] >= min(out["wanted"], 2 * out["rmem_max"])
    got, lost = out["got"], out["frames_lost"]
    assert lost > 0 and lost == out["kernel"]  # every drop of the namespace, on this socket, counted
    assert len(out["errors"]) == 1
    code, dlc, detail, where = out["errors"][0]
    assert [code, dlc, detail] == out["expected_error"]
    assert got[:where] == list(range(where)) and got[where] == -1  # in order up to the loss, then the error
    assert got[where + 1 :] == list(range(where + lost, 103))  # then what followed the lost datagrams


SILENT_LOSS_SCRIPT = textwrap.dedent(
    """
    import json
    import can
    from bus.cia301.slave import SlaveNode
    from bus.errors import SdoAbort
    from bus.transports.config import ChannelConfig, open_bus

    class App:  # the least a CANopen slave's application is
        nmt_state = 0x7F
        lost = 0
        def nmt_command(self, cs): pass
        def read_object(self, index, sub): raise SdoAbort(0x06020000, "none")
        def write_object(self, index, sub, data): raise SdoAbort(0x06020000, "none")
        def pop_emcy(self): return []
        def frames_lost(self): self.lost += 1

    cfg = ChannelConfig("udp_multicast", "239.74.163.14", {"port": 43140, "hop_limit": 1}, private_netns=True)
    io_cfg = ChannelConfig("udp_multicast", "239.74.163.15", {"port": 43150, "hop_limit": 1}, private_netns=True)
    small = ChannelConfig(cfg.interface, cfg.channel, {**cfg.kwargs, "receive_buffer_bytes": 8192}, private_netns=True)
    with open_bus(small) as fieldbus, open_bus(io_cfg) as io, open_bus(cfg) as tx:
        app = App()
        node = SlaveNode(app, fieldbus, io, node_id=5)
        for i in range(100):  # far more than 8 KiB of receive buffer holds; then silence
            tx.send(can.Message(arbitration_id=0x185, is_extended_id=False, data=i.to_bytes(2, "big")))
        handled = []
        while not app.lost and len(handled) < 50:
            handled.append(node.step(0.1))
        print(json.dumps({"lost_calls": app.lost, "steps": handled, "frames_lost": fieldbus.frames_lost}))
    """
)


@pytest.mark.netns
@pytest.mark.multiprocess
def test_a_node_hears_the_loss_of_the_last_datagram_before_a_silence(tmp_path: Path) -> None:
    """No datagram follows the loss to carry the socket's drop count (udp_multicast): the node's
    drain ends with a receive that finds nothing, which reads the drop count (``SO_MEMINFO``), so
    the loss reaches the application as a receive overflow (a drive: EMCY 0x8110) all the same,
    once, in the node's first steps."""
    out = script_report_in_netns(tmp_path, "silent_loss.py", SILENT_LOSS_SCRIPT, timeout_s=60)
    assert out["lost_calls"] == 1 and out["frames_lost"] > 0, out
    assert len(out["steps"]) <= 3, out


@pytest.mark.netns
@pytest.mark.multiprocess
@pytest.mark.slow
def test_a_lost_datagram_is_a_fault_of_the_run(tmp_path: Path) -> None:
    """``ilcrig run --bus udp_multicast`` with fieldbus receive buffers far too small for an SDO
    block: the losses are reported as bus errors and the run stops with a fault (exit code 3)
    instead of going on with frames missing. The losses come at the first bursts of the bus (the
    nodes' boot-ups answering the host's NMT reset, the host's first SDO requests): a loss in the
    host's receiver (it may have been a boot-up or an SDO response) or a node's EMCY 0x8110 (a
    drive's or the plant node's receiver lost the NMT command or an SDO request) is the run's fault at once, whichever comes
    first; never the host's ``--wait`` running out (30 s here) or an SDO request timing out."""
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(reason)
    out = tmp_path / "rig"
    env = {
        **os.environ,
        "ILCRIG_PRIVATE_NETNS": "1",
        "CAN_CONFIG_fieldbus": json.dumps({"receive_buffer_bytes": 4096}),
        "ILCRIG_ROLE_CMD_HOST": f"{sys.executable} -P -m host.cli host --wait 30",
    }
    cmd = [sys.executable, "-m", "host.cli", "run", "--iterations", "1", "--bus", "udp_multicast", "--out", str(out)]
    wrapped = ["unshare", "-rn", "sh", "-c", f'{NETNS_SETUP} && exec "$0" "$@"', *cmd]
    res = subprocess.run(wrapped, capture_output=True, text=True, env=env, timeout=300, start_new_session=True, check=False)
    assert res.returncode == 3, res.stdout[-2000:] + res.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is False and summary["faults"]  # which loss comes first is a race
    first = summary["faults"][0]
    assert (first["kind"], first["message"]) in (
        # the host's receiver or a channel monitor's
        ("frame_lost", "frames lost on fieldbus: a receiver's queue overflowed (receive-overflow error frame)"),
        ("frame_lost", f"fieldbus frames lost in {first['node']}'s receiver (receive overflow) (EMCY 0x8110)"),  # a drive's
        (
            "frame_lost",
            "fieldbus frames lost in the plant node's receiver (receive overflow) at tick 0 (EMCY 0x8110 of the plant node)",
        ),
    ), first
    logs = "".join(p.read_text() for p in (out / "logs").glob("*.log"))
    assert "datagram(s) lost" in logs and "reported as a bus error frame" in logs
