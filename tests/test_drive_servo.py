"""The drive as a servo drive: the cascade of robot mode holds the robot.

In one process: four drives of a SYNC-stepped plant (robot mode, :meth:`Drive.step_on_sync`) on
the robot's plant (:class:`plant.mechanics.Mechanics` at its home pose), CSP by SDO, one SYNC
and one io tick per period.  A 5° move of all four joints (smooth-step over 500 ms) then 200 ms of
hold: every joint ends within 30 counts (0.001°) of its target.  The paper's PD loop
(0x2110:4 = 0, the ILC experiments' default) sags under gravity by thousands of counts; the same
check documents that too.  Also: the cascade's anti-windup, its objects and their boot values.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from drive402_util import echo_drive, rd, wr
from robot_util import plant_factory

from bus import fixedpoint as fp
from bus import units
from bus.cia301.nmt import NmtCommand
from bus.objects import GainsSub, LoopStructure, Obj, PositionControlSub, VelocityControlSub
from firmware_model import control_law
from firmware_model.drive import Drive
from plant.mechanics import Mechanics

#: the hold requirement [counts]: 0.001°
HOLD_COUNTS = 30
MOVE_MS = 500
HOLD_MS = 200


def _robot_move(robot_mode: bool, signs: tuple[int, ...]) -> np.ndarray:
    """The final position error [counts] of the four joints after the move and the hold."""
    mech = Mechanics(plant_factory(1e-3, 4))
    mech.home()
    plant = mech.plant
    drives = [Drive(n) for n in range(1, 5)]
    for d in drives:
        if robot_mode:
            d.step_on_sync(time.monotonic)
        d.nmt_command(NmtCommand.START)
        wr(d, Obj.MODES_OF_OPERATION, 0, "i8", 8)
    held = np.zeros(4, dtype=bool)
    counts = plant.encoder_counts().astype(np.int64)

    def period(targets: np.ndarray) -> None:
        nonlocal counts
        tau = np.zeros(4, dtype=np.int64)
        for j, d in enumerate(drives):
            wr(d, Obj.TARGET_POSITION, 0, "i32", int(targets[j]))
            d.on_sync()
            tau[j] = d.io_tick(0, int(counts[j]))
            d.service()
        assert mech.step(tau, held) is None  # inside the workspace: no limit reached
        counts = plant.encoder_counts().astype(np.int64)

    start = counts.copy()
    period(start)
    for cw in (0x06, 0x07, 0x0F):
        for d in drives:
            wr(d, Obj.CONTROLWORD, 0, "u16", cw)
        period(start)
    assert all(d.torque_enabled for d in drives)
    dq = round(math.radians(5.0) / units.RAD_PER_COUNT)
    goal = start + np.array(signs, dtype=np.int64) * dq
    for k in range(1, MOVE_MS + 1):
        s = k / MOVE_MS
        s = s * s * (3 - 2 * s)
        period(np.round(start + (goal - start) * s).astype(np.int64))
    for _ in range(HOLD_MS):
        period(goal)
    assert all(d.torque_enabled for d in drives)
    return goal - counts


@pytest.mark.parametrize("signs", [(1, 1, 1, 1), (-1, -1, -1, -1), (1, 1, -1, -1)])
def test_robot_mode_holds_a_5_degree_csp_move_within_30_counts(signs: tuple[int, ...]) -> None:
    err = _robot_move(True, signs)
    assert np.all(np.abs(err) <= HOLD_COUNTS), err


def test_the_pd_loop_sags_under_gravity() -> None:
    """The ILC experiments' loop (0x2110:4 = 0): the holding torque is Kp·e, thousands of counts."""
    err = _robot_move(False, (1, 1, 1, 1))
    assert np.all(np.abs(err) > 1000), err


def test_robot_mode_boots_with_the_cascade_and_keeps_it_over_reset_node() -> None:
    d = Drive(1)
    assert rd(d, Obj.GAINS, GainsSub.LOOP, "u8") == LoopStructure.PD  # the EDS default
    d.step_on_sync(time.monotonic)
    assert rd(d, Obj.GAINS, GainsSub.LOOP, "u8") == LoopStructure.CASCADE
    wr(d, Obj.GAINS, GainsSub.LOOP, "u8", LoopStructure.PD)  # a master may choose the PD loop
    d.nmt_command(NmtCommand.RESET_NODE)
    assert rd(d, Obj.GAINS, GainsSub.LOOP, "u8") == LoopStructure.CASCADE
    assert int(d._st[control_law.P_LOOP]) == LoopStructure.CASCADE


def test_cascade_gains_reach_the_loop_in_their_formats() -> None:
    d = Drive(1)
    wr(d, Obj.POSITION_CONTROL, PositionControlSub.KPP, "i32", 100 << 16)
    wr(d, Obj.POSITION_CONTROL, PositionControlSub.VELOCITY_FF, "i32", 1 << 15)
    wr(d, Obj.POSITION_CONTROL, PositionControlSub.TORQUE_FF, "i32", 0)
    wr(d, Obj.VELOCITY_CONTROL, VelocityControlSub.KVP, "i32", 123456)
    wr(d, Obj.VELOCITY_CONTROL, VelocityControlSub.KVI, "i32", 1_000_001)
    st = d._st
    assert int(st[control_law.P_KPP]) == 100 << 16
    assert int(st[control_law.P_KVFF]) == 1 << 15 and int(st[control_law.P_KTFF]) == 0
    assert int(st[control_law.P_KVP]) == 123456
    assert int(st[control_law.P_KVI]) == fp.ki_per_tick_q16(1_000_001, 1000) == 1000  # Kvi · 1 ms, nearest
    wr(d, Obj.CONTROL_PERIOD, 0, "u32", 2000)  # the per-period I gain follows the period
    assert int(st[control_law.P_KVI]) == 2000


def _cascade_state(kvp: int, kvi_tick: int, kpp: int, limit: int) -> np.ndarray:
    st = control_law.new_state()
    st[control_law.P_LOOP] = control_law.LOOP_CASCADE
    st[control_law.P_KVP] = kvp
    st[control_law.P_KVI] = kvi_tick
    st[control_law.P_KPP] = kpp
    st[control_law.P_TLIM] = limit
    return st


def test_cascade_arithmetic_and_anti_windup_by_clamping() -> None:
    """One tick by hand; then a blocked joint: the integrator stops at the torque limit (clamping),
    and the torque leaves the limit on the first tick the velocity error reverses."""
    tables = control_law.new_tables(1)
    rec = control_law.new_recorder(1)
    st = _cascade_state(kvp=3 << 16, kvi_tick=1 << 16, kpp=10 << 16, limit=10**9)
    tables[control_law.ROW_REF_POS, 0] = 100
    tables[control_law.ROW_FF, 0] = 7
    tau, status = control_law.control_tick(0, 0, -1, st, tables, rec)
    # v_cmd = 10·100 = 1000 counts/s, v_est = 0 (first tick): I = 1000, τ = 3·1000 + 1000 + 7
    assert (tau, status) == (4007, control_law.STATUS_OK)
    assert int(st[control_law.S_VINT]) == 1000 << 16 and int(st[control_law.S_VCMD]) == 1000

    limit = 50_000
    st = _cascade_state(kvp=1 << 16, kvi_tick=1 << 16, kpp=10 << 16, limit=limit)
    for _ in range(200):  # the joint does not move: error 100 counts for ever
        tau, _ = control_law.control_tick(0, 0, -1, st, tables, rec)
    # the integrator stops one I step short of the limit (it would push the torque beyond it)
    assert limit - 1007 <= tau <= limit
    assert int(st[control_law.S_VINT]) <= limit << 16  # bounded, not wound up
    tables[control_law.ROW_REF_POS, 0] = 0  # the demand comes back: the torque falls at once
    tau, _ = control_law.control_tick(0, 0, -1, st, tables, rec)
    assert tau < limit


# ------------------------------------------------------------------ CiA 402 windows


def _setpoint(d: Drive, target: int) -> None:
    wr(d, Obj.TARGET_POSITION, 0, "i32", target)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x0F)
    wr(d, Obj.CONTROLWORD, 0, "u16", 0x1F)


def test_pp_target_reached_only_inside_the_position_window_for_its_time() -> None:
    """Bit 10 from the ACTUAL position: the actual pushed out of 0x6067 clears it at once; back in,
    it returns after 0x6068; with 0x6067 = 0xFFFFFFFF it follows the demand."""
    d, plant = echo_drive(mode=1, start=0)
    wr(d, Obj.POSITION_WINDOW, 0, "u32", 20)
    wr(d, Obj.POSITION_WINDOW_TIME, 0, "u16", 5)
    _setpoint(d, 300)
    plant.run(d, 100)
    assert plant.count == 300 and d.statusword & 0x0400
    plant.count += 21  # pushed outside the window (the echo plant then holds it there for a tick)
    plant.step(d)
    assert not d.statusword & 0x0400
    plant.count = 300 + 20  # back inside (at its edge)
    reached = []
    for _ in range(6):
        d.io_tick(plant.tick, plant.count)  # held at the edge of the window
        plant.tick += 1
        reached.append(bool(d.statusword & 0x0400))
    assert reached == [False, False, False, False, True, True]  # 5 ms = 5 cycles in the window
    wr(d, Obj.POSITION_WINDOW, 0, "u32", 0xFFFFFFFF)  # the window off: the demand decides
    d.io_tick(plant.tick, 300 + 1000)
    assert d.statusword & 0x0400


def test_following_error_time_out_then_fault() -> None:
    """|e| above 0x6065: statusword bit 13 while it lasts up to 0x6066, a fault (0x8611) after."""
    d, plant = echo_drive(mode=8, start=0)
    wr(d, Obj.FOLLOWING_ERROR_WINDOW, 0, "u32", 50)
    wr(d, Obj.FOLLOWING_ERROR_TIME_OUT, 0, "u16", 3)  # ms = 3 control cycles
    wr(d, Obj.TARGET_POSITION, 0, "i32", 100)
    for _ in range(3):  # the joint does not follow: 100 counts off, for 3 cycles tolerated
        d.io_tick(plant.tick, 0)
        plant.tick += 1
        assert d.torque_enabled and d.statusword & 0x2000
    d.io_tick(plant.tick, 0)
    assert not d.torque_enabled
    assert [e[0] for e in d.pop_emcy()][-1] == 0x8611
    # 0x6066 = 0: a fault on the first cycle outside the window (as before the time-out existed)
    d, plant = echo_drive(mode=8, start=0)
    wr(d, Obj.FOLLOWING_ERROR_WINDOW, 0, "u32", 50)
    wr(d, Obj.TARGET_POSITION, 0, "i32", 100)
    d.io_tick(plant.tick, 0)
    assert not d.torque_enabled


def test_cascade_matches_its_float_twin_within_the_bound_of_its_formats() -> None:
    """The fixed-point cascade against :class:`firmware_twin.CascadeTwin` (the reference of a C
    port) on a random unsaturated run: per tick the velocity error differs by at most 1 count/s
    (two roundings of v_cmd), so the torque by Kvp·1 + 1 µN·m and the integrator by Kvi·1 per tick
    plus the quantisation of Kvi·Ts (half a Q16 LSB) times the errors integrated."""
    from firmware_twin import CascadeParams, CascadeTwin

    kpp, kvff, ktff, kvp, kvi_tick = 80 << 16, 60000, 70000, 2356194, fp.ki_per_tick_q16(235619400, 1000)
    limit = 10**12  # never reached here: the unsaturated law
    st = _cascade_state(kvp=kvp, kvi_tick=kvi_tick, kpp=kpp, limit=limit)
    st[control_law.P_KVFF], st[control_law.P_KTFF] = kvff, ktff
    q = 1 << 16
    twin = CascadeTwin(CascadeParams(kpp / q, kvff / q, ktff / q, kvp / q, kvi_tick / q, 1000.0, float(limit)))
    rng = np.random.default_rng(35)
    tables, rec = control_law.new_tables(1), control_law.new_recorder(1)
    count, sum_ev, n = 0, 0.0, 300
    for k in range(n):
        ref_pos = int(2000 * math.sin(k / 30))
        ref_vel = int(2000 * math.cos(k / 30) * 1000 / 30)
        ff = int(rng.integers(-50_000, 50_000))
        tables[:, 0] = ref_pos, ref_vel, ff
        tau, _ = control_law.control_tick(count, 0, -1, st, tables, rec)
        tau_twin = twin.step(count, ref_pos, ref_vel, ff)
        sum_ev += abs(int(st[control_law.S_VCMD]) - int(st[control_law.S_VEST]))
        bound = kvp / q * 1.0 + 1.0 + (k + 1) * kvi_tick / q * 1.0 + 0.5 / q * sum_ev + 1.0
        assert abs(tau - tau_twin) <= bound, (k, tau, tau_twin, bound)
        count += int(rng.integers(-40, 41)) + (ref_pos - count) // 4  # a plant that roughly follows


def test_a_csp_drive_enabled_again_starts_without_a_velocity_reference() -> None:
    """Disable, the target written where the joint stands now (far from the last target of the
    earlier enable), enable again: the first period's torque is the one a drive enabled for the
    first time gives there (velocity reference 0), not a kick from the difference of the two
    targets (the random foreign master's runaway into the screw stop, tests/test_robot_master_fsm.py)."""

    def first_torque_after_enable(d: Drive, target: int, count: int) -> int:
        """Enabled one SYNC per controlword at ``target``: the torque of the first enabled period."""
        wr(d, Obj.TARGET_POSITION, 0, "i32", target)
        torques = []
        for cw in (0x06, 0x07, 0x0F):
            wr(d, Obj.CONTROLWORD, 0, "u16", cw)
            d.on_sync()
            torques.append(d.io_tick(0, count))
        assert d.torque_enabled and torques[:2] == [0, 0]
        return torques[2]

    def csp_drive() -> Drive:
        d = Drive(2)
        d.step_on_sync(time.monotonic)  # robot mode: the cascade, with velocity feed-forward
        d.nmt_command(NmtCommand.START)
        wr(d, Obj.MODES_OF_OPERATION, 0, "i8", 8)
        return d

    fresh = first_torque_after_enable(csp_drive(), 50_000, 50_000)
    again = csp_drive()
    first_torque_after_enable(again, 0, 0)  # enabled at 0, holding there
    wr(again, Obj.CONTROLWORD, 0, "u16", 0x06)  # torque off
    again.on_sync()
    again.io_tick(0, 50_000)  # the joint stands 50,000 counts further now
    assert not again.torque_enabled
    assert first_torque_after_enable(again, 50_000, 50_000) == fresh
