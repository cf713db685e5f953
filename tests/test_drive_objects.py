"""Drive object dictionary: EDS, access/abort codes, NMT, trial playback, faults and EMCY."""

from __future__ import annotations

import struct

import canopen
import numpy as np
import pytest

from bus import fixedpoint as fp
from bus.cia301.emcy import EmcyCode
from bus.cia301.nmt import NmtState
from bus.errors import AbortCode, SdoAbort
from bus.objects import (
    FaultCause,
    GainsSub,
    Obj,
    RecorderStatus,
    RecorderSub,
    TableSub,
    TrialState,
    TrialSub,
    i32,
    pack_int32,
    u16,
    u32,
    unpack_int32,
    unpack_recorder,
)
from bus.safe_state import parse_safe_state
from firmware_model.cia402 import Cia402State
from firmware_model.drive import DEFAULT_EDS_PATH, Drive, NmtCommandError

NODE = 3


def rd_u(d: Drive, index: int, sub: int = 0) -> int:
    return int.from_bytes(d.read_object(index, sub), "little")


def rd_i(d: Drive, index: int, sub: int = 0) -> int:
    return int.from_bytes(d.read_object(index, sub), "little", signed=True)


def abort_code(fn, *args) -> int:
    with pytest.raises(SdoAbort) as exc:
        fn(*args)
    return exc.value.code


def loaded_drive(n: int = 5, kp: float = 1000.0, kd: float = 0.0, ff: int = 7) -> Drive:
    """A drive in table playback (-1, set explicitly: the default mode is profile position) with
    its three tables loaded."""
    d = Drive(NODE)
    d.write_object(Obj.MODES_OF_OPERATION, 0, struct.pack("<b", -1))
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(n))
    d.write_object(Obj.REF_POSITION_TABLE, 0, pack_int32(np.arange(n) * 10))
    d.write_object(Obj.REF_VELOCITY_TABLE, 0, pack_int32(np.zeros(n, dtype=int)))
    d.write_object(Obj.FEEDFORWARD_TABLE, 0, pack_int32(np.full(n, ff)))
    d.write_object(Obj.GAINS, GainsSub.KP, i32(fp.kp_to_fixed(kp)))
    d.write_object(Obj.GAINS, GainsSub.KD, i32(fp.kd_to_fixed(kd)))
    return d


def enable(d: Drive) -> None:
    d.nmt_command(0x01)
    for cw in (0x06, 0x07, 0x0F):
        d.write_object(Obj.CONTROLWORD, 0, u16(cw))
    assert d.cia402_state == Cia402State.OPERATION_ENABLED


# ------------------------------------------------------------------ EDS


def test_eds_loads_with_import_od() -> None:
    od = canopen.objectdictionary.import_od(str(DEFAULT_EDS_PATH), NODE)
    assert od[0x1000].default == 0x00020192
    assert od[0x1014].default == 0x80 + NODE
    assert od[0x1200][1].default == 0x600 + NODE and od[0x1200][2].default == 0x580 + NODE
    assert od[0x6076].default == 88_200 and od[0x6072].default == 3000
    assert od[0x2110][GainsSub.KP].data_type == canopen.objectdictionary.INTEGER32
    assert od[0x2210].data_type == canopen.objectdictionary.DOMAIN and od[0x2210].access_type == "ro"
    assert od[0x2120][TrialSub.COMMAND].access_type == "wo"
    assert od[0x2110][GainsSub.VEL_FILTER].max == 32768 and od[0x2110][GainsSub.VEL_FILTER].min == 1
    assert od["Statusword"].index == 0x6041
    for index in Obj:
        assert index in od, f"0x{index:04X} missing from the EDS"


def test_remote_node_can_use_the_eds_to_decode_drive_bytes() -> None:
    """The host's canopen RemoteNode, built from the same EDS, decodes what the drive sends."""
    network = canopen.Network()  # never connected: only the OD/codec side is used
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS_PATH))
    network.add_node(node)
    d = Drive(NODE)
    for (index, sub), var in d.store.vars.items():
        if var.access_type == "wo":
            continue
        sdo_var = node.sdo[index] if sub == 0 and not hasattr(node.sdo[index], "__getitem__") else node.sdo[index][sub]
        raw = sdo_var.od.decode_raw(d.read_object(index, sub))
        if sdo_var.od.data_type not in (canopen.objectdictionary.DOMAIN,):
            expected = var.default if var.default is not None else 0
            if index in (Obj.STATUSWORD, Obj.INTERPOLATION_PERIOD, Obj.TABLE):
                continue  # live values
            assert raw == expected, f"0x{index:04X}:{sub}"
    assert node.sdo[0x6041].od.decode_raw(d.read_object(0x6041, 0)) == 0x0240


# ------------------------------------------------------------------ access and abort codes


def test_abort_codes() -> None:
    d = Drive(NODE)
    assert abort_code(d.read_object, 0x6073, 0) == AbortCode.NO_OBJECT == 0x06020000
    assert abort_code(d.read_object, 0x0002, 0) == AbortCode.NO_OBJECT
    assert abort_code(d.read_object, 0x2110, 9) == AbortCode.NO_SUBINDEX == 0x06090011
    assert abort_code(d.read_object, 0x6041, 1) == AbortCode.NO_SUBINDEX
    assert abort_code(d.write_object, 0x6041, 0, u16(0)) == AbortCode.READ_ONLY == 0x06010002
    assert abort_code(d.write_object, 0x1000, 0, u32(0)) == AbortCode.READ_ONLY
    assert abort_code(d.write_object, 0x2110, 0, b"\x03") == AbortCode.READ_ONLY  # const sub 0
    assert abort_code(d.read_object, 0x2120, TrialSub.COMMAND) == AbortCode.WRITE_ONLY == 0x06010001
    assert abort_code(d.write_object, 0x6040, 0, b"\x06") == AbortCode.LENGTH_MISMATCH == 0x06070010
    assert abort_code(d.write_object, 0x6040, 0, b"\x06\x00\x00") == AbortCode.LENGTH_MISMATCH
    assert abort_code(d.write_object, 0x2110, GainsSub.KP, i32(-1)) == AbortCode.VALUE_TOO_LOW == 0x06090032
    assert abort_code(d.write_object, 0x2110, GainsSub.VEL_FILTER, u16(40000)) == AbortCode.VALUE_TOO_HIGH
    assert abort_code(d.write_object, 0x2110, GainsSub.VEL_FILTER, u16(0)) == AbortCode.VALUE_TOO_LOW
    assert abort_code(d.write_object, 0x6060, 0, b"\x07") == AbortCode.VALUE_RANGE == 0x06090030  # interpolated: not supported
    assert abort_code(d.write_object, 0x2300, 0, u32(50)) == AbortCode.VALUE_TOO_LOW
    # tables need a length first, then exactly 4·N bytes
    assert abort_code(d.write_object, 0x2100, 0, i32(1)) == AbortCode.DEVICE_STATE
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(2))
    assert abort_code(d.write_object, 0x2100, 0, i32(1)) == AbortCode.LENGTH_MISMATCH
    assert abort_code(d.write_object, 0x2103, 1, u32(10**6)) == AbortCode.VALUE_TOO_HIGH
    # arming without all tables
    assert abort_code(d.write_object, 0x2120, 1, b"\x01") == AbortCode.DEVICE_STATE == 0x08000022


def test_read_write_round_trip_and_defaults() -> None:
    d = Drive(NODE)
    assert rd_u(d, 0x1000) == 0x00020192
    assert rd_u(d, 0x1014) == 0x80 + NODE
    assert rd_u(d, 0x1018, 4) == NODE
    assert d.read_object(0x1008, 0) == b"ilcrig drive"
    assert rd_i(d, 0x6060) == 1 and rd_i(d, 0x6061) == 1  # profile position: a mode every CiA 402 master knows
    assert rd_u(d, 0x6076) == 88_200 and rd_u(d, 0x6072) == 3000
    assert rd_u(d, 0x2300) == 1000
    assert rd_u(d, 0x60C2, 1) == 1 and rd_i(d, 0x60C2, 2) == -3
    d.write_object(0x2300, 0, u32(500))
    assert rd_u(d, 0x60C2, 1) == 5 and rd_i(d, 0x60C2, 2) == -4
    d.write_object(0x60C2, 2, struct.pack("<b", -3))  # 5 ms
    assert rd_u(d, 0x2300) == 5000
    d.write_object(0x1017, 0, u16(100))
    assert rd_u(d, 0x1017) == 100
    d.write_object(0x2110, GainsSub.KP, i32(12345))
    assert rd_i(d, 0x2110, GainsSub.KP) == 12345
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(3))
    d.write_object(0x2102, 0, pack_int32([1, -2, 3]))
    assert list(unpack_int32(d.read_object(0x2102, 0))) == [1, -2, 3]
    assert rd_u(d, 0x2103, TableSub.LOADED) == 4
    assert d.read_object(0x2100, 0) == b""  # not loaded


def test_nmt_states_and_resets() -> None:
    d = Drive(NODE)
    assert d.nmt_state == NmtState.PRE_OPERATIONAL == 0x7F
    assert d.nmt_command(0x01) == 0x05
    assert d.nmt_command(0x02) == 0x04
    assert d.nmt_command(0x80) == 0x7F
    d.write_object(0x1017, 0, u16(250))
    d.write_object(0x2110, GainsSub.KP, i32(777))
    assert d.nmt_command(0x82) == 0x7F  # reset communication: 0x1xxx back to defaults only
    assert rd_u(d, 0x1017) == 0 and rd_i(d, 0x2110, 1) == 777
    d.write_object(0x1017, 0, u16(250))
    assert d.nmt_command(0x81) == 0x7F  # reset node: everything
    kp_default = d.store.lookup(0x2110, GainsSub.KP).default  # the EDS default: the robot's tuning
    assert rd_u(d, 0x1017) == 0 and rd_i(d, 0x2110, 1) == kp_default == fp.kp_to_fixed(2000.0)
    with pytest.raises(NmtCommandError, match="0x42"):
        d.nmt_command(0x42)


def test_torque_only_when_enabled_and_nmt_start_brings_none_back() -> None:
    d = loaded_drive()
    assert d.io_tick(0, -100) == 0  # switch on disabled
    d.nmt_command(0x01)
    assert d.io_tick(1, -100) == 0  # not enabled
    assert rd_i(d, 0x6064) == -100  # position actual follows the encoder anyway
    for cw in (0x06, 0x07, 0x0F):
        d.write_object(Obj.CONTROLWORD, 0, u16(cw))
    assert rd_u(d, 0x6041) == 0x0237
    # idle: holds the position seen on the first enabled tick
    assert d.io_tick(2, -100) == 0
    kp_q = fp.kp_to_fixed(1000)
    assert d.io_tick(3, -110) == fp.rshift_round(kp_q * 10, 16)
    d.nmt_command(0x80)  # leaving OPERATIONAL: abort connection, 0x6007 = 1 → Fault
    assert d.io_tick(4, -110) == 0 and rd_u(d, 0x6041) == 0x0208
    d.nmt_command(0x01)  # NMT START: no controlword, no torque
    assert d.io_tick(5, -110) == 0 and rd_u(d, 0x6041) == 0x0208


def run_trial(d: Drive, counts: list[int]) -> list[int]:
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, b"\x01")
    return [d.io_tick(n, c) for n, c in enumerate(counts)]


def test_trial_playback_recorder_and_actuals() -> None:
    d = loaded_drive(n=5, kp=1000.0, ff=7)
    enable(d)
    kp_q = fp.kp_to_fixed(1000)
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.IDLE
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, b"\x01")
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.ARMED
    counts = [0, 5, 20, 30, 40, 40, 40]
    taus = [d.io_tick(n, c) for n, c in enumerate(counts[:3])]
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.RUNNING
    assert rd_u(d, Obj.RECORDER, RecorderSub.STATUS) == RecorderStatus.RECORDING
    assert abort_code(d.read_object, Obj.RECORDER_DATA, 0) == AbortCode.DEVICE_STATE
    assert abort_code(d.write_object, Obj.FEEDFORWARD_TABLE, 0, pack_int32(np.zeros(5, int))) == (AbortCode.DEVICE_STATE)
    assert abort_code(d.write_object, Obj.CONTROL_PERIOD, 0, u32(500)) == AbortCode.DEVICE_STATE
    taus += [d.io_tick(n, c) for n, c in enumerate(counts[3:], start=3)]
    ref = [0, 10, 20, 30, 40, 40, 40]
    assert taus == [fp.rshift_round(kp_q * (r - c), 16) + 7 for r, c in zip(ref, counts)]
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.DONE
    assert rd_u(d, Obj.TRIAL, TrialSub.TICKS) == 5
    assert rd_u(d, Obj.RECORDER, RecorderSub.STATUS) == RecorderStatus.COMPLETE
    assert rd_u(d, Obj.RECORDER, RecorderSub.SAMPLES) == 5
    planes = unpack_recorder(d.read_object(Obj.RECORDER_DATA, 0), 5)
    assert list(planes[0]) == counts[:5]
    assert list(planes[1]) == [0, 5000, 15000, 10000, 10000]  # counts/s by difference at 1 kHz
    assert list(planes[2]) == taus[:5]
    assert list(planes[3]) == [t - 7 for t in taus[:5]]
    assert rd_i(d, 0x6064) == 40
    assert rd_i(d, 0x606C) == 0
    d.io_tick(99, 30)  # after the trial: no sequence check, holds the last reference
    assert rd_i(d, 0x606C) == -10_000
    tau = fp.rshift_round(kp_q * 10, 16) + 7
    assert rd_i(d, 0x6077) == round(tau / 88_200)
    # a second trial: re-arm, the recorder restarts
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, b"\x01")
    assert rd_u(d, Obj.RECORDER, RecorderSub.SAMPLES) == 0
    assert run_trial(d, counts[:5]) == taus[:5]


def test_trial_velocity_estimator_starts_at_reference_velocity() -> None:
    d = loaded_drive(n=3, kp=0.0, kd=10.0, ff=0)
    d.write_object(Obj.REF_VELOCITY_TABLE, 0, pack_int32([4000, 4000, 4000]))
    enable(d)
    d.io_tick(0, 12345)  # idle ticks build some estimator history
    d.io_tick(1, 22345)
    taus = run_trial(d, [0, 4, 8])
    assert taus == [0, 0, 0]  # v_est = ref_vel from the first trial tick


@pytest.mark.parametrize(("ticks", "bad"), [([0, 1, 3], 3), ([0, 1, 1], 1), ([0, 1, 2, 0], 0), ([5], 5)])
def test_tick_sequence_fault_and_emcy(ticks: list[int], bad: int) -> None:
    d = loaded_drive(n=10)
    enable(d)
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, b"\x01")
    taus = [d.io_tick(t, 0) for t in ticks]
    assert taus[-1] == 0
    played = len(ticks) - 1
    assert d.cia402_state == Cia402State.FAULT
    assert rd_u(d, 0x6041) == 0x0208
    assert rd_u(d, 0x1001) == 0x11  # generic + communication
    assert rd_u(d, 0x603F) == EmcyCode.PROTOCOL_ERROR == 0x8200
    assert d.pop_emcy() == [(0x8200, 0x11, struct.pack("<BHH", FaultCause.TICK_SEQUENCE, played, bad))]
    assert d.pop_emcy() == []
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.FAULT
    assert rd_u(d, Obj.TRIAL, TrialSub.FAULT_CAUSE) == FaultCause.TICK_SEQUENCE
    assert rd_u(d, Obj.RECORDER, RecorderSub.STATUS) == (RecorderStatus.STOPPED if played else RecorderStatus.EMPTY)
    assert rd_u(d, Obj.RECORDER, RecorderSub.SAMPLES) == played
    assert len(d.read_object(Obj.RECORDER_DATA, 0)) == 16 * played
    assert d.io_tick(len(ticks), 0) == 0  # torque stays off
    assert abort_code(d.write_object, Obj.TRIAL, TrialSub.COMMAND, b"\x01") == AbortCode.DEVICE_STATE
    # fault reset: rising edge of bit 7 -> switch on disabled, EMCY 0x0000, 0x1001 cleared
    d.write_object(Obj.CONTROLWORD, 0, u16(0x80))
    assert d.cia402_state == Cia402State.SWITCH_ON_DISABLED
    assert d.pop_emcy() == [(0x0000, 0x00, bytes(5))]
    assert rd_u(d, 0x1001) == 0 and rd_u(d, 0x603F) == 0
    enable(d)
    assert run_trial(d, [0] * 10)[0] == 7  # works again


def test_following_error_fault() -> None:
    d = loaded_drive(n=5, kp=100.0, ff=0)
    d.write_object(Obj.FOLLOWING_ERROR_WINDOW, 0, u32(1000))
    enable(d)
    taus = run_trial(d, [0, 5, -1000])  # e = 20 - (-1000) = 1020 > 1000
    assert taus[2] == 0 and taus[1] != 0
    assert d.cia402_state == Cia402State.FAULT
    assert rd_u(d, 0x1001) == 0x21
    assert d.pop_emcy() == [(0x8611, 0x21, struct.pack("<Bi", FaultCause.FOLLOWING_ERROR, 1020))]
    assert rd_u(d, Obj.RECORDER, RecorderSub.SAMPLES) == 3
    planes = unpack_recorder(d.read_object(Obj.RECORDER_DATA, 0), 3)
    assert planes[2, 2] == 0 and planes[3, 2] > 0  # torque removed on the faulting tick


def test_safe_state_records_name_the_fault_tick_only_for_the_fault(caplog: pytest.LogCaptureFixture) -> None:
    """One SAFE-STATE record per loss of torque: the fault's record carries the ticks the trial
    played (0x2120:3, the faulting tick included); a later disable (after a fault reset) has no
    trial tick."""
    d = loaded_drive(n=5, kp=100.0, ff=0)
    d.write_object(Obj.FOLLOWING_ERROR_WINDOW, 0, u32(1000))
    enable(d)
    caplog.set_level("INFO", logger="firmware_model")
    run_trial(d, [0, 5, -1000])  # following error at tick 2
    assert rd_u(d, Obj.TRIAL, TrialSub.TICKS) == 3
    d.write_object(Obj.CONTROLWORD, 0, u16(0x80))  # fault reset
    enable(d)
    d.write_object(Obj.CONTROLWORD, 0, u16(0x06))  # shutdown: torque off
    records = [r for r in map(parse_safe_state, caplog.messages) if r]
    assert [(r["reason"], r["cia402"], r["tick"]) for r in records] == [
        ("fault-following_error", "FAULT", "3"),
        ("cia402-ready_to_switch_on", "READY_TO_SWITCH_ON", "-"),
    ]


def test_following_error_window_off() -> None:
    d = loaded_drive(n=2, kp=100.0)
    d.write_object(Obj.FOLLOWING_ERROR_WINDOW, 0, u32(0xFFFFFFFF))
    enable(d)
    assert run_trial(d, [0, 10**9])[1] != 0
    assert d.cia402_state == Cia402State.OPERATION_ENABLED


def test_torque_limit_from_0x6072() -> None:
    d = loaded_drive(n=2, kp=1000.0, ff=0)
    d.write_object(Obj.MAX_TORQUE, 0, u16(10))  # 10 ‰ of 88.2 N·m = 0.882 N·m
    enable(d)
    taus = run_trial(d, [-100_000, -100_000])
    assert taus == [882_000, 882_000]
    assert rd_u(d, 0x6041) & 0x0800  # internal limit active
    assert rd_i(d, 0x6077) == 10


def test_disable_during_trial_ends_it() -> None:
    d = loaded_drive(n=5)
    enable(d)
    run_trial(d, [0, 10])
    d.write_object(Obj.CONTROLWORD, 0, u16(0x07))  # disable operation
    assert d.io_tick(2, 20) == 0
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.FAULT
    assert rd_u(d, Obj.TRIAL, TrialSub.FAULT_CAUSE) == FaultCause.NONE
    assert rd_u(d, Obj.RECORDER, RecorderSub.STATUS) == RecorderStatus.STOPPED
    assert rd_u(d, Obj.RECORDER, RecorderSub.SAMPLES) == 2
    assert d.pop_emcy() == []


def test_disarm_and_table_length_change() -> None:
    d = loaded_drive(n=4)
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, b"\x01")
    assert abort_code(d.write_object, Obj.TABLE, TableSub.LENGTH, u32(3)) == AbortCode.DEVICE_STATE
    d.write_object(Obj.TRIAL, TrialSub.COMMAND, b"\x00")
    assert rd_u(d, Obj.TRIAL, TrialSub.STATE) == TrialState.IDLE
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(4))  # same length keeps the tables
    assert rd_u(d, Obj.TABLE, TableSub.LOADED) == 7
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(3))
    assert rd_u(d, Obj.TABLE, TableSub.LOADED) == 0
