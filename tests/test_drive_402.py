"""The CiA 402 behaviour of the drive firmware, in process (firmware_model/): profile position,
homing, CSV, quick stop by 0x605A, the abort connection reactions of 0x6007, the communication
errors and 0x1029, the error history 0x1003, parameter storage 0x1010/0x1011, the CiA 301 rules of
0x1005, 0x1014, 0x1019 -- and that the statusword always tells the truth about the power stage.

Motion is checked with the echo plant of tests/drive402_util.py: the encoder count of tick n+1 is
the drive's position demand of tick n, so positions are predicted exactly from the integer
profile.  Time is the drive's lockstep time (0x2300 per io tick), so every timer is exact.
"""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from drive402_util import K_ECHO, EchoPlant, echo_drive, rd, reference_profile, wr

from bus import fixedpoint as fp
from bus.cia301.nmt import NmtCommand, NmtState
from bus.errors import AbortCode, SdoAbort
from bus.objects import (
    RESTORE_SIGNATURE,
    STORE_SIGNATURE,
    Cia402State,
    FaultCause,
    GainsSub,
    ModeOfOperation,
    Obj,
    TrialSub,
    state_from_statusword,
)
from bus.pdo_objects import PDO_NOT_VALID
from firmware_model.drive import Drive
from firmware_model.profile import ProfileGenerator

NODE = 2
PP = ModeOfOperation.PROFILE_POSITION


def abort(fn, *args) -> int:  # type: ignore[no-untyped-def]
    with pytest.raises(SdoAbort) as exc:
        fn(*args)
    return exc.value.code


def rates(d: Drive) -> tuple[int, int, int]:
    period = rd(d, Obj.CONTROL_PERIOD, 0, "u32")
    return (
        fp.per_tick_q16(rd(d, Obj.PROFILE_VELOCITY, 0, "u32"), period, 1),
        fp.per_tick_q16(rd(d, Obj.PROFILE_ACCELERATION, 0, "u32"), period, 2),
        fp.per_tick_q16(rd(d, Obj.PROFILE_DECELERATION, 0, "u32"), period, 2),
    )


def new_setpoint(d: Drive, target: int, bits: int = 0) -> None:
    """0x607A, then the set-point handshake's rising edge of bit 4 (and bit 4 low again)."""
    wr(d, Obj.TARGET_POSITION, 0, "i32", target)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F | bits)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x1F | bits)


def truthful(d: Drive) -> bool:
    """The statusword says Operation enabled / Quick stop active exactly while torque is on."""
    state = state_from_statusword(d.statusword)
    return (state in (Cia402State.OPERATION_ENABLED, Cia402State.QUICK_STOP_ACTIVE)) == d.torque_enabled


# ------------------------------------------------------------------ profile position


def test_pp_move_ends_exactly_on_the_target_along_the_integer_profile() -> None:
    d, plant = echo_drive(mode=PP, start=1000)
    wr(d, Obj.PROFILE_VELOCITY, 0, "u32", 200_000)  # counts/s: 200 counts per 1 ms cycle
    wr(d, Obj.PROFILE_ACCELERATION, 0, "u32", 4_000_000)  # 4 counts/cycle²
    wr(d, Obj.PROFILE_DECELERATION, 0, "u32", 2_000_000)
    window_ms = 10
    wr(d, Obj.POSITION_WINDOW_TIME, 0, "u16", window_ms)  # (the default 0: reached on entering the window)
    assert d.statusword == 0x0637  # enabled, target reached (bit 10), no acknowledge
    new_setpoint(d, 31_000)
    assert d.statusword & 0x1400 == 0x1000  # acknowledged, target not reached
    expected = reference_profile(1000, 31_000, *rates(d))
    demands, actuals = [], []
    for _ in range(len(expected)):
        plant.step(d)
        demands.append(rd(d, Obj.POSITION_DEMAND, 0, "i32"))
        actuals.append(rd(d, Obj.POSITION_ACTUAL, 0, "i32"))
    assert demands == expected
    assert actuals == [1000, *expected[:-1]]  # tick n+1 is at the demand of tick n
    # the demand is on the target, the actual position one cycle behind but inside the 30-count
    # position window: target reached only once it has stayed there for 0x6068 (CiA 402: from the
    # actual position), here 10 ms = 10 cycles counting this one
    assert demands[-1] == 31_000 and abs(actuals[-1] - 31_000) <= 30 and not d.statusword & 0x0400
    plant.step(d)
    assert rd(d, Obj.POSITION_ACTUAL, 0, "i32") == 31_000 and plant.step(d) == 0  # there, no torque
    plant.run(d, window_ms - 4)  # in the window for 0x6068 - 1 cycles: not yet
    assert not d.statusword & 0x0400
    plant.step(d)
    assert d.statusword & 0x0400  # in the window for 0x6068: target reached
    steps = [b - a for a, b in zip([1000, *expected], expected)]
    assert max(steps) == 200 and all(s >= 0 for s in steps)  # profile velocity, no reversal
    # the continuous trapezoid: 30 000 / 200 + 200 / (2·4) + 200 / (2·2) = 225 cycles
    assert abs(len(expected) - 225) <= 2


def test_pp_handshake_relative_buffer_change_immediately_and_halt() -> None:
    d, plant = echo_drive(mode=PP, start=0)
    wr(d, Obj.PROFILE_VELOCITY, 0, "u32", 100_000)
    wr(d, Obj.PROFILE_ACCELERATION, 0, "u32", 10_000_000)
    wr(d, Obj.PROFILE_DECELERATION, 0, "u32", 10_000_000)
    new_setpoint(d, 500)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)  # bit 4 low: acknowledge returns to 0
    assert not d.statusword & 0x1000
    plant.run(d, 2)
    # a second set-point while moving, single set-point mode: buffered; relative to the last target
    new_setpoint(d, 250, bits=0x40)
    assert d.statusword & 0x1000  # acknowledged and buffered: no further set-point now
    new_setpoint(d, 9999)  # ignored: the buffer is full (acknowledge still 1)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)
    assert d.statusword & 0x1000
    seen = plant.run(d, 40)
    assert 500 in seen and seen[-1] == 750  # first the target 500, then 500 + 250
    assert not d.statusword & 0x1000 and d.statusword & 0x0400
    # change immediately (bit 5): the new target replaces the one being approached
    new_setpoint(d, 2000)
    plant.run(d, 3)
    new_setpoint(d, 800, bits=0x20)
    assert plant.run(d, 60)[-1] == 800
    # halt (bit 8): decelerate with 0x6084 and hold, target reached = standstill; release resumes
    new_setpoint(d, 5000)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)
    plant.run(d, 3)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x10F)
    held = plant.run(d, 20)
    assert held[-1] == held[-2] < 5000 and d.statusword & 0x0400
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)
    assert not d.statusword & 0x0400
    assert plant.run(d, 80)[-1] == 5000


def test_pp_set_point_needs_operation_enabled() -> None:
    d, plant = echo_drive(mode=PP, start=0, enable=False)
    wr(d, Obj.TARGET_POSITION, 0, "i32", 100)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x16)  # shutdown with bit 4: no set-point outside Operation enabled
    assert not d.statusword & 0x1000
    assert abort(wr, d, Obj.TRIAL, TrialSub.COMMAND, "u8", 1) == AbortCode.DEVICE_STATE  # no trials in pp


def test_profile_generator_reaches_every_target_exactly() -> None:
    g = ProfileGenerator()
    for start, target, v, a, dec in [(0, 1, 5 << 16, 1, 1), (0, -123_457, 300 << 16, 3 << 16, 1 << 16), (7, 7, 1, 1, 1)]:
        g.reset(start)
        for _ in range(100_000):
            if g.step_to(target, v, a, dec):
                break
        assert g.p == target << 16 and g.v == 0


# ------------------------------------------------------------------ homing, CSV


def test_homing_on_the_current_position_sets_the_home_offset() -> None:
    d, plant = echo_drive(mode=PP, start=5000)
    wr(d, Obj.HOME_OFFSET, 0, "i32", 100)
    assert abort(wr, d, Obj.HOMING_METHOD, 0, "i8", 36) == AbortCode.VALUE_RANGE
    assert abort(wr, d, Obj.HOMING_METHOD, 0, "i8", 34) == AbortCode.VALUE_TOO_LOW
    wr(d, Obj.HOMING_METHOD, 0, "i8", 35)
    wr(d, Obj.MODES_OF_OPERATION, 0, "i8", ModeOfOperation.HOMING)
    assert d.statusword & 0x3400 == 0x0400  # not started
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x1F)
    assert d.statusword & 0x3400 == 0x1400  # attained, target reached
    assert rd(d, Obj.POSITION_ACTUAL, 0, "i32") == 100
    assert plant.step(d) == 0 and rd(d, Obj.POSITION_ACTUAL, 0, "i32") == 100  # encoder 5000 is 100 now
    wr(d, Obj.MODES_OF_OPERATION, 0, "i8", PP)
    new_setpoint(d, 300)
    plant.run(d, 50)
    assert rd(d, Obj.POSITION_ACTUAL, 0, "i32") == 300 and plant.count == 5200
    d.nmt_command(NmtCommand.RESET_NODE)  # the offset goes with a reset
    plant.step(d)
    assert rd(d, Obj.POSITION_ACTUAL, 0, "i32") == 5200


def test_csv_integrates_the_target_velocity() -> None:
    d, plant = echo_drive(mode=ModeOfOperation.CSV, start=-40)
    wr(d, Obj.TARGET_VELOCITY, 0, "i32", 2500)  # counts/s: 2.5 counts per 1 ms cycle, exact in Q16
    demands = []
    for _ in range(4):
        plant.step(d)
        demands.append(rd(d, Obj.POSITION_DEMAND, 0, "i32"))
    assert demands == [-37, -35, -32, -30]  # -40 + 2.5·k, rounded half up
    assert plant.count == -30 and d.statusword & 0x1000  # follows the command value


# ------------------------------------------------------------------ quick stop


def moving_pp(option: int) -> tuple[Drive, EchoPlant, int]:
    """A pp drive at full speed (200 counts/cycle) with 0x605A = ``option``; its velocity."""
    d, plant = echo_drive(mode=PP, start=0)
    wr(d, Obj.QUICK_STOP_OPTION, 0, "i16", option)
    wr(d, Obj.PROFILE_VELOCITY, 0, "u32", 200_000)
    wr(d, Obj.PROFILE_ACCELERATION, 0, "u32", 20_000_000)
    wr(d, Obj.QUICK_STOP_DECELERATION, 0, "u32", 10_000_000)  # 10 counts/cycle²
    wr(d, Obj.PROFILE_DECELERATION, 0, "u32", 5_000_000)
    new_setpoint(d, 1_000_000)
    plant.run(d, 30)
    return d, plant, 200


@pytest.mark.parametrize(("option", "ticks", "end"), [(1, 40, 0x0240), (2, 20, 0x0240), (5, 40, 0x0617), (6, 20, 0x0617)])
def test_quick_stop_ramps_down_then_disables_or_holds(option: int, ticks: int, end: int) -> None:
    d, plant, _ = moving_pp(option)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0B)  # quick stop (bit 2 = 0)
    assert d.statusword == 0x0217 and d.torque_enabled and truthful(d)
    seen = plant.run(d, ticks)  # 200 counts/cycle at 5 or 10 per cycle²: standstill in the last
    assert d.statusword == 0x0217  # the ramp's cycles, the last one's included, are Quick stop active
    plant.step(d)
    assert d.statusword == end and truthful(d)  # the next cycle completes the quick stop
    steps = [b - a for a, b in zip(seen, seen[1:])]
    assert steps == sorted(steps, reverse=True)  # decelerating
    if end == 0x0240:
        assert plant.step(d) == 0 and not d.torque_enabled
        wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)  # Enable operation from Switch on disabled: nothing
        assert d.statusword == 0x0240
    else:
        here = plant.count
        assert plant.run(d, 5) == [here] * 5  # holding, with torque
        wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)  # transition 16: Quick stop active → Operation enabled
        assert state_from_statusword(d.statusword) == Cia402State.OPERATION_ENABLED and d.torque_enabled


def test_quick_stop_option_0_removes_torque_at_once_and_2_ignores_enable() -> None:
    d, plant, _ = moving_pp(0)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0B)
    assert d.statusword == 0x0240 and plant.step(d) == 0 and truthful(d)
    d, plant, _ = moving_pp(2)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0B)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)  # 2 does not allow transition 16
    assert d.statusword == 0x0217
    assert abort(wr, d, Obj.QUICK_STOP_OPTION, 0, "i16", 3) == AbortCode.VALUE_RANGE
    assert abort(wr, d, Obj.QUICK_STOP_OPTION, 0, "i16", 7) == AbortCode.VALUE_TOO_HIGH


@pytest.mark.parametrize(("option", "end"), [(1, 0x0240), (2, 0x0240), (5, 0x0617), (6, 0x0617)])
def test_quick_stop_at_standstill_lasts_one_control_cycle(option: int, end: int) -> None:
    """From standstill the ramp takes one control cycle: Quick stop active until the next one."""
    d, plant = echo_drive(mode=PP, start=1234)
    wr(d, Obj.QUICK_STOP_OPTION, 0, "i16", option)
    assert plant.run(d, 3) == [1234] * 3
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x02)
    assert d.statusword == 0x0217 and d.torque_enabled and truthful(d)  # entered on the controlword
    assert plant.run(d, 1) == [1234] and d.statusword == 0x0217 and d.torque_enabled  # the ramp's cycle
    assert plant.run(d, 1) == [1234] and d.statusword == end and truthful(d)  # completed in the next one
    assert d.torque_enabled is (end == 0x0617)  # 5, 6 hold with torque


# ------------------------------------------------------------------ abort connection, NMT


@pytest.mark.parametrize(
    ("option", "state", "torque"),
    [(0, Cia402State.OPERATION_ENABLED, True), (1, Cia402State.FAULT, False), (2, Cia402State.SWITCH_ON_DISABLED, False)],
)
@pytest.mark.parametrize("command", [NmtCommand.STOP, NmtCommand.ENTER_PRE_OPERATIONAL])
def test_leaving_operational_is_an_abort_connection(option: int, state: Cia402State, torque: bool, command: NmtCommand) -> None:
    d, plant, _ = moving_pp(2)
    wr(d, Obj.ABORT_CONNECTION_OPTION, 0, "i16", option)
    d.pop_emcy()
    d.nmt_command(command)
    assert d.cia402_state == state and d.torque_enabled is torque and truthful(d)
    if option == 0:
        assert d.pop_emcy() == [] and rd(d, Obj.ERROR_HISTORY, 0, "u8") == 0
        return
    assert rd(d, Obj.ERROR_HISTORY, 1, "u32") == 0x8100  # recorded
    emcy = [(0x8100, 0x11, bytes([FaultCause.NMT_ABORT, command, 0, 0, 0]))]
    assert d.pop_emcy() == ([] if command == NmtCommand.STOP else emcy)  # no EMCY in STOPPED
    if option == 1:
        assert rd(d, Obj.ERROR_CODE, 0, "u16") == 0x8100
    # NMT START brings no torque back: only the controlword sequence does
    d.nmt_command(NmtCommand.START)
    assert plant.step(d) == 0 and not d.torque_enabled and truthful(d)
    for cw in (0x80, 0x06, 0x07, 0x0F):
        wr(d, Obj.CONTROLWORD, 0, "u16", cw)
    assert d.torque_enabled and truthful(d)


def test_abort_connection_quick_stop_ramps_in_stopped() -> None:
    d, plant, _ = moving_pp(2)
    wr(d, Obj.ABORT_CONNECTION_OPTION, 0, "i16", 3)
    d.nmt_command(NmtCommand.STOP)
    assert d.statusword == 0x0217 and d.torque_enabled  # ramping down with torque, in STOPPED
    plant.run(d, 20)  # 200 counts/cycle at 10 per cycle²: standstill in the 20th
    assert d.statusword == 0x0217 and d.torque_enabled
    plant.step(d)
    assert d.statusword == 0x0240 and not d.torque_enabled


def test_torque_off_states_never_say_operation_enabled() -> None:
    d, plant = echo_drive(mode=PP, start=0)
    for action in (
        lambda: d.nmt_command(NmtCommand.STOP),
        lambda: d.nmt_command(NmtCommand.START),
        lambda: [wr(d, Obj.CONTROLWORD, 0, "u16", c) for c in (0x80, 0x06, 0x07, 0x0F)],
        lambda: d.nmt_command(NmtCommand.RESET_COMMUNICATION),
        lambda: d.nmt_command(NmtCommand.START),
        lambda: d.nmt_command(NmtCommand.RESET_NODE),
    ):
        action()
        plant.step(d)
        assert truthful(d), hex(d.statusword)


# ------------------------------------------------------------------ communication errors


def test_rpdo_deadline_is_a_communication_error() -> None:
    d, plant = echo_drive(mode=PP, start=0, enable=False)
    d.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    wr(d, 0x1400, 1, "u32", 0x200 + NODE)  # RPDO1 (controlword) valid
    wr(d, 0x1400, 5, "u16", 50)  # ms
    d.nmt_command(NmtCommand.START)
    d.on_rpdo(0x200 + NODE, struct.pack("<H", 0x06))
    d.on_rpdo(0x200 + NODE, struct.pack("<H", 0x07))
    d.on_rpdo(0x200 + NODE, struct.pack("<H", 0x0F))  # enabled by RPDO, at lockstep time t0
    assert d.torque_enabled
    plant.run(d, 49)
    assert d.pop_emcy() == [] and d.torque_enabled
    plant.step(d)  # 50 ms without an RPDO
    assert d.pop_emcy() == [(0x8250, 0x11, bytes([FaultCause.RPDO_TIMEOUT, 1, 0, 0, 0]))]
    assert d.cia402_state == Cia402State.FAULT and not d.torque_enabled  # 0x6007 = 1
    assert d.nmt_state == NmtState.PRE_OPERATIONAL  # 0x1029:1 = 0
    assert rd(d, Obj.ERROR_HISTORY, 1, "u32") == 0x8250 and rd(d, Obj.ERROR_CODE, 0, "u16") == 0x8250
    plant.run(d, 100)
    assert d.pop_emcy() == []  # once per loss


@pytest.mark.parametrize(("behaviour", "nmt"), [(0, NmtState.PRE_OPERATIONAL), (1, NmtState.OPERATIONAL), (2, NmtState.STOPPED)])
def test_sync_watchdog_and_error_behaviour(behaviour: int, nmt: NmtState) -> None:
    d, plant = echo_drive(mode=PP, start=0)
    wr(d, Obj.ERROR_BEHAVIOUR, 1, "u8", behaviour)
    wr(d, Obj.ABORT_CONNECTION_OPTION, 0, "i16", 2)
    wr(d, Obj.COMM_CYCLE_PERIOD, 0, "u32", 10_000)  # µs: lost after 15 ms without SYNC
    d.on_sync()
    plant.run(d, 14)
    assert d.torque_enabled
    plant.step(d)
    assert d.pop_emcy() == [(0x8100, 0x11, bytes([FaultCause.SYNC_LOST, 0, 0, 0, 0]))]
    assert d.cia402_state == Cia402State.SWITCH_ON_DISABLED and d.nmt_state == nmt


def test_error_history_newest_first_and_cleared_by_zero() -> None:
    d, plant = echo_drive(mode=PP, start=0)
    d.heartbeat_lost(127)
    for cw in (0x80, 0x06, 0x07, 0x0F):
        wr(d, Obj.CONTROLWORD, 0, "u16", cw)
    wr(d, Obj.FOLLOWING_ERROR_WINDOW, 0, "u32", 10)
    d.io_tick(9, 1000)  # following error
    assert rd(d, Obj.ERROR_HISTORY, 0, "u8") == 2
    assert [rd(d, Obj.ERROR_HISTORY, s, "u32") for s in (1, 2, 3)] == [0x8611, 0x8130, 0]
    assert abort(wr, d, Obj.ERROR_HISTORY, 0, "u8", 1) == AbortCode.VALUE_RANGE
    assert abort(wr, d, Obj.ERROR_HISTORY, 1, "u32", 0) == AbortCode.READ_ONLY
    wr(d, Obj.ERROR_HISTORY, 0, "u8", 0)
    assert rd(d, Obj.ERROR_HISTORY, 0, "u8") == 0 and rd(d, Obj.ERROR_HISTORY, 1, "u32") == 0


def test_fault_reset_clears_a_communication_error_register() -> None:
    d, _ = echo_drive(mode=PP, start=0, enable=False)
    d.heartbeat_lost(127)  # torque off: no CiA 402 reaction, but the error is recorded
    assert d.cia402_state == Cia402State.SWITCH_ON_DISABLED
    assert rd(d, Obj.ERROR_REGISTER, 0, "u8") == 0x11
    d.pop_emcy()
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x80)
    assert rd(d, Obj.ERROR_REGISTER, 0, "u8") == 0 and d.pop_emcy() == [(0, 0, bytes(5))]


# ------------------------------------------------------------------ CiA 301 objects


def test_cob_id_sync_emcy_and_sync_counter_rules() -> None:
    d = Drive(NODE)
    assert abort(wr, d, Obj.COB_ID_SYNC, 0, "u32", 0x4000_0080) == AbortCode.VALUE_RANGE  # no SYNC producer
    wr(d, Obj.COB_ID_SYNC, 0, "u32", 0x0090)
    assert d.sync_cob_id() == 0x090
    assert abort(wr, d, Obj.COB_ID_EMCY, 0, "u32", 0x0F0) == AbortCode.VALUE_RANGE  # valid: invalidate first
    wr(d, Obj.COB_ID_EMCY, 0, "u32", PDO_NOT_VALID | (0x80 + NODE))
    wr(d, Obj.COB_ID_EMCY, 0, "u32", PDO_NOT_VALID | 0x0F0)
    wr(d, Obj.COB_ID_EMCY, 0, "u32", 0x0F0)
    assert abort(wr, d, Obj.COB_ID_EMCY, 0, "u32", 0x2000_00F0) == AbortCode.VALUE_RANGE
    assert abort(wr, d, Obj.SYNC_COUNTER_OVERFLOW, 0, "u8", 1) == AbortCode.VALUE_RANGE
    assert abort(wr, d, Obj.SYNC_COUNTER_OVERFLOW, 0, "u8", 241) == AbortCode.VALUE_TOO_HIGH
    wr(d, Obj.COMM_CYCLE_PERIOD, 0, "u32", 1000)
    assert abort(wr, d, Obj.SYNC_COUNTER_OVERFLOW, 0, "u8", 10) == AbortCode.DEVICE_STATE  # 0x1006 ≠ 0
    wr(d, Obj.COMM_CYCLE_PERIOD, 0, "u32", 0)
    wr(d, Obj.SYNC_COUNTER_OVERFLOW, 0, "u8", 10)


def test_cob_id_objects_refuse_the_restricted_can_ids() -> None:
    """0x1005 and a valid 0x1014 refuse every restricted CAN-ID of CiA 301 (Table 3) with 0x06090030
    (an invalid 0x1014 may hold one: it is never sent); a refused write changes nothing."""
    from bus.pdo_objects import RESTRICTED_CAN_IDS

    d = Drive(NODE)
    wr(d, Obj.COB_ID_EMCY, 0, "u32", PDO_NOT_VALID | (0x80 + NODE))
    for lo, hi in RESTRICTED_CAN_IDS:
        for can_id in sorted({lo, hi, (lo + hi) // 2}):
            assert abort(wr, d, Obj.COB_ID_SYNC, 0, "u32", can_id) == AbortCode.VALUE_RANGE, hex(can_id)
            wr(d, Obj.COB_ID_EMCY, 0, "u32", PDO_NOT_VALID | can_id)
            assert abort(wr, d, Obj.COB_ID_EMCY, 0, "u32", can_id) == AbortCode.VALUE_RANGE, hex(can_id)
    assert d.sync_cob_id() == 0x080
    assert rd(d, Obj.COB_ID_EMCY, 0, "u32") == PDO_NOT_VALID | 0x7FF
    # the issue's case: node 2 taking node 1's heartbeat identifier
    d2 = Drive(2)
    wr(d2, Obj.COB_ID_EMCY, 0, "u32", PDO_NOT_VALID | 0x82)
    assert abort(wr, d2, Obj.COB_ID_EMCY, 0, "u32", 0x701) == AbortCode.VALUE_RANGE
    assert rd(d2, Obj.COB_ID_EMCY, 0, "u32") == PDO_NOT_VALID | 0x82


def test_a_mapping_of_more_than_8_objects_is_a_value_too_high() -> None:
    """docs/canopen-objects.md §10: sub 0 above the EDS HighLimit 8 is 0x06090031."""
    d = Drive(NODE)
    for index in (0x1600, 0x1A00):
        assert abort(wr, d, index, 0, "u8", 9) == AbortCode.VALUE_TOO_HIGH


def test_vendor_id_is_the_documented_one() -> None:
    from bus.objects import PRODUCT_CODE, REVISION_NUMBER, VENDOR_ID

    d = Drive(NODE)
    assert [rd(d, Obj.IDENTITY, s, "u32") for s in (1, 2, 3, 4)] == [VENDOR_ID, PRODUCT_CODE, REVISION_NUMBER, NODE]
    assert VENDOR_ID != 0 and 0xAFFF_0000 <= VENDOR_ID <= 0xFFFE_FFFF  # never a CiA-assigned vendor


#: 0x2110:1 as bus/drive.eds ships it (2000 N·m/rad, the robot's tuning), Q16 µN·m per count
KP_DEFAULT = 78_539_816
#: 0x2110:2 as bus/drive.eds ships it (40 N·m·s/rad), Q16 µN·m per count/s
KD_DEFAULT = 1_570_796


def test_store_and_restore_parameters_in_a_file(tmp_path: Path) -> None:
    d = Drive(NODE, param_dir=tmp_path)
    wr(d, Obj.GAINS, GainsSub.KP, "i32", 4321)
    wr(d, Obj.PRODUCER_HEARTBEAT, 0, "u16", 250)
    wr(d, Obj.MODES_OF_OPERATION, 0, "i8", ModeOfOperation.CSP)
    wr(d, Obj.TARGET_POSITION, 0, "i32", 77)  # a set-point, not a parameter
    assert rd(d, Obj.STORE_PARAMETERS, 1, "u32") == 1 and rd(d, Obj.RESTORE_DEFAULTS, 1, "u32") == 1
    assert abort(wr, d, Obj.STORE_PARAMETERS, 1, "u32", 1) == AbortCode.CANNOT_STORE == 0x08000020
    wr(d, Obj.STORE_PARAMETERS, 1, "u32", STORE_SIGNATURE)
    assert (tmp_path / f"node{NODE}.json").exists()
    again = Drive(NODE, param_dir=tmp_path)  # a new process
    assert rd(again, Obj.GAINS, GainsSub.KP, "i32") == 4321 and rd(again, Obj.PRODUCER_HEARTBEAT, 0, "u16") == 250
    assert rd(again, Obj.MODES_OF_OPERATION_DISPLAY, 0, "i8") == ModeOfOperation.CSP
    assert rd(again, Obj.TARGET_POSITION, 0, "i32") == 0
    # restore the communication defaults: after reset communication 0x1017 is 0 again, Kp stays
    assert abort(wr, again, Obj.RESTORE_DEFAULTS, 2, "u32", STORE_SIGNATURE) == AbortCode.CANNOT_STORE
    wr(again, Obj.RESTORE_DEFAULTS, 2, "u32", RESTORE_SIGNATURE)
    assert rd(again, Obj.PRODUCER_HEARTBEAT, 0, "u16") == 250  # effective at the next reset
    again.nmt_command(NmtCommand.RESET_COMMUNICATION)
    assert rd(again, Obj.PRODUCER_HEARTBEAT, 0, "u16") == 0 and rd(again, Obj.GAINS, GainsSub.KP, "i32") == 4321
    wr(again, Obj.RESTORE_DEFAULTS, 1, "u32", RESTORE_SIGNATURE)
    assert rd(Drive(NODE, param_dir=tmp_path), Obj.GAINS, GainsSub.KP, "i32") == KP_DEFAULT  # the EDS default again


def test_store_parameters_in_memory_survive_a_reset_node_only() -> None:
    d = Drive(NODE)
    wr(d, Obj.GAINS, GainsSub.KD, "i32", 99)
    wr(d, Obj.STORE_PARAMETERS, 3, "u32", STORE_SIGNATURE)  # application parameters
    wr(d, Obj.GAINS, GainsSub.KD, "i32", 5)
    d.nmt_command(NmtCommand.RESET_NODE)
    assert rd(d, Obj.GAINS, GainsSub.KD, "i32") == 99
    assert rd(Drive(NODE), Obj.GAINS, GainsSub.KD, "i32") == KD_DEFAULT  # memory: not in another drive


def test_echo_plant_is_exact() -> None:
    d, plant = echo_drive(mode=PP, start=10)
    tau = d.io_tick(1, 7)
    assert tau == K_ECHO * 3  # the demand holds 10
