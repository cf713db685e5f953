"""The Plant process model: reset/encoder quantisation, torque clamp and ZOH, RK4 accuracy,
determinism, fault path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bus.units import RAD_PER_COUNT, TORQUE_LSB_NM
from plant import dynamics as d
from plant import kinematics as k
from plant.params import default_true_plant
from plant.simulator import Plant, PlantError

TRUE = default_true_plant()
CENTRE = np.array([0.0, 0.0, -0.65, 0.0])
HOLD = np.array([-3_000_000, -3_300_000, -3_000_000, -3_300_000], dtype=np.int64)  # µN·m


def _plant(**kw) -> Plant:
    return Plant(kw.pop("config", TRUE), kw.pop("ts_s", 1e-3), kw.pop("substeps", 4), RAD_PER_COUNT, TORQUE_LSB_NM)


def test_reset_sets_state_time_and_counts() -> None:
    p = _plant()
    q0 = k.inverse_kinematics(CENTRE)
    p.reset(q0, np.array([0.1, 0.0, -0.1, 0.0]))
    np.testing.assert_array_equal(p.q, q0)
    np.testing.assert_array_equal(p.qd, [0.1, 0.0, -0.1, 0.0])
    assert p.time_s == 0.0 and not p.faulted
    np.testing.assert_allclose(p.Y, k.subplatform_from_task(CENTRE), atol=1e-12)
    np.testing.assert_allclose(p.task_pose(), CENTRE, atol=1e-12)
    c = p.encoder_counts()
    assert c.dtype == np.int64 and c.shape == (4,)
    np.testing.assert_array_equal(c, np.rint(q0 / RAD_PER_COUNT).astype(np.int64))


def test_encoder_counts_are_nearest_integer_of_q_over_lsb() -> None:
    p = _plant()
    p.reset_to_pose(CENTRE)
    for n in range(50):
        p.step(HOLD + 200_000 * n)
        c = p.encoder_counts()
        np.testing.assert_array_equal(c, np.rint(p.q / RAD_PER_COUNT).astype(np.int64))
        assert np.all(np.abs(c * RAD_PER_COUNT - p.q) <= 0.5 * RAD_PER_COUNT * (1 + 1e-9))
    assert p.time_s == pytest.approx(0.050) and p.n_steps == 50


def test_torque_is_clamped_to_joint_limit() -> None:
    lim = TRUE.joint_torque_limit_nm
    big = np.array([400_000_000, -400_000_000, 10_000_000, -264_600_000], dtype=np.int64)
    a, b = _plant(), _plant()
    for p in (a, b):
        p.reset_to_pose(CENTRE)
    a.step(big)
    np.testing.assert_allclose(a.applied_torque_nm, [lim, -lim, 10.0, -lim], rtol=1e-12)
    np.testing.assert_array_equal(a.saturated, [True, True, False, False])
    # identical to commanding exactly the limit
    b.step(np.array([264_600_000, -264_600_000, 10_000_000, -264_600_000], dtype=np.int64))
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.qd, b.qd)


def test_disturbance_adds_to_the_clamped_torque() -> None:
    a, b = _plant(), _plant()
    for p in (a, b):
        p.reset_to_pose(CENTRE)
    big = np.full(4, 10**9, dtype=np.int64)
    a.step(big, np.array([1.0, -2.0, 0.5, 0.0]))
    lim_units = int(round(TRUE.joint_torque_limit_nm / TORQUE_LSB_NM))
    b.step(np.full(4, lim_units, dtype=np.int64), np.array([1.0, -2.0, 0.5, 0.0]))
    np.testing.assert_allclose(a.applied_torque_nm, TRUE.joint_torque_limit_nm, rtol=1e-15)
    np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-15)
    # and the disturbance really acts: without it the state differs
    c = _plant()
    c.reset_to_pose(CENTRE)
    c.step(big)
    assert np.abs(c.qd - a.qd).max() > 1e-4


def test_one_period_matches_fine_integration_of_true_dynamics() -> None:
    """ZOH torque over Ts, 4 RK4 sub-steps vs 200 RK4 sub-steps on the same dynamics."""
    tau_units = np.array([20_000_000, -15_000_000, 5_000_000, 8_000_000], dtype=np.int64)
    coarse = _plant(substeps=4)
    fine = _plant(substeps=200)
    q0 = k.inverse_kinematics(np.array([0.05, 0.02, -0.63, 0.4]))
    qd0 = np.array([3.0, -2.0, 1.0, 4.0])
    for p in (coarse, fine):
        p.reset(q0, qd0)
        for _ in range(20):
            p.step(tau_units)
    np.testing.assert_allclose(coarse.q, fine.q, atol=1e-9)
    np.testing.assert_allclose(coarse.qd, fine.qd, atol=1e-6)
    # and the acceleration at the start is what true_forward_dynamics says
    qdd0 = d.true_forward_dynamics(q0, qd0, tau_units * TORQUE_LSB_NM, TRUE)
    p = _plant(ts_s=1e-5, substeps=1)
    p.reset(q0, qd0)
    p.step(tau_units)
    np.testing.assert_allclose((p.qd - qd0) / 1e-5, qdd0, rtol=2e-3, atol=1e-2)


def test_step_is_deterministic_and_reset_reproducible() -> None:
    rng = np.random.default_rng(7)
    taus = (HOLD + rng.integers(-20_000_000, 20_000_000, size=(300, 4))).astype(np.int64)
    dist = rng.normal(0.0, 1.0, size=(300, 4))
    first, second = _plant(), _plant()
    runs = []
    for p in (first, second, first):  # the third run reuses the first plant after a reset
        p.reset_to_pose(CENTRE)
        trace = []
        for n in range(300):
            p.step(taus[n], dist[n])
            trace.append(np.concatenate([p.q, p.qd, p.encoder_counts()]))
        runs.append(np.array(trace))
    np.testing.assert_array_equal(runs[0], runs[1])
    np.testing.assert_array_equal(runs[0], runs[2])


def test_accepts_int32_and_lists() -> None:
    a, b = _plant(), _plant()
    for p in (a, b):
        p.reset_to_pose(CENTRE)
    a.step(HOLD.astype(np.int32), [0.1, 0.0, 0.0, 0.0])
    b.step(HOLD, np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(a.q, b.q)
    with pytest.raises(ValueError, match="shape"):
        a.step(np.zeros(3, dtype=np.int64))


def test_fault_path() -> None:
    p = _plant()
    with pytest.raises(PlantError, match="reset"):
        p.step(HOLD)
    p.reset_to_pose(CENTRE)
    with pytest.raises(PlantError, match="non-finite|did not converge"):
        p.step(HOLD, np.array([math.nan, 0.0, 0.0, 0.0]))
    assert p.faulted and p.fault_text
    with pytest.raises(PlantError, match="faulted"):
        p.step(HOLD)
    p.reset_to_pose(CENTRE)
    assert not p.faulted
    p.step(HOLD)
    with pytest.raises(ValueError, match="finite"):
        p.reset(np.array([math.inf, 0, 0, 0]))


def test_fault_when_driven_through_the_workspace_limit() -> None:
    """Unlimited torque drives the arms into a singularity / out of assembly: PlantError, no hang."""
    from plant.params import nominal_plant_config

    p = Plant(nominal_plant_config(torque_limit_enabled=False), 1e-3, 4, RAD_PER_COUNT, TORQUE_LSB_NM)
    p.reset_to_pose(CENTRE)
    push = np.array([2_000_000_000, -2_000_000_000, 2_000_000_000, -2_000_000_000], dtype=np.int64)
    with pytest.raises(PlantError):
        for _ in range(2000):
            p.step(push)
    assert p.faulted


def test_nominal_plant_has_no_friction() -> None:
    p = Plant.nominal(1e-3, 4, RAD_PER_COUNT, TORQUE_LSB_NM)
    assert not p.config.has_friction and p.config.mass.I_ee == 0.0 and p.config.mass.rho == 0.5
    q0 = k.inverse_kinematics(CENTRE)
    G = d.gravity_vector(q0, p.config.mass)
    p.reset(q0)
    units = np.rint(G / TORQUE_LSB_NM).astype(np.int64)
    for _ in range(100):
        p.step(units)
    np.testing.assert_allclose(p.q, q0, atol=1e-6)  # holds (µN·m rounding only)
