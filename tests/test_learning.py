"""Learning laws, the O(N) closed-loop model and the matrix-free convergence check.

The O(N) implementations are compared with the dense lifted matrices of ``tests/dense_learning.py``
on small N (within 1e-9 relative); the laws run on a small linear plant with a model error.
"""

from __future__ import annotations

import numpy as np
import pytest
from dense_learning import dense_g, dense_k, dense_l, dense_norm_optimal, time_op

from host.learning import check as chk
from host.learning.gains import GAIN_PRESETS, GainSpec, resolve_gains
from host.learning.identification import PARAMETER_NAMES, DynamicsEstimate
from host.learning.laws.base import BuiltinLaw, LawContext
from host.learning.laws.checked import build_law
from host.learning.laws.table import PROJECT_LAWS
from host.learning.model import ClosedLoopModel
from host.learning.names import DEFAULT_LAW, LAWS, PROJECT_LAW_NAMES
from host.learning.norm_optimal import NormOptimalStep
from host.learning.protocol import TrialData
from host.learning.signals import ZeroPhaseFilter, backward_difference, backward_difference_t, lead, lead_t

TS = 1e-3
N = 160
SMALL = 48  # dense comparisons: 4N × 4N matrices


def inertia_seq(scale: float = 1.0, n: int = N) -> np.ndarray:
    base = np.array([[0.12, 0.01, 0.02, 0.01], [0.01, 0.11, 0.01, 0.015], [0.02, 0.01, 0.12, 0.01], [0.01, 0.015, 0.01, 0.11]])
    t = np.linspace(0, 1, n)[:, None, None]
    return scale * base[None] * (1 + 0.2 * np.sin(2 * np.pi * t))


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / max(np.max(np.abs(b)), 1e-300))


def context(spec: GainSpec, n: int = N, scale: float = 1.0) -> LawContext:
    m = inertia_seq(scale, n)
    gains = resolve_gains(spec, np.mean(np.diagonal(m, axis1=1, axis2=2), axis=0), TS)
    return LawContext(gains=gains, ts_s=TS, model=ClosedLoopModel(m, gains.kp, gains.kd, TS))


def trial(u: np.ndarray, e: np.ndarray, tau: np.ndarray, k: int = 0) -> TrialData:
    """A learning trial as a law receives it: feed-forward u, error e, total torque tau (feedback tau − u)."""
    return TrialData(k, u, e, tau, tau - u, TS)


def simulate_linear(minv: np.ndarray, kp, kd, u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Direct simulation of the discrete closed loop the model describes; returns e = −δq."""
    n = u.shape[0]
    q, qd, qprev = np.zeros(4), np.zeros(4), np.zeros(4)
    e = np.zeros((n, 4))
    for i in range(n):
        e[i] = -q
        tau = u[i] + d[i] - kp * q - kd * (q - qprev) / TS
        acc = minv[i] @ tau
        qprev = q.copy()
        q = q + TS * qd + 0.5 * TS * TS * acc
        qd = qd + TS * acc
    return e


# ------------------------------------------------------------------ O(N) operators = dense ones


def test_model_matches_direct_simulation_and_dense_g() -> None:
    kp, kd = np.array([900.0, 800, 900, 800]), np.array([20.0, 18, 20, 18])
    model = ClosedLoopModel(inertia_seq(n=SMALL), kp, kd, TS)
    u = np.random.default_rng(1).normal(size=(SMALL, 4))
    y = np.random.default_rng(2).normal(size=(SMALL, 4))
    G = dense_g(model.minv, kp, kd, TS)
    assert rel(model.g(u), simulate_linear(model.minv, kp, kd, u, np.zeros_like(u))) < 1e-9
    assert rel(model.g(u), (G @ u.reshape(-1)).reshape(SMALL, 4)) < 1e-9
    assert rel(model.g_t(y), (G.T @ y.reshape(-1)).reshape(SMALL, 4)) < 1e-9
    assert rel(model.column_norms_sq(), np.sum(G * G, axis=0).reshape(SMALL, 4)) < 1e-9
    assert np.all(G[:4, :] == 0)  # relative degree one: u[n] first shows in e[n+1]
    blocks = np.array([G[(i + 1) * 4 : (i + 2) * 4, i * 4 : (i + 1) * 4] for i in range(SMALL - 1)])
    assert rel(model.first_markov()[:-1], blocks) < 1e-9
    K = dense_k(SMALL, kp, kd, TS)
    assert rel(model.k(y), (K @ y.reshape(-1)).reshape(SMALL, 4)) < 1e-9
    assert rel(model.k_t(y), (K.T @ y.reshape(-1)).reshape(SMALL, 4)) < 1e-9


@pytest.mark.parametrize("m", [0, 1, 3])
def test_signal_transposes(m: int) -> None:
    for f, ft in (
        (lambda x: lead(x, m), lambda x: lead_t(x, m)),
        (lambda x: backward_difference(x, TS), lambda x: backward_difference_t(x, TS)),
    ):
        assert rel(time_op(ft, SMALL, 4), time_op(f, SMALL, 4).T) < 1e-12


@pytest.mark.parametrize(("cutoff", "order"), [(150.0, 2), (40.0, 2), (40.0, 3)])
def test_zero_phase_filter_is_filtfilt_and_its_transpose_exact(cutoff: float, order: int) -> None:
    from scipy import signal

    q = ZeroPhaseFilter(cutoff, order, TS)
    x = np.random.default_rng(3).normal(size=(SMALL, 4))
    b, a = signal.butter(order, cutoff * 2 * TS)
    ref = signal.filtfilt(b, a, x, axis=0, padtype="odd", padlen=min(3 * max(len(a), len(b)), SMALL - 1))
    np.testing.assert_array_equal(q(x), ref)
    assert rel(time_op(q.transpose, SMALL, 4), time_op(q, SMALL, 4).T) < 1e-9
    with pytest.raises(ValueError, match="cut-off"):
        ZeroPhaseFilter(600.0, 2, TS)


@pytest.mark.parametrize("w", [1e-6, 1e-4])
def test_riccati_norm_optimal_equals_lifted_solution(w: float) -> None:
    model = ClosedLoopModel(inertia_seq(n=SMALL), np.full(4, 500.0), np.full(4, 70.0), TS)
    e = np.random.default_rng(4).normal(size=(SMALL, 4))
    step = NormOptimalStep(model, w)
    dense = dense_norm_optimal(dense_g(model.minv, model.kp, model.kd, TS), w)
    assert rel(step(e), (dense @ e.reshape(-1)).reshape(SMALL, 4)) < 1e-9
    with pytest.raises(ValueError, match="weight"):
        NormOptimalStep(model, 0.0)


def dense_map(name: str, ctx: LawContext) -> tuple[str, np.ndarray]:
    """The law's lifted iteration map E as a dense matrix (the textbook forms)."""
    model, g = ctx.model, ctx.gains
    n, m = model.n, g.spec.lead
    G = dense_g(model.minv, model.kp, model.kd, TS)
    K = dense_k(n, model.kp, model.kd, TS)
    eye = np.eye(n * 4)
    if name == "pd-ilc":
        return "error", eye + G @ (K + dense_l(n, g.lp, g.ld, TS, m))
    if name in ("pd-ol", "p-ol", "d-ilc"):
        return "error", eye + G @ dense_l(n, g.lp, g.ld, TS, m, name != "d-ilc", name != "p-ol")
    if name in ("no-ilc", "no-ilc-id"):
        return "error", eye + G @ dense_norm_optimal(G, g.spec.no_weight)
    cutoff = g.spec.q_cutoff_hz if name == "q-ilc" else g.spec.pdq_cutoff_hz
    Q = time_op(ZeroPhaseFilter(cutoff, g.spec.q_order, TS), n, 4)
    M = dense_l(n, g.lp, g.ld, TS, m) + (K if name == "pd-ilc-q" else 0)
    return "input", Q @ (eye + M @ G)


def id_context(spec: GainSpec, n: int) -> LawContext:
    """A context that also serves no-ilc-id (the reference and mass model are unused before a trial)."""
    from host.planning.joint_reference import JointReference
    from plant.params import Geometry, nominal_mass_model

    ctx = context(spec, n)
    t = np.arange(n) * TS
    z = np.zeros((n, 4))
    return LawContext(ctx.gains, TS, ctx.model, JointReference(t, z, z, z), None, nominal_mass_model(), Geometry())


@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("lead_m", [1, 2])
def test_iteration_maps_equal_dense_and_check_uses_structure(name: str, lead_m: int) -> None:
    spec = GainSpec(lead=lead_m)
    ctx = id_context(spec, SMALL)
    law = build_law(name, ctx)
    imap = law.iteration_map(ctx.model)
    kind, E = dense_map(name, ctx)
    assert imap.kind == kind
    x = np.random.default_rng(5).normal(size=(SMALL, 4))
    assert rel(imap.apply(x), (E @ x.reshape(-1)).reshape(SMALL, 4)) < 1e-9
    if imap.apply_t is not None:
        assert rel(imap.apply_t(x), (E.T @ x.reshape(-1)).reshape(SMALL, 4)) < 1e-9
    else:
        assert imap.symmetric and rel(E, E.T) < 1e-9
    # the restricted map and its spectral radius / 2-norm
    sl = slice(4, None) if kind == "error" else slice(None, -4)
    Er = E[sl, sl]
    rho_dense = float(np.max(np.abs(np.linalg.eigvals(Er))))
    norm_dense = float(np.linalg.norm(Er, 2))
    rep = law.check(ctx.model, None, iterations=12, inertia_scales=())
    causal = kind == "error" and lead_m <= 1 and not imap.symmetric
    assert (rep.rho_method == "exact") == causal
    if causal:
        # block lower triangular: the eigenvalues are those of the diagonal blocks (a dense
        # eigensolver is inaccurate on such a non-normal matrix, hence the blocks of the dense map)
        nb = Er.shape[0] // 4
        blocks = Er.reshape(nb, 4, nb, 4)
        assert all(np.all(blocks[i, :, i + 1 :, :] == 0) for i in range(nb))
        rho_dense = max(float(np.max(np.abs(np.linalg.eigvals(blocks[i, :, i, :])))) for i in range(nb))
        assert abs(rep.rho_max - rho_dense) < 1e-9 * rho_dense
    elif imap.symmetric:
        # Lanczos, KRYLOV_STEPS steps: a lower bound (the top eigenvalues cluster near 1)
        assert rho_dense * 0.99 < rep.rho_max <= rho_dense * (1 + 1e-9)
    else:
        # Arnoldi on a non-normal map: an estimate (so is the dense eigensolver's answer)
        assert abs(rep.rho_max - rho_dense) < 0.03 * rho_dense
    assert rep.norm2 <= norm_dense * (1 + 1e-9) and rep.norm2 > 0.98 * norm_dense  # power iteration: from below
    # the predicted error ratio = the dense map applied K times
    t = np.arange(SMALL)[:, None] * TS
    probe = np.sin(2 * np.pi * t / t[-1, 0] + np.arange(4)[None, :])
    G = dense_g(ctx.model.minv, ctx.model.kp, ctx.model.kd, TS)
    x = G @ probe.reshape(-1) if kind == "error" else probe.reshape(-1)
    e0 = np.linalg.norm(G @ x if kind == "input" else x)
    x12 = np.linalg.matrix_power(E, 12) @ x
    ratio = np.linalg.norm(G @ x12 if kind == "input" else x12) / e0
    assert abs(rep.predicted_ratio - ratio) <= 1e-9 * ratio + 1e-300


def test_prediction_cost_does_not_grow_with_the_trials() -> None:
    ctx = context(GAIN_PRESETS["normalized"], SMALL)
    law = build_law("pd-ol", ctx)
    calls = {"n": 0}
    imap = law.iteration_map(ctx.model)

    def counted(x: np.ndarray) -> np.ndarray:
        calls["n"] += 1
        return imap.apply(x)

    counting = chk.IterationMap(imap.kind, counted, imap.apply_t, imap.diagonal, imap.symmetric)
    counts = {}
    reports = {}
    for k in (chk.SIMULATED_TRIALS + 50, 100_000_000):
        calls["n"] = 0
        reports[k] = chk.check_iteration_map(counting, ctx.model, ctx.gains.ld, TS, None, k)
        counts[k] = calls["n"]
    assert counts[100_000_000] == counts[chk.SIMULATED_TRIALS + 50] <= chk.SIMULATED_TRIALS + 2 * chk.NORM_STEPS
    assert "extrapolated to 100000000" in reports[100_000_000].prediction


def test_check_long_run_verdict_flags_growth() -> None:
    # the literal paper's law (total torque) grows over a long run; its open-loop form does not
    ctx = context(GAIN_PRESETS["normalized"])
    pd = build_law("pd-ilc", ctx).check(None, None, 10)
    ol = build_law("pd-ol", ctx).check(None, None, 10)
    assert not pd.long_bounded and pd.predicted_long_growth > 1e3
    assert ol.long_bounded
    no = build_law("no-ilc", ctx).check(None, None, 10)
    assert no.long_bounded and no.norm2 < 1 and no.rho_method.startswith("lanczos")


# ------------------------------------------------------------------ the laws on a linear plant


def run_iterations(name: str, spec: GainSpec, iterations: int = 12, mismatch: float = 1.1):
    """ILC on the linear plant with a 10 % inertia error against the model used by the law."""
    ctx = id_context(spec, N)
    law = build_law(name, ctx)
    t = np.arange(N) * TS
    d = np.stack([3 * np.sin(2 * np.pi * 4 * t + p) for p in range(4)], axis=1)  # repetitive torque
    report = law.check(ctx.model, d, iterations)
    true = ClosedLoopModel(inertia_seq(mismatch), ctx.model.kp, ctx.model.kd, TS)
    e_free = true.g(d)
    u = np.zeros((N, 4))
    rms = []
    for _ in range(iterations):
        e = e_free + true.g(u)
        tau = u + true.k(e)
        rms.append(float(np.sqrt(np.mean(e**2))))
        u = law.update(trial(u, e, tau))
    return rms, report


@pytest.mark.parametrize("name", [n for n in LAWS if n != "no-ilc-id"])
def test_every_law_converges_or_is_flagged(name: str) -> None:
    rms, report = run_iterations(name, GAIN_PRESETS["normalized"])
    if report.ok:
        assert rms[-1] < 0.5 * rms[0], (name, rms)
    else:
        assert rms[-1] > rms[0], (name, rms)


def test_pd_ilc_update_is_the_papers_law() -> None:
    ctx = context(GAIN_PRESETS["normalized"], SMALL)
    rng = np.random.default_rng(6)
    u, e, tau = (rng.normal(size=(SMALL, 4)) for _ in range(3))
    g = ctx.gains
    term = np.zeros_like(e)
    term += g.lp * lead(e, 1)
    term += g.ld * lead(backward_difference(e, TS), 1)
    expected = tau + term  # bit for bit: the trace digest of a pd-ilc run depends on it
    np.testing.assert_array_equal(build_law("pd-ilc", ctx).update(trial(u, e, tau)), expected)
    robust = build_law("pd-ilc-q", ctx)
    q = ZeroPhaseFilter(g.spec.pdq_cutoff_hz, g.spec.q_order, TS)
    np.testing.assert_allclose(robust.update(trial(u, e, tau)), u + q(tau - u + expected - tau), rtol=1e-12)


def test_paper_literal_gains_are_flagged_and_diverge() -> None:
    rms, report = run_iterations("pd-ilc", GAIN_PRESETS["paper"], iterations=6)
    assert not report.ok and not report.long_bounded
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


def test_registry_and_errors() -> None:
    assert tuple(PROJECT_LAWS) == PROJECT_LAW_NAMES and DEFAULT_LAW in LAWS
    assert all(PROJECT_LAWS[n].name == n and PROJECT_LAWS[n].description for n in PROJECT_LAW_NAMES)
    assert all(issubclass(PROJECT_LAWS[n], BuiltinLaw) for n in LAWS)
    ctx = context(GainSpec(), SMALL)
    with pytest.raises(ValueError, match="unknown law 'x-ilc'"):
        build_law("x-ilc", ctx)
    with pytest.raises(ValueError, match="needs the reference"):
        build_law("no-ilc-id", ctx)
    with pytest.raises(ValueError, match="alpha must be a finite number"):
        resolve_gains(GainSpec(alpha=float("nan")), np.full(4, 0.1), TS)
    law = build_law("pd-ol", ctx)
    bad = np.full((SMALL, 4), np.nan)
    with pytest.raises(FloatingPointError, match="non-finite"):
        law.update(trial(bad, bad, bad))


# ------------------------------------------------------------------ the estimated model


def test_identification_recovers_the_true_parameters() -> None:
    from host.planning.joint_reference import joint_reference
    from host.planning.paths import resolve_path
    from host.planning.task_plan import plan_task
    from plant.params import Geometry, default_true_plant, nominal_mass_model

    ref = joint_reference(plan_task(resolve_path("1"), 0.25, "ruckig", TS))
    true = default_true_plant()
    est = DynamicsEstimate(nominal_mass_model(), Geometry(), TS)
    theta_true = np.concatenate(
        [
            [
                true.mass.m_up_eff,
                true.mass.m_low_eff,
                true.mass.joint_inertia(true.geometry.l_a),
                true.mass.arm_gravity_coefficient(true.geometry.l_a) / true.mass.g,
                true.mass.I_ee,
            ],
            true.coulomb_nm,
            true.viscous_nm_s_per_rad,
        ]
    )
    # torques consistent with what add_trial regresses on: ½(τ[n−1] + τ[n]) = Y(q_n, central differences) θ
    q = ref.q
    qd = (q[2:] - q[:-2]) / (2 * TS)
    qdd = (q[2:] - 2 * q[1:-1] + q[:-2]) / TS**2
    b = np.einsum("nji,i->nj", est.regressor(q[1:-1], qd, qdd), theta_true)
    tau = np.zeros_like(q)
    tau[0] = b[0]
    for n in range(1, len(q) - 1):
        tau[n] = 2 * b[n - 1] - tau[n - 1]
    est.add_trial(q, np.zeros_like(q), tau)
    assert len(PARAMETER_NAMES) == 13
    np.testing.assert_allclose(est.theta[:5], theta_true[:5], rtol=2e-3)
    assert est.residual_rms_nm < 1e-3
    M = est.mass_matrices(q[:5])
    assert M.shape == (5, 4, 4) and np.allclose(M, np.swapaxes(M, 1, 2))


# ------------------------------------------------------------------ the default law on the true plant


def _sim(**overrides) -> np.ndarray:
    """RMSE (K, 4) deg of an in-process run of the default experiment with ``overrides``."""
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.experiment.trial_loop import run_experiment
    from host.sim.inprocess import InProcessBench

    cfg = build_config(None, overrides)
    res = run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim")
    assert res.fault is None
    return np.array([m.rmse_deg for m in res.metrics])


@pytest.mark.parametrize("disturbance", ["none", "both"])
def test_default_law_is_bounded_over_200_trials_on_a_short_trial(disturbance: str) -> None:
    rmse = _sim(cycle_s=0.15, iterations=200, disturbance=disturbance).mean(axis=1)
    blocks = np.convolve(rmse, np.ones(20) / 20, mode="valid")
    assert blocks[-1] <= 2.0 * blocks.min(), (blocks[-1], blocks.min())
    assert blocks[-1] < 0.2 * rmse[0]  # learnt (with disturbance: down to its non-repeatable floor)


def test_default_law_settles_by_the_third_trial() -> None:
    from bus.units import DEG_PER_COUNT

    rmse = _sim()
    assert np.all(rmse[3] <= 2.0 * rmse[-1]), rmse
    assert np.all(rmse[-1] <= 5 * DEG_PER_COUNT), rmse[-1] / DEG_PER_COUNT


# ------------------------------------------------------------------ the rig's rehearsal of the first update


def test_the_rig_host_pays_the_laws_first_update_imports_before_the_run_and_leaves_the_law_as_it_was() -> None:
    """The rig's host process rehearses the law's first update on a copy (plan.rehearse_first_update,
    called by host.rig.host_role before it opens the bus): what the update imports on first use
    (here scipy.signal, for the identification's zero-phase filter) is imported before the nodes
    watch the host's heartbeat, and the plan's law gives the same first update as one that was not
    rehearsed. Planning alone (the launcher's preflight, the API's check) imports nothing of it."""
    import inspect
    import subprocess
    import sys

    from host.rig import host_role

    assert "rehearse_first_update(plan.law, plan.u0)" in inspect.getsource(host_role.run_host_role)
    code = """
import sys
import numpy as np
from host.experiment.config import build_config
from host.experiment.plan import prepare, rehearse_first_update
cfg = build_config(None, {"cycle_s": 0.15, "iterations": 2})
plain = prepare(cfg)
rig = prepare(cfg, rig=True)
print("planned", "scipy.signal" in sys.modules)
rehearse_first_update(rig.law, rig.u0)
print("rehearsed", "scipy.signal" in sys.modules)
rng = np.random.default_rng(5)
e = 1e-4 * rng.standard_normal(plain.u0.shape)
tau = plain.u0 + rng.standard_normal(plain.u0.shape)
from host.learning.protocol import TrialData
def t(u, k):
    return TrialData(k, u, e * k, tau, tau - u, cfg.ts_s)
same = all(np.array_equal(plain.law.update(t(plain.u0, k)), rig.law.update(t(rig.u0, k))) for k in (1, 2, 3))
print("same", same)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True).stdout.split()
    assert out == ["planned", "False", "rehearsed", "True", "same", "True"]
