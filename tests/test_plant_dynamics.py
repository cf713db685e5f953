"""Dynamics of the plant (docs/robot-model.md §4): structure of M/C/G, consistency with the Lagrangian,
holding torques, energy conservation, friction dissipation, true-plant terms."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from plant import dynamics as d
from plant import kinematics as k
from plant.params import (
    COULOMB_SPREAD,
    VISCOUS_SPREAD,
    Geometry,
    TruePlantConfig,
    default_true_plant,
    nominal_mass_model,
    robot_md_mass_model,
)
from plant.simulator import Plant

NOM = nominal_mass_model()
TRUE = default_true_plant()
CENTRE = np.array([0.0, 0.0, -0.65, 0.0])
POSE = np.array([0.05, -0.03, -0.64, 0.3])
QD = np.array([2.0, -1.5, 1.0, 3.0])


def _state() -> tuple[np.ndarray, np.ndarray]:
    return k.inverse_kinematics(POSE), QD.copy()


def test_params_lead_drivetrain_and_true_plant_differences() -> None:
    assert NOM.n == 10 and NOM.J_m == pytest.approx(7.16e-4)
    assert NOM.joint_inertia(0.296) == pytest.approx(0.0246 + 0.0032 + 0.0716, abs=1e-4)
    assert TRUE.joint_torque_limit_nm == pytest.approx(264.6)
    assert TRUE.joint_speed_limit_rad_s == pytest.approx(52.36, abs=0.01)
    m = TRUE.mass
    assert m.rho == pytest.approx(2 / 3) and m.l_c == 0.135 and m.payload == 0.2 and m.I_ee == 2e-4
    assert m.I_a == pytest.approx(1.1 * NOM.I_a) and m.m_up == pytest.approx(1.05 * 0.855)
    assert m.spin_equivalent_mass(0.04) == pytest.approx(4.93, abs=0.01)
    assert all(0.8 <= f <= 1.2 for f in COULOMB_SPREAD + VISCOUS_SPREAD)
    assert TRUE.coulomb_nm[0] == pytest.approx(1.5 * COULOMB_SPREAD[0])
    with pytest.raises(ValueError, match="rho"):
        replace(NOM, rho=1.5)


def test_holding_torques_at_path_centre_match_robot_md() -> None:
    q = k.inverse_kinematics(CENTRE)
    G = d.gravity_vector(q, robot_md_mass_model())
    np.testing.assert_allclose(G, [-2.9, -3.2, -2.9, -3.2], atol=0.05)
    # gravity does not depend on J_m
    np.testing.assert_array_equal(G, d.gravity_vector(q, NOM))
    # holding torque = G gives zero acceleration at rest
    np.testing.assert_allclose(d.forward_dynamics(q, np.zeros(4), G, NOM), 0.0, atol=1e-12)


def test_mass_matrix_equals_paper_eq2() -> None:
    q, _ = _state()
    M = d.mass_matrix(q, NOM)
    Y = k.forward_kinematics(q)
    Jup, Jlow = k.jacobian_up_low(q, Y)
    Ib = NOM.joint_inertia(0.296)
    ref = Jlow.T @ (NOM.m_low_eff * Jlow) + Jup.T @ (NOM.m_up_eff * Jup) + Ib * np.eye(4)
    np.testing.assert_allclose(M, ref, rtol=1e-12)
    np.testing.assert_allclose(M, M.T, rtol=0, atol=0)
    assert np.all(np.linalg.eigvalsh(M) > 0)


def test_tool_spin_adds_screw_coupling_to_mass_matrix() -> None:
    q, _ = _state()
    Y = k.forward_kinematics(q)
    J = k.jacobian(q, Y)
    m = replace(NOM, I_ee=2e-4)
    dz = J[2] - J[3]
    kk = (2 * math.pi / 0.04) ** 2 * 2e-4
    np.testing.assert_allclose(d.mass_matrix(q, m) - d.mass_matrix(q, NOM), kk * np.outer(dz, dz), atol=1e-12)


def test_coriolis_matches_lagrangian_finite_differences() -> None:
    """C q̇ = Ṁ q̇ − ½ ∂(q̇ᵀMq̇)/∂q, computed by central differences of M (model with I_ee)."""
    m = TRUE.mass
    q, qd = _state()
    h = 1e-6
    dM = []
    for j in range(4):
        e = np.zeros(4)
        e[j] = h
        dM.append((d.mass_matrix(q + e, m) - d.mass_matrix(q - e, m)) / (2 * h))
    Mdot = sum(dM[j] * qd[j] for j in range(4))
    grad = np.array([qd @ dM[i] @ qd for i in range(4)])
    ref = Mdot @ qd - 0.5 * grad
    np.testing.assert_allclose(d.coriolis_vector(q, qd, m), ref, atol=1e-6 * np.abs(ref).max())


def test_gravity_is_gradient_of_potential() -> None:
    m = TRUE.mass
    q, _ = _state()
    h = 1e-6
    fd = np.array([(d.potential_energy(q + h * e, m) - d.potential_energy(q - h * e, m)) / (2 * h) for e in np.eye(4)])
    np.testing.assert_allclose(d.gravity_vector(q, m), fd, atol=1e-7)


def test_inverse_and_forward_dynamics_are_inverse_and_vectorised() -> None:
    rng = np.random.default_rng(1)
    X = np.column_stack(
        [rng.uniform(-0.15, 0.15, 20), rng.uniform(-0.15, 0.15, 20), rng.uniform(-0.7, -0.6, 20), rng.uniform(-3, 3, 20)]
    )
    q = k.inverse_kinematics(X)
    qd = rng.uniform(-10, 10, (20, 4))
    qdd = rng.uniform(-300, 300, (20, 4))
    tau = d.inverse_dynamics(q, qd, qdd, NOM)
    assert tau.shape == (20, 4)
    for n in (0, 7, 19):
        np.testing.assert_allclose(d.inverse_dynamics(q[n], qd[n], qdd[n], NOM), tau[n], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(d.forward_dynamics(q, qd, tau, NOM), qdd, rtol=1e-9, atol=1e-9)
    # the true plant needs friction on top of its rigid-body torque
    tau_t = d.true_inverse_dynamics(q, qd, qdd, TRUE)
    np.testing.assert_allclose(d.true_forward_dynamics(q, qd, tau_t, TRUE), qdd, rtol=1e-9, atol=1e-9)


def test_friction_model_values() -> None:
    qd = np.array([[1.0, -1.0, 0.0, 10.0]])
    f = d.friction_torque(qd, TRUE)[0]
    fc = np.array(TRUE.coulomb_nm)
    fv = np.array(TRUE.viscous_nm_s_per_rad)
    np.testing.assert_allclose(f, fc * np.tanh(qd[0] / 0.01) + fv * qd[0], rtol=1e-15)
    assert f[2] == 0.0
    # optional Stribeck hump
    st = replace(TRUE, stribeck_ratio=1.3)
    v = np.array([0.02, 0.05, 1.0, -0.02])
    ref = fc * (1 + 0.3 * np.exp(-((v / 0.05) ** 2))) * np.tanh(v / 0.01) + fv * v
    np.testing.assert_allclose(d.friction_torque(v, st), ref, rtol=1e-14)
    # smooth through zero velocity, odd in q̇
    small = np.linspace(-0.05, 0.05, 11)[:, None] * np.ones(4)
    f = d.friction_torque(small, TRUE)
    np.testing.assert_allclose(f, -f[::-1], atol=1e-15)


def _run_free(plant: Plant, steps: int, model) -> np.ndarray:
    q0, qd0 = _state()
    plant.reset(q0, qd0)
    E = [d.energy(q0, qd0, model)]
    zero = np.zeros(4, dtype=np.int64)
    for _ in range(steps):
        plant.step(zero)
        E.append(d.energy(plant.q, plant.qd, model))
    return np.array(E)


def test_energy_conserved_in_free_nominal_motion() -> None:
    """No friction, zero torque, RK4 dt = 0.25 ms, 0.2 s: drift tiny against the kinetic energy."""
    plant = Plant.nominal(1e-3, 4, 1e-9, 1e-6)
    E = _run_free(plant, 200, NOM)
    kin = 0.5 * plant.qd @ d.mass_matrix(plant.q, NOM) @ plant.qd
    assert kin > 1.0  # the robot really moved (it falls and swings)
    assert np.max(np.abs(E - E[0])) < 1e-10 * max(kin, 1.0)


def test_energy_conserved_with_tool_spin_term() -> None:
    cfg = TruePlantConfig(mass=TRUE.mass, geometry=Geometry())  # true masses, no friction
    E = _run_free(Plant(cfg, 1e-3, 4, 1e-9, 1e-6), 200, TRUE.mass)
    assert np.max(np.abs(E - E[0])) < 1e-9


def test_true_plant_with_friction_loses_energy() -> None:
    E = _run_free(Plant(TRUE, 1e-3, 4, 1e-9, 1e-6), 200, TRUE.mass)
    assert np.all(np.diff(E) <= 1e-12)
    assert E[-1] < E[0] - 0.1
