"""Iterative learning laws, their gains, and the convergence check run before an experiment.

Sign convention (one for the whole project)
-------------------------------------------
``e = q_d − q`` (rad) and ``ė`` its backward difference ``(e[n] − e[n−1])/Ts`` (rad/s).
The drive's feedback is ``τ_fb = Kp·e + Kd·ė`` (negative feedback for Kp, Kd > 0) and every
learning term *adds* ``L·e`` to the next feed-forward (error positive = the joint lags = push more).

Mapping to the paper (Li et al. 2022, eqs. 8–10, which write ``e = q − q_d``): its feedback
``(1−α)Lp·e + (1−β)Ld·ė`` is, in our convention, ``Kp = (α−1)Lp``, ``Kd = (β−1)Ld`` — taken as
printed. Its learning term ``Lp·e_k + Ld·ė_k`` has the wrong sign with ``e = q − q_d`` (it would
push a lagging joint back); we use it with ``e = q_d − q``. So "the paper's law" here is::

    u_{k+1}[n] = τ_k[n] + Lp·e_k[n+1] + Ld·(e_k[n+1] − e_k[n])/Ts        (law "pd-ilc")
    τ_{k+1}[n] = u_{k+1}[n] + (α−1)Lp·e_{k+1}[n] + (β−1)Ld·ė_{k+1}[n]     (in the drive)

where ``τ_k`` is the *total* torque the drive applied in trial k (feed-forward + feedback, read
back from its recorder) and the learning term uses a one-sample lead (the torque at tick n first
shows in the encoder at tick n+1). Because τ_k contains the feedback, the effective learning gains
are ``Lp + Kp`` and ``Ld + Kd``: at low frequency the iteration factor is ≈ −L/K = −1/(α−1), so the
total-torque form needs α, β > 2 to converge. The paper's literal α = 1.1, β = 1.22 give a factor
≈ 10 and diverge on this plant (preset ``paper``); the default preset uses α = β = 3.

The other form, which accumulates only the feed-forward (``u_{k+1} = u_k + L e_k``), is the
open-loop PD-type law ``pd-ol``; with the same Kp, Kd it is shown beside the paper's law.

Laws: ``pd-ilc`` (paper, total torque), ``pd-ol`` (open-loop PD-type = paper's law accumulating
feed-forward only), ``p-ol`` (open-loop P-type), ``d-ilc`` (classical Arimoto D-type, the paper's
baseline: ``u_{k+1} = u_k + Ld·ė_k`` with lead), ``q-ilc`` (robust: zero-phase low-pass Q filter
plus a learning lead of m samples), ``no-ilc`` (norm-optimal on the lifted model linearised along
the trajectory).

Gains are normalised to the plant: ``lp_norm = Lp·Ts²/I_j`` and ``ld_norm = Ld·Ts/I_j`` with I_j the
mean nominal joint inertia along the trajectory, so one preset fits every joint and sample time.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import signal, sparse

logger = logging.getLogger(__name__)

__all__ = [
    "LAWS",
    "GAIN_PRESETS",
    "GainSpec",
    "Gains",
    "LearningLaw",
    "LiftedModel",
    "ConvergenceReport",
    "make_law",
    "resolve_gains",
    "backward_difference",
    "lead",
]

from host.learning.names import LAWS  # noqa: E402  (one list for CLI and laws)


@dataclass(frozen=True)
class GainSpec:
    """Gains as the user gives them: α, β and learning gains, absolute or normalised.

    Exactly one of (lp, lp_norm) and one of (ld, ld_norm) is used: absolute values (N·m/rad,
    N·m·s/rad, the same for every joint) win when given.
    """

    alpha: float = 3.0
    beta: float = 3.0
    lp_norm: float = 0.001
    ld_norm: float = 0.15
    lp: float | None = None
    ld: float | None = None
    lead: int = 1
    q_cutoff_hz: float = 150.0
    q_order: int = 2
    no_weight: float = 1e-9
    name: str = "normalized"


#: named gain presets; ``paper`` are the paper's literal numbers (which do not transfer here)
GAIN_PRESETS: dict[str, GainSpec] = {
    "normalized": GainSpec(),
    "paper": GainSpec(alpha=1.1, beta=1.22, lp=1000.0, ld=230.0, name="paper"),
}


@dataclass(frozen=True)
class Gains:
    """Per-joint gains in SI units after normalisation."""

    kp: np.ndarray  # feedback, N·m/rad
    kd: np.ndarray  # feedback, N·m·s/rad
    lp: np.ndarray  # learning, N·m/rad
    ld: np.ndarray  # learning, N·m·s/rad
    inertia: np.ndarray  # mean nominal joint inertia, kg·m²
    spec: GainSpec = field(default_factory=GainSpec)

    def as_dict(self) -> dict:
        return {
            "preset": self.spec.name,
            "alpha": self.spec.alpha,
            "beta": self.spec.beta,
            "lead": self.spec.lead,
            "kp_nm_per_rad": self.kp.tolist(),
            "kd_nms_per_rad": self.kd.tolist(),
            "lp_nm_per_rad": self.lp.tolist(),
            "ld_nms_per_rad": self.ld.tolist(),
            "inertia_kgm2": self.inertia.tolist(),
        }


def resolve_gains(spec: GainSpec, inertia: np.ndarray, ts_s: float) -> Gains:
    """Turn a :class:`GainSpec` into per-joint gains for joint inertias ``inertia`` (kg·m²)."""
    inertia = np.asarray(inertia, dtype=float)
    for name in ("alpha", "beta", "lp_norm", "ld_norm", "q_cutoff_hz", "no_weight"):
        v = getattr(spec, name)
        if not math.isfinite(v):
            raise ValueError(f"gain {name} must be a finite number, got {v}")
    for name in ("lp", "ld"):
        v = getattr(spec, name)
        if v is not None and (not math.isfinite(v) or v < 0):
            raise ValueError(f"gain {name} must be a finite number >= 0, got {v}")
    if spec.alpha < 1 or spec.beta < 1:
        raise ValueError(f"alpha and beta must be >= 1 (feedback (alpha-1)Lp must be >= 0), got {spec.alpha}, {spec.beta}")
    if spec.lead < 0:
        raise ValueError(f"lead must be >= 0 samples, got {spec.lead}")
    lp = np.full(4, spec.lp) if spec.lp is not None else spec.lp_norm * inertia / ts_s**2
    ld = np.full(4, spec.ld) if spec.ld is not None else spec.ld_norm * inertia / ts_s
    return Gains(kp=(spec.alpha - 1.0) * lp, kd=(spec.beta - 1.0) * ld, lp=lp, ld=ld,
                 inertia=inertia, spec=spec)


def backward_difference(x: np.ndarray, ts_s: float) -> np.ndarray:
    """(x[n] − x[n−1])/Ts along axis 0, with 0 at n = 0 (the trial starts aligned)."""
    d = np.zeros_like(x, dtype=float)
    d[1:] = (x[1:] - x[:-1]) / ts_s
    return d


def lead(x: np.ndarray, m: int) -> np.ndarray:
    """Non-causal shift by m samples along axis 0: y[n] = x[n+m], the last value repeated."""
    if m == 0:
        return np.array(x, dtype=float, copy=True)
    return np.concatenate([x[m:], np.repeat(x[-1:], m, axis=0)], axis=0)


# --------------------------------------------------------------------------------------------
# lifted (time-major) model of the closed loop, linearised along the reference
# --------------------------------------------------------------------------------------------


class LiftedModel:
    """Lifted map from feed-forward u to error e = q_d − q around the reference.

    Model: nominal inertia M(q_d(t_n)) at each sample (Coriolis, gravity and friction
    Jacobians neglected), zero-order hold over Ts, the drive's PD loop with the velocity from
    the backward difference of the position.  Vectors are time-major: index n·J + j.

    ``G`` (NJ × NJ) maps δu to δe; ``K`` maps e to the drive's feedback torque τ_fb.
    """

    def __init__(self, inertia_seq: np.ndarray, kp: np.ndarray, kd: np.ndarray, ts_s: float) -> None:
        m = np.asarray(inertia_seq, dtype=float)
        self.n, self.j = m.shape[0], m.shape[1]
        self.ts_s = ts_s
        self.kp = np.asarray(kp, dtype=float)
        self.kd = np.asarray(kd, dtype=float)
        self.minv = np.linalg.inv(m)
        self.G = self._build_g()
        self.K = self._build_k()

    def _build_g(self) -> np.ndarray:
        n, j, ts = self.n, self.j, self.ts_s
        kp, kd = np.diag(self.kp), np.diag(self.kd)
        eye = np.eye(j)
        ns = 3 * j  # state (δq, δq̇, δq_prev)
        G = np.zeros((n * j, n * j))
        S = np.zeros((n, ns, j))  # S[i_in]: current state response to a unit input at i_in
        for i in range(n):
            if i > 0:
                # e = −δq; block row i, block columns 0..i−1
                G[i * j:(i + 1) * j, : i * j] = -S[:i, :j, :].transpose(1, 0, 2).reshape(j, i * j)
            mi = self.minv[i]
            # τ = δu − Kp δq − Kd (δq − δq_prev)/Ts
            ftau = np.hstack([-(kp + kd / ts), np.zeros((j, j)), kd / ts])  # τ from state
            A = np.zeros((ns, ns))
            A[:j, :j] = eye
            A[:j, j:2 * j] = ts * eye
            A[:j] += 0.5 * ts * ts * mi @ ftau
            A[j:2 * j, j:2 * j] = eye
            A[j:2 * j] += ts * mi @ ftau
            A[2 * j:, :j] = eye
            B = np.vstack([0.5 * ts * ts * mi, ts * mi, np.zeros((j, j))])
            if i > 0:
                S[:i] = np.matmul(A, S[:i])
            S[i] = B
        return G

    def _build_k(self) -> sparse.csr_matrix:
        """τ_fb[n] = Kp e[n] + Kd (e[n] − e[n−1])/Ts as a (sparse) lifted matrix; at n = 0 the
        difference is 0 (the trial starts aligned)."""
        ts = self.ts_s
        return sparse.kron(sparse.identity(self.n), sparse.diags(self.kp), format="csr") + \
            sparse.kron(sparse.csr_matrix(backward_difference(np.eye(self.n), ts)), sparse.diags(self.kd), format="csr")

    # time-operator helpers: apply an (N×N) time operator to every joint
    def per_joint(self, t_op: np.ndarray) -> np.ndarray:
        return np.kron(t_op, np.eye(self.j))


def _time_ops(n: int, ts_s: float, m: int) -> tuple[sparse.csr_matrix, sparse.csr_matrix]:
    """(lead_m, lead_m ∘ backward-difference) as sparse N×N matrices (the same edge rules as
    the array functions above)."""
    eye = np.eye(n)
    return sparse.csr_matrix(lead(eye, m)), sparse.csr_matrix(lead(backward_difference(eye, ts_s), m))


@dataclass(frozen=True)
class ConvergenceReport:
    """Convergence check of a law along the trajectory (before the run)."""

    rho_max: float  # spectral radius of the lifted iteration map
    norm2: float  # its 2-norm: < 1 means monotonic convergence (in the 2-norm)
    paper_rho18: float  # eq. (18) with C·B = Ts·M⁻¹(q_d(t)), max over the trajectory
    ok: bool
    map_kind: str  # "error" (e_{k+1} = E e_k) or "input" (u_{k+1} = E u_k)
    predicted_ratio: float = 0.0  # ‖e_K‖/‖e_0‖ predicted by the linearised model
    predicted_peak: float = 0.0  # max_k ‖e_k‖/‖e_0‖ on the way
    iterations: int = 0
    long_horizon: int = 0  # a longer horizon, to warn about slow divergence beyond the run
    rho_method: str = "exact"
    predicted_ratio_long: float = 0.0

    def as_dict(self) -> dict:
        return {
            "rho_max": self.rho_max,
            "ok": self.ok,
            "norm2": self.norm2,
            "monotonic": self.norm2 < 1.0,
            "paper_condition_18_rho": self.paper_rho18,
            "map": self.map_kind,
            "predicted_error_ratio": self.predicted_ratio,
            "predicted_error_peak": self.predicted_peak,
            "predicted_over_iterations": self.iterations,
            "predicted_error_ratio_long": self.predicted_ratio_long,
            "long_horizon": self.long_horizon,
            "rho_method": self.rho_method,
        }


def _spectral_radius(E: np.ndarray, j: int) -> tuple[float, str]:
    """Spectral radius and how it was obtained: exact from the diagonal blocks when E is block
    lower triangular (lead ≤ 1, no Q filter), else ARPACK (bounded), else an estimate."""
    n = E.shape[0] // j
    blocks = E.reshape(n, j, n, j)
    upper = 0.0
    for i in range(n - 1):
        upper = max(upper, float(np.max(np.abs(blocks[i, :, i + 1:, :]))))
        if upper > 0.0:
            break
    if upper == 0.0:
        return float(max(np.max(np.abs(np.linalg.eigvals(blocks[i, :, i, :]))) for i in range(n))), "exact"
    from scipy.sparse.linalg import ArpackNoConvergence, eigs

    try:  # bounded: ARPACK can take minutes when the eigenvalues cluster near the unit circle
        vals = eigs(E, k=1, which="LM", return_eigenvectors=False, tol=1e-6, maxiter=15)
        return float(np.max(np.abs(vals))), "arpack"
    except ArpackNoConvergence:
        logger.info("ARPACK did not converge: spectral radius estimated by power iteration")
    # Gelfand: rho = lim ||E^k v||^(1/k); 200 steps from a fixed start (an estimate)
    v = np.random.default_rng(0).standard_normal(E.shape[0])
    v /= np.linalg.norm(v)
    log_growth = 0.0
    steps = 200
    for _ in range(steps):
        v = E @ v
        nv = np.linalg.norm(v)
        if nv == 0.0:
            return 0.0, "power-iteration"
        log_growth += np.log(nv)
        v /= nv
    return float(np.exp(log_growth / steps)), "power-iteration estimate (an upper-side estimate)"


def _norm2(E: np.ndarray, iterations: int = 60) -> float:
    """Largest singular value by power iteration on EᵀE from a fixed start (a lower bound that
    is tight after a few dozen steps; ARPACK needs minutes when the top values cluster near 1)."""
    v = np.random.default_rng(0).standard_normal(E.shape[1])
    v /= np.linalg.norm(v)
    sigma = 0.0
    for _ in range(iterations):
        w = E.T @ (E @ v)
        nw = np.linalg.norm(w)
        if nw == 0.0:
            return 0.0
        sigma_new = float(np.sqrt(nw))
        v = w / nw
        if abs(sigma_new - sigma) < 1e-6 * sigma_new:
            return sigma_new
        sigma = sigma_new
    return sigma


# --------------------------------------------------------------------------------------------
# laws
# --------------------------------------------------------------------------------------------


@dataclass
class LearningLaw:
    """One learning law: ``update(u_k, e_k, tau_k) -> u_{k+1}`` on (N, J) arrays (N·m, rad)."""

    name: str
    gains: Gains
    ts_s: float
    _update: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] = field(repr=False, default=None)  # type: ignore[assignment]
    _lifted: Callable[[LiftedModel], tuple[str, np.ndarray]] = field(repr=False, default=None)  # type: ignore[assignment]
    needs_model: bool = False

    def update(self, u_k: np.ndarray, e_k: np.ndarray, tau_k: np.ndarray) -> np.ndarray:
        """Next feed-forward table.

        :param u_k: (N, J) feed-forward applied in trial k, N·m
        :param e_k: (N, J) error q_d − q measured in trial k, rad
        :param tau_k: (N, J) total torque applied in trial k (feed-forward + feedback), N·m
        """
        out = self._update(u_k, e_k, tau_k)
        if not np.all(np.isfinite(out)):
            raise FloatingPointError(f"law {self.name} produced a non-finite feed-forward")
        return out

    #: trials of the long-horizon prediction (slow divergence beyond a short run)
    LONG_HORIZON = 40

    def check(self, model: LiftedModel, probe_torque: np.ndarray | None = None,
              iterations: int = 10) -> ConvergenceReport:
        """Check the lifted iteration map before a run.

        * ``rho_max``: spectral radius (< 1: converges eventually — for a block lower-triangular
          map this only looks at the diagonal and says nothing about the transient);
        * ``norm2``: < 1 means monotonic convergence in the 2-norm;
        * ``predicted_ratio``: ‖e_K‖/‖e_0‖ after ``iterations`` trials of the linearised model,
          starting from the error that ``probe_torque`` (N, J) — e.g. a 10 % error of the
          nominal torque — causes, and ``predicted_peak`` the largest ‖e_k‖/‖e_0‖ on the way;
        * ``paper_rho18``: the paper's condition (18), with C·B = Ts·M⁻¹(q_d(t)).

        ``ok`` = rho_max < 1 and the predicted error after the planned trials is smaller than
        the initial one.
        """
        kind, E = self._lifted(model)
        j = model.j
        if probe_torque is None:
            t = np.arange(model.n)[:, None] * self.ts_s
            probe_torque = np.sin(2 * np.pi * t / max(t[-1, 0], self.ts_s) + np.arange(j)[None, :])
        probe = np.asarray(probe_torque, dtype=float).reshape(-1)
        horizon = max(iterations, self.LONG_HORIZON)
        if kind == "error":
            x = model.G @ probe
            e0 = np.linalg.norm(x)
            norms = []
            for _ in range(horizon):
                x = E @ x
                norms.append(np.linalg.norm(x))
        else:  # input map on u; error = G (u − u*) with u* = −probe (the ideal feed-forward)
            x = probe.copy()
            e0 = np.linalg.norm(model.G @ x)
            norms = []
            for _ in range(horizon):
                x = E @ x
                norms.append(np.linalg.norm(model.G @ x))
        all_ratios = np.array(norms) / e0 if e0 > 0 else np.zeros(horizon)
        ratios = all_ratios[:iterations]
        # e[0] is fixed by the aligned start and u[N−1] reaches no recorded sample (relative
        # degree one): rho and the norm are taken on the samples learning can act on.
        E = E[j:, j:] if kind == "error" else E[:-j, :-j]
        rho, rho_method = _spectral_radius(E, j)
        nrm = _norm2(E)
        ld = np.diag(self.gains.ld)
        r18 = 0.0
        eye = np.eye(j)
        for mi in model.minv:
            cb = self.ts_s * mi
            S = np.linalg.solve(eye + ld @ cb, eye - ld @ cb)
            r18 = max(r18, float(np.max(np.abs(np.linalg.eigvals(S)))))
        ratio = float(ratios[-1]) if len(ratios) else 0.0
        return ConvergenceReport(rho_max=rho, norm2=nrm, paper_rho18=r18,
                                 ok=bool(rho < 1.0 and ratio < 1.0), map_kind=kind,
                                 predicted_ratio=ratio, predicted_peak=float(np.max(ratios, initial=0.0)),
                                 iterations=iterations, long_horizon=horizon, rho_method=rho_method,
                                 predicted_ratio_long=float(all_ratios[-1]) if len(all_ratios) else 0.0)


def make_law(name: str, gains: Gains, ts_s: float, model: LiftedModel | None = None) -> LearningLaw:
    """Build a law by name (see :data:`LAWS`). ``no-ilc`` needs the lifted ``model``."""
    if name not in LAWS:
        raise ValueError(f"unknown law {name!r}; choose one of {', '.join(LAWS)}")
    g, m, ts = gains, gains.spec.lead, ts_s
    lp, ld = g.lp, g.ld

    def pd_term(e: np.ndarray, use_p: bool = True, use_d: bool = True) -> np.ndarray:
        out = np.zeros_like(e)
        if use_p:
            out += lp * lead(e, m)
        if use_d:
            out += ld * lead(backward_difference(e, ts), m)
        return out

    def lifted_l(model_: LiftedModel, use_p: bool = True, use_d: bool = True) -> sparse.csr_matrix:
        lead_m, dlead = _time_ops(model_.n, ts, m)
        L = sparse.csr_matrix((model_.n * model_.j,) * 2)
        if use_p:
            L = L + sparse.kron(lead_m, sparse.diags(lp), format="csr")
        if use_d:
            L = L + sparse.kron(dlead, sparse.diags(ld), format="csr")
        return L

    eye_of = lambda mdl: np.eye(mdl.n * mdl.j)  # noqa: E731

    def g_times(mdl: LiftedModel, S: sparse.csr_matrix) -> np.ndarray:
        """G @ S for a sparse S, computed as (Sᵀ Gᵀ)ᵀ (sparse × dense)."""
        return np.asarray((S.T @ mdl.G.T).T)

    if name == "pd-ilc":
        upd = lambda u, e, tau: tau + pd_term(e)  # noqa: E731
        lif = lambda mdl: ("error", eye_of(mdl) + g_times(mdl, mdl.K + lifted_l(mdl)))  # noqa: E731
    elif name in ("pd-ol", "p-ol", "d-ilc"):
        use_p, use_d = name != "d-ilc", name != "p-ol"
        upd = lambda u, e, tau: u + pd_term(e, use_p, use_d)  # noqa: E731
        lif = lambda mdl: ("error", eye_of(mdl) + g_times(mdl, lifted_l(mdl, use_p, use_d)))  # noqa: E731
    elif name == "q-ilc":
        fc = gains.spec.q_cutoff_hz
        nyq = 0.5 / ts
        if not 0 < fc < nyq:
            raise ValueError(f"q_cutoff_hz must be in (0, {nyq:g}) Hz, got {fc}")
        b, a = signal.butter(gains.spec.q_order, fc / nyq)

        def qf(x: np.ndarray) -> np.ndarray:
            return signal.filtfilt(b, a, x, axis=0, padtype="odd", padlen=min(3 * max(len(a), len(b)), x.shape[0] - 1))

        upd = lambda u, e, tau: qf(u + pd_term(e))  # noqa: E731

        def lif(mdl: LiftedModel) -> tuple[str, np.ndarray]:
            Qt = qf(np.eye(mdl.n))
            inner = eye_of(mdl) + np.asarray(lifted_l(mdl) @ mdl.G)
            # kron(Qt, I_J) @ inner, without forming the Kronecker product
            nj = mdl.n * mdl.j
            return "input", np.einsum("ab,bjc->ajc", Qt, inner.reshape(mdl.n, mdl.j, nj)).reshape(nj, nj)
    else:  # no-ilc
        if model is None:
            raise ValueError("law no-ilc needs the lifted model")
        G = model.G
        w = gains.spec.no_weight
        # scale-aware regularisation: w relative to the largest squared gain of G
        scale = float(np.max(np.sum(G * G, axis=0)))
        Lno = -np.linalg.solve(G.T @ G + w * scale * np.eye(G.shape[0]) + 1e-300, G.T)
        def upd(u: np.ndarray, e: np.ndarray, tau: np.ndarray) -> np.ndarray:
            return u + (Lno @ e.reshape(-1)).reshape(e.shape)

        lif = lambda mdl: ("error", eye_of(mdl) + mdl.G @ Lno)  # noqa: E731

    return LearningLaw(name=name, gains=gains, ts_s=ts, _update=upd, _lifted=lif, needs_model=name == "no-ilc")
