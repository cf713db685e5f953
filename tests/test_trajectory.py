"""Tests of host.planning (motion_laws, journeys, ruckig_adapter, task_plan, joint_reference,
feasibility): motion laws, trial planning (poly4567, poly5, ruckig), joint references by IK and the
feasibility check."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.planning.feasibility import JointLimits, check_feasibility
from host.planning.joint_reference import joint_reference
from host.planning.journeys import trial_samples
from host.planning.motion_laws import poly5, poly4567
from host.planning.paths import BUILTIN_PATHS, PathSpec
from host.planning.planning_errors import InfeasibleTaskError, TrajectoryError
from host.planning.ruckig_adapter import CartesianLimits
from host.planning.task_plan import PROFILES, plan_task

TS = 1e-3
CYCLES = (0.15, 0.25, 0.50)
P1 = BUILTIN_PATHS[1]


# ----------------------------------------------------------------------------- motion laws


@pytest.mark.parametrize("law", [poly4567, poly5])
def test_law_boundary_values(law) -> None:
    s, s1, s2, s3 = law(np.array([0.0, 1.0]))
    assert s.tolist() == [0.0, 1.0]
    assert s1.tolist() == [0.0, 0.0]
    assert s2.tolist() == [0.0, 0.0]
    # held outside [0, 1]
    s, s1, s2, s3 = law(np.array([-0.5, 1.5]))
    assert s.tolist() == [0.0, 1.0]
    assert not np.any(s1) and not np.any(s2) and not np.any(s3)


def test_poly4567_zero_jerk_at_ends_and_poly5_not() -> None:
    assert poly4567(0.0)[3] == 0.0 and poly4567(1.0)[3] == 0.0
    assert poly5(0.0)[3] == pytest.approx(60.0) and poly5(1.0)[3] == pytest.approx(60.0)


@pytest.mark.parametrize(
    ("law", "v_max", "a_max", "tau_a"),
    [(poly4567, 2.1875, 7.513, 0.2764), (poly5, 1.875, 5.774, 0.2113)],
)
def test_law_maxima_robot_md(law, v_max: float, a_max: float, tau_a: float) -> None:
    tau = np.linspace(0.0, 1.0, 200001)
    s, s1, s2, _ = law(tau)
    assert s1.max() == pytest.approx(v_max, rel=1e-9)
    assert tau[np.argmax(s1)] == pytest.approx(0.5, abs=1e-5)
    assert np.abs(s2).max() == pytest.approx(a_max, abs=1e-3)
    assert tau[np.argmax(s2)] == pytest.approx(tau_a, abs=1e-4)
    assert tau[np.argmin(s2)] == pytest.approx(1.0 - tau_a, abs=1e-4)
    assert np.all(np.diff(s) >= 0.0)  # monotonic: no overshoot


@settings(max_examples=50, deadline=None)
@given(tau=st.floats(0.01, 0.99), law=st.sampled_from([poly4567, poly5]))
def test_law_derivatives_are_consistent(tau: float, law) -> None:
    h = 1e-6
    for k in range(3):
        d_num = (law(tau + h)[k] - law(tau - h)[k]) / (2 * h)
        assert float(d_num) == pytest.approx(float(law(tau)[k + 1]), rel=1e-5, abs=1e-4)


# ----------------------------------------------------------------------------- trial plan


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("cycle", CYCLES)
def test_trial_duration_exact_and_returns_to_pick(profile: str, cycle: float) -> None:
    task = plan_task(P1, cycle, profile, TS)
    m = round(cycle / TS)
    assert task.n_samples == 2 * m + 1 == trial_samples(cycle, TS)
    assert task.t[-1] == pytest.approx(2 * cycle, abs=1e-12)
    assert np.array_equal(task.t, np.arange(2 * m + 1) * TS)
    assert task.duration_s == pytest.approx(2 * cycle, abs=1e-12)
    pick = np.array([*P1.pick_xyz, 0.0])
    place = np.array([*P1.place_xyz, P1.rotation_rad])
    np.testing.assert_allclose(task.X[0], pick, atol=1e-12)
    np.testing.assert_allclose(task.X[m], place, atol=1e-12)
    np.testing.assert_allclose(task.X[-1], pick, atol=1e-12)
    for n in (0, m, 2 * m):  # at rest at pick, place, pick
        np.testing.assert_allclose(task.Xd[n], 0.0, atol=1e-12)
        np.testing.assert_allclose(task.Xdd[n], 0.0, atol=1e-9)
    for arr in (task.X, task.Xd, task.Xdd):
        assert arr.shape == (2 * m + 1, 4) and np.all(np.isfinite(arr))


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("number", sorted(BUILTIN_PATHS))
def test_lateral_move_is_straight_and_in_box(profile: str, number: int) -> None:
    path = BUILTIN_PATHS[number]
    task = plan_task(path, 0.25, profile, TS)
    a = np.array([path.pick_xyz[0], path.pick_xyz[1], 0.0])
    b = np.array([path.place_xyz[0], path.place_xyz[1], path.rotation_rad])
    d = b - a
    P = task.X[:, [0, 1, 3]] - a
    lam = P @ d / (d @ d)
    assert np.abs(P - np.outer(lam, d)).max() < 1e-12
    assert lam.min() >= -1e-12 and lam.max() <= 1 + 1e-12
    z = task.X[:, 2]
    assert z.min() >= path.pick_xyz[2] - 1e-12 and z.max() <= path.top_z_m + 1e-12
    # the gate's corners are rounded but the top is reached: z = top while moving laterally
    m = round(0.25 / TS)
    assert z[m // 2] == pytest.approx(path.top_z_m, abs=1e-12)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("cycle", CYCLES)
def test_rates_match_finite_differences(profile: str, cycle: float) -> None:
    task = plan_task(BUILTIN_PATHS[3], cycle, profile, TS)
    fd_v = (task.X[2:] - task.X[:-2]) / (2 * TS)
    # sampled jerk: one-sample differences of the acceleration
    jerk = np.abs(np.diff(task.Xdd, axis=0)).max(axis=0) / TS
    # velocity: central differences of X, error ≤ h²/6·max|jerk|
    assert np.all(np.abs(fd_v - task.Xd[1:-1]).max(axis=0) <= 1.5 * TS**2 * jerk / 6 + 1e-12)
    # acceleration: the velocity is the trapezoidal integral of Xdd (robust to the jerk steps of
    # poly5 and of the jerk-limited profile at the window edges) ...
    v_scale = np.abs(task.Xd).max(axis=0)
    steps = 0.5 * (task.Xdd[1:] + task.Xdd[:-1]) * TS
    integ = task.Xd[0] + np.concatenate([np.zeros((1, 4)), np.cumsum(steps, axis=0)])
    # (trapezoid error: h²/12 per jerk step, h²/8 per jerk kink between samples)
    assert np.all(np.abs(integ - task.Xd).max(axis=0) <= 1e-2 * v_scale + 4 * TS**2 * jerk + 1e-12)
    # ... and central differences of Xd match Xdd within one sample of jerk
    fd_a = (task.Xd[2:] - task.Xd[:-2]) / (2 * TS)
    assert np.all(np.abs(fd_a - task.Xdd[1:-1]).max(axis=0) <= TS * jerk + 1e-9)
    if profile == "ruckig":
        assert np.all(jerk <= CartesianLimits().jerk * (1 + 1e-9))


@pytest.mark.parametrize("profile", ["poly4567", "poly5"])
def test_polynomial_return_mirrors_outward_journey(profile: str) -> None:
    task = plan_task(P1, 0.25, profile, TS)
    m = 250
    np.testing.assert_allclose(task.X[m : 2 * m + 1], task.X[m::-1], atol=1e-12)


@pytest.mark.parametrize("number", sorted(BUILTIN_PATHS))
@pytest.mark.parametrize("cycle", CYCLES)
def test_ruckig_respects_limits(number: int, cycle: float) -> None:
    lim = CartesianLimits()
    task = plan_task(BUILTIN_PATHS[number], cycle, "ruckig", TS, limits=lim)
    tol = 1 + 1e-9
    assert np.all(np.abs(task.Xd).max(axis=0) <= lim.velocity * tol)
    assert np.all(np.abs(task.Xdd).max(axis=0) <= lim.acceleration * tol)
    # jerk from sampled acceleration (piecewise linear, so a one-sample difference is a mean jerk)
    jerk = np.abs(np.diff(task.Xdd, axis=0)).max(axis=0) / TS
    assert np.all(jerk <= lim.jerk * tol)


def test_ruckig_stretch_modes() -> None:
    lim = CartesianLimits()
    # "hold": Ruckig stretches at the full limits, the peak acceleration stays at the limit
    hold = {c: plan_task(P1, c, "ruckig", TS, ruckig_stretch="hold") for c in CYCLES}
    assert np.abs(hold[0.15].Xdd[:, 0]).max() == pytest.approx(lim.a_xyz_m_s2, rel=1e-6)
    assert np.abs(hold[0.25].Xdd[:, 0]).max() > 0.9 * lim.a_xyz_m_s2
    # "scale" (default): the time-optimal profile slowed down uniformly -> a ∝ 1/T²
    scale = {c: plan_task(P1, c, "ruckig", TS) for c in CYCLES}
    peak = {c: np.abs(scale[c].Xdd[:, 0]).max() for c in CYCLES}
    assert peak[0.50] / peak[0.25] == pytest.approx((174 / 350) ** 2, rel=1e-3)  # lateral windows
    for c in CYCLES:
        assert peak[c] <= np.abs(hold[c].Xdd[:, 0]).max() + 1e-9
    # at the shortest feasible cycle both modes are the time-optimal profile at the limit
    fastest = plan_task(P1, 0.132, "ruckig", TS)
    assert np.abs(fastest.Xdd[:, 0]).max() == pytest.approx(lim.a_xyz_m_s2, rel=2e-2)
    with pytest.raises(TrajectoryError, match="unknown ruckig_stretch"):
        plan_task(P1, 0.25, "ruckig", TS, ruckig_stretch="fast")


@pytest.mark.parametrize("cycle", CYCLES)
def test_ruckig_hold_respects_limits_and_is_straight(cycle: float) -> None:
    lim = CartesianLimits()
    task = plan_task(BUILTIN_PATHS[3], cycle, "ruckig", TS, ruckig_stretch="hold")
    assert np.all(np.abs(task.Xd).max(axis=0) <= lim.velocity * (1 + 1e-9))
    assert np.all(np.abs(task.Xdd).max(axis=0) <= lim.acceleration * (1 + 1e-9))
    assert np.all(np.abs(np.diff(task.Xdd, axis=0)).max(axis=0) / TS <= lim.jerk * (1 + 1e-9))
    np.testing.assert_allclose(task.X[:, 0], task.X[:, 1], atol=1e-12)  # 45° diagonal
    np.testing.assert_allclose(task.X[-1], task.X[0], atol=1e-12)


def test_ruckig_honours_custom_limits() -> None:
    slow = CartesianLimits(v_xyz_m_s=1.5, a_xyz_m_s2=30.0, j_xyz_m_s3=2000.0)
    task = plan_task(P1, 0.50, "ruckig", TS, limits=slow)
    assert np.abs(task.Xd[:, :3]).max() <= 1.5 + 1e-9
    assert np.abs(task.Xdd[:, :3]).max() <= 30.0 + 1e-9


@pytest.mark.parametrize("cycle", [0.05, 0.12])
def test_infeasible_cycle_raises_with_message(cycle: float) -> None:
    with pytest.raises(InfeasibleTaskError) as exc:
        plan_task(P1, cycle, "ruckig", TS)
    msg = str(exc.value)
    assert msg.startswith(f"cycle {cycle:g} s is too short for path 1 with profile ruckig: needs ≥ ")
    assert "\n" not in msg
    assert isinstance(exc.value, ValueError)
    need = float(msg.rsplit("≥ ", 1)[1].split()[0])
    # the reported minimum is feasible and one sample less is not
    plan_task(P1, need, "ruckig", TS)
    with pytest.raises(InfeasibleTaskError):
        plan_task(P1, round(need - TS, 6), "ruckig", TS)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"profile": "trapezoid"}, "unknown motion profile 'trapezoid'"),
        ({"cycle_s": 0.1505}, "not a whole number of samples"),
        ({"cycle_s": -0.25}, "cycle time must be > 0"),
        ({"ts_s": 0.0}, "sample period must be > 0"),
        ({"fz": 0.6}, "f_z must be in"),
        ({"fh": 0.5}, "f_h must be in"),
        ({"journeys": 0}, "journeys must be"),
        ({"cycle_s": 0.001}, "too short to place the axis windows"),
    ],
)
def test_bad_arguments(kwargs: dict, message: str) -> None:
    args = {"path": P1, "cycle_s": 0.25, "profile": "poly4567", "ts_s": TS} | kwargs
    with pytest.raises(TrajectoryError, match=message):
        plan_task(**args)


def test_one_journey_and_arch_variant() -> None:
    task = plan_task(P1, 0.25, "poly4567", TS, journeys=1, fz=0.5, fh=0.0)
    assert task.n_samples == 251
    np.testing.assert_allclose(task.X[-1], [*P1.place_xyz, P1.rotation_rad], atol=1e-12)


def test_different_heights_use_lift_above_higher_point() -> None:
    path = PathSpec("slope", (-0.1, 0.0, -0.68), (0.1, 0.0, -0.64), 0.02, 0.0)
    for profile in PROFILES:
        task = plan_task(path, 0.25, profile, TS)
        assert task.X[:, 2].max() == pytest.approx(-0.62, abs=1e-12)
        assert task.X[250, 2] == pytest.approx(-0.64, abs=1e-12)
        assert task.X[-1, 2] == pytest.approx(-0.68, abs=1e-12)


# ----------------------------------------------------------------------------- joint side


@pytest.fixture(scope="module")
def nominal():
    from plant.params import nominal_mass_model

    return nominal_mass_model()


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("number", sorted(BUILTIN_PATHS))
def test_joint_reference_matches_finite_differences(profile: str, number: int) -> None:
    task = plan_task(BUILTIN_PATHS[number], 0.25, profile, TS)
    ref = joint_reference(task)
    assert ref.q.shape == ref.qd.shape == ref.qdd.shape == (task.n_samples, 4)
    assert np.array_equal(ref.t, task.t)
    fd_qd = (ref.q[2:] - ref.q[:-2]) / (2 * TS)
    fd_qdd = (ref.qd[2:] - ref.qd[:-2]) / (2 * TS)
    qd_scale = np.abs(ref.qd).max()
    qdd_scale = np.abs(ref.qdd).max()
    jerk = np.abs(np.diff(ref.qdd, axis=0)).max() / TS  # sampled joint jerk, rad/s³
    assert np.abs(fd_qd - ref.qd[1:-1]).max() <= 2e-3 * qd_scale
    assert np.abs(fd_qdd - ref.qdd[1:-1]).max() <= TS * jerk + 1e-3 * qdd_scale
    # at rest at pick, place, pick; back where it started
    for n in (0, 250, 500):
        np.testing.assert_allclose(ref.qd[n], 0.0, atol=1e-9)
    np.testing.assert_allclose(ref.q[-1], ref.q[0], atol=1e-12)


def test_joint_reference_is_consistent_with_forward_kinematics() -> None:
    from plant.kinematics import forward_kinematics, subplatform_from_task, task_velocity

    task = plan_task(P1, 0.25, "poly4567", TS)
    ref = joint_reference(task)
    idx = np.arange(0, task.n_samples, 25)
    Y = forward_kinematics(ref.q[idx])
    np.testing.assert_allclose(Y, subplatform_from_task(task.X[idx]), atol=1e-10)
    np.testing.assert_allclose(task_velocity(ref.q[idx], ref.qd[idx], Y), task.Xd[idx], atol=1e-9)


def test_out_of_reach_raises_with_time_and_point() -> None:
    from plant.kinematics import OutOfReachError

    far = PathSpec("far path", (0.0, 0.0, -0.65), (0.60, 0.0, -0.65), 0.025, 0.0)
    task = plan_task(far, 0.25, "poly4567", TS)
    with pytest.raises(OutOfReachError) as exc:
        joint_reference(task)
    msg = str(exc.value)
    assert "\n" not in msg and isinstance(exc.value, ValueError)
    assert msg.startswith("far path (poly4567, 0.25 s): point out of reach at t = 0.")
    t = float(msg.split("t = ")[1].split(" s")[0])
    n = round(t / TS)
    assert f"X = ({task.X[n, 0]:.4f} m, {task.X[n, 1]:.4f} m, {task.X[n, 2]:.4f} m" in msg
    # the sample before is reachable (first failing sample is named)
    from plant.kinematics import inverse_kinematics

    inverse_kinematics(task.X[n - 1])
    with pytest.raises(OutOfReachError):
        inverse_kinematics(task.X[n])


def test_feasibility_report(nominal) -> None:
    ref = joint_reference(plan_task(P1, 0.25, "poly4567", TS))
    rep = check_feasibility(ref, nominal)
    lim = JointLimits()
    assert lim.tau_max_nm == pytest.approx(264.6)
    assert rep.tau_limit_nm == pytest.approx(0.9 * 264.6)
    # the x run loads limbs 1 and 3 most (docs/robot-model.md §6.5); limbs 2/4 mirror each other
    assert rep.peak_tau_nm[0] > 3 * rep.peak_tau_nm[1]
    assert rep.peak_tau_nm[1] == pytest.approx(rep.peak_tau_nm[3], rel=1e-6)
    assert 40.0 < rep.peak_tau_nm[0] < 120.0
    assert rep.peak_qd_rad_s == pytest.approx(tuple(np.abs(ref.qd).max(axis=0)))
    assert all(lo < hi for lo, hi in zip(rep.q_min_rad, rep.q_max_rad))
    d = rep.as_dict()
    assert set(d) >= {"peak_tau_nm", "peak_qd_rad_s", "q_min_deg", "q_max_deg", "rms_tau_nm"}
    assert len(rep.format().splitlines()) == 4


@pytest.mark.parametrize(
    ("limits", "pattern"),
    [
        (
            JointLimits(tau_max_nm=50.0),
            r"joint 1 peak torque \d+\.\d N·m exceeds the limit 45\.0 N·m \(0\.9 × 50\.0 N·m\) at t = ",
        ),
        (JointLimits(qd_max_rad_s=5.0), r"joint 1 speed \d+\.\d\d rad/s exceeds the limit 5\.00 rad/s at t = "),
        (JointLimits(q_max_rad=math.radians(45.0)), r"joint 1 angle 52\.\d deg is above the range limit 45\.0 deg"),
        (JointLimits(q_min_rad=math.radians(20.0)), r"joint 1 angle 8\.\d deg is below the range limit 20\.0 deg"),
    ],
)
def test_infeasible_joint_limits_raise(nominal, limits: JointLimits, pattern: str) -> None:
    ref = joint_reference(plan_task(P1, 0.25, "poly4567", TS))
    with pytest.raises(InfeasibleTaskError, match=r"^path 1 \(poly4567, 0\.25 s\): " + pattern) as exc:
        check_feasibility(ref, nominal, limits)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("number", sorted(BUILTIN_PATHS))
def test_builtin_paths_feasible_at_fastest_cycle(nominal, profile: str, number: int) -> None:
    rep = check_feasibility(joint_reference(plan_task(BUILTIN_PATHS[number], 0.15, profile, TS)), nominal)
    assert max(rep.peak_tau_nm) < rep.tau_limit_nm


def test_bad_joint_limits() -> None:
    with pytest.raises(TrajectoryError):
        JointLimits(tau_margin=0.0)
    with pytest.raises(TrajectoryError):
        JointLimits(q_min_rad=1.0, q_max_rad=0.5)


@settings(max_examples=25, deadline=None)
@given(
    pick=st.tuples(st.floats(-0.15, 0.15), st.floats(-0.15, 0.15), st.floats(-0.72, -0.60)),
    place=st.tuples(st.floats(-0.15, 0.15), st.floats(-0.15, 0.15), st.floats(-0.72, -0.60)),
    lift=st.floats(0.005, 0.05),
    rot_deg=st.floats(-180.0, 180.0),
    profile=st.sampled_from(PROFILES),
    m=st.integers(150, 600),
)
def test_property_any_gate_plans_exactly(pick, place, lift, rot_deg, profile, m) -> None:
    path = PathSpec("random", pick, place, lift, math.radians(rot_deg))
    try:
        task = plan_task(path, m * TS, profile, TS)
    except InfeasibleTaskError as exc:  # only ruckig has Cartesian limits
        assert profile == "ruckig" and "is too short for random with profile ruckig" in str(exc)
        return
    assert task.n_samples == 2 * m + 1
    a = np.array([*pick, 0.0])
    b = np.array([*place, math.radians(rot_deg)])
    np.testing.assert_allclose(task.X[[0, m, 2 * m]], [a, b, a], atol=1e-12)
    np.testing.assert_allclose(task.Xd[[0, m, 2 * m]], 0.0, atol=1e-12)
    d = (b - a)[[0, 1, 3]]
    P = task.X[:, [0, 1, 3]] - a[[0, 1, 3]]
    lam = P @ d / (d @ d) if d @ d > 0 else np.zeros(len(P))
    assert np.abs(P - np.outer(lam, d)).max() < 1e-9
    assert task.X[:, 2].max() <= path.top_z_m + 1e-12


@pytest.mark.parametrize("profile", PROFILES)
def test_vertical_pick_and_place_and_negligible_rotation(profile: str) -> None:
    for rot in (0.0, 1e-276):
        path = PathSpec("vertical", (0.0, 0.0, -0.625), (0.0, 0.0, -0.625), 0.03, rot)
        task = plan_task(path, 0.15, profile, TS)
        np.testing.assert_allclose(task.X[:, [0, 1, 3]], 0.0, atol=1e-12)
        assert task.X[:, 2].max() == pytest.approx(-0.595, abs=1e-12)


def test_ruckig_profile_boundary_case_is_planned() -> None:
    # a 40 mm lift from -0.625 m sits exactly where the acceleration touches 200 m/s² with
    # j = 2e4 m/s³; Ruckig 0.19 fails in step 1 there without the retry in _ruckig_plan
    path = PathSpec("boundary", (0.0, 0.0, -0.625), (0.0, 0.0, -0.625), 0.04, 0.0)
    task = plan_task(path, 0.15, "ruckig", TS)
    assert task.X[:, 2].max() == pytest.approx(-0.585, abs=1e-12)
    assert np.abs(task.Xdd[:, 2]).max() <= CartesianLimits().a_xyz_m_s2
