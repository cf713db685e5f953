"""Tests of firmware_model/drive_node.py: the drive node runtime on python-can virtual buses, checked
from the host side with the canopen library (RemoteNode, SDO client, NMT, heartbeat).

Synchronisation is by events only: a test waits for the frame or state it expects (with a
timeout that only bounds a failure), never sleeps for a guessed time.  That something does NOT
happen is shown with a probe sent behind it on the same bus (the node serves each bus in
order): once the probe's effect is seen, the earlier frame has been handled.  Heartbeat timing
is checked on a manual node clock, never against the wall clock."""

from __future__ import annotations

import itertools
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import canopen
import clock_util
import pytest
from can.interfaces.virtual import VirtualBus
from clock_util import ManualClock
from hypothesis import example, given, settings
from hypothesis import strategies as st

from bus import io_frames
from bus.can_errors import overflow_error_frame
from bus.cia301.emcy import EmcyCode
from bus.cia301.nmt import NmtCommand, NmtState, next_state
from bus.errors import AbortCode, SdoAbort
from bus.objects import Cia402State, ControlCommand, FaultCause, state_from_statusword
from firmware_model.control_law import warm_up
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode, DriveOptions, run_drive

EDS = Path(__file__).resolve().parents[1] / "bus" / "drive.eds"
NODE = 2
_counter = itertools.count()

pytestmark = pytest.mark.usefixtures("no_leaked_virtual_channels")


class FakeDrive:
    """Minimal stand-in for firmware_model.drive.Drive (object access, NMT, EMCY, io_tick and
    the torque-frame state: ``torque_enabled``, ``statusword``)."""

    def __init__(self, node_id: int) -> None:
        self.node_id = node_id
        self.nmt_state = NmtState.PRE_OPERATIONAL
        self.objects: dict[tuple[int, int], bytes] = {
            (0x1017, 0): struct.pack("<H", 0),
            (0x1018, 1): struct.pack("<L", 0x1234),
            (0x6040, 0): struct.pack("<H", 0),
            (0x6041, 0): struct.pack("<H", 0x0240),
        }
        self.emcy: list[tuple[int, int, bytes]] = []
        self.ticks: list[tuple[int, int]] = []
        self.nmt_log: list[int] = []

    def read_object(self, index: int, sub: int) -> bytes:
        try:
            return self.objects[(index, sub)]
        except KeyError:
            raise SdoAbort(AbortCode.NO_OBJECT) from None

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        if (index, sub) not in self.objects:
            raise SdoAbort(AbortCode.NO_OBJECT)
        if index == 0x6041:
            raise SdoAbort(AbortCode.READ_ONLY)
        self.objects[(index, sub)] = bytes(data)
        if index == 0x6040:
            sw = {0x06: 0x0221, 0x07: 0x0223, 0x0F: 0x0237}.get(data[0], 0x0240)
            self.objects[(0x6041, 0)] = struct.pack("<H", sw)
            if data[0] == 0xFF:
                self.emcy.append((EmcyCode.FOLLOWING_ERROR, 0x21, b"\x01"))

    def nmt_command(self, cs: int) -> None:
        self.nmt_log.append(cs)
        self.nmt_state = next_state(self.nmt_state, NmtCommand(cs))

    def pop_emcy(self) -> list[tuple[int, int, bytes]]:
        out, self.emcy = self.emcy, []
        return out

    def io_tick(self, tick: int, encoder_count: int) -> int:
        self.ticks.append((tick, encoder_count))
        return -encoder_count

    torque_enabled = True

    @property
    def statusword(self) -> int:
        return int(struct.unpack("<H", self.objects[(0x6041, 0)])[0])


class Rig:
    """A DriveNode in a thread + a canopen host Network + a plant-side io bus."""

    def __init__(self, drive: object, fieldbus: type[VirtualBus] = VirtualBus) -> None:
        k = next(_counter)
        self.fb_channel, self.io_channel = f"node-fb-{k}", f"node-io-{k}"
        self.drive = drive
        self.stop = threading.Event()
        self.fb = fieldbus(channel=self.fb_channel)
        self.io = can.Bus(interface="virtual", channel=self.io_channel)
        self.node = DriveNode(drive, self.fb, self.io)  # type: ignore[arg-type]
        self.plant = can.Bus(interface="virtual", channel=self.io_channel)
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.02
        self.network.connect(interface="virtual", channel=self.fb_channel)
        self.heartbeats: list[int] = []  # NMT state byte of every heartbeat / boot-up frame
        self.emcys: list[bytes] = []
        self.network.subscribe(0x700 + NODE, lambda _id, data, _t: self.heartbeats.append(data[0]))
        self.network.subscribe(0x080 + NODE, lambda _id, data, _t: self.emcys.append(bytes(data)))
        self.remote = canopen.RemoteNode(NODE, str(EDS))
        self.network.add_node(self.remote)
        self.thread = threading.Thread(target=self.node.run, args=(self.stop,), daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2.0)
        assert not self.thread.is_alive()
        self.network.disconnect()
        self.plant.shutdown()
        self.fb.shutdown()
        self.io.shutdown()


def wait_for(predicate: Callable[[], object], timeout_s: float = 1.0) -> bool:
    """:func:`clock_util.wait_for`, by default for 1 s."""
    return clock_util.wait_for(predicate, timeout_s)


@pytest.fixture
def fake_rig() -> Iterator[Rig]:
    rig = Rig(FakeDrive(NODE))
    try:
        yield rig
    finally:
        rig.close()


def test_bootup_sdo_nmt_heartbeat_fake_drive(fake_rig: Rig) -> None:
    rig = fake_rig
    assert wait_for(lambda: rig.heartbeats[:1] == [0x00])  # boot-up
    assert rig.remote.sdo.upload(0x1018, 1) == struct.pack("<L", 0x1234)
    assert rig.remote.sdo[0x6041].raw == 0x0240
    for cw, sw in ((0x06, 0x0221), (0x07, 0x0223), (0x0F, 0x0237)):
        rig.remote.sdo[0x6040].raw = cw
        assert rig.remote.sdo[0x6041].raw == sw
    with pytest.raises(canopen.SdoAbortedError) as err:
        rig.remote.sdo[0x6041].raw = 1
    assert err.value.code == 0x06010002
    rig.remote.sdo[0x1017].raw = 20  # ms; the period itself: test_heartbeat_period_is_0x1017_on_the_node_clock
    rig.remote.nmt.send_command(0x01)
    assert wait_for(lambda: rig.heartbeats.count(0x05) >= 3)
    assert rig.drive.nmt_log == [0x01]
    # NMT to another node is ignored: a STOP for node 3, then a probe for this node behind it
    # (enter pre-operational); once the probe is applied, the STOP has been seen and dropped
    rig.network.send_message(0, bytes([0x02, NODE + 1]))
    rig.network.send_message(0, bytes([0x80, NODE]))
    assert wait_for(lambda: rig.drive.nmt_log[-1:] == [0x80])
    assert rig.drive.nmt_log == [0x01, 0x80]
    assert rig.drive.nmt_state == NmtState.PRE_OPERATIONAL


def test_stopped_node_ignores_sdo_and_reset_sends_bootup(fake_rig: Rig) -> None:
    rig = fake_rig
    rig.remote.sdo.RESPONSE_TIMEOUT = 0.05
    rig.remote.nmt.send_command(0x02)  # stop
    assert wait_for(lambda: rig.drive.nmt_state == NmtState.STOPPED)
    with pytest.raises(canopen.SdoCommunicationError):
        rig.remote.sdo.upload(0x1018, 1)
    rig.heartbeats.clear()
    rig.remote.nmt.send_command(0x81)  # reset node (all via node id)
    assert wait_for(lambda: 0x00 in rig.heartbeats)
    assert rig.remote.sdo.upload(0x1018, 1) == struct.pack("<L", 0x1234)


def test_emcy_frames_sent(fake_rig: Rig) -> None:
    rig = fake_rig
    rig.remote.sdo[0x6040].raw = 0xFF  # the fake raises a following-error EMCY
    assert wait_for(lambda: bool(rig.emcys))
    assert rig.emcys[0] == bytes.fromhex("11 86 21 01 00 00 00 00")


def test_io_tick_round_trip_and_tick_unwrap(fake_rig: Rig) -> None:
    rig = fake_rig
    joint = NODE - 1
    rig.plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 0, 70000))
    torques = []
    for n in [0, 1, 2]:
        rig.plant.send(io_frames.encode_encoder(joint, n, 1000 + n))
        rig.plant.send(io_frames.encode_encoder(joint + 1, n, 5))  # another joint: ignored
        msg = rig.plant.recv(timeout=1.0)
        assert msg is not None
        torques.append(io_frames.decode_torque(msg))
    assert [(t.tick, t.torque_units) for t in torques] == [(0, -1000), (1, -1001), (2, -1002)]
    assert torques[0].status == io_frames.TorqueStatus.ENABLED
    assert rig.drive.ticks == [(0, 1000), (1, 1001), (2, 1002)]


def test_tick_is_relative_to_trial_start_and_unwrapped(fake_rig: Rig) -> None:
    """The drive sees n = 0, 1, ... from TRIAL_START on, across the 16-bit wire wrap; the
    torque frames echo the wire tick."""
    rig = fake_rig
    joint = NODE - 1
    rig.plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 65533, 6))
    wire = []
    for k in range(6):
        rig.plant.send(io_frames.encode_encoder(joint, 65533 + k, k))
        msg = rig.plant.recv(timeout=1.0)
        assert msg is not None
        wire.append(io_frames.decode_torque(msg).tick)
    assert [t for t, _ in rig.drive.ticks] == [0, 1, 2, 3, 4, 5]
    assert wire == [65533, 65534, 65535, 0, 1, 2]


def test_own_frames_are_ignored(fake_rig: Rig) -> None:
    """udp_multicast echoes a node's own frames: SDO responses, heartbeats, torques.  Probes
    behind the echoes on the same buses (an NMT command, an encoder frame) show that the echoes
    have been handled: the only effects are the probes'."""
    rig = fake_rig
    node = rig.node
    assert wait_for(lambda: rig.heartbeats[:1] == [0x00])  # serving
    assert (rig.drive.ticks, rig.drive.nmt_log) == ([], [])
    rig.network.send_message(0x580 + NODE, bytes(8))
    rig.network.send_message(0x700 + NODE, b"\x05")
    rig.plant.send(io_frames.encode_torque(NODE - 1, 0, 1, 0))
    rig.network.send_message(0, bytes([0x80, NODE]))  # probe: enter pre-operational
    rig.plant.send(io_frames.encode_encoder(NODE - 1, 0, 321))  # probe: one io tick
    answer = rig.plant.recv(timeout=1.0)  # the first io frame of the node is the probe's torque
    assert answer is not None
    torque = io_frames.decode_torque(answer)
    assert (answer.arbitration_id, torque.tick, torque.torque_units) == (io_frames.torque_cob_id(NODE - 1), 0, -321)
    assert wait_for(lambda: rig.drive.nmt_log != [])
    assert (rig.drive.ticks, rig.drive.nmt_log) == ([(0, 321)], [0x80])
    assert not node.sdo.busy
    assert rig.remote.sdo.upload(0x1018, 1) == struct.pack("<L", 0x1234)  # and SDO still answers


def _virtual_buses(name: str) -> tuple[can.BusABC, can.BusABC, can.BusABC]:
    """Fresh virtual buses: the node's fieldbus end, the host's end of it, the node's io bus."""
    k = next(_counter)
    fb = f"{name}-fb-{k}"
    return (
        can.Bus(interface="virtual", channel=fb),
        can.Bus(interface="virtual", channel=fb),
        can.Bus(interface="virtual", channel=f"{name}-io-{k}"),
    )


def _stepper(
    node: DriveNode, host: can.BusABC, clock: ManualClock
) -> tuple[Callable[[], list[tuple[int, bytes]]], Callable[[float], list[tuple[int, bytes]]]]:
    """For a node the test steps on a manual clock: ``sent()``, the frames waiting at the host
    (id, data), and ``step_at(t)``, one step of the node at clock time ``t`` s and what it sent."""

    def sent() -> list[tuple[int, bytes]]:
        out = []
        while (msg := host.recv(timeout=0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out

    def step_at(t: float) -> list[tuple[int, bytes]]:
        clock.now = t
        node.step(0.0)
        return sent()

    return sent, step_at


def test_heartbeat_period_is_0x1017_on_the_node_clock() -> None:
    """Heartbeat timing, deterministic: the node is stepped by the test (no thread) on a manual
    clock; a virtual bus delivers on send, so after ``step`` every frame the node sent is
    waiting.  The period comes from 0x1017 (written over SDO, the timer restarts then); one
    beat per period with the NMT state, none before it is due, a late step sends one beat (no
    burst) and a beat less than a period late keeps the phase."""
    fb_node, host, io_node = _virtual_buses("hb")
    clock = ManualClock(1000.0)
    drive = FakeDrive(NODE)
    node = DriveNode(drive, fb_node, io_node, clock=clock)  # type: ignore[arg-type]

    sent, step_at = _stepper(node, host, clock)

    beat = (0x702, b"\x7f")  # pre-operational
    try:
        node.start()
        assert sent() == [(0x702, b"\x00")]  # boot-up; 0x1017 = 0: no heartbeat
        assert step_at(1010.0) == []
        host.send(
            can.Message(arbitration_id=0x602, data=bytes.fromhex("2B 17 10 00 7D 00 00 00"), is_extended_id=False)
        )  # 0x1017 := 125 ms
        t0 = 1020.0  # the download is handled at t0: first beat due at t0 + 0.125
        assert step_at(t0) == [(0x582, bytes.fromhex("60 17 10 00 00 00 00 00"))]
        assert step_at(t0 + 0.124) == []
        assert step_at(t0 + 0.125) == [beat]
        assert step_at(t0 + 0.125) == []
        assert step_at(t0 + 0.249) == []
        assert step_at(t0 + 0.25) == [beat]
        host.send(can.Message(arbitration_id=0, data=bytes([0x01, NODE]), is_extended_id=False))
        assert step_at(t0 + 0.3) == []  # NMT start applied; the heartbeat keeps its own timer
        assert drive.nmt_state == NmtState.OPERATIONAL
        beat = (0x702, b"\x05")
        assert step_at(t0 + 0.4) == [beat]  # due at t0 + 0.375: 25 ms late
        assert step_at(t0 + 0.499) == []  # the phase is kept: next due t0 + 0.5
        assert step_at(t0 + 0.5) == [beat]
        assert step_at(t0 + 0.875) == [beat]  # two periods missed: one beat, no burst
        assert step_at(t0 + 0.875) == []
        # between steps (a drive waiting for its processor-in-the-loop target): the same timer
        clock.now = t0 + 0.999
        node.heartbeat_if_due()
        assert sent() == []
        clock.now = t0 + 1.0
        node.heartbeat_if_due()
        assert sent() == [beat]
        assert step_at(t0 + 1.1) == []  # the step after it keeps the phase: next due t0 + 1.125
        assert step_at(t0 + 1.125) == [beat]
    finally:
        for bus in (fb_node, host, io_node):
            bus.shutdown()


def test_real_drive_enable_sequence() -> None:
    """The real firmware: 0x1018/0x6041 over SDO, the CiA 402 enable sequence, NMT start,
    heartbeat."""
    warm_up()  # compile the control kernel first (as run_node does), not inside the first io tick
    rig = Rig(Drive(NODE))
    try:
        remote = rig.remote
        assert wait_for(lambda: rig.heartbeats[:1] == [0x00])
        vendor = remote.sdo[0x1018][1].raw
        assert isinstance(vendor, int)
        sw = remote.sdo[0x6041].raw
        assert state_from_statusword(sw) == Cia402State.SWITCH_ON_DISABLED
        remote.sdo[0x1017].raw = 20
        remote.nmt.send_command(0x01)
        assert wait_for(lambda: 0x05 in rig.heartbeats)
        for cw, state in (
            (ControlCommand.SHUTDOWN, Cia402State.READY_TO_SWITCH_ON),
            (ControlCommand.SWITCH_ON, Cia402State.SWITCHED_ON),
            (ControlCommand.ENABLE_OPERATION, Cia402State.OPERATION_ENABLED),
        ):
            remote.sdo[0x6040].raw = int(cw)
            assert state_from_statusword(remote.sdo[0x6041].raw) == state
        remote.nmt.wait_for_heartbeat(timeout=1.0)
        assert remote.nmt.state == "OPERATIONAL"
        # one io tick: the enabled drive answers with a torque frame, status ENABLED
        rig.plant.send(io_frames.encode_encoder(NODE - 1, 0, 12345))
        msg = rig.plant.recv(timeout=10.0)  # bounds a failure only
        assert msg is not None
        torque = io_frames.decode_torque(msg)
        assert torque.tick == 0 and torque.status & io_frames.TorqueStatus.ENABLED
        # disable voltage: torque removed, status no longer ENABLED
        remote.sdo[0x6040].raw = int(ControlCommand.DISABLE_VOLTAGE)
        rig.plant.send(io_frames.encode_encoder(NODE - 1, 1, 12345))
        msg = rig.plant.recv(timeout=10.0)
        assert msg is not None
        torque = io_frames.decode_torque(msg)
        assert torque.torque_units == 0 and not torque.status & io_frames.TorqueStatus.ENABLED
    finally:
        rig.close()


class ErrorFramesVirtualBus(VirtualBus):
    """python-can's virtual bus delivering error frames whatever its acceptance filters, as
    SocketCAN (its error mask) and the project's udp_multicast bus do."""

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg, filtered = super()._recv_internal(timeout)
        return msg, filtered or (msg is not None and msg.is_error_frame)


@pytest.mark.parametrize(
    ("behaviour", "enable", "nmt", "state"),
    [
        (0, False, NmtState.PRE_OPERATIONAL, Cia402State.SWITCH_ON_DISABLED),  # 0x1029:1 = 0, the default
        (0, True, NmtState.PRE_OPERATIONAL, Cia402State.FAULT),  # leaving OPERATIONAL: 0x6007 = 1, Fault
        (1, True, NmtState.OPERATIONAL, Cia402State.OPERATION_ENABLED),  # no NMT change: torque stays
        (2, False, NmtState.STOPPED, Cia402State.SWITCH_ON_DISABLED),
    ],
)
def test_lost_fieldbus_frames_are_emcy_8110_and_react_per_0x1029(
    behaviour: int, enable: bool, nmt: NmtState, state: Cia402State
) -> None:
    """A receive-overflow error frame on the fieldbus (udp_multicast's report of dropped datagrams):
    EMCY 0x8110 "CAN overrun" with the error register's communication bit, 0x1003, and the NMT
    state 0x1029:1 says -- in STOPPED the EMCY waits until the node leaves it (CiA 301)."""
    warm_up()
    drive = Drive(NODE)
    rig = Rig(drive, fieldbus=ErrorFramesVirtualBus)
    try:
        remote = rig.remote
        assert wait_for(lambda: rig.heartbeats[:1] == [0x00], 10.0)
        remote.sdo[0x1029][1].raw = behaviour
        remote.sdo[0x1017].raw = 10
        remote.nmt.send_command(0x01)
        assert wait_for(lambda: rig.heartbeats[-1:] == [0x05], 10.0)
        if enable:
            for cw in (ControlCommand.SHUTDOWN, ControlCommand.SWITCH_ON, ControlCommand.ENABLE_OPERATION):
                remote.sdo[0x6040].raw = int(cw)
            assert drive.torque_enabled
        rig.network.bus.send(overflow_error_frame(time.time()))
        byte = {NmtState.PRE_OPERATIONAL: 0x7F, NmtState.OPERATIONAL: 0x05, NmtState.STOPPED: 0x04}[nmt]
        assert wait_for(lambda: rig.heartbeats[-2:] == [byte, byte], 10.0), rig.heartbeats[-5:]
        assert drive.nmt_state == nmt and drive.cia402_state == state
        emcy = bytes.fromhex("10 81 11") + bytes([FaultCause.CAN_OVERRUN, 0, 0, 0, 0])
        if nmt == NmtState.STOPPED:
            assert rig.emcys == []  # none in STOPPED
            remote.nmt.send_command(0x80)
        assert wait_for(lambda: rig.emcys == [emcy], 10.0), rig.emcys
        assert remote.sdo[0x1001].raw == 0x11
        assert (remote.sdo[0x1003][0].raw, remote.sdo[0x1003][1].raw) == (1, 0x8110)
        assert remote.sdo[0x603F].raw == (0x8110 if state == Cia402State.FAULT else 0)
    finally:
        rig.close()


def test_other_error_frames_are_passed_over() -> None:
    """A bus error frame of another kind (a CRC error of a damaged frame): nothing happens."""
    drive = Drive(NODE)
    rig = Rig(drive, fieldbus=ErrorFramesVirtualBus)
    try:
        remote = rig.remote
        assert wait_for(lambda: rig.heartbeats[:1] == [0x00], 10.0)
        crc = can.Message(is_error_frame=True, arbitration_id=0x008, is_extended_id=False, data=bytes([0, 0, 0, 8, 0, 0, 0, 0]))
        rig.network.bus.send(crc)
        assert remote.sdo[0x1001].raw == 0  # the probe behind it: the error frame was handled
        assert remote.sdo[0x1003][0].raw == 0 and rig.emcys == [] and drive.nmt_state == NmtState.PRE_OPERATIONAL
    finally:
        rig.close()


class SocketPairBus(can.BusABC):
    """A two-party python-can bus over a SOCK_SEQPACKET socketpair: it has a fileno(), so the
    node takes its select() path."""

    _REC = struct.Struct("<IB8s")

    def __init__(self, sock, **kwargs) -> None:  # noqa: ANN001
        self._sock = sock
        super().__init__(channel="pair", **kwargs)

    @classmethod
    def pair(cls) -> tuple[SocketPairBus, SocketPairBus]:
        import socket

        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        return cls(a), cls(b)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._sock.send(self._REC.pack(msg.arbitration_id, msg.dlc, bytes(msg.data)))

    def _recv_internal(self, timeout: float | None):  # noqa: ANN202
        import select as _select

        ready, _, _ = _select.select([self._sock], [], [], timeout)
        if not ready:
            return None, False
        cob, dlc, data = self._REC.unpack(self._sock.recv(64))
        return can.Message(arbitration_id=cob, data=data[:dlc], is_extended_id=False), False

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()


def test_select_path_with_fileno_buses() -> None:
    """The select() path: boot-up, SDO, io tick, and heartbeats that only the heartbeat deadline
    can wake (MAX_WAIT_S is made huge), on a manual node clock: one beat each time the clock
    passes a 0x1017 period, none before, none extra."""
    drive = FakeDrive(NODE)
    drive.objects[(0x1017, 0)] = struct.pack("<H", 125)  # ms (exact in binary: exact due times)
    fb_node, fb_host = SocketPairBus.pair()
    io_node, io_plant = SocketPairBus.pair()
    clock = ManualClock(1000.0)
    node = DriveNode(drive, fb_node, io_node, clock=clock)  # type: ignore[arg-type]
    node.MAX_WAIT_S = 3600.0  # a quiet select() ends at the heartbeat deadline or not at all
    assert node._fds is not None
    stop = threading.Event()
    thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
    thread.start()
    try:
        boot = fb_host.recv(timeout=1.0)
        assert boot is not None and (boot.arbitration_id, bytes(boot.data)) == (0x702, b"\x00")
        upload = can.Message(arbitration_id=0x602, data=bytes.fromhex("40 18 10 01 00 00 00 00"), is_extended_id=False)
        fb_host.send(upload)
        resp = fb_host.recv(timeout=1.0)  # the clock stands still: no heartbeat before the answer
        assert resp is not None and resp.arbitration_id == 0x582
        assert bytes(resp.data) == bytes.fromhex("43 18 10 01 34 12 00 00")
        io_plant.send(io_frames.encode_encoder(NODE - 1, 0, 42))
        torque = io_plant.recv(timeout=1.0)
        assert torque is not None and io_frames.decode_torque(torque).torque_units == -42
        for k in (1, 2, 3):
            clock.now = 1000.0 + 0.125 * k  # due: the node's select() times out and beats
            beat = fb_host.recv(timeout=5.0)
            assert beat is not None and (beat.arbitration_id, bytes(beat.data)) == (0x702, b"\x7f"), k
        fb_host.send(upload)  # probe: the next frame is its answer, no extra beat in between
        resp = fb_host.recv(timeout=1.0)
        assert resp is not None and resp.arbitration_id == 0x582
    finally:
        stop.set()
        thread.join(timeout=2.0)
        for bus in (fb_node, fb_host, io_node, io_plant):
            bus.shutdown()
    assert not thread.is_alive()


def test_run_drive_process_entry_with_stop_event() -> None:
    """run_drive (``ilcrig drive``'s typed entry over run_node) builds the real Drive and both
    buses, serves, cleans up on stop and exits 0."""
    k = next(_counter)
    fb_cfg = {"interface": "virtual", "channel": f"run-fb-{k}"}
    io_cfg = {"interface": "virtual", "channel": f"run-io-{k}"}
    codes: list[int] = []
    with can.Bus(**fb_cfg) as host, can.Bus(**io_cfg) as plant:
        stop = threading.Event()
        opts = DriveOptions(3, fb_cfg, io_cfg)
        thread = threading.Thread(target=lambda: codes.append(run_drive(opts, stop)), daemon=True)
        thread.start()
        try:
            boot = host.recv(timeout=5.0)
            assert boot is not None and boot.arbitration_id == 0x703 and bytes(boot.data) == b"\x00"
            plant.send(io_frames.encode_encoder(2, 0, 99))
            msg = plant.recv(timeout=1.0)
            assert msg is not None and io_frames.decode_torque(msg).torque_units == 0  # disabled
        finally:
            stop.set()
            thread.join(timeout=2.0)
        assert not thread.is_alive() and codes == [0]


def test_emcy_cob_id_valid_bit_and_inhibit_time_and_rtr_on_the_node_clock() -> None:
    """0x1014 and 0x1015 as the node runtime applies them, stepped on a manual clock: the EMCY goes
    out on the COB-ID of 0x1014 (none while its bit 31 is set), at most one per inhibit time (the
    next waits, then goes out exactly when the time ends); a remote frame on a TPDO whose bit 30
    is 0 is answered with the TPDO."""
    fb_node, host, io_node = _virtual_buses("emcy")
    clock = ManualClock(50.0)
    drive = Drive(NODE)
    for index, sub, value in ((0x1A00, 0, 0), (0x1A00, 1, 0x60410010), (0x1A00, 0, 1), (0x1800, 1, 0x180 + NODE)):
        drive.write_object(index, sub, value.to_bytes(4 if sub else 1, "little"))
    node = DriveNode(drive, fb_node, io_node, clock=clock)

    sent, step_at = _stepper(node, host, clock)

    def sdo_write(index: int, sub: int, data: bytes, t: float) -> None:
        cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[len(data)]
        request = bytes([cs, index & 0xFF, index >> 8, sub]) + data.ljust(4, b"\0")
        host.send(can.Message(arbitration_id=0x600 + NODE, data=request, is_extended_id=False))
        assert step_at(t) == [(0x580 + NODE, bytes([0x60, index & 0xFF, index >> 8, sub, 0, 0, 0, 0]))]

    emcy = (0x80 + NODE, bytes.fromhex("10 81 11 00 00 00 00 00"))
    try:
        node.start()
        sent()
        drive.power.warning(0x8110, bytes(5))
        drive.power.warning(0x8110, bytes(5))
        assert step_at(50.0) == [emcy, emcy]  # no inhibit time: both at once
        sdo_write(0x1015, 0, struct.pack("<H", 100), 51.0)  # 10 ms
        drive.power.warning(0x8110, bytes(5))
        drive.power.warning(0x8110, bytes(5))
        assert step_at(52.0) == [emcy]
        assert step_at(52.0099) == []
        assert step_at(52.010) == [emcy]
        sdo_write(0x1014, 0, struct.pack("<I", 0x8000_0000 | (0x80 + NODE)), 53.0)
        drive.power.warning(0x8110, bytes(5))
        assert step_at(54.0) == []  # not valid: not sent
        sdo_write(0x1014, 0, struct.pack("<I", 0x8000_00F0), 55.0)
        sdo_write(0x1014, 0, struct.pack("<I", 0x0F0), 56.0)
        drive.power.warning(0x8110, bytes(5))
        assert step_at(57.0) == [(0x0F0, emcy[1])]
        host.send(can.Message(arbitration_id=0, data=bytes([0x01, NODE]), is_extended_id=False))
        step_at(58.0)
        sent()  # the event TPDO of the start
        host.send(can.Message(arbitration_id=0x180 + NODE, is_remote_frame=True, dlc=2, is_extended_id=False))
        assert step_at(59.0) == [(0x180 + NODE, struct.pack("<H", 0x0240))]
    finally:
        for bus in (fb_node, host, io_node):
            bus.shutdown()


def test_lockstep_drive_of_a_sync_stepped_plant() -> None:
    """``DriveNode(lockstep=True)`` (``ilcrig drive --lockstep``): the heartbeat and the SYNC watchdog
    run on the node's clock (here a manual one), so they go on while no SYNC comes; the event timer
    of a TPDO counts the control periods of the io ticks; a synchronous TPDO carries the io tick
    of its SYNC, after the torque frame."""
    k = next(_counter)
    fb_node = can.Bus(interface="virtual", channel=f"ls-fb-{k}")
    host = can.Bus(interface="virtual", channel=f"ls-fb-{k}")
    io_node = can.Bus(interface="virtual", channel=f"ls-io-{k}")
    plant = can.Bus(interface="virtual", channel=f"ls-io-{k}")
    now = [100.0]
    drive = Drive(NODE)
    node = DriveNode(drive, fb_node, io_node, clock=lambda: now[0], lockstep=True)

    def frames() -> list[tuple[int, bytes]]:
        out = []
        while (msg := host.recv(timeout=0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out

    def sdo(index: int, sub: int, fmt: str, value: int) -> None:
        data = struct.pack("<" + fmt, value).ljust(4, b"\0")
        size = {1: 0x2F, 2: 0x2B, 4: 0x23}[struct.calcsize(fmt)]
        host.send(
            can.Message(
                arbitration_id=0x600 + NODE, data=bytes([size]) + struct.pack("<HB", index, sub) + data, is_extended_id=False
            )
        )
        node.step(0.0)

    def sync_and_tick(count: int) -> None:
        host.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        node.step(0.0)
        plant.send(io_frames.encode_encoder(NODE - 1, drive.time_us // 1000, count))
        node.step(0.0)
        assert plant.recv(timeout=1.0) is not None  # the torque frame

    try:
        node.start()
        sdo(0x1017, 0, "H", 5)  # heartbeat 5 ms
        sdo(0x1800, 1, "I", 0x8000_0180 + NODE)  # TPDO1: position actual, synchronous
        sdo(0x1A00, 0, "B", 0)
        sdo(0x1A00, 1, "I", 0x60640020)
        sdo(0x1A00, 0, "B", 1)
        sdo(0x1800, 2, "B", 1)
        sdo(0x1800, 1, "I", 0x180 + NODE)
        sdo(0x1801, 1, "I", 0x8000_0280 + NODE)  # TPDO2: statusword, on change, event timer 5 ms
        sdo(0x1A01, 0, "B", 0)
        sdo(0x1A01, 1, "I", 0x60410010)
        sdo(0x1A01, 0, "B", 1)
        sdo(0x1801, 2, "B", 255)
        sdo(0x1801, 5, "H", 5)
        sdo(0x1801, 1, "I", 0x280 + NODE)
        sdo(0x1006, 0, "I", 10_000)  # SYNC every 10 ms: lost after 15 ms
        host.send(can.Message(arbitration_id=0, data=bytes([0x01, NODE]), is_extended_id=False))
        node.step(0.0)
        frames()
        now[0] += 0.005
        node.step(0.0)
        assert [cob for cob, _ in frames()] == [0x700 + NODE]  # heartbeat on the node's clock, no event TPDO
        seen = []
        for count in range(1000, 1005):
            sync_and_tick(count)
            seen.append(frames())
        # each SYNC's TPDO1 carries the count of its own tick; TPDO2's event timer at the 5th period
        assert [[(cob, data) for cob, data in f if cob != 0x280 + NODE] for f in seen] == [
            [(0x180 + NODE, struct.pack("<i", c))] for c in range(1000, 1005)
        ]
        assert [sum(cob == 0x280 + NODE for cob, _ in f) for f in seen] == [0, 0, 0, 0, 1]
        assert drive.lockstep_time_s() == 0.005
        now[0] += 0.0149
        node.step(0.0)
        assert all(cob == 0x700 + NODE for cob, _ in frames())  # heartbeats only: the SYNC is not late yet
        now[0] += 0.0002
        node.step(0.0)
        emcy = [data for cob, data in frames() if cob == 0x80 + NODE]
        assert emcy and emcy[0][:2] == struct.pack("<H", 0x8100)  # SYNC lost, on the node's clock
        assert drive.lockstep_time_s() == 0.005  # no io tick: the lockstep time stood still
    finally:
        for bus in (fb_node, host, io_node, plant):
            bus.shutdown()


class _PairedLockstepDrive:
    """A real drive of a SYNC-stepped plant (``lockstep=True``) on socket-pair buses (the select()
    path), stepped by the test: RPDO1 = controlword + target, TPDO1 = statusword + position actual,
    both synchronous; heartbeat off, so that only frames end a wait."""

    def __init__(self) -> None:
        self.fb_node, self.fb = SocketPairBus.pair()
        self.io_node, self.io = SocketPairBus.pair()
        self.drive = Drive(NODE)
        self.node = DriveNode(self.drive, self.fb_node, self.io_node, lockstep=True)
        self.node.start()
        self.download(0x1017, 0, struct.pack("<H", 0))
        for comm, entries, cob in (
            (0x1800, (0x60410010, 0x60640020), 0x180 + NODE),
            (0x1400, (0x60400010, 0x607A0020), 0x200 + NODE),
        ):
            self.download(comm, 1, struct.pack("<I", 0x8000_0000 | cob))
            self.download(comm + 0x200, 0, b"\x00")
            for sub, entry in enumerate(entries, start=1):
                self.download(comm + 0x200, sub, struct.pack("<I", entry))
            self.download(comm + 0x200, 0, bytes([len(entries)]))
            self.download(comm, 2, b"\x01")
            self.download(comm, 1, struct.pack("<I", cob))
        self.fb.send(can.Message(arbitration_id=0, data=bytes([0x01, NODE]), is_extended_id=False))
        self.node.step(1.0)
        self.wire = 0

    def fieldbus_frames(self) -> list[tuple[int, bytes]]:
        out = []
        while (msg := self.fb.recv(timeout=0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out

    def download(self, index: int, sub: int, data: bytes) -> None:
        command = {1: 0x2F, 2: 0x2B, 4: 0x23}[len(data)]
        request = bytes([command]) + struct.pack("<HB", index, sub) + data.ljust(4, b"\0")
        self.fb.send(can.Message(arbitration_id=0x600 + NODE, data=request, is_extended_id=False))
        self.node.step(1.0)
        answers = [data for cob, data in self.fieldbus_frames() if cob == 0x580 + NODE]
        assert answers and answers[-1][0] == 0x60, (hex(index), sub, answers)

    def rpdo_and_sync(self, target: int) -> None:
        self.fb.send(can.Message(arbitration_id=0x200 + NODE, data=struct.pack("<Hi", 0x06, target), is_extended_id=False))
        self.fb.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))

    def encoder(self, count: int) -> None:
        self.io.send(io_frames.encode_encoder(NODE - 1, self.wire & io_frames.TICK_MASK, count))
        self.wire += 1

    def step_in_thread(self, max_wait_s: float) -> tuple[threading.Thread, list[int]]:
        """``node.step(max_wait_s)`` in a thread of its own; its frame count lands in the list."""
        got: list[int] = []
        thread = threading.Thread(target=lambda: got.append(self.node.step(max_wait_s)), daemon=True)
        thread.start()
        return thread, got

    def close(self) -> None:
        for bus in (self.fb_node, self.fb, self.io_node, self.io):
            bus.shutdown()


def test_a_sync_stepped_drive_takes_a_periods_sync_and_rpdo_with_its_encoder_frame_in_one_wake_up() -> None:
    """After an io tick of the robot the drive waits for the next encoder frame alone (at most
    ``IO_LEAD_S``): the SYNC and RPDO that came first are taken with it, in order, in one step --
    and the period's TPDO1 carries that tick. A frame no encoder frame follows (an SDO request)
    is answered once ``IO_LEAD_S`` ran out; an encoder frame before its SYNC waits for it, which
    then wakes the drive as ever."""
    rig = _PairedLockstepDrive()
    try:
        # a wake-up for the SYNC alone would end a step with 2 frames; the lead runs from an io tick
        rig.node.IO_LEAD_S = 60.0
        for k in range(3):  # the first periods: both frames wait before each step
            rig.rpdo_and_sync(0)
            rig.encoder(1000 + k)
            assert rig.node.step(1.0) == 3
            assert rig.io.recv(timeout=1.0) is not None
        assert [cob for cob, _ in rig.fieldbus_frames()] == [0x180 + NODE] * 3
        rig.rpdo_and_sync(0)
        thread, got = rig.step_in_thread(60.0)
        rig.encoder(2000)  # whenever it comes, the step took the period's three frames together
        thread.join(timeout=30.0)
        assert not thread.is_alive() and got == [3]
        torque = rig.io.recv(timeout=1.0)
        assert torque is not None and io_frames.decode_torque(torque).tick == (rig.wire - 1) & io_frames.TICK_MASK
        assert rig.fieldbus_frames() == [(0x180 + NODE, struct.pack("<Hi", rig.drive.statusword, 2000))]

        rig.node.IO_LEAD_S = 0.05  # an SDO request with no encoder frame after it: answered after the lead
        rig.rpdo_and_sync(0)
        rig.encoder(2001)
        assert rig.node.step(1.0) == 3
        rig.fb.send(can.Message(arbitration_id=0x600 + NODE, data=bytes.fromhex("40 41 60 00 00 00 00 00"), is_extended_id=False))
        thread, got = rig.step_in_thread(60.0)
        thread.join(timeout=30.0)
        assert not thread.is_alive() and got == [1]
        frames = rig.fieldbus_frames()
        assert [cob for cob, _ in frames] == [0x180 + NODE, 0x580 + NODE]
        assert frames[1][1][:4] == bytes.fromhex("4B 41 60 00")

        rig.node.IO_LEAD_S = 60.0  # an encoder frame before its SYNC is held; the SYNC then wakes the drive
        rig.rpdo_and_sync(0)
        rig.encoder(2002)
        assert rig.node.step(1.0) == 3
        rig.fieldbus_frames()
        rig.io.recv(timeout=1.0)
        rig.encoder(2003)
        assert rig.node.step(1.0) == 1  # held: no SYNC yet
        thread, got = rig.step_in_thread(60.0)
        rig.rpdo_and_sync(0)
        thread.join(timeout=30.0)
        assert not thread.is_alive() and got and got[0] >= 1
        if got[0] == 1:  # the RPDO came alone: the SYNC wakes the next step
            assert rig.node.step(1.0) == 1
        assert rig.io.recv(timeout=1.0) is not None
        assert rig.fieldbus_frames() == [(0x180 + NODE, struct.pack("<Hi", rig.drive.statusword, 2003))]
    finally:
        rig.close()


class CountingNode(DriveNode):
    """A drive node that counts its services (:meth:`on_service` calls)."""

    services = 0

    def on_service(self, now: float) -> None:
        self.services += 1
        super().on_service(now)


class AlwaysServedNode(CountingNode):
    """The node as it was before a wake-up of io ticks alone could leave its service out: the
    reference the service-skipping node is compared with."""

    def io_settled(self) -> bool:
        super().io_settled()
        return False


def _ticking_script(node_cls: type[CountingNode]) -> tuple[list[tuple[float, int, bytes]], int]:
    """A drive ticked every 1 ms on a manual clock for 1.5 s while its timers run: heartbeat 50 ms,
    two EMCYs under a 10 ms inhibit time raised between ticks, an SDO upload the master leaves
    hanging, then (back in PRE-OPERATIONAL and started again) an event-driven TPDO1 with an event
    timer of 20 ms. Returns (clock time [s], COB-ID, data) of every fieldbus frame the node sent,
    and the number of its services."""
    fb_node, host, io_node = _virtual_buses("settle")
    plant = can.Bus(interface="virtual", channel=io_node.channel_id)  # type: ignore[attr-defined]
    clock = ManualClock(100.0)
    drive = Drive(NODE)
    node = node_cls(drive, fb_node, io_node, clock=clock)
    out: list[tuple[float, int, bytes]] = []

    def step(t: float) -> None:
        clock.now = t
        node.step(0.0)
        while (msg := host.recv(timeout=0)) is not None:
            out.append((round(t, 6), msg.arbitration_id, bytes(msg.data)))
        while plant.recv(timeout=0) is not None:
            pass

    def send(cob: int, data: bytes, t: float) -> None:
        host.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
        step(t)

    def sdo_write(index: int, sub: int, value: int, size: int, t: float) -> None:
        cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        send(0x600 + NODE, bytes([cs, index & 0xFF, index >> 8, sub]) + value.to_bytes(size, "little").ljust(4, b"\0"), t)

    try:
        node.start()
        sdo_write(0x1017, 0, 50, 2, 100.0)  # heartbeat 50 ms
        sdo_write(0x1015, 0, 100, 2, 100.0)  # EMCY inhibit time 10 ms
        send(0, bytes([0x01, NODE]), 100.0)  # NMT start
        for k in range(1500):
            t = 100.0 + 0.001 * (k + 1)
            if k == 100:
                drive.power.warning(0x8110, bytes(5))
                drive.power.warning(0x8110, bytes(5))
            if k == 200:  # 0x1008 (device name): a segmented upload the master never continues
                send(0x600 + NODE, bytes.fromhex("40 08 10 00 00 00 00 00"), t)
            if k == 1300:  # TPDO1 = statusword, type 255, event timer 20 ms, mapped in PRE-OPERATIONAL
                send(0, bytes([0x80, NODE]), t)
                for index, sub, value, size in (
                    (0x1800, 1, 0x8000_0180 + NODE, 4),
                    (0x1A00, 0, 0, 1),
                    (0x1A00, 1, 0x60410010, 4),
                    (0x1A00, 0, 1, 1),
                    (0x1800, 2, 255, 1),
                    (0x1800, 5, 20, 2),
                    (0x1800, 1, 0x180 + NODE, 4),
                ):
                    sdo_write(index, sub, value, size, t)
                send(0, bytes([0x01, NODE]), t)
            plant.send(io_frames.encode_encoder(NODE - 1, k, 1000 + k))
            step(t)
        for t in (102.0, 102.5):  # no more ticks: the service on its own deadlines
            step(t)
    finally:
        for bus in (fb_node, host, io_node, plant):
            bus.shutdown()
    return out, node.services


def test_a_wake_up_of_io_ticks_alone_serves_every_timer_on_time() -> None:
    """A wake-up that handled only io ticks may leave the node's service out until its next deadline
    (:meth:`DriveNode.io_settled`). Every frame the service sends must still go out at the same
    clock time as from a node that serves every wake-up: heartbeats, EMCYs under their inhibit
    time, the SDO server's timeout, an event-driven TPDO's event timer."""
    warm_up()
    settled, services = _ticking_script(CountingNode)
    served, every = _ticking_script(AlwaysServedNode)

    assert settled == served
    assert every > 1500 and services < 0.4 * every  # it did leave the service out (not with the event timer)
    kinds = {(cob, data[:2]) for _, cob, data in served}
    assert (0x700 + NODE, b"\x05") in kinds  # heartbeats in OPERATIONAL
    assert [t for t, cob, _ in served if cob == 0x80 + NODE] == [100.101, 100.111]  # the inhibit time
    assert sum(1 for _, cob, _ in served if cob == 0x180 + NODE) >= 10  # the event timer
    (abort,) = [(t, data) for t, cob, data in served if cob == 0x580 + NODE and data[0] == 0x80]
    assert abort == (101.202, bytes.fromhex("80 08 10 00 00 00 04 05"))  # the SDO timeout (1 s): on time


def test_lost_io_frames_are_a_fault_at_once_named_by_the_host() -> None:
    """A receive-overflow error frame on io (udp_multicast's report of datagrams the drive's io
    socket dropped) in a trial: an encoder frame never comes, so the drive faults at once -- EMCY
    0x8110 with cause 10 and the tick expected next, CiA 402 Fault, torque 0 with the fault bit in
    the next torque frame -- and the host names the loss, where the plant would only report the
    missing tick at its 1 s deadline."""
    import numpy as np

    from bus.can_errors import overflow_error_frame as overflow
    from bus.objects import ModeOfOperation
    from host.nodes.drive_client import DriveClient
    from host.rig.fault_classify import EmcyFrame, FaultKind, emcy_fault

    warm_up()
    k = next(_counter)
    fb_node = can.Bus(interface="virtual", channel=f"iolost-fb-{k}")
    host = can.Bus(interface="virtual", channel=f"iolost-fb-{k}")
    io_node = ErrorFramesVirtualBus(channel=f"iolost-io-{k}")
    plant = can.Bus(interface="virtual", channel=f"iolost-io-{k}")
    clock = ManualClock(10.0)
    drive = Drive(NODE)
    node = DriveNode(drive, fb_node, io_node, clock=clock)
    sent, step_at = _stepper(node, host, clock)

    def tick(n: int) -> io_frames.TorqueFrame:
        plant.send(io_frames.encode_encoder(NODE - 1, n, 0))
        step_at(10.0 + 0.001 * n)
        msg = plant.recv(timeout=1.0)
        assert msg is not None
        return io_frames.decode_torque(msg)

    try:
        node.start()
        host.send(can.Message(arbitration_id=0, data=bytes([0x01, NODE]), is_extended_id=False))
        step_at(10.0)
        client = DriveClient(drive, NODE)  # the host's set-up, on the firmware's objects directly
        client.configure(30.0, 1.0)
        client.set_mode(ModeOfOperation.TABLE_PLAYBACK)
        client.load_reference(np.zeros(100), np.zeros(100))
        client.load_feedforward(np.zeros(100))
        client.enable()
        client.arm_trial()
        plant.send(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 0, 100))
        step_at(10.0)
        sent()
        for n in range(5):
            assert tick(n).status & io_frames.TorqueStatus.ENABLED
        plant.send(overflow(time.time()))  # before the frame after the loss: tick 5 never comes
        assert step_at(10.01) == [(0x80 + NODE, bytes.fromhex("10 81 11 0A 05 00 00 00"))]
        assert drive.cia402_state == Cia402State.FAULT and not drive.torque_enabled
        assert drive.read_object(0x2120, 4) == bytes([FaultCause.IO_FRAMES_LOST])
        after = tick(6)
        assert (after.torque_units, after.status & io_frames.TorqueStatus.FAULT) == (0, io_frames.TorqueStatus.FAULT)
        record = emcy_fault(EmcyFrame(NODE, 0x8110, bytes.fromhex("0A 05 00 00 00"), 1.0, 2.0))
        assert (record.kind, record.node, record.tick, record.latency_ms) == (FaultKind.FRAME_LOST, f"drive{NODE}", 5, 0.0)
        assert record.message == f"io frames lost in drive{NODE}'s receiver (receive overflow) before tick 5 (EMCY 0x8110)"
    finally:
        for bus in (fb_node, host, io_node, plant):
            bus.shutdown()


_EVENTS = st.lists(
    st.one_of(
        st.tuples(st.just("tick"), st.integers(1, 40)),  # an encoder frame after n × 0.5 ms
        st.tuples(st.just("burst"), st.integers(1, 1500)),  # n encoder frames 1 ms apart
        st.tuples(st.just("idle"), st.integers(1, 400)),  # no frame: a step after n × 0.5 ms
        st.tuples(st.just("warn"), st.just(0)),  # the drive raises an EMCY between wake-ups
        st.tuples(st.just("heartbeat"), st.sampled_from([0, 10, 50, 100])),  # 0x1017 [ms] by SDO
        st.tuples(st.just("inhibit"), st.sampled_from([0, 20, 100])),  # 0x1015 [100 µs] by SDO
        st.tuples(st.just("hang"), st.just(0)),  # a segmented upload the master never continues
        st.tuples(st.just("nmt"), st.sampled_from([0x01, 0x02, 0x80])),
    ),
    max_size=60,
)


class _Played:
    """One drive node on virtual buses and a manual clock, played by a test as the master (``host``)
    and the plant (``plant``): :attr:`out` is every frame the node sent on either bus, with the
    clock time of the step that sent it."""

    def __init__(self, node_cls: type[CountingNode], name: str, *, lockstep: bool = False) -> None:
        self.fb_node, self.host, self.io_node = _virtual_buses(name)
        self.plant = can.Bus(interface="virtual", channel=self.io_node.channel_id)  # type: ignore[attr-defined]
        self.clock = ManualClock(100.0)
        self.node = node_cls(Drive(NODE), self.fb_node, self.io_node, clock=self.clock, lockstep=lockstep)
        drive = self.node.drive
        assert isinstance(drive, Drive)
        self.drive = drive
        self.out: list[tuple[float, str, int, bytes]] = []
        #: the script's clock time [s]
        self.t = 100.0

    def step(self, t: float | None = None) -> None:
        """The node's step at clock time ``t`` [s] (default :attr:`t`); what it sent to :attr:`out`."""
        t = self.t if t is None else t
        self.clock.now = t
        self.node.step(0.0)
        for name, bus in (("fieldbus", self.host), ("io", self.plant)):
            while (msg := bus.recv(timeout=0)) is not None:
                self.out.append((round(t, 6), name, msg.arbitration_id, bytes(msg.data)))

    def sdo_write(self, index: int, sub: int, value: int, size: int) -> None:
        """An expedited SDO download from the master (not stepped)."""
        cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        data = bytes([cs, index & 0xFF, index >> 8, sub]) + value.to_bytes(size, "little").ljust(4, b"\0")
        self.host.send(can.Message(arbitration_id=0x600 + NODE, data=data, is_extended_id=False))

    def hang(self) -> None:
        """A segmented SDO upload (0x1008) the master never continues."""
        self.host.send(
            can.Message(arbitration_id=0x600 + NODE, data=bytes.fromhex("40 08 10 00 00 00 00 00"), is_extended_id=False)
        )

    def nmt(self, cs: int) -> None:
        """NMT command ``cs`` to the node."""
        self.host.send(can.Message(arbitration_id=0, data=bytes([cs, NODE]), is_extended_id=False))

    def play(
        self, events: list[tuple[str, int]], own: Callable[[str, int], bool], setup: Callable[[], None] | None = None
    ) -> list[tuple[float, str, int, bytes]]:
        """Start the node, ``setup()``, then each event: ``own(kind, value)`` plays the script's own
        kinds, stepping as it needs (True: it did); the shared ones here are "warn" (the drive raises
        an EMCY between wake-ups, no step), "hang" and "nmt" (each followed by a step). At the end
        the timers alone, 2 s later; the buses closed. Returns :attr:`out`."""
        try:
            self.node.start()
            self.step()
            if setup is not None:
                setup()
            for kind, value in events:
                if own(kind, value):
                    continue
                if kind == "warn":
                    self.drive.power.warning(0x8110, bytes(5))
                    continue
                if kind == "hang":
                    self.hang()
                else:
                    self.nmt(value)
                self.step()
            self.step(self.t + 2.0)  # then the timers alone
        finally:
            self.close()
        return self.out

    def close(self) -> None:
        for bus in (self.fb_node, self.host, self.io_node, self.plant):
            bus.shutdown()


def _random_script(node_cls: type[CountingNode], events: list[tuple[str, int]]) -> list[tuple[float, str, int, bytes]]:
    """``events`` played to one drive on a manual clock; every frame it sent on either bus, with
    the clock time of the step that sent it."""
    played = _Played(node_cls, "settle-random")
    wire = 0

    def encoder() -> None:
        nonlocal wire
        played.plant.send(io_frames.encode_encoder(NODE - 1, wire, 1000 + wire))
        wire += 1

    def own(kind: str, value: int) -> bool:
        if kind == "tick":
            played.t += 0.0005 * value
            encoder()
        elif kind == "burst":
            for _ in range(value - 1):
                played.t += 0.001
                encoder()
                played.step()
            played.t += 0.001
            encoder()
        elif kind == "idle":
            played.t += 0.0005 * value
        elif kind in ("heartbeat", "inhibit"):
            played.sdo_write(0x1017 if kind == "heartbeat" else 0x1015, 0, value, 2)
        else:
            return False
        played.step()
        return True

    return played.play(events, own)


@given(events=_EVENTS)
@example(events=[("hang", 0), ("burst", 1500)])  # an SDO timeout while the ticks never stop
@example(events=[("nmt", 0x01), ("heartbeat", 10), ("inhibit", 100), ("burst", 30), ("warn", 0), ("warn", 0), ("burst", 40)])
@settings(max_examples=60, deadline=None)
def test_at_random_a_node_that_leaves_its_service_out_sends_what_one_that_never_does_sends(events: list[tuple[str, int]]) -> None:
    """The service skip from outside, at random: io ticks at random intervals and in long bursts, wake-ups without
    frames, EMCYs raised between wake-ups, 0x1017 and 0x1015 changed by SDO, SDO transfers left
    hanging, NMT commands -- the drive that leaves its service out after io ticks sends every frame,
    on both buses, at the same clock time as the one that serves every wake-up."""
    warm_up()
    assert _random_script(CountingNode, events) == _random_script(AlwaysServedNode, events)


_LOCKSTEP_EVENTS = st.lists(
    st.one_of(
        st.tuples(st.just("period"), st.integers(1, 300)),  # n periods: RPDO1 + SYNC, the encoder frame 0.25 ms after
        st.tuples(st.just("ahead"), st.integers(1, 6)),  # n × (RPDO1 + SYNC) at once: the later ones wait in the backlog
        st.tuples(st.just("early"), st.just(0)),  # the encoder frame before its SYNC: held
        st.tuples(st.just("rpdos"), st.integers(1, 40)),  # n RPDO1s 1 ms apart and no SYNC: the watchdog's time passes
        st.tuples(st.just("idle"), st.integers(1, 400)),  # no frame: a step after n × 0.5 ms
        st.tuples(st.just("warn"), st.just(0)),  # the drive raises an EMCY between wake-ups
        st.tuples(st.just("heartbeat"), st.sampled_from([0, 10, 50])),  # 0x1017 [ms] by SDO
        st.tuples(st.just("watchdog"), st.sampled_from([0, 2000, 10000])),  # 0x1006 [µs] by SDO: the SYNC watchdog
        st.tuples(st.just("hang"), st.just(0)),  # a segmented upload the master never continues
        st.tuples(st.just("rtr"), st.just(0)),  # a remote frame for TPDO1
        st.tuples(st.just("nmt"), st.sampled_from([0x01, 0x80])),
    ),
    max_size=40,
)


def _random_lockstep_script(node_cls: type[CountingNode], events: list[tuple[str, int]]) -> list[tuple[float, str, int, bytes]]:
    """``events`` played to a drive of a SYNC-stepped plant (``lockstep=True``: RPDO1 = controlword +
    target, TPDO1 = statusword + position on every SYNC, CSP) on a manual clock; every frame it sent
    on either bus, with the clock time of the step that sent it."""
    played = _Played(node_cls, "settle-lockstep", lockstep=True)
    host = played.host
    wire = 0
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)

    def sdo_write(index: int, sub: int, value: int, size: int) -> None:
        played.sdo_write(index, sub, value, size)
        played.step()

    def rpdo() -> None:
        host.send(can.Message(arbitration_id=0x200 + NODE, data=struct.pack("<Hi", 0x0F, 0), is_extended_id=False))

    def encoder() -> None:
        nonlocal wire
        played.plant.send(io_frames.encode_encoder(NODE - 1, wire, 1000))
        wire += 1

    def advance(dt_s: float) -> None:
        played.t += dt_s
        played.step()

    def setup() -> None:
        for index, sub, value, size in (
            (0x1800, 1, 0x8000_0180 + NODE, 4),  # TPDO1: statusword + position actual, on every SYNC
            (0x1A00, 0, 0, 1),
            (0x1A00, 1, 0x60410010, 4),
            (0x1A00, 2, 0x60640020, 4),
            (0x1A00, 0, 2, 1),
            (0x1800, 2, 1, 1),
            (0x1800, 1, 0x180 + NODE, 4),
            (0x1400, 1, 0x8000_0200 + NODE, 4),  # RPDO1: controlword + target position, synchronous
            (0x1600, 0, 0, 1),
            (0x1600, 1, 0x60400010, 4),
            (0x1600, 2, 0x607A0020, 4),
            (0x1600, 0, 2, 1),
            (0x1400, 2, 1, 1),
            (0x1400, 1, 0x200 + NODE, 4),
            (0x6060, 0, 8, 1),  # CSP
        ):
            sdo_write(index, sub, value, size)
        played.nmt(0x01)
        played.step()

    def own(kind: str, value: int) -> bool:
        if kind == "period":
            for _ in range(value):
                rpdo()
                host.send(sync)
                advance(0.00025)
                encoder()
                advance(0.00075)
        elif kind == "ahead":
            for _ in range(value):
                rpdo()
                host.send(sync)
            advance(0.00025)
            for _ in range(value):
                encoder()
                advance(0.00025)
        elif kind == "rpdos":
            for _ in range(value):
                rpdo()
                advance(0.001)
        elif kind == "early":
            encoder()
            advance(0.00025)
            rpdo()
            host.send(sync)
            advance(0.00025)
        elif kind == "idle":
            advance(0.0005 * value)
        elif kind in ("heartbeat", "watchdog"):
            sdo_write(0x1017 if kind == "heartbeat" else 0x1006, 0, value, 2 if kind == "heartbeat" else 4)
        elif kind == "rtr":
            host.send(can.Message(arbitration_id=0x180 + NODE, is_remote_frame=True, dlc=6, is_extended_id=False))
            played.step()
        else:
            return False
        return True

    return played.play(events, own, setup)


@given(events=_LOCKSTEP_EVENTS)
@example(events=[("period", 300)])
@example(events=[("watchdog", 2000), ("period", 3), ("rpdos", 20)])  # the watchdog armed by a SYNC fires among RPDOs
@example(events=[("watchdog", 2000), ("period", 20), ("idle", 10), ("period", 5), ("ahead", 4), ("early", 0), ("period", 3)])
@example(events=[("heartbeat", 10), ("period", 100), ("warn", 0), ("period", 30), ("hang", 0), ("period", 200)])
@settings(max_examples=30, deadline=None)
def test_at_random_a_lockstep_drive_that_leaves_its_service_out_after_syncs_sends_what_one_that_never_does_sends(
    events: list[tuple[str, int]],
) -> None:
    """The service skip after a wake-up of SYNCs and RPDOs (:meth:`DriveNode.fieldbus_settled`), from
    outside, at random: periods of RPDO1 + SYNC and their encoder frame, SYNCs ahead of the plant
    (the backlog), an encoder frame before its SYNC, RPDOs without a SYNC, pauses, EMCYs, 0x1017 and 0x1006 (the SYNC
    watchdog) changed by SDO, SDO transfers left hanging, remote frames, NMT commands -- every frame,
    on both buses, at the same clock time as from the drive that serves every wake-up."""
    warm_up()
    assert _random_lockstep_script(CountingNode, events) == _random_lockstep_script(AlwaysServedNode, events)


def test_a_sync_stepped_drive_leaves_its_service_out_on_most_periods() -> None:
    """The skip does happen: 300 periods of RPDO1 + SYNC and their encoder frame, heartbeat 50 ms,
    no SYNC watchdog -- the service runs about once per heartbeat and the node's ``MAX_WAIT_S``, not
    twice a period."""
    warm_up()
    counted: list[int] = []

    class Counted(CountingNode):
        def on_service(self, now: float) -> None:
            super().on_service(now)
            counted.append(1)

    frames = _random_lockstep_script(Counted, [("heartbeat", 50), ("period", 300)])
    assert sum(cob == 0x180 + NODE for _, _, cob, _ in frames) >= 300  # a TPDO1 every period
    assert len(counted) < 0.2 * 600
