"""The robot's real-time schedule (:class:`plant.plant_node_robot_pacing.RobotPacing`) on a
scripted clock: how it locks onto the master's phase, what counts as late, missing or a late
period."""

from __future__ import annotations

import pytest

from plant.plant_node_robot_pacing import RobotPacing

TS = 1e-3


def _period(p: RobotPacing, arrival_s: float, duration_s: float = 0.3e-3) -> tuple[float, bool]:
    """One period: its SYNC arrives, it starts when due (or at once), and runs ``duration_s``."""
    due, late = p.schedule(arrival_s)
    start = max(due, arrival_s)
    p.started(start)
    p.completed(start + duration_s)
    return due, late


def test_on_time_syncs_with_jitter_lock_onto_the_least_delay() -> None:
    p = RobotPacing(TS)
    delays = [100e-6, 40e-6, 180e-6, 60e-6, 200e-6, 45e-6] * 20
    for k, d in enumerate(delays):
        due, late = _period(p, 10.0 + k * TS + d)
        assert not late and due <= 10.0 + k * TS + d
    # the schedule sits at the master's time plus the least delay seen (40 us)
    assert p.t0_s == pytest.approx(10.0 + 40e-6)
    assert (p.late, p.missing, p.late_periods, p.deadline_misses, p.relocks) == (0, 0, 0, 0, 0)
    assert p.periods == len(delays)


def test_a_sync_more_than_half_a_period_late_is_a_late_sync_and_a_late_period() -> None:
    p = RobotPacing(TS)
    for k in range(10):
        _period(p, k * TS)
    due, late = _period(p, 10 * TS + 0.6 * TS)
    assert late and due == pytest.approx(10 * TS)
    assert (p.late, p.late_periods, p.missing) == (1, 1, 0)
    # the next ones are on time again: the phase did not move
    for k in range(11, 20):
        assert _period(p, k * TS) == (pytest.approx(k * TS), False)
    assert (p.late, p.late_periods, p.relocks) == (1, 1, 0)


def test_a_cycle_without_sync_is_missing_and_the_schedule_keeps_its_phase() -> None:
    p = RobotPacing(TS)
    for k in range(10):
        _period(p, k * TS + 50e-6)
    # the master skips cycle 10: the SYNC of cycle 11 comes on time
    due, late = _period(p, 11 * TS + 70e-6)
    assert not late and due == pytest.approx(11 * TS + 50e-6)
    for k in range(12, 20):
        assert _period(p, k * TS + 50e-6) == (pytest.approx(k * TS + 50e-6), False)
    assert (p.missing, p.late, p.late_periods, p.relocks) == (1, 0, 0, 0)
    # three whole periods without a SYNC
    _period(p, 23 * TS + 50e-6)
    assert p.missing == 4 and p.late_periods == 0


def test_a_master_whose_phase_moved_later_is_followed_after_eight_syncs() -> None:
    p = RobotPacing(TS)
    for k in range(10):
        _period(p, k * TS)
    lates = []
    for k in range(10, 30):  # the master comes back 0.7 periods later (it paused, its clock stepped)
        _, late = _period(p, k * TS + 0.7 * TS)
        lates.append(late)
    assert lates == [True] * (RobotPacing.RELOCK - 1) + [False] * (20 - RobotPacing.RELOCK + 1)
    assert p.relocks == 1 and p.late == RobotPacing.RELOCK - 1
    assert p.t0_s == pytest.approx(0.7 * TS)


def test_a_schedule_behind_the_master_is_held_and_then_moved_earlier() -> None:
    p = RobotPacing(TS)
    _period(p, 0.0 + 0.9 * TS)  # the first SYNC came late (delayed 0.9 Ts): the schedule starts there
    dues = []
    for k in range(1, 12):
        due, late = p.schedule(k * TS)
        assert not late
        dues.append(due - k * TS)
        p.started(max(due, k * TS))
        p.completed(max(due, k * TS) + 0.2e-3)
    # held 0.9 Ts behind each SYNC until eight in a row came that early, then at once
    held = RobotPacing.RELOCK - 1
    assert dues[:held] == [pytest.approx(0.9 * TS)] * held
    assert dues[held:] == [pytest.approx(0.0)] * (len(dues) - held)
    assert p.relocks == 1 and p.late_periods == 0


def test_a_period_that_ends_after_the_next_ones_time_is_a_deadline_miss_counted_once() -> None:
    p = RobotPacing(TS)
    for k in range(5):
        _period(p, k * TS)
    _period(p, 5 * TS, duration_s=1.2 * TS)  # ends after period 6's time
    assert (p.deadline_misses, p.late_periods) == (1, 1)
    # late start and deadline miss in one period: one late period
    _period(p, 7 * TS + 0.6 * TS, duration_s=0.9 * TS)
    assert (p.late, p.deadline_misses, p.late_periods) == (1, 2, 2)
    info = p.info()
    assert (info["late_syncs"], info["deadline_misses"], info["late_periods"], info["missing_syncs"]) == (1, 2, 2, 1)
    assert info["lateness_max_us"] == pytest.approx(600.0)
