"""The fixed-point control kernel against its float twin, at extremes, and its resolution."""

from __future__ import annotations

import numpy as np
import pytest
from firmware_twin import TwinParams, run_twin
from hypothesis import given, settings
from hypothesis import strategies as st

from bus import fixedpoint as fp
from bus.units import RAD_PER_COUNT, TORQUE_LSB_NM
from firmware_model import control_law


def _setup(kp_q: int, kd_q: int, a_q: int, limit: int, ref_pos, ref_vel, ff, period_us: int = 1000):
    n = len(ref_pos)
    s = control_law.new_state()
    s[control_law.P_KP] = kp_q
    s[control_law.P_KD] = kd_q
    s[control_law.P_ALPHA] = a_q
    s[control_law.P_RATE] = fp.rate_q12_from_period_us(period_us)
    s[control_law.P_TLIM] = limit
    tables = control_law.new_tables(n)
    tables[0, :n] = ref_pos
    tables[1, :n] = ref_vel
    tables[2, :n] = ff
    # trial start: no previous count, estimator at the reference velocity of sample 0
    s[control_law.S_HAVE_PREV] = 0
    s[control_law.S_VF] = int(ref_vel[0]) << fp.VEL_STATE_Q
    return s, tables, control_law.new_recorder(n)


@st.composite
def trials(draw):
    n = draw(st.integers(1, 40))
    extra = draw(st.integers(0, 5))
    start = draw(st.integers(-500_000, 500_000))
    steps = draw(st.lists(st.integers(-1000, 1000), min_size=n + extra, max_size=n + extra))
    counts = np.clip(start + np.cumsum(steps), -500_000, 500_000)
    ints = lambda lo, hi: st.lists(st.integers(lo, hi), min_size=n, max_size=n)  # noqa: E731
    ref_pos = np.array(draw(ints(-500_000, 500_000)))
    ref_vel = np.array(draw(ints(-10_000_000, 10_000_000)))
    ff = np.array(draw(ints(-200_000_000, 200_000_000)))
    kp = draw(st.floats(0.0, 2000.0))
    kd = draw(st.floats(0.0, 60.0))
    alpha = draw(st.floats(0.01, 1.0))
    limit = draw(st.sampled_from([264_600_000, 50_000_000, 1_000_000, 0]))
    return counts, ref_pos, ref_vel, ff, kp, kd, alpha, limit


@settings(max_examples=150, deadline=None)
@given(trials())
def test_fixed_point_matches_float_twin_within_lsb_bound(trial) -> None:
    counts, ref_pos, ref_vel, ff, kp, kd, alpha, limit = trial
    kp_q, kd_q, a_q = fp.kp_to_fixed(kp), fp.kd_to_fixed(kd), fp.vel_filter_to_fixed(alpha)
    s, tables, rec = _setup(kp_q, kd_q, a_q, limit, ref_pos, ref_vel, ff)
    tau_fix = control_law.run_table(counts, s, tables, len(ref_pos), rec)
    params = TwinParams.from_fixed(kp_q, kd_q, a_q, 1000, limit)
    tau_flt, fb_flt, v_flt = run_twin(counts, ref_pos, ref_vel, ff, params)

    bound = params.torque_bound_units()
    # Kd <= 60 N·m·s/rad = 36 µN·m per count/s: bound <= 36·(0.5 + 1/(8192 α)) + 0.5 µN·m
    assert bound < 18.5 + 36 / (8192 * params.alpha) + 1e-6
    assert np.all(np.abs(tau_fix - tau_flt) <= bound + 1e-9 * np.abs(tau_flt) + 1e-6)
    n = min(len(ref_pos), len(counts))
    assert np.all(np.abs(rec[3, :n] - fb_flt[:n]) <= bound + 1e-9 * np.abs(fb_flt[:n]) + 1e-6)
    assert np.all(np.abs(rec[1, :n] - v_flt[:n]) <= params.velocity_bound() + 1e-9 * np.abs(v_flt[:n]))
    assert np.array_equal(rec[0, :n], counts[:n])
    assert np.array_equal(rec[2, :n], tau_fix[:n])
    assert np.all(np.abs(tau_fix) <= limit)


def test_bound_is_a_few_lsb_for_typical_gains() -> None:
    p = TwinParams.from_fixed(fp.kp_to_fixed(1000), fp.kd_to_fixed(50), fp.VEL_FILTER_ONE, 1000, 264_600_000)
    # 50 N·m·s/rad = 30 µN·m per count/s; half a count/s of velocity rounding dominates
    kd_unm = 50 * RAD_PER_COUNT / TORQUE_LSB_NM
    assert p.torque_bound_units() == pytest.approx(kd_unm * (0.5 + 1 / 8192) + 0.5, rel=1e-6)
    assert p.torque_bound_units() * 1e-6 < 2e-5  # N·m


def test_exact_values_one_tick() -> None:
    kp_q, kd_q = fp.kp_to_fixed(1000), fp.kd_to_fixed(50)
    s, tables, rec = _setup(kp_q, kd_q, fp.VEL_FILTER_ONE, 264_600_000, [100], [0], [7])
    tau, status = control_law.control_tick(0, 0, 0, s, tables, rec)
    assert status == control_law.STATUS_OK
    assert tau == fp.rshift_round(kp_q * 100, 16) + 7
    # next tick moved by +2 counts: v = 2000 counts/s
    tau2, _ = control_law.control_tick(2, 0, -1, s, tables, rec)
    assert s[control_law.S_VEST] == 2000
    assert tau2 == fp.rshift_round(kp_q * 98 + kd_q * (-2000), 16) + 7


@pytest.mark.parametrize("count", [fp.INT32_MIN, fp.INT32_MAX, 1 << 40, -(1 << 40)])
@pytest.mark.parametrize("ref", [fp.INT32_MIN, fp.INT32_MAX])
def test_saturates_at_extremes(count: int, ref: int) -> None:
    big = fp.INT32_MAX
    s, tables, rec = _setup(big, big, fp.VEL_FILTER_ONE, 1 << 40, [ref, ref], [ref, -ref - 1], [big, -big - 1])
    prev = -count if abs(count) <= fp.INT32_MAX else 0
    s[control_law.S_PREV_COUNT] = prev
    s[control_law.S_HAVE_PREV] = 1
    for idx in (0, 1):
        tau, _ = control_law.control_tick(count, idx, idx, s, tables, rec)
        c = fp.sat32(count)
        e = fp.sat32(ref - c)
        # with maximal gains the output is at the int32 rail in the error's direction
        assert fp.INT32_MIN <= tau <= fp.INT32_MAX
        assert s[control_law.S_ERR] == e
        assert fp.INT32_MIN <= s[control_law.S_VEST] <= fp.INT32_MAX
        assert rec[0, idx] == c
        fb = int(s[control_law.S_TAU_FB])
        assert fp.INT32_MIN <= fb <= fp.INT32_MAX
        if e > 0 and tables[1, idx] - s[control_law.S_VEST] >= 0:
            assert fb == fp.INT32_MAX
        if e < 0 and tables[1, idx] - s[control_law.S_VEST] <= 0:
            assert fb == fp.INT32_MIN


def test_extreme_velocity_step_saturates_not_wraps() -> None:
    s, tables, rec = _setup(0, fp.INT32_MAX, fp.VEL_FILTER_ONE, 1 << 40, [0], [0], [0])
    control_law.control_tick(fp.INT32_MIN, 0, -1, s, tables, rec)
    tau, _ = control_law.control_tick(fp.INT32_MAX, 0, -1, s, tables, rec)  # +2^32 counts in one tick
    assert s[control_law.S_VEST] == fp.INT32_MAX
    assert tau == fp.INT32_MIN  # ė = -v, huge Kd: negative rail, not a wrapped positive value
    tau, _ = control_law.control_tick(fp.INT32_MIN, 0, -1, s, tables, rec)
    assert s[control_law.S_VEST] == fp.INT32_MIN and tau == fp.INT32_MAX


def test_torque_clamped_to_limit() -> None:
    s, tables, rec = _setup(fp.kp_to_fixed(1000), 0, fp.VEL_FILTER_ONE, 1_000_000, [0], [0], [0])
    tau, _ = control_law.control_tick(-1_000_000, 0, 0, s, tables, rec)  # wants ≈ +599 N·m
    assert tau == 1_000_000 and s[control_law.S_LIMITED] == 1
    assert rec[3, 0] > 1_000_000  # the feedback part is recorded before the clamp
    tau, _ = control_law.control_tick(1_000_000, 0, 0, s, tables, rec)
    assert tau == -1_000_000


def test_following_error_status() -> None:
    s, tables, rec = _setup(fp.kp_to_fixed(100), 0, fp.VEL_FILTER_ONE, 1_000_000, [0], [0], [0])
    s[control_law.P_FE_WINDOW] = 1000
    assert control_law.control_tick(1000, 0, -1, s, tables, rec)[1] == control_law.STATUS_OK
    assert control_law.control_tick(-1001, 0, -1, s, tables, rec)[1] == control_law.STATUS_FOLLOWING_ERROR
    s[control_law.P_FE_WINDOW] = -1
    assert control_law.control_tick(fp.INT32_MAX, 0, -1, s, tables, rec)[1] == control_law.STATUS_OK


def test_after_table_end_holds_last_reference() -> None:
    kp_q = fp.kp_to_fixed(500)
    s, tables, rec = _setup(kp_q, 0, fp.VEL_FILTER_ONE, 1 << 30, [0, 50, 100], [0, 0, 0], [1, 2, 3])
    counts = np.array([0, 0, 0, 0, 0, 0])
    tau = control_law.run_table(counts, s, tables, 3, rec)
    last = fp.rshift_round(kp_q * 100, 16) + 3
    assert list(tau[2:]) == [last] * 4


def test_velocity_filter_first_order() -> None:
    a = fp.vel_filter_to_fixed(0.25)
    s, tables, rec = _setup(0, 0, a, 1 << 30, [0], [0], [0])
    control_law.control_tick(0, 0, -1, s, tables, rec)
    v = []
    for k in range(1, 6):
        control_law.control_tick(10 * k, 0, -1, s, tables, rec)  # constant 10 counts/tick = 10 000 counts/s
        v.append(int(s[control_law.S_VEST]))
    expected = [round(10_000 * (1 - 0.75**k)) for k in range(1, 6)]
    assert all(abs(x - y) <= 1 for x, y in zip(v, expected))


def test_resolution_lsbs_move_position_far_less_than_one_count() -> None:
    """Steady state with feedback Kp: Kp·e = −Δτ.  One LSB of ff (1 µN·m) and one LSB of
    the torque command shift the equilibrium by 1 µN·m / Kp; for the smallest typical
    Kp (100 N·m/rad) that is 0.017 encoder counts."""
    kp_q = fp.kp_to_fixed(100.0)
    unm_per_count = kp_q / 65536  # µN·m of feedback per count of error
    shift_counts = 1.0 / unm_per_count
    assert shift_counts < 0.02
    # the same through the kernel: with ff = k LSB the torque crosses zero at e = k / Kp
    s, tables, rec = _setup(kp_q, 0, fp.VEL_FILTER_ONE, 1 << 30, [0], [0], [60])
    tau0, _ = control_law.control_tick(0, 0, -1, s, tables, rec)
    tau1, _ = control_law.control_tick(1, 0, -1, s, tables, rec)  # one count of error
    assert tau0 - tau1 == pytest.approx(unm_per_count, abs=1)  # ≈ 60 µN·m per count
    # gains' quantisation: relative error tiny
    assert abs(fp.kp_from_fixed(kp_q) - 100.0) / 100.0 < 3e-7
    assert abs(fp.kd_from_fixed(fp.kd_to_fixed(10.0)) - 10.0) / 10.0 < 3e-6
