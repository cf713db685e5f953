"""Kinematics of the plant (docs/robot-model.md §3): IK/FK round trip, reach errors, J and J̇q̇ against
finite differences, joint rates from task rates, the screw pair and the rotation check."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plant import kinematics as k
from plant.params import Geometry

# a box inside the workspace (cond(J) <= 2.2 there; the gate path lies inside it)
XS = st.floats(-0.16, 0.16)
ZS = st.floats(-0.72, -0.58)
THS = st.floats(-math.pi, math.pi)
POSES = st.tuples(XS, XS, ZS, THS).map(np.array)
RATES = st.tuples(*(st.floats(-2.0, 2.0) for _ in range(4))).map(np.array)

CENTRE = np.array([0.0, 0.0, -0.65, 0.0])


@settings(max_examples=150, deadline=None)
@given(X=POSES)
def test_ik_fk_round_trip(X: np.ndarray) -> None:
    q = k.inverse_kinematics(X)
    Y = k.forward_kinematics(q)
    np.testing.assert_allclose(k.task_from_subplatform(Y), X, atol=1e-10)
    np.testing.assert_allclose(Y, k.subplatform_from_task(X), atol=1e-11)


def test_ik_centre_angles_match_robot_md() -> None:
    q = np.degrees(k.inverse_kinematics(CENTRE))
    np.testing.assert_allclose(q, [30.23, 37.70, 30.23, 37.70], atol=0.01)


def test_ik_batch_keeps_shape_and_matches_single() -> None:
    X = np.array([[0.1, 0.0, -0.62, 0.5], [-0.1525, 0.0, -0.65, 0.0], [0.0, 0.1, -0.7, -1.0]])
    qb = k.inverse_kinematics(X)
    assert qb.shape == (3, 4)
    for i in range(3):
        np.testing.assert_array_equal(qb[i], k.inverse_kinematics(X[i]))
    assert k.inverse_kinematics(X.reshape(3, 1, 4)).shape == (3, 1, 4)


def test_out_of_reach_raises_with_limb_and_point() -> None:
    with pytest.raises(k.OutOfReachError, match=re.escape("limb 1 cannot reach X = (0 m, 0 m, -1.2 m, 0 rad)")):
        k.inverse_kinematics([0.0, 0.0, -1.2, 0.0])
    with pytest.raises(ValueError, match=r"limb \d cannot reach .* \(sample 1\)"):
        k.inverse_kinematics([[0.0, 0.0, -0.65, 0.0], [0.9, 0.0, -0.65, 0.0]])
    with pytest.raises(ValueError, match="shape"):
        k.inverse_kinematics([0.0, 0.0, -0.65])


def test_fk_failure_raises() -> None:
    with pytest.raises(k.ForwardKinematicsError, match="did not converge"):
        k.forward_kinematics([math.nan, 0.5, 0.5, 0.5])


def test_screw_pair_and_coordinates() -> None:
    g = Geometry()
    X = np.array([0.01, -0.02, -0.63, math.pi / 2])
    Y = k.subplatform_from_task(X)
    # a 90° turn needs Δz = h/4 = 10 mm on top of d0
    assert Y[2] - Y[3] == pytest.approx(g.d0 + 0.010, abs=1e-15)
    np.testing.assert_allclose(k.task_from_subplatform(Y), X, atol=1e-15)
    Xd = np.array([0.1, 0.2, 0.3, 2 * math.pi])
    Yd = k.subplatform_rates_from_task(Xd)
    assert Yd[2] - Yd[3] == pytest.approx(g.h)
    np.testing.assert_allclose(k.task_rates_from_subplatform(Yd), Xd, atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(X=POSES)
def test_jacobian_matches_central_differences_of_fk(X: np.ndarray) -> None:
    q = k.inverse_kinematics(X)
    Y = k.forward_kinematics(q)
    J = k.jacobian(q, Y)
    h = 1e-6
    for j in range(4):
        e = np.zeros(4)
        e[j] = h
        fd = (k.forward_kinematics(q + e, Y) - k.forward_kinematics(q - e, Y)) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, atol=1e-8)
    Jup, Jlow = k.jacobian_up_low(q, Y)
    np.testing.assert_array_equal(Jup, J[[0, 1, 2]])
    np.testing.assert_array_equal(Jlow, J[[0, 1, 3]])


@settings(max_examples=40, deadline=None)
@given(X=POSES, qd=RATES)
def test_jdot_qdot_matches_central_differences(X: np.ndarray, qd: np.ndarray) -> None:
    q = k.inverse_kinematics(X)
    Y = k.forward_kinematics(q)
    eps = 1e-6
    qp, qm = q + eps * qd, q - eps * qd
    Jp = k.jacobian(qp, k.forward_kinematics(qp, Y))
    Jm = k.jacobian(qm, k.forward_kinematics(qm, Y))
    fd = (Jp - Jm) @ qd / (2 * eps)
    Yd = k.jacobian(q, Y) @ qd
    np.testing.assert_allclose(k.jdot_qdot(q, qd, Y, Yd), fd, atol=1e-6 * (1 + np.abs(fd).max()))


@settings(max_examples=40, deadline=None)
@given(X=POSES, V=RATES, A=RATES)
def test_joint_rates_from_task_match_finite_differences_of_ik(X: np.ndarray, V: np.ndarray, A: np.ndarray) -> None:
    """q̇, q̈ from the exact maps vs central differences of IK along X(t) = X + V t + A t²/2."""
    V = V * np.array([1.0, 1.0, 1.0, 5.0])
    A = 50.0 * A * np.array([1.0, 1.0, 1.0, 5.0])
    q, qd, qdd = k.joint_states_from_task(X, V, A)
    h = 1e-4

    def ik_at(t: float) -> np.ndarray:
        return k.inverse_kinematics(X + V * t + 0.5 * A * t * t)

    hv = 1e-6  # central-difference truncation ~ hv²·q‴/6 stays far below atol even at |q̇| ≈ 10 rad/s
    qd_fd = (ik_at(hv) - ik_at(-hv)) / (2 * hv)
    qdd_fd = (ik_at(h) - 2 * ik_at(0.0) + ik_at(-h)) / h**2
    np.testing.assert_allclose(qd, qd_fd, atol=1e-7)
    np.testing.assert_allclose(qdd, qdd_fd, atol=2e-4 + 1e-5 * np.abs(qdd).max())
    # the component functions agree with the combined helper
    Y = k.subplatform_from_task(X)
    Yd = k.subplatform_rates_from_task(V)
    Ydd = k.subplatform_rates_from_task(A)
    np.testing.assert_allclose(k.joint_velocity(q, Y, Yd), qd, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(k.joint_acceleration(q, qd, Y, Yd, Ydd), qdd, rtol=1e-13, atol=1e-13)
    # and q̈ = J⁻¹(Ÿ − J̇q̇)
    J = k.jacobian(q, Y)
    np.testing.assert_allclose(J @ qdd + k.jdot_qdot(q, qd, Y, Yd), Ydd, atol=1e-9 * (1 + np.abs(Ydd).max()))


def test_joint_states_vectorised_over_trajectory() -> None:
    t = np.linspace(0.0, 0.25, 251)
    X = np.zeros((t.size, 4))
    X[:, 0] = -0.1525 + 0.305 * t / 0.25
    X[:, 2] = -0.65
    X[:, 3] = math.pi / 2 * t / 0.25
    Xd = np.zeros_like(X)
    Xd[:, 0] = 0.305 / 0.25
    Xd[:, 3] = math.pi / 2 / 0.25
    q, qd, qdd = k.joint_states_from_task(X, Xd, np.zeros_like(X))
    assert q.shape == qd.shape == qdd.shape == (251, 4)
    for n in (0, 100, 250):
        qn, qdn, qddn = k.joint_states_from_task(X[n], Xd[n], np.zeros(4))
        np.testing.assert_allclose(q[n], qn, rtol=0, atol=0)
        np.testing.assert_allclose(qd[n], qdn, rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(qdd[n], qddn, rtol=1e-15, atol=1e-15)


def test_rotation_at_fixed_tcp_moves_only_limbs_1_and_3() -> None:
    """docs/robot-model.md §2.1: θ̇ = 1 rad/s at a fixed TCP gives q̇ = (-0.0165, 0, -0.0165, 0) rad/s."""
    q, qd, _ = k.joint_states_from_task(CENTRE, np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(4))
    np.testing.assert_allclose(qd, [-0.0165, 0.0, -0.0165, 0.0], atol=5e-5)
    assert qd[1] == 0.0 and qd[3] == 0.0
    # and the other way round: moving only limbs 1 and 3 turns the tool but keeps the TCP
    Xd = k.task_velocity(q, np.array([1.0, 0.0, 1.0, 0.0]))
    np.testing.assert_allclose(Xd[:3], 0.0, atol=1e-12)
    assert Xd[3] == pytest.approx(-1 / 0.01647, rel=1e-3)
