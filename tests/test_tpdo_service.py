"""TPDOs of the drive, in process: on SYNC (types 0–240 counted per TPDO, SYNC counter 0x1019 and
start value 0x1800:6), on change (254/255) with inhibit time 0x1800:3 and event timer 0x1800:5,
on RTR, and the lockstep trial in which a SYNC's TPDO carries the sample of its own io tick
(bus/cia301/pdo.py, firmware_model/cyclic_pdo.py).  No plant is needed for SYNC-driven TPDOs:
they are sampled at the SYNC.  Time is the drive's lockstep time (1 ms per io tick): exact.
"""

from __future__ import annotations

import struct

import pytest
from drive402_util import echo_drive, rd, wr

from bus.cia301.nmt import NmtCommand
from bus.cyclic import decode_tpdo, encode_csp_rpdo, pdo_config_writes, rpdo_cob_id, tpdo_cob_id
from bus.errors import AbortCode, SdoAbort
from bus.objects import GainsSub, ModeOfOperation, Obj, TableSub, TrialSub
from bus.pdo_objects import PDO_NO_RTR, PDO_NOT_VALID
from firmware_model.drive import Drive

NODE = 3
TPDO1, TPDO2 = 0x180 + NODE, 0x280 + NODE


def tpdo(d: Drive, k: int, tt: int, entries: list[int], *, inhibit: int = 0, timer: int = 0, start: int = 0) -> None:
    """Configure TPDO k (1-based) in PRE-OPERATIONAL: mapping, type, inhibit [100 µs], event timer
    [ms], SYNC start value, then valid."""
    comm, mapping = 0x1800 + k - 1, 0x1A00 + k - 1
    cob = 0x180 + 0x100 * (k - 1) + NODE
    wr(d, comm, 1, "u32", PDO_NOT_VALID | cob)
    wr(d, mapping, 0, "u8", 0)
    for sub, entry in enumerate(entries, start=1):
        wr(d, mapping, sub, "u32", entry)
    wr(d, mapping, 0, "u8", len(entries))
    wr(d, comm, 2, "u8", tt)
    wr(d, comm, 3, "u16", inhibit)
    wr(d, comm, 5, "u16", timer)
    wr(d, comm, 6, "u8", start)
    wr(d, comm, 1, "u32", cob)


STATUSWORD = 0x60410010
POSITION = 0x60640020


def test_sync_tpdos_every_nth_sync_without_io_ticks() -> None:
    d = Drive(NODE)
    tpdo(d, 1, 3, [STATUSWORD])
    tpdo(d, 2, 1, [STATUSWORD, POSITION])
    d.nmt_command(NmtCommand.START)
    sent = []
    for n in range(1, 10):
        d.on_sync()
        sent.append((n, [cob for cob, _ in d.pop_tpdos()]))
    assert sent == [(n, ([TPDO1] if n % 3 == 0 else []) + [TPDO2]) for n in range(1, 10)]
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x06)
    d.on_sync()
    assert d.pop_tpdos() == [(TPDO2, struct.pack("<Hi", 0x0231, 0))]  # the statusword of the SYNC's moment
    d.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    d.on_sync()
    assert d.pop_tpdos() == []  # only in OPERATIONAL


def test_sync_start_value_and_the_sync_counter() -> None:
    d = Drive(NODE)
    wr(d, Obj.SYNC_COUNTER_OVERFLOW, 0, "u8", 6)
    tpdo(d, 1, 2, [STATUSWORD], start=4)
    d.nmt_command(NmtCommand.START)
    due = []
    for counter in [1, 2, 3, 4, 5, 6, 1, 2, 3]:
        d.on_sync(counter)
        if d.pop_tpdos():
            due.append(counter)
    assert due == [4, 6, 2]  # first at the counter 4, then every 2nd SYNC
    assert d.pop_emcy() == []
    d.on_sync()  # no counter byte although 0x1019 = 6: EMCY 0x8240, once
    d.on_sync()
    assert d.pop_emcy() == [(0x8240, 0x11, bytes([0, 0, 0, 0, 0]))]


def test_type_0_goes_out_at_a_sync_only_after_a_change() -> None:
    d = Drive(NODE)
    tpdo(d, 1, 0, [STATUSWORD])
    d.nmt_command(NmtCommand.START)
    d.on_sync()
    assert d.pop_tpdos() == [(TPDO1, struct.pack("<H", 0x0240))]
    d.on_sync()
    assert d.pop_tpdos() == []
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x06)
    assert d.pop_tpdos() == []  # a change waits for the SYNC
    d.on_sync()
    assert d.pop_tpdos() == [(TPDO1, struct.pack("<H", 0x0231))]


def test_event_driven_tpdo_with_inhibit_time_and_event_timer() -> None:
    d, plant = echo_drive(node_id=NODE, mode=1, start=0, enable=False)
    d.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    tpdo(d, 1, 255, [STATUSWORD], inhibit=100, timer=50)  # 10 ms, 50 ms
    d.nmt_command(NmtCommand.START)
    log: list[tuple[int, int]] = []  # (lockstep time ms, statusword)

    def tick(n: int = 1) -> None:
        for _ in range(n):
            plant.step(d)  # io tick, then the timers (as the node runtime serves)
            log.extend((d.time_us // 1000, struct.unpack("<H", data)[0]) for _, data in d.pop_tpdos())

    tick()
    assert log == [(2, 0x0240)]  # the first poll in OPERATIONAL sends it
    tick(3)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x06)  # at 5 ms: within the inhibit time of the one at 2 ms
    tick()
    assert log[-1] == (2, 0x0240)
    tick(6)
    assert log[-1] == (12, 0x0231)  # when the inhibit time ended, with the data of that moment
    tick(20)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x07)  # at 32 ms: sent at once
    d.service()
    log.extend((d.time_us // 1000, struct.unpack("<H", data)[0]) for _, data in d.pop_tpdos())
    tick(60)
    assert log == [(2, 0x0240), (12, 0x0231), (32, 0x0233), (82, 0x0233)]  # the event timer: 50 ms later


def test_rtr_is_answered_only_where_the_cob_id_allows_it() -> None:
    d = Drive(NODE)
    tpdo(d, 1, 255, [STATUSWORD])
    tpdo(d, 2, 1, [POSITION])
    d.nmt_command(NmtCommand.START)
    d.service()
    d.pop_tpdos()
    assert d.rtr_cob_ids() == [TPDO1, TPDO2]
    assert d.on_rtr(TPDO2) and d.pop_tpdos() == [(TPDO2, struct.pack("<i", 0))]
    assert not d.on_rtr(0x480 + NODE)  # TPDO4: not valid
    d.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    assert not d.on_rtr(TPDO1)  # not OPERATIONAL
    wr(d, 0x1800, 1, "u32", PDO_NOT_VALID | TPDO1)
    wr(d, 0x1800, 1, "u32", PDO_NO_RTR | TPDO1)
    d.nmt_command(NmtCommand.START)
    assert d.rtr_cob_ids() == [TPDO2] and not d.on_rtr(TPDO1)


def test_inhibit_time_and_start_value_change_only_while_the_tpdo_is_not_valid() -> None:
    d = Drive(NODE)
    tpdo(d, 1, 255, [STATUSWORD])
    for sub, fmt in ((3, "u16"), (6, "u8")):
        with pytest.raises(SdoAbort) as err:
            wr(d, 0x1800, sub, fmt, 5)
        assert err.value.code == AbortCode.VALUE_RANGE
    wr(d, 0x1800, 5, "u16", 7)  # the event timer may change any time
    wr(d, 0x1800, 1, "u32", PDO_NOT_VALID | TPDO1)
    wr(d, 0x1800, 3, "u16", 5)


def test_in_a_lockstep_trial_a_syncs_tpdo_carries_its_tick() -> None:
    d = Drive(NODE)
    for index, sub, value, size in pdo_config_writes(NODE):
        d.write_object(index, sub, value.to_bytes(size, "little"))
    d.nmt_command(NmtCommand.START)
    wr(d, Obj.GAINS, GainsSub.KP, "i32", 0)  # torque 0 whatever the position
    wr(d, Obj.GAINS, GainsSub.KD, "i32", 0)
    wr(d, Obj.MODES_OF_OPERATION, 0, "i8", ModeOfOperation.CSP)
    for cw in (0x06, 0x07, 0x0F):
        wr(d, Obj.CONTROLWORD, 0, "u16", cw)
    wr(d, Obj.TABLE, TableSub.LENGTH, "u32", 3)
    wr(d, Obj.TRIAL, TrialSub.COMMAND, "u8", 1)
    d.on_rpdo(rpdo_cob_id(NODE), encode_csp_rpdo(0, 0))
    d.on_sync()
    assert d.pop_tpdos() == []  # waits for its tick
    d.io_tick(0, 111)
    assert [(c, decode_tpdo(b)) for c, b in d.pop_tpdos()] == [(tpdo_cob_id(NODE), (111, 0))]
    d.on_sync()
    d.on_sync()  # the tick of the last SYNC never came: its TPDO goes out now, before this one waits
    assert [decode_tpdo(b)[0] for _, b in d.pop_tpdos()] == [111]
    d.io_tick(1, 222)
    assert [decode_tpdo(b)[0] for _, b in d.pop_tpdos()] == [222]
    assert rd(d, Obj.TRIAL, TrialSub.STATE, "u8") == 2


def test_a_drive_of_a_sync_stepped_plant_runs_each_tick_after_its_sync() -> None:
    """``Drive.step_on_sync`` (``ilcrig drive --lockstep``): outside a trial an io tick waits for
    its SYNC in every mode and NMT state, the credits (at most two) survive NMT commands, and a
    SYNC's TPDO carries the io tick of that SYNC in profile position too."""
    d = Drive(NODE)
    d.step_on_sync(lambda: 0.0)
    assert rd(d, Obj.MODES_OF_OPERATION_DISPLAY, 0, "i8") == ModeOfOperation.PROFILE_POSITION
    assert not d.tick_ready  # PRE-OPERATIONAL, profile position: the encoder frame waits
    d.on_sync()
    assert d.tick_ready
    d.io_tick(0, 10)
    assert not d.tick_ready
    d.nmt_command(NmtCommand.STOP)
    for _ in range(3):
        d.on_sync()  # STOPPED: the plant's periods go on, so do the credits (two at most)
    d.nmt_command(NmtCommand.RESET_NODE)
    d.io_tick(1, 20)
    assert d.tick_ready
    d.io_tick(2, 30)
    assert not d.tick_ready
    tpdo(d, 1, 1, [POSITION])
    d.nmt_command(NmtCommand.START)
    d.on_sync()
    assert d.pop_tpdos() == []  # waits for the tick of its SYNC
    d.io_tick(3, 40)
    assert d.pop_tpdos() == [(TPDO1, struct.pack("<i", 40))]
    assert d.lockstep_time_s() == 0.004 and d.clock() == 0.004  # the PDO timers count periods
