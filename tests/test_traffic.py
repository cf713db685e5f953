"""bus.traffic and host.rig.bus_accounting: known frames give known bits and times; SDO frames are
attributed to their transfer by the protocol's multiplexer; what does not fit a control period is
reported as not fitting, by how much; the per-trial exchange follows from the transfers' sizes."""

from __future__ import annotations

import can
import pytest

from bus import io_frames
from bus.bus_features import frames_from_messages
from bus.objects import Obj
from bus.plant_objects import DEFAULT_PLANT_NODE_ID, PlantObj
from bus.traffic import IoTickCounter, SdoTransferCounter, TickBudget, bits_to_s, frame_bits_of
from host.rig.bus_accounting import BusTimeAccounting, bus_time_lines, kind_of


def frame(cob: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=cob, is_extended_id=False, data=data)


def test_known_frames_give_known_bits_and_times() -> None:
    # 6-byte encoder frame: 95 bits, 115 with worst-case stuffing; 7-byte torque frame: 103 / 125
    enc = io_frames.encode_encoder(0, 7, 1234)
    tq = io_frames.encode_torque(0, 7, -5, io_frames.TorqueStatus.ENABLED)
    assert (frame_bits_of(enc, worst_case=False), frame_bits_of(enc)) == (95, 115)
    assert (frame_bits_of(tq, worst_case=False), frame_bits_of(tq)) == (103, 125)
    assert frame_bits_of(can.Message(arbitration_id=1, is_fd=True, data=b"\0" * 12)) == 0
    # one tick: 4 x 115 + 4 x 125 = 960 bits = 0.96 ms at 1 Mbit/s, 1.92 ms at 500 kbit/s
    assert bits_to_s(960, 1_000_000) == pytest.approx(960e-6)
    assert bits_to_s(960, 500_000) == pytest.approx(1.92e-3)
    with pytest.raises(ValueError):
        bits_to_s(1, 0)


def test_tick_budget_never_reports_more_than_the_capacity() -> None:
    fast, slow = TickBudget(1_000_000, 1e-3), TickBudget(500_000, 1e-3)
    assert fast.capacity_bits == 1000 and slow.capacity_bits == 500
    ok = fast.fit(960)
    assert ok["fits"] and ok["utilisation_percent"] == pytest.approx(96.0) and ok["excess_bits"] == 0
    over = slow.fit(960)
    assert not over["fits"]
    assert over["utilisation_percent"] == 100.0  # never above the capacity
    assert over["excess_bits"] == 460 and over["excess_percent_of_capacity"] == pytest.approx(92.0)
    assert over["time_needed_s"] == pytest.approx(1.92e-3)


def ticks(counter: IoTickCounter, first: int, n: int) -> None:
    for t in range(first, first + n):
        for j in range(4):
            counter.add(io_frames.encode_encoder(j, t, 100 * j))
        for j in (3, 1, 0, 2):  # answers in any order
            counter.add(io_frames.encode_torque(j, t, 7, io_frames.TorqueStatus.ENABLED))


def test_io_ticks_are_binned_by_their_tick_counter_and_control_frames_counted_apart() -> None:
    c = IoTickCounter()
    c.add(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 65_530, 20))
    ticks(c, 65_530, 20)  # the 16-bit wire tick wraps inside the trial
    c.add(io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, 65_550, 20))
    c.add(frame(0x7FF, b"\x01"))
    c.close()
    assert (c.ticks, c.bits_mean, c.bits_max) == (20, 960.0, 960)
    assert (c.control_frames, c.control_bits) == (2, 250)
    assert (c.other_frames, c.frames) == (1, 160)


def test_a_late_frame_joins_its_own_tick() -> None:
    c = IoTickCounter()
    ticks(c, 0, 3)
    c.add(io_frames.encode_torque(1, 1, 0, 0))  # a duplicate of tick 1 arriving late
    c.close()
    assert (c.ticks, c.bits_max, c.bits_total) == (3, 1085, 3 * 960 + 125)


def sdo_upload_expedited(c: SdoTransferCounter, node: int, index: int, sub: int) -> None:
    c.add(frame(0x600 + node, bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])))
    c.add(frame(0x580 + node, bytes([0x43, index & 0xFF, index >> 8, sub, 1, 0, 0, 0])))


def test_sdo_frames_belong_to_the_transfer_their_initiate_opened() -> None:
    c = SdoTransferCounter()
    sdo_upload_expedited(c, 32, 0x2410, 4)
    sdo_upload_expedited(c, 32, 0x2410, 4)
    # block download of 14 bytes to drive 1, 0x2102: the data segments' first bytes (1, 0x82) look
    # like other command specifiers and must not open transfers
    c.add(frame(0x601, bytes([0xC6, 0x02, 0x21, 0, 14, 0, 0, 0])))
    c.add(frame(0x581, bytes([0xA4, 0x02, 0x21, 0, 127, 0, 0, 0])))
    c.add(frame(0x601, bytes([0x01, 1, 2, 3, 4, 5, 6, 7])))
    c.add(frame(0x601, bytes([0x82, 1, 2, 3, 4, 5, 6, 7])))
    c.add(frame(0x581, bytes([0xA2, 2, 127, 0, 0, 0, 0, 0])))
    c.add(frame(0x601, bytes([0xC1, 0, 0, 0, 0, 0, 0, 0])))
    c.add(frame(0x581, bytes([0xA1, 0, 0, 0, 0, 0, 0, 0])))
    # then an expedited download to drive 1 opens the next transfer
    c.add(frame(0x601, bytes([0x2F, 0x20, 0x21, 1, 1, 0, 0, 0])))
    c.add(frame(0x581, bytes([0x60, 0x20, 0x21, 1, 0, 0, 0, 0])))
    c.add(frame(0x701, b"\x05"))
    c.add(frame(0x000, b"\x01\x00"))
    c.add(frame(0x081, b"\0" * 8))
    poll = c.sdo[(32, 0x2410, 4, "upload")]
    assert (poll.transfers, poll.frames, poll.bits) == (2, 4, 4 * 135)
    table = c.sdo[(1, 0x2102, 0, "download")]
    assert (table.transfers, table.frames) == (1, 7)
    arm = c.sdo[(1, 0x2120, 1, "download")]
    assert (arm.transfers, arm.frames) == (1, 2)
    assert {k: t.frames for k, t in c.classes.items()} == {"heartbeat": 1, "nmt": 1, "emcy": 1}


def test_objects_are_grouped_by_what_the_experiment_defines() -> None:
    bench = DEFAULT_PLANT_NODE_ID
    assert kind_of((1, int(Obj.FEEDFORWARD_TABLE), 0, "download")) == ("per_trial", "feed-forward table downloads")
    assert kind_of((2, int(Obj.RECORDER_DATA), 0, "upload")) == ("per_trial", "recorder uploads")
    assert kind_of((bench, int(PlantObj.INITIAL_STATE), 0, "download")) == ("per_trial", "trial set-up")
    assert kind_of((bench, int(PlantObj.TRIAL), 4, "upload"))[0] == "speed_dependent"
    assert kind_of((bench, int(PlantObj.TRIAL_TIMING), 0, "upload"))[0] == "diagnostics"
    assert kind_of((3, int(Obj.REF_POSITION_TABLE), 0, "download")) == ("setup", "set-up")
    assert kind_of((3, 0x1000, 0, "upload"))[0] == "speed_dependent"


def test_per_trial_exchange_follows_from_the_transfer_sizes_not_the_number_of_polls() -> None:
    def run(polls: int) -> dict:
        acc = BusTimeAccounting(io_bitrate=500_000, fieldbus_bitrate=500_000, ts_s=1e-3, trial_s=0.5, heartbeat_ms=100, n_nodes=5)
        for trial in range(3):
            sdo_upload_expedited(acc.fieldbus, 1, int(Obj.TABLE), 1)  # per trial: 270 bits
            for _ in range(polls):
                sdo_upload_expedited(acc.fieldbus, 32, int(PlantObj.TRIAL), 4)
            ticks(acc.io, 5 * trial, 5)
        sdo_upload_expedited(acc.fieldbus, 1, int(Obj.TABLE), 1)  # one more read, e.g. at set-up
        return acc.summary(trials=3)

    a, b = run(polls=2), run(polls=9)
    for s in (a, b):
        between = s["fieldbus"]["between_trials"]
        assert between["bits_per_trial"] == 270
        assert between["seconds_per_trial"] == pytest.approx(270 / 500_000)
        assert between["cycle_s"] == pytest.approx(0.5 + 270 / 500_000)
        io = s["io"]
        assert io["worst_tick"]["bits"] == 960 and not io["worst_tick"]["fits"]
        assert io["worst_tick"]["excess_bits"] == 460
    assert a["fieldbus"]["between_trials"] == b["fieldbus"]["between_trials"]
    assert a["io"] == b["io"]
    polls = {s["fieldbus"]["counted_apart"]["sdo"]["status polls"]["frames"] for s in (a, b)}
    assert polls == {12, 54}  # counted, but apart
    lines = bus_time_lines(a)
    assert "does NOT fit: 460 bits over" in lines[0] and "500 kbit/s" in lines[0]
    assert "0.001 s per trial" in lines[1]


def test_io_frames_counted_as_arrays_give_the_same_figures() -> None:
    msgs = [io_frames.encode_control(io_frames.IoControlCommand.TRIAL_START, 65_530, 30)]
    for n in range(65_530, 65_530 + 30):  # wraps; the torque frames of a tick arrive late and mixed
        tick = n & 0xFFFF
        msgs += [io_frames.encode_encoder(j, tick, j) for j in range(4)]
        msgs += [io_frames.encode_torque(j, (tick - (j % 2)) & 0xFFFF, 0, 0) for j in range(4)]
    msgs += [
        io_frames.encode_torque(1, 65_531, 0, 0),  # a duplicate long after its tick: a bin of its own
        frame(0x7FF, b"\x01"),
        frame(0x101, b"\x01\x02"),
        io_frames.encode_control(io_frames.IoControlCommand.TRIAL_STOP, 65_560, 30),
    ]
    one, many = IoTickCounter(), IoTickCounter()
    for m in msgs:
        one.add(m)
    frames = frames_from_messages(msgs)
    for part in (frames[:7], frames[7:8], frames[8:150], frames[150:150], frames[150:]):
        many.add_frames(part)
    one.close()
    many.close()
    assert vars(many) == vars(one)
    assert one.ticks > 30
