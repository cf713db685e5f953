"""CiA 301 PDOs and SYNC on the drive, and the CiA 402 cyclic synchronous modes.

* the PDO objects in bus/drive.eds, the re-mapping rules and their abort codes (bus/cia301/pdo.py);
* CSP and CST on the firmware: RPDO → SYNC → io tick → TPDO, byte for byte;
* the stock ``canopen`` library (not the project's host) configures a drive node's PDOs with its
  PDO API, enables CST and moves it with SYNC + RPDO on a python-can virtual bus, while the test
  plays the plant on the io channel.
"""

from __future__ import annotations

import queue
import struct
import time

import can
import canopen
import pytest
from drive402_util import canopen_view

from bus import fixedpoint as fp
from bus import io_frames
from bus.cia301.nmt import NmtCommand
from bus.cyclic import (
    CSP_RPDO_MAP,
    TPDO_MAP,
    decode_tpdo,
    encode_csp_rpdo,
    pdo_config_writes,
    rpdo_cob_id,
    tpdo_cob_id,
)
from bus.errors import AbortCode, SdoAbort
from bus.objects import DRIVE_EDS_PATH, RATED_TORQUE_MNM, GainsSub, ModeOfOperation, Obj, TableSub, i32, u8, u16, u32
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode

NODE = 2


def abort(fn, *args) -> int:  # type: ignore[no-untyped-def]
    with pytest.raises(SdoAbort) as exc:
        fn(*args)
    return exc.value.code


def configured_drive(mode: ModeOfOperation = ModeOfOperation.CSP, kp: float = 0.0) -> Drive:
    d = Drive(NODE)
    for index, sub, value, size in pdo_config_writes(NODE, mode):
        d.write_object(index, sub, value.to_bytes(size, "little"))
    d.write_object(Obj.GAINS, GainsSub.KP, i32(fp.kp_to_fixed(kp)))
    d.write_object(Obj.GAINS, GainsSub.KD, i32(0))
    d.nmt_command(NmtCommand.START)
    d.write_object(Obj.MODES_OF_OPERATION, 0, struct.pack("<b", mode))
    for cw in (0x06, 0x07, 0x0F):
        d.write_object(Obj.CONTROLWORD, 0, u16(cw))
    return d


def test_eds_describes_four_pdos_each_way_for_the_canopen_library() -> None:
    od = canopen.objectdictionary.import_od(str(DRIVE_EDS_PATH), NODE)
    for k in range(4):
        assert od[0x1400 + k][1].default == 0x80000000 | (0x200 + 0x100 * k + NODE)  # not valid
        assert od[0x1800 + k][1].default == 0x80000000 | (0x180 + 0x100 * k + NODE)
        assert od[0x1600 + k][0].max == 8 and len(od[0x1A00 + k]) == 9
    for index in (Obj.TARGET_POSITION, Obj.TORQUE_OFFSET, Obj.TARGET_TORQUE, Obj.POSITION_ACTUAL, Obj.TORQUE_ACTUAL):
        assert od[index].pdo_mappable
    assert not od[Obj.FOLLOWING_ERROR_WINDOW].pdo_mappable
    # the library's PDO objects find the maps and read their defaults
    node = canopen.RemoteNode(NODE, str(DRIVE_EDS_PATH))
    canopen.Network().add_node(node)
    assert sorted(node.rpdo.map) == [1, 2, 3, 4] and sorted(node.tpdo.map) == [1, 2, 3, 4]
    node.tpdo.read(from_od=True)
    assert node.tpdo[1].cob_id == 0x180 + NODE and not node.tpdo[1].enabled
    assert [v.index for v in node.tpdo[1].map] == [Obj.STATUSWORD]


def test_remapping_rules_and_abort_codes() -> None:
    d = Drive(NODE)
    w = d.write_object
    # the default RPDO1 is not valid: its mapping may change in PRE-OPERATIONAL, entries only with sub 0 = 0
    assert abort(w, 0x1600, 1, u32(0x607A0020)) == AbortCode.UNSUPPORTED_ACCESS == 0x06010000
    w(0x1600, 0, u8(0))
    assert abort(w, 0x1600, 1, u32(0x5FFF0020)) == AbortCode.NO_OBJECT
    assert abort(w, 0x1600, 1, u32(0x60650020)) == AbortCode.NOT_MAPPABLE == 0x06040041  # PDOMapping=0
    assert abort(w, 0x1600, 1, u32(0x607A0010)) == AbortCode.NOT_MAPPABLE  # 16 bits of an INTEGER32
    assert abort(w, 0x1600, 1, u32(0x60640020)) == AbortCode.NOT_MAPPABLE  # read-only: not RPDO-mappable
    for sub in range(1, 4):
        w(0x1600, sub, u32(0x607A0020))
    assert abort(w, 0x1600, 0, u8(3)) == AbortCode.PDO_LENGTH == 0x06040042  # 96 bits
    assert abort(w, 0x1600, 0, u8(9)) in (AbortCode.PDO_LENGTH, AbortCode.VALUE_TOO_HIGH)
    w(0x1600, 0, u8(2))
    assert abort(w, 0x1600, 1, u32(0x60B20010)) == AbortCode.UNSUPPORTED_ACCESS  # sub 0 ≠ 0
    # COB-ID: valid → another valid one is refused; restricted identifiers and 29-bit too
    w(0x1400, 1, u32(0x200 + NODE))
    assert abort(w, 0x1600, 0, u8(0)) == AbortCode.UNSUPPORTED_ACCESS  # PDO valid
    assert abort(w, 0x1400, 1, u32(0x300 + NODE)) == AbortCode.VALUE_RANGE == 0x06090030
    w(0x1400, 1, u32(0x80000000 | 0x300 + NODE))
    assert abort(w, 0x1400, 1, u32(0x581)) == AbortCode.VALUE_RANGE  # SDO response range
    assert abort(w, 0x1400, 1, u32(0x20000000 | 0x300)) == AbortCode.VALUE_RANGE
    assert abort(w, 0x1400, 2, u8(252)) == AbortCode.VALUE_RANGE
    w(0x1400, 2, u8(1))
    # mapping in OPERATIONAL: refused even with the PDO invalid
    d.nmt_command(NmtCommand.START)
    assert abort(w, 0x1600, 0, u8(0)) == AbortCode.DEVICE_STATE == 0x08000022
    d.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    w(0x1600, 0, u8(0))
    # reset communication restores the EDS defaults
    d.nmt_command(NmtCommand.RESET_COMMUNICATION)
    assert d.read_object(0x1400, 1) == u32(0x80000200 + NODE) and d.read_object(0x1600, 1) == u32(0x60400010)


def test_modes_of_operation() -> None:
    d = Drive(NODE)
    for mode in ModeOfOperation:
        d.write_object(Obj.MODES_OF_OPERATION, 0, struct.pack("<b", mode))
        assert d.read_object(Obj.MODES_OF_OPERATION_DISPLAY, 0) == struct.pack("<b", mode)
    for other in (0, 2, 3, 4, 7, -2):
        assert abort(d.write_object, Obj.MODES_OF_OPERATION, 0, struct.pack("<b", other)) == AbortCode.VALUE_RANGE
    # 0x6502 lists exactly these: pp bit 0, hm bit 5, csp bit 7, csv bit 8, cst bit 9, -1 bit 16
    assert d.read_object(Obj.SUPPORTED_DRIVE_MODES, 0) == u32(0x000103A1)


def test_mode_change_is_refused_while_a_trial_is_armed_and_sets_the_mode_bits() -> None:
    d = configured_drive(ModeOfOperation.CSP)
    assert d.statusword & 0x1000  # CSx, torque on: the drive follows the command value
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(2))
    d.write_object(Obj.TRIAL, 1, u8(1))
    table = struct.pack("<b", ModeOfOperation.TABLE_PLAYBACK)
    assert abort(d.write_object, Obj.MODES_OF_OPERATION, 0, table) == AbortCode.DEVICE_STATE
    assert d.read_object(Obj.MODES_OF_OPERATION_DISPLAY, 0) == struct.pack("<b", ModeOfOperation.CSP)
    d.write_object(Obj.TRIAL, 1, u8(0))  # disarm
    d.write_object(Obj.MODES_OF_OPERATION, 0, table)
    assert not d.statusword & 0x1000 and d.tick_ready  # table playback: no bit 12, no SYNC pacing


def test_csp_tick_waits_for_sync_and_applies_the_rpdo_of_its_cycle() -> None:
    kp = 1000.0
    d = configured_drive(ModeOfOperation.CSP, kp=kp)
    rated = RATED_TORQUE_MNM
    assert d.tick_ready is False  # operational + CSP: an io tick needs its SYNC
    assert d.on_rpdo(rpdo_cob_id(NODE), encode_csp_rpdo(1000, 5))
    assert d.pop_tpdos() == []
    d.on_sync()
    assert d.tick_ready
    tau = d.io_tick(0, 400)
    assert d.tick_ready is False  # one credit per SYNC
    kp_q16 = fp.kp_to_fixed(kp)
    fb = fp.rshift_round(kp_q16 * 600, fp.ACC_Q)
    assert tau == fb + 5 * rated
    # outside a trial the TPDO of a SYNC carries the latest completed cycle: sampled at the SYNC,
    # before this tick (no cycle yet: position 0, torque 0); the next SYNC's carries this tick
    ((cob, data),) = d.pop_tpdos()
    assert cob == tpdo_cob_id(NODE)
    assert decode_tpdo(data) == (0, 0)
    assert d.statusword & 0x1000  # drive follows the command value
    # a synchronous RPDO received now takes effect only at the next SYNC
    d.on_rpdo(rpdo_cob_id(NODE), encode_csp_rpdo(1000, -7))
    assert d.read_object(Obj.TORQUE_OFFSET, 0) == struct.pack("<h", 5)
    d.on_sync()
    assert d.read_object(Obj.TORQUE_OFFSET, 0) == struct.pack("<h", -7)
    ((_, data),) = d.pop_tpdos()
    assert decode_tpdo(data) == (400, fp.torque_units_to_permille(tau, rated))
    # a short RPDO is not processed: EMCY 0x8210 with the RPDO number
    d.on_rpdo(rpdo_cob_id(NODE), b"\x01\x02")
    assert d.pdo.engine.length_errors == 1
    assert d.pop_emcy() == [(0x8210, 0x11, bytes([0, 1, 0, 0, 0]))]


def test_csp_trial_records_like_table_playback() -> None:
    d = configured_drive(ModeOfOperation.CSP, kp=500.0)
    n = 4
    d.write_object(Obj.TABLE, TableSub.LENGTH, u32(n))
    d.write_object(Obj.TRIAL, 1, u8(1))  # arm: needs only the length in a cyclic mode
    targets = [0, 10, 30, 60]
    for k in range(n):
        d.on_rpdo(rpdo_cob_id(NODE), encode_csp_rpdo(targets[k], 1))
        d.on_sync()
        d.io_tick(k, targets[k])
        assert len(d.pop_tpdos()) == 1
    assert d.read_object(Obj.TRIAL, 2) == u8(3)  # DONE
    assert int.from_bytes(d.read_object(Obj.RECORDER, 2), "little") == n
    rec = d.read_object(Obj.RECORDER_DATA, 0)
    pos = struct.unpack(f"<{n}i", rec[: 4 * n])
    tau = struct.unpack(f"<{n}i", rec[8 * n : 12 * n])
    assert list(pos) == targets
    assert list(tau) == [RATED_TORQUE_MNM] * n  # zero error, velocity reference = backward difference


def test_cst_torque_is_target_plus_offset_without_feedback() -> None:
    d = configured_drive(ModeOfOperation.CST, kp=1000.0)
    d.on_rpdo(rpdo_cob_id(NODE), struct.pack("<hh", 100, -3))
    d.on_sync()
    assert d.io_tick(0, 123456) == 97 * RATED_TORQUE_MNM


# ---------------------------------------------------------------------------------------
# the stock canopen library drives a drive node over a python-can virtual bus
# ---------------------------------------------------------------------------------------


def test_canopen_library_configures_pdos_enables_cst_and_moves_the_drive_with_sync_and_rpdo() -> None:
    prefix = f"pdo-{time.monotonic_ns()}"
    fb_node = can.Bus(interface="virtual", channel=f"{prefix}-fb")
    io_node = can.Bus(interface="virtual", channel=f"{prefix}-io")
    plant = can.Bus(interface="virtual", channel=f"{prefix}-io")
    node_rt = DriveNode(Drive(NODE), fb_node, io_node)
    try:
        with canopen_view(node_rt, NODE, interface="virtual", channel=f"{prefix}-fb") as (network, node):
            node.nmt.send_command(0x80)  # pre-operational (it booted there already)
            node.rpdo.read()
            node.tpdo.read()
            rpdo, tpdo = node.rpdo[1], node.tpdo[1]
            rpdo.clear()
            rpdo.add_variable("Target torque")
            rpdo.add_variable("Torque offset")
            rpdo.trans_type = 1
            rpdo.enabled = True
            tpdo.clear()
            for index, sub, _ in TPDO_MAP:
                tpdo.add_variable(index, sub)
            tpdo.trans_type = 1
            tpdo.enabled = True
            rpdo.save()
            tpdo.save()
            # the drive holds exactly what the library wrote
            assert node.sdo[0x1400][1].raw == 0x200 + NODE and node.sdo[0x1400][2].raw == 1
            assert [node.sdo[0x1600][s].raw for s in range(3)] == [2, 0x60710010, 0x60B20010]
            assert [node.sdo[0x1A00][s].raw for s in range(3)] == [2, 0x60640020, 0x60770010]
            node.sdo[0x6060].raw = int(ModeOfOperation.CST)
            node.nmt.state = "OPERATIONAL"
            for cw in (0x06, 0x07, 0x0F):
                node.sdo[0x6040].raw = cw
            assert node.sdo[0x6041].raw & 0x106F == 0x1027  # operation enabled, follows the command
            assert node.sdo[0x6061].raw == 10

            def plant_tick(tick: int, count: int) -> io_frames.TorqueFrame:
                plant.send(io_frames.encode_encoder(NODE - 1, tick, count))
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline:
                    msg = plant.recv(0.5)
                    if msg is not None and msg.arbitration_id == io_frames.torque_cob_id(NODE - 1):
                        return io_frames.decode_torque(msg)
                raise AssertionError(f"no torque frame for tick {tick}")

            received: queue.Queue[bytes] = queue.Queue()
            tpdo.add_callback(lambda m: received.put(bytes(m.data)))
            got = []
            for tick, (target, offset) in enumerate([(100, 0), (250, -50), (-30, 10)]):
                rpdo["Target torque"].raw = target
                rpdo["Torque offset"].raw = offset
                rpdo.transmit()
                network.sync.transmit()
                frame = plant_tick(tick, 1000 + tick)
                data = received.get(timeout=10)
                assert data == tpdo.data
                got.append((frame.torque_units, tpdo["Position actual value"].raw, tpdo["Torque actual value"].raw))
                assert frame.status & io_frames.TorqueStatus.ENABLED
            r = RATED_TORQUE_MNM
            # each SYNC's TPDO carries the latest completed control cycle (the previous tick's)
            assert got == [(100 * r, 0, 0), (200 * r, 1000, 100), (-20 * r, 1001, 200)]
    finally:
        for bus in (fb_node, io_node, plant):
            bus.shutdown()


def test_rig_mapping_constants_are_the_config_writes() -> None:
    writes = pdo_config_writes(NODE)
    entries = [v for (i, s, v, _) in writes if i == 0x1600 and s >= 1]
    assert entries == [(i << 16) | (s << 8) | b for i, s, b in CSP_RPDO_MAP]
