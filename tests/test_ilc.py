"""Learning laws and the lifted convergence check on a small linear case."""

from __future__ import annotations

import numpy as np
import pytest

from host.learning.ilc import (
    GAIN_PRESETS,
    LAWS,
    GainSpec,
    LiftedModel,
    backward_difference,
    lead,
    make_law,
    resolve_gains,
)

TS = 1e-3
N = 160


def inertia_seq(scale: float = 1.0, n: int = N) -> np.ndarray:
    base = np.array([[0.12, 0.01, 0.02, 0.01],
                     [0.01, 0.11, 0.01, 0.015],
                     [0.02, 0.01, 0.12, 0.01],
                     [0.01, 0.015, 0.01, 0.11]])
    t = np.linspace(0, 1, n)[:, None, None]
    return scale * base[None] * (1 + 0.2 * np.sin(2 * np.pi * t))


def simulate_linear(minv: np.ndarray, kp, kd, u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Direct simulation of the discrete closed loop that LiftedModel lifts; returns e = −δq."""
    n = u.shape[0]
    q = np.zeros(4)
    qd = np.zeros(4)
    qprev = np.zeros(4)
    e = np.zeros((n, 4))
    for i in range(n):
        e[i] = -q
        tau = u[i] + d[i] - kp * q - kd * (q - qprev) / TS
        acc = minv[i] @ tau
        qprev = q.copy()
        q = q + TS * qd + 0.5 * TS * TS * acc
        qd = qd + TS * acc
    return e


def test_lifted_g_matches_direct_simulation() -> None:
    m = inertia_seq()
    kp, kd = np.array([900.0, 800, 900, 800]), np.array([20.0, 18, 20, 18])
    lm = LiftedModel(m, kp, kd, TS)
    rng = np.random.default_rng(1)
    u = rng.normal(size=(N, 4))
    e_direct = simulate_linear(lm.minv, kp, kd, u, np.zeros_like(u))
    e_lift = (lm.G @ u.reshape(-1)).reshape(N, 4)
    np.testing.assert_allclose(e_lift, e_direct, rtol=1e-9, atol=1e-15)
    # relative degree: u[n] first shows in e[n+1]
    assert np.all(lm.G[:4, :] == 0)


def test_feedback_operator_matches_definition() -> None:
    lm = LiftedModel(inertia_seq(), np.full(4, 100.0), np.full(4, 10.0), TS)
    e = np.random.default_rng(2).normal(size=(N, 4))
    tau = (lm.K @ e.reshape(-1)).reshape(N, 4)
    np.testing.assert_allclose(tau, 100.0 * e + 10.0 * backward_difference(e, TS), rtol=1e-12)


def test_lead_and_difference() -> None:
    x = np.arange(5.0)[:, None]
    np.testing.assert_array_equal(lead(x, 2)[:, 0], [2, 3, 4, 4, 4])
    np.testing.assert_array_equal(backward_difference(x, 0.5)[:, 0], [0, 2, 2, 2, 2])


def run_iterations(name: str, spec: GainSpec, iterations: int = 12, mismatch: float = 1.1) -> tuple[list[float], object]:
    """ILC on the linear plant with a 10 % inertia error against the model used by the law."""
    m_nom = inertia_seq()
    gains = resolve_gains(spec, np.mean(np.diagonal(m_nom, axis1=1, axis2=2), axis=0), TS)
    model = LiftedModel(m_nom, gains.kp, gains.kd, TS)
    law = make_law(name, gains, TS, model=model)
    t = np.arange(N) * TS
    d = np.stack([3 * np.sin(2 * np.pi * 4 * t + p) for p in range(4)], axis=1)  # repetitive torque
    report = law.check(model, d, iterations)
    true = LiftedModel(inertia_seq(mismatch), gains.kp, gains.kd, TS)
    e_free = (true.G @ d.reshape(-1)).reshape(N, 4)
    u = np.zeros((N, 4))
    rms = []
    for _ in range(iterations):
        e = e_free + (true.G @ u.reshape(-1)).reshape(N, 4)
        tau = u + (true.K @ e.reshape(-1)).reshape(N, 4)
        rms.append(float(np.sqrt(np.mean(e**2))))
        u = law.update(u, e, tau)
    return rms, report


@pytest.mark.parametrize("name", LAWS)
def test_every_law_converges_or_is_flagged(name: str) -> None:
    rms, report = run_iterations(name, GAIN_PRESETS["normalized"])
    if report.ok:
        assert rms[-1] < 0.5 * rms[0], (name, rms)
    else:
        assert rms[-1] > rms[0], (name, rms)


def test_paper_literal_gains_are_flagged_and_diverge() -> None:
    rms, report = run_iterations("pd-ilc", GAIN_PRESETS["paper"], iterations=6)
    assert not report.ok
    assert rms[-1] > 10 * rms[0]


def test_check_reports_paper_condition_18() -> None:
    # literal paper gains satisfy the paper's own condition (18) although the iteration diverges
    _, report = run_iterations("pd-ilc", GAIN_PRESETS["paper"], iterations=1)
    assert report.paper_rho18 < 1.0
    assert not report.ok and report.predicted_ratio > 1.0


def test_norm_optimal_beats_pd_ilc() -> None:
    rms_no, rep_no = run_iterations("no-ilc", GAIN_PRESETS["normalized"], iterations=6)
    rms_pd, _ = run_iterations("pd-ilc", GAIN_PRESETS["normalized"], iterations=6)
    assert rep_no.ok
    assert rms_no[-1] < rms_pd[-1]


def test_unknown_law_and_nan_gain() -> None:
    gains = resolve_gains(GainSpec(), np.full(4, 0.1), TS)
    with pytest.raises(ValueError, match="unknown law 'x-ilc'"):
        make_law("x-ilc", gains, TS)
    with pytest.raises(ValueError, match="alpha must be a finite number"):
        resolve_gains(GainSpec(alpha=float("nan")), np.full(4, 0.1), TS)
