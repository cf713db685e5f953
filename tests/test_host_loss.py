"""Host loss is a fault on the bus: the nodes consume the host's heartbeat (0x1016,
CiA 301) and react — the drive with torque off, CiA 402 Fault and EMCY 0x8130, the plant node by
ending a running trial (HOST_LOST, EMCY 0x8130).  Settings that shape the motion (gains, the
following-error window, the max torque) are refused while a trial is armed or running, and the max
torque is bounded by the motor's rating in the EDS.

Timing is checked on a manual node clock (the node is stepped by the test, a virtual bus delivers
on send), never against the wall clock."""

from __future__ import annotations

import itertools
import struct
from typing import Any

import can
import pytest
from clock_util import ManualClock
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bus.cia301.nmt import (
    CONSUMER_TIME_MS,
    HOST_NODE_ID,
    NmtCommand,
    NmtState,
    NodeHeartbeatConsumer,
    consumer_entry,
    decode_consumer_entry,
)
from bus.errors import AbortCode, SdoAbort
from bus.objects import Cia402State, FaultCause, GainsSub, Obj, TableSub, TrialState, TrialSub
from bus.plant_objects import PlantFault, PlantStatus
from bus.safe_state import parse_safe_state
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode
from host.experiment.faults import FaultKind
from host.nodes.plant_client import PlantState as PlantClientState
from host.rig.fault_classify import EmcyFrame, emcy_fault
from plant.plant_node import PlantNode

_counter = itertools.count()


def u16(v: int) -> bytes:
    return struct.pack("<H", v)


def u32(v: int) -> bytes:
    return struct.pack("<I", v)


def enabled_drive(node_id: int = 2) -> Drive:
    d = Drive(node_id)
    d.nmt_command(NmtCommand.START)
    for cw in (0x06, 0x07, 0x0F):
        d.write_object(Obj.CONTROLWORD, 0, u16(cw))
    assert d.torque_enabled
    return d


def armed_drive(n: int = 5) -> Drive:
    d = enabled_drive()
    d.write_object(Obj.MODES_OF_OPERATION, 0, b"\xff")  # table playback (-1)
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(n))
    for index in (Obj.REF_POSITION_TABLE, Obj.REF_VELOCITY_TABLE, Obj.FEEDFORWARD_TABLE):
        d.write_object(index, 0, bytes(4 * n))
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, bytes([1]))
    return d


# --------------------------------------------------------------------------- consumer, pure


def test_consumer_entry_codec() -> None:
    assert consumer_entry(HOST_NODE_ID, 250) == 0x007F00FA
    assert decode_consumer_entry(0x007F00FA) == (127, 250)
    assert decode_consumer_entry(0) is None and decode_consumer_entry(0x007F0000) is None


def test_node_consumer_starts_at_the_first_heartbeat_and_fires_once_per_loss() -> None:
    c = NodeHeartbeatConsumer()
    c.configure({127: 0.25})
    assert c.next_deadline() is None and c.expired(100.0) == []  # never heard: not monitored yet
    c.on_heartbeat(127, 10.0)
    assert c.next_deadline() == pytest.approx(10.25)
    assert c.expired(10.2499) == []
    assert c.expired(10.25) == [127]
    assert c.expired(11.0) == []  # once
    c.on_heartbeat(127, 12.0)  # re-armed by the next heartbeat
    assert c.expired(12.3) == [127]
    c.configure({})
    c.on_heartbeat(127, 13.0)
    assert c.next_deadline() is None


# --------------------------------------------------------------------------- drive firmware


def test_drive_heartbeat_loss_is_a_fault_with_emcy_0x8130(caplog: pytest.LogCaptureFixture) -> None:
    d = armed_drive()
    d.io_tick(0, 0)
    d.io_tick(1, 0)
    caplog.set_level("INFO", logger="firmware_model")
    d.heartbeat_lost(HOST_NODE_ID)
    assert not d.torque_enabled
    assert d.cia402_state == Cia402State.FAULT
    assert d.trial_state == TrialState.FAULT
    assert d.read_object(Obj.TRIAL, TrialSub.FAULT_CAUSE) == bytes([FaultCause.HEARTBEAT])
    assert d.pop_emcy() == [(0x8130, 0x11, bytes([FaultCause.HEARTBEAT, HOST_NODE_ID, 0, 0, 0]))]
    assert d.io_tick(2, 0) == 0  # no torque any more
    records = [r for r in map(parse_safe_state, caplog.messages) if r]
    assert records[-1]["node"] == "drive2" and records[-1]["reason"] == "heartbeat-of-node-127-lost"
    assert records[-1]["cia402"] == "FAULT" and records[-1]["tick"] == "2"


def test_drive_heartbeat_loss_in_nmt_stopped_is_only_logged() -> None:
    d = enabled_drive()
    d.nmt_command(NmtCommand.STOP)  # an abort connection: 0x6007 = 1 (default) faults the drive
    assert d.cia402_state == Cia402State.FAULT and not d.torque_enabled
    errors = d.read_object(0x1003, 0)
    d.heartbeat_lost(HOST_NODE_ID)  # the master stopped it on purpose: nothing more happens
    assert d.read_object(0x1003, 0) == errors
    assert d.pop_emcy() == []  # no EMCY in NMT STOPPED


def test_drive_bus_loss_removes_torque() -> None:
    d = enabled_drive()
    d.bus_lost("hub closed the connection")
    assert not d.torque_enabled and d.cia402_state == Cia402State.FAULT
    assert d.read_object(Obj.TRIAL, TrialSub.FAULT_CAUSE) == bytes([FaultCause.BUS_LOST])


@pytest.mark.parametrize(
    ("index", "sub", "data"),
    [
        (Obj.GAINS, GainsSub.KP, struct.pack("<i", 1000)),
        (Obj.GAINS, GainsSub.KD, struct.pack("<i", 1000)),
        (Obj.GAINS, GainsSub.VEL_FILTER, u16(1000)),
        (Obj.FOLLOWING_ERROR_WINDOW, 0, u32(0xFFFFFFFF)),
        (Obj.MAX_TORQUE, 0, u16(100)),
    ],
)
def test_motion_settings_are_refused_while_a_trial_is_armed_or_running(index: int, sub: int, data: bytes) -> None:
    d = armed_drive()
    with pytest.raises(SdoAbort) as exc:
        d.write_object(index, sub, data)
    assert exc.value.code == AbortCode.DEVICE_STATE
    d.io_tick(0, 0)  # running
    with pytest.raises(SdoAbort) as exc:
        d.write_object(index, sub, data)
    assert exc.value.code == AbortCode.DEVICE_STATE
    for n in range(1, 5):
        d.io_tick(n, 0)
    assert d.trial_state == TrialState.DONE
    d.write_object(index, sub, data)  # between trials: accepted


def test_max_torque_is_bounded_by_the_motor_rating() -> None:
    d = Drive(1)
    assert d.store.lookup(Obj.MAX_TORQUE, 0).max == 3000
    d.write_object(Obj.MAX_TORQUE, 0, u16(3000))
    with pytest.raises(SdoAbort) as exc:
        d.write_object(Obj.MAX_TORQUE, 0, u16(3001))
    assert exc.value.code == AbortCode.VALUE_TOO_HIGH
    with pytest.raises(SdoAbort) as exc:
        d.write_object(Obj.MAX_TORQUE, 0, u16(65535))
    assert exc.value.code == AbortCode.VALUE_TOO_HIGH


# --------------------------------------------------------------------------- slave runtime


class Stepped:
    """A node stepped by the test on a manual clock, with a host bus on its fieldbus."""

    def __init__(self, make) -> None:  # type: ignore[no-untyped-def]
        k = next(_counter)
        self.fb = can.Bus(interface="virtual", channel=f"hl-fb-{k}")
        self.io = can.Bus(interface="virtual", channel=f"hl-io-{k}")
        self.host = can.Bus(interface="virtual", channel=f"hl-fb-{k}")
        self.plant = can.Bus(interface="virtual", channel=f"hl-io-{k}")
        self.clock = ManualClock(1000.0)
        self.node = make(self.fb, self.io, self.clock)
        self.node.start()
        self.sent()

    def sent(self) -> list[tuple[int, bytes]]:
        out = []
        while (msg := self.host.recv(timeout=0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out

    def step_at(self, t: float) -> list[tuple[int, bytes]]:
        self.clock.now = t
        self.node.step(0.0)
        return self.sent()

    def sdo_write(self, node_id: int, index: int, sub: int, value: int, t: float) -> None:
        data = bytes([0x23, index & 0xFF, index >> 8, sub]) + u32(value)
        self.host.send(can.Message(arbitration_id=0x600 + node_id, data=data, is_extended_id=False))
        assert self.step_at(t) == [(0x580 + node_id, bytes([0x60, index & 0xFF, index >> 8, sub, 0, 0, 0, 0]))]

    def start_trial(self, t: float, ticks: int = 10) -> None:
        """The bench's trial of ``ticks`` ticks from a zero initial state, started at ``t`` [s]."""
        bench = self.node
        bench.store.write_object(0x2420, 0, bytes(64))
        bench.store.write_object(0x2410, 2, u32(ticks))
        bench.store.write_object(0x2410, 3, bytes([1]))  # start
        self.step_at(t)
        assert bench.status == PlantStatus.RUNNING

    def host_beat(self) -> None:
        self.host.send(can.Message(arbitration_id=0x700 + HOST_NODE_ID, data=b"\x05", is_extended_id=False))

    def close(self) -> None:
        for bus in (self.fb, self.io, self.host, self.plant):
            bus.shutdown()


def test_drive_node_consumes_the_host_heartbeat_within_the_consumer_time() -> None:
    drive = enabled_drive(2)
    rig = Stepped(lambda fb, io, clock: DriveNode(drive, fb, io, clock=clock))
    try:
        t0 = 1001.0
        c = CONSUMER_TIME_MS / 1000.0
        rig.sdo_write(2, 0x1016, 1, consumer_entry(HOST_NODE_ID, CONSUMER_TIME_MS), t0)
        assert rig.node.consumer.producers == {HOST_NODE_ID: c}
        assert rig.step_at(t0 + 5.0) == []  # no heartbeat heard yet: nothing monitored
        rig.host_beat()
        assert rig.step_at(t0 + 5.1) == []
        assert rig.node.consumer.next_deadline() == pytest.approx(t0 + 5.1 + c)
        rig.host_beat()
        assert rig.step_at(t0 + 5.2) == []
        assert rig.step_at(t0 + 5.2 + c - 0.001) == []
        assert drive.torque_enabled
        frames = rig.step_at(t0 + 5.2 + c)  # one consumer time after the last heartbeat
        assert (0x082, bytes([0x30, 0x81, 0x11, FaultCause.HEARTBEAT, HOST_NODE_ID, 0, 0, 0])) in frames
        assert not drive.torque_enabled and drive.cia402_state == Cia402State.FAULT
        assert rig.step_at(t0 + 5.2 + 3 * c) == []  # reported once
    finally:
        rig.close()


def _freeze_in_next_wait(rig: Stepped, until: float) -> None:
    """The machine stops while the node waits in its next step: its clock reads ``until`` when it
    runs again (the io bus's receive is where a virtual bus's node waits)."""
    recv = rig.io.recv

    def frozen_recv(timeout: float | None = None) -> can.Message | None:
        rig.clock.now = max(rig.clock.now, until)
        rig.io.recv = recv  # type: ignore[method-assign]
        return recv(timeout=timeout)

    rig.io.recv = frozen_recv  # type: ignore[method-assign]


def _drive_consuming_the_host(t0: float) -> tuple[Drive, Stepped]:
    """Drive 2, enabled, on a :class:`Stepped` rig, consuming the host's heartbeat from ``t0`` (heard at t0 + 0.1)."""
    drive = enabled_drive(2)
    rig = Stepped(lambda fb, io, clock: DriveNode(drive, fb, io, clock=clock))
    rig.sdo_write(2, 0x1016, 1, consumer_entry(HOST_NODE_ID, CONSUMER_TIME_MS), t0)
    rig.host_beat()
    assert rig.step_at(t0 + 0.1) == []
    return drive, rig


_HOST_LOST_EMCY = (0x082, bytes([0x30, 0x81, 0x11, FaultCause.HEARTBEAT, HOST_NODE_ID, 0, 0, 0]))


def test_a_node_that_did_not_run_itself_loses_no_host_for_that_time(caplog: pytest.LogCaptureFixture) -> None:
    """The whole machine froze (the node and the host with it: no heartbeat could come): the node,
    woken more than half its consumer time after its wake-up was due, judges its producers from then
    on, and says so in its log; a host still silent a consumer time after that is lost."""
    t0, c = 1001.0, CONSUMER_TIME_MS / 1000.0
    drive, rig = _drive_consuming_the_host(t0)
    try:
        assert rig.node.consumer.stall_s == pytest.approx(c / 2)
        resumed = t0 + 0.2 + 3 * c
        _freeze_in_next_wait(rig, resumed)  # the machine stops while the node waits for its wake-up at t0 + 0.2
        with caplog.at_level("INFO", logger="bus.cia301.nmt"):
            assert rig.step_at(t0 + 0.2) == []  # no EMCY
        assert drive.torque_enabled and drive.cia402_state == Cia402State.OPERATION_ENABLED
        assert "node 2: ran again 1500 ms after its wake-up was due: heartbeats judged from now" in caplog.text
        assert rig.node.consumer.next_deadline() == pytest.approx(resumed + c)
        assert rig.step_at(resumed + c - 0.001) == []
        assert _HOST_LOST_EMCY in rig.step_at(resumed + c)  # the host stays silent: lost a consumer time after the freeze
        assert not drive.torque_enabled
    finally:
        rig.close()


def test_a_node_stopped_between_two_steps_of_its_loop_loses_no_host_for_that_time(caplog: pytest.LogCaptureFixture) -> None:
    """The machine froze after a step's service and before the next step (or after the answer loop
    returned, before the step that follows it): in its loop (:meth:`SlaveNode.run`) the node finds
    the time it did not run at the next step and judges its producers from then on -- before, a
    plant stopped there judged the host lost the moment it ran again, its consumer's deadline past
    and the host's beat not yet sent (the CI failure of ``test_a_freeze_of_the_whole_machine_is_no_fault``)."""
    t0, c = 1001.0, CONSUMER_TIME_MS / 1000.0
    drive, rig = _drive_consuming_the_host(t0)
    try:
        rig.node._ran_s = rig.clock.now  # as SlaveNode.run does before its loop (the test steps the node itself)
        assert rig.step_at(t0 + 0.2) == []
        resumed = t0 + 0.2 + 3 * c  # the node did not run from the end of that step until now: no wait was due
        with caplog.at_level("INFO", logger="bus.cia301.nmt"):
            assert rig.step_at(resumed) == []  # no EMCY
        assert drive.torque_enabled and drive.cia402_state == Cia402State.OPERATION_ENABLED
        assert "node 2: ran again 1500 ms after its wake-up was due: heartbeats judged from now" in caplog.text
        assert rig.step_at(resumed + 0.2) == [] and rig.step_at(resumed + 0.4) == []  # steps closer than a stall
        assert _HOST_LOST_EMCY in rig.step_at(resumed + c)  # the host stays silent: lost a consumer time after the freeze
    finally:
        rig.close()


def test_a_node_woken_late_by_less_than_half_its_consumer_time_judges_as_ever() -> None:
    """A late wake-up short of the stall bound is not a stall: the host silent past its consumer time is lost."""
    t0, c = 1001.0, CONSUMER_TIME_MS / 1000.0
    _, rig = _drive_consuming_the_host(t0)
    try:
        _freeze_in_next_wait(rig, t0 + 0.1 + c - 0.01 + 0.4 * c)
        assert _HOST_LOST_EMCY in rig.step_at(t0 + 0.1 + c - 0.01)
    finally:
        rig.close()


def test_a_drive_that_did_not_run_keeps_an_sdo_transfer_open() -> None:
    """A segmented upload in progress when the machine stops for 3 s (the SDO server's timeout is
    1 s): the drive, running again, aborts nothing -- the client did not run either -- and answers
    the next segment request."""
    t0 = 1001.0
    _, rig = _drive_consuming_the_host(t0)
    try:
        rig.host.send(can.Message(arbitration_id=0x602, data=bytes([0x40, 0x08, 0x10, 0, 0, 0, 0, 0]), is_extended_id=False))
        (answer,) = rig.step_at(t0 + 0.15)
        assert answer[0] == 0x582 and answer[1][0] == 0x41  # segmented upload initiated (0x1008 device name)
        _freeze_in_next_wait(rig, t0 + 3.2)
        assert rig.step_at(t0 + 0.2) == []  # no abort 0x05040000
        rig.host.send(can.Message(arbitration_id=0x602, data=bytes([0x60, 0, 0, 0, 0, 0, 0, 0]), is_extended_id=False))
        (segment,) = rig.step_at(t0 + 3.3)
        assert segment[0] == 0x582 and segment[1][0] & 0xE0 == 0x00  # an upload segment
    finally:
        rig.close()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(
        st.tuples(st.sampled_from(["beat", "wait", "freeze", "pause"]), st.floats(min_value=0.001, max_value=1.5)),
        min_size=1,
        max_size=30,
    )
)
def test_at_random_a_drive_loses_the_host_only_for_silence_it_ran_through(events: list[tuple[str, float]]) -> None:
    """An outsider at random: host heartbeats, waits of the drive (stepped at their end), freezes of
    the whole machine during a wait, and between two steps of the drive's loop (pauses). After every
    step the drive has reported the host lost (EMCY 0x8130, torque off) exactly when the host was
    silent for a consumer time the drive itself ran through: a freeze or a pause longer than half the
    consumer time counts from its end, a shorter one as time."""
    t0, c = 1001.0, CONSUMER_TIME_MS / 1000.0
    drive, rig = _drive_consuming_the_host(t0)
    try:
        rig.node._ran_s = rig.clock.now  # as SlaveNode.run does before its loop: a pause between two steps is seen
        t, last = t0 + 0.1, t0 + 0.1  # the node's time; when the model last heard the host (or graced)
        for kind, dt in events:
            if kind == "beat":
                rig.host_beat()
                t += 0.001
                last = t
                frames = rig.step_at(t)
            elif kind == "wait":
                dt = min(dt, 0.9 * c / 2)  # a step well within every half consumer time: the drive judges on time
                t += dt
                frames = rig.step_at(t)
            elif kind == "pause":  # the machine stops after a step, before the next one
                ran, t = t, t + dt
                frames = rig.step_at(t)
                if t - ran > c / 2:  # as the node reckons it: run again this long after its last step
                    last = t
            else:  # the machine stops while the drive waits for a wake-up due now
                woke, t = t, t + dt
                _freeze_in_next_wait(rig, t)
                frames = rig.step_at(woke)
                if t - woke > c / 2:  # as the node reckons it: run again this long after its wake-up was due
                    last = t
            lost = t - last >= c
            assert (_HOST_LOST_EMCY in frames) == lost, (kind, dt, t - last)
            assert drive.torque_enabled == (not lost)
            if lost:
                return  # the drive is in Fault: the rest of the sequence tells nothing more
    finally:
        rig.close()


def test_a_plant_that_did_not_run_gives_the_ticks_torques_their_time_from_then() -> None:
    """A trial's tick waits for its torques when the machine stops for 3 s (the tick deadline is
    1 s, 2 s for tick 0): the plant, running again, ends no trial -- the drives did not run either
    -- and its tick deadline counts from then on."""
    rig = _stepped_bench(tick_timeout_s=1.0, first_tick_timeout_s=2.0)
    bench = rig.node
    try:
        t0 = 1001.0
        bench.nmt_command(NmtCommand.START)
        rig.sdo_write(32, 0x1016, 1, consumer_entry(HOST_NODE_ID, CONSUMER_TIME_MS), t0)
        rig.start_trial(t0 + 0.01)
        _freeze_in_next_wait(rig, t0 + 3.0)
        rig.step_at(t0 + 0.02)
        assert bench.status == PlantStatus.RUNNING
        assert rig.step_at(t0 + 3.0 + 2.0 - 0.001) == [] and bench.status == PlantStatus.RUNNING
        rig.step_at(t0 + 3.0 + 2.0)  # the drives stay silent: tick 0's deadline from the resume
        assert bench.status == PlantStatus.FAULT and bench.fault == PlantFault.TICK_TIMEOUT
    finally:
        rig.close()


class _StillPlant:
    """A plant that never moves (the plant node's trial logic is what is tested)."""

    def reset(self, q0: Any, qd0: Any) -> None:
        pass

    def encoder_counts(self) -> Any:
        import numpy as np

        return np.zeros(4, dtype=np.int64)

    def step(self, tau: Any, dist: Any) -> None:
        pass


def _stepped_bench(tick_timeout_s: float = 60.0, first_tick_timeout_s: float = 60.0) -> Any:
    """A plant node on a :class:`Stepped` rig with a still plant and (by default) long tick deadlines."""
    import numpy as np

    return Stepped(
        lambda fb, io, clock: PlantNode(
            fb,
            io,
            plant_factory=lambda ts, n: _StillPlant(),
            disturbance_fn=lambda *a: np.zeros((a[3], 4)),
            clock=clock,
            tick_timeout_s=tick_timeout_s,
            first_tick_timeout_s=first_tick_timeout_s,
        )
    )


def test_plant_node_ends_a_running_trial_when_the_host_is_lost() -> None:
    rig = _stepped_bench()
    bench = rig.node
    try:
        t0 = 1001.0
        bench.nmt_command(NmtCommand.START)
        rig.sdo_write(32, 0x1016, 1, consumer_entry(HOST_NODE_ID, 250), t0)
        rig.host_beat()
        rig.step_at(t0 + 0.01)
        rig.start_trial(t0 + 0.02)
        frames = rig.step_at(t0 + 0.27)
        assert bench.status == PlantStatus.FAULT and bench.fault == PlantFault.HOST_LOST
        assert any(cob == 0x0A0 and data[:2] == b"\x30\x81" for cob, data in frames)
        msg = rig.plant.recv(timeout=0)
        stops = []
        while msg is not None:
            stops.append(msg.arbitration_id == 0x010 and msg.data[0] == 2)
            msg = rig.plant.recv(timeout=0)
        assert stops[-1]  # TRIAL_STOP went out to the drives
    finally:
        rig.close()


def test_plant_node_faults_on_a_bus_error_frame_during_a_trial() -> None:
    rig = _stepped_bench()
    bench = rig.node
    try:
        bench.nmt_command(NmtCommand.START)
        rig.start_trial(1000.01)
        rig.plant.send(can.Message(is_error_frame=True, arbitration_id=0x008, data=bytes(8)))
        rig.step_at(1000.02)
        assert bench.status == PlantStatus.FAULT and bench.fault == PlantFault.BAD_FRAME
        assert int(bench.nmt_state) == NmtState.OPERATIONAL
    finally:
        rig.close()


def test_plant_node_says_io_frames_its_receiver_lost_at_once_not_a_damaged_frame() -> None:
    """A receive-overflow error frame on the plant's io channel (udp_multicast's report of a torque
    datagram its socket dropped): the trial ends at once with IO_FRAMES_LOST (EMCY 0x8110, fault 8,
    the tick), and the host names it a lost frame in the plant's receiver -- not a damaged frame,
    not a drive that did not answer at the tick deadline."""
    from bus.can_errors import overflow_error_frame

    rig = _stepped_bench()
    bench = rig.node
    try:
        bench.nmt_command(NmtCommand.START)
        rig.start_trial(1000.01)
        rig.plant.send(overflow_error_frame(1000.0, "io"))
        frames = rig.step_at(1000.02)
        assert bench.status == PlantStatus.FAULT and bench.fault == PlantFault.IO_FRAMES_LOST
        assert "io frames lost in the plant's receiver" in bench.last_fault_message
        emcy = [data for cob, data in frames if cob == 0x0A0]
        assert [data[:5] for data in emcy] == [b"\x10\x81\x11\x08\x00"]
        rec = emcy_fault(EmcyFrame(32, 0x8110, emcy[0][3:], 1.0, 2.0))
        assert (rec.kind, rec.node, rec.tick) == (FaultKind.FRAME_LOST, "plant", int.from_bytes(emcy[0][5:7], "little"))
        assert rec.message.startswith("io frames lost in the plant node's receiver (receive overflow) at tick ")
        assert PlantClientState(PlantStatus.FAULT, 3, PlantFault.IO_FRAMES_LOST, 3, 0).describe() == (
            "fault: io frames lost in the plant node's receiver (receive overflow) at tick 3 (3 ticks done)"
        )
    finally:
        rig.close()


def test_plant_node_says_fieldbus_frames_its_receiver_lost_during_a_trial_and_between_trials() -> None:
    """A receive-overflow error frame on the plant's fieldbus (udp_multicast's report of datagrams
    the kernel dropped): a running trial ends with FRAMES_LOST; between trials its EMCY (0x8110,
    fault 7) says so; never only a log line."""
    from bus.can_errors import overflow_error_frame

    rig = _stepped_bench()
    bench = rig.node
    try:
        bench.nmt_command(NmtCommand.START)
        bench._on_fieldbus(overflow_error_frame(1000.0, "fieldbus"))  # as the select loop hands it over, past the filters
        frames = rig.step_at(1000.005)
        assert bench.status != PlantStatus.FAULT
        assert [(cob, data[:4]) for cob, data in frames if cob == 0x0A0] == [(0x0A0, b"\x10\x81\x11\x07")]
        rig.start_trial(1000.01)
        bench._on_fieldbus(overflow_error_frame(1000.0, "fieldbus"))
        rig.step_at(1000.02)
        assert bench.status == PlantStatus.FAULT and bench.fault == PlantFault.FRAMES_LOST
        assert "fieldbus frames lost" in bench.last_fault_message
    finally:
        rig.close()
