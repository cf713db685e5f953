"""The convergence check run before an experiment, matrix-free and O(N).

This module owns :class:`IterationMap` (a law's trial-to-trial map as operators, from
the laws of :mod:`host.learning.laws`), :func:`check_iteration_map` and its result :class:`ConvergenceReport`.

A law is linearised into its iteration map on the closed-loop model of :mod:`host.learning.model`:
``error`` maps e_{k+1} = E e_k (laws that add a correction to the feed-forward) or ``input`` maps
x_{k+1} = E x_k with e = G x (Q-filtered laws: x is the feed-forward's distance from the law's fixed
point).  E is never formed; the check uses only products E v, Eᵀ v (each O(N)) and, when E is block
lower triangular (a causal map: lead ≤ 1 and no Q filter), its 4 × 4 diagonal blocks.  What is
computed:

* ``rho_max`` — the spectral radius on the samples learning can act on (for an error map the first
  sample, fixed by the aligned start, is removed; for an input map the last input sample, which
  reaches no recorded sample).  Causal map: exactly, the largest eigenvalue modulus of the diagonal
  blocks (``rho_method`` = ``exact``).  Otherwise the largest Ritz value after :data:`KRYLOV_STEPS`
  Krylov steps from a fixed start: Lanczos for a symmetric map (norm-optimal; a lower bound, tight
  at the ends of the spectrum), Arnoldi otherwise (Q-filtered laws; an estimate).
* ``norm2`` — the largest singular value: for a symmetric positive semi-definite map it equals ρ;
  otherwise :data:`NORM_STEPS` steps of power iteration on EᵀE from a fixed start (a lower bound,
  tight after a few dozen steps).  < 1: monotonic convergence in the 2-norm.
* ``predicted_ratio`` / ``predicted_peak`` — ‖e_K‖/‖e_0‖ after the planned K trials and the largest
  ratio on the way, for the error e_0 that the probe torque causes.  The linear model is simulated
  exactly for k ≤ :data:`SIMULATED_TRIALS` trials (one E v per trial); beyond, the ratio is
  extrapolated geometrically with the mean rate of the last :data:`EXTRAPOLATION_WINDOW` simulated
  trials.  So the cost is at most SIMULATED_TRIALS products, whatever K is.
* ``long_bounded`` / ``predicted_long_growth`` — the long-run verdict over :data:`LONG_HORIZON`
  trials: the mean predicted RMSE of the last :data:`BOUNDED_BLOCK` trials at most
  :data:`BOUNDED_LIMIT` × the best block mean (the growth part of the runs' criterion,
  ``host.analysis.convergence_verdicts``), with every predicted RMSE floored at one encoder LSB
  (what a run can resolve; a mode growing from far below it stays invisible over the horizon).
  The verdict is the worst over the model and the plants with the inertia scaled by
  :data:`ROBUST_INERTIA_SCALES` (the law's own operators fixed): a law that only converges on
  exactly the nominal inertia is not called bounded (``long_worst_case`` names the plant).
* ``paper_rho18`` — the paper's condition (18), max over t of ρ([I + L_d C B]⁻¹ [I − L_d C B]) with
  C·B = Ts·M⁻¹(q_d(t)).

``ok`` = rho_max < 1 and predicted_ratio < 1.  These are predictions of the linearised nominal
model; the true plant (friction, model errors, disturbances, torque limit) is what a run measures.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from bus import units
from host.learning.model import ClosedLoopModel

logger = logging.getLogger(__name__)

__all__ = [
    "ConvergenceReport",
    "IterationMap",
    "check_iteration_map",
    "not_checked",
    "LONG_HORIZON",
    "SIMULATED_TRIALS",
    "EXTRAPOLATION_WINDOW",
    "BOUNDED_BLOCK",
    "BOUNDED_LIMIT",
    "NORM_STEPS",
    "KRYLOV_STEPS",
    "PROBE_TORQUE_FRACTION",
    "ROBUST_INERTIA_SCALES",
]

Array = npt.NDArray[np.float64]


@njit(cache=True)
def _sumsq(x: Array) -> float:
    acc = 0.0
    for v in x:
        acc += v * v
    return acc


def _norm(x: Array) -> float:
    """‖x‖₂ of an array of any shape.  A single-threaded kernel: the BLAS level-1 routines behind
    np.linalg.norm / np.vdot start threads that, on a busy machine, cost more than the sum."""
    return math.sqrt(_sumsq(np.ascontiguousarray(x).reshape(-1)))


@njit(cache=True)
def _orthogonalise(basis: Array, k: int, w: Array, h: Array) -> None:
    """w −= Σ_{i≤k} (basis_i·w) basis_i (classical Gram-Schmidt), h[i] += basis_i·w."""
    size = w.shape[0]
    coef = np.zeros(k + 1)
    for i in range(k + 1):
        acc = 0.0
        for c in range(size):
            acc += basis[i, c] * w[c]
        coef[i] = acc
        h[i] += acc
    for i in range(k + 1):
        ci = coef[i]
        for c in range(size):
            w[c] -= ci * basis[i, c]


#: trials of the long-run prediction (the horizon of ``ilcrig reproduce``'s long runs)
LONG_HORIZON = 200
#: the linear model is simulated exactly for this many trials; beyond, extrapolated
SIMULATED_TRIALS = 200
#: trials whose mean rate extrapolates beyond the simulated ones
EXTRAPOLATION_WINDOW = 20
#: long-run criterion: last block mean ≤ BOUNDED_LIMIT × best block mean (blocks of trials)
BOUNDED_BLOCK = 20
BOUNDED_LIMIT = 2.0
#: power-iteration steps of the 2-norm (on EᵀE)
NORM_STEPS = 60
#: Krylov (Arnoldi / Lanczos) steps of the spectral radius of a non-causal map
KRYLOV_STEPS = 40
#: the experiment's probe: this fraction of the nominal inverse-dynamics torque (a model error)
PROBE_TORQUE_FRACTION = 0.1
#: the long-run verdict also holds the law against plants with the nominal inertia scaled by these
#: factors.  The nominal model is the light end of what the robot can be (no payload, no tool spin
#: inertia, the lighter forearm lumping ρ = 1/2: the emulated robot has 1.7–2.0× the nominal joint
#: inertia), so the check looks at a plant twice as heavy; lighter plants are not checked (against
#: half the nominal inertia the inverting laws no-ilc, no-ilc-id and pd-ol, d-ilc would not be bounded)
ROBUST_INERTIA_SCALES: tuple[float, ...] = (2.0,)


@dataclass(frozen=True)
class IterationMap:
    """A law's trial-to-trial map E as operators on (N, J) arrays.

    ``kind`` ``error``: e_{k+1} = E e_k; ``input``: x_{k+1} = E x_k with the error e = G x.
    ``apply_t`` is Eᵀ (None: not available, no 2-norm); ``diagonal`` gives the (N − 1, J, J) diagonal
    blocks of the restricted map when E is block lower triangular; ``symmetric`` marks a symmetric
    positive semi-definite E (norm-optimal laws)."""

    kind: str
    apply: Callable[[Array], Array]
    apply_t: Callable[[Array], Array] | None = None
    diagonal: Callable[[], Array] | None = None
    symmetric: bool = False


@dataclass(frozen=True)
class ConvergenceReport:
    """Convergence check of a law along the trajectory (before the run); see the module docstring."""

    rho_max: float
    norm2: float
    paper_rho18: float
    ok: bool
    map_kind: str
    predicted_ratio: float = 0.0
    predicted_peak: float = 0.0
    iterations: int = 0
    long_horizon: int = 0
    rho_method: str = "exact"
    predicted_ratio_long: float = 0.0
    long_bounded: bool = True
    predicted_long_growth: float = 1.0
    long_worst_case: str = "nominal"
    norm_method: str = "power iteration (lower bound)"
    prediction: str = ""
    #: False: the law gives no linear iteration map, nothing was checked (:func:`not_checked`)
    checked: bool = True

    def as_dict(self) -> dict[str, Any]:
        if not self.checked:
            return {
                "checked": False,
                "ok": None,
                "rho_max": None,
                "norm2": None,
                "paper_condition_18_rho": self.paper_rho18,
                "map": self.map_kind,
                "prediction": self.prediction,
            }
        return {
            "checked": True,
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
            "long_bounded": self.long_bounded,
            "predicted_long_growth": self.predicted_long_growth,
            "long_worst_case": self.long_worst_case,
            "rho_method": self.rho_method,
            "norm_method": self.norm_method,
            "prediction": self.prediction,
        }


# --------------------------------------------------------------------------------- the pieces


class _Restricted:
    """E on the samples learning can act on: zero the first (error map) or last (input map) sample
    of the argument and of the result."""

    def __init__(self, imap: IterationMap, n: int, j: int) -> None:
        self.imap, self.n, self.j = imap, n, j
        self.idx = 0 if imap.kind == "error" else n - 1

    def _cut(self, x: Array) -> Array:
        x = x.reshape(self.n, self.j).copy()
        x[self.idx] = 0.0
        return x

    def mv(self, v: Array) -> Array:
        return self._cut(self.imap.apply(self._cut(v))).reshape(-1)

    def rmv(self, v: Array) -> Array:
        assert self.imap.apply_t is not None
        return self._cut(self.imap.apply_t(self._cut(v))).reshape(-1)

    def start(self) -> Array:
        v = self._cut(np.random.default_rng(0).standard_normal(self.n * self.j)).reshape(-1)
        return v / _norm(v)


def _krylov_rho(r: _Restricted, symmetric: bool) -> tuple[float, str]:
    """Largest Ritz value modulus after KRYLOV_STEPS Arnoldi (Lanczos when symmetric) steps with
    full re-orthogonalisation, from a fixed start.  For a symmetric map it is a lower bound that
    converges fast at the ends of the spectrum; otherwise an estimate."""
    size = r.n * r.j
    m = max(1, min(KRYLOV_STEPS, size - 1))
    basis = np.zeros((m + 1, size))
    hess = np.zeros((m + 1, m))
    basis[0] = r.start()
    steps = m
    for k in range(m):
        w = r.mv(basis[k])
        scale = _norm(w)
        w = np.array(w, dtype=float, copy=True)
        col = np.zeros(k + 1)
        for _ in range(2):  # classical Gram-Schmidt, twice
            _orthogonalise(basis, k, w, col)
        hess[: k + 1, k] = col
        hn = _norm(w)
        hess[k + 1, k] = hn
        if hn <= 1e-12 * max(scale, 1e-300):  # an invariant subspace: the Ritz values are exact
            steps = k + 1
            break
        basis[k + 1] = w / hn
    h = hess[:steps, :steps]
    if symmetric:
        vals = np.linalg.eigvalsh(0.5 * (h + h.T))
        return float(np.max(np.abs(vals))), f"lanczos ({steps} steps)"
    return float(np.max(np.abs(np.linalg.eigvals(h)))), f"arnoldi ({steps} steps)"


def _spectral_radius(imap: IterationMap, r: _Restricted) -> tuple[float, str]:
    if imap.diagonal is not None:
        blocks = imap.diagonal()
        if blocks.size == 0:
            return 0.0, "exact"
        return float(np.max(np.abs(np.linalg.eigvals(blocks)))), "exact"
    return _krylov_rho(r, imap.symmetric)


def _norm2(imap: IterationMap, r: _Restricted, rho: float) -> tuple[float, str]:
    if imap.symmetric:
        return rho, "= spectral radius (symmetric map)"
    if imap.apply_t is None:
        return float("nan"), "not available"
    v = r.start()
    sigma = 0.0
    for _ in range(NORM_STEPS):
        w = r.rmv(r.mv(v))
        nw = _norm(w)
        if nw == 0.0:
            return 0.0, "power iteration"
        sigma_new = math.sqrt(nw)
        v = w / nw
        if abs(sigma_new - sigma) < 1e-6 * sigma_new:
            return sigma_new, "power iteration"
        sigma = sigma_new
    return sigma, "power iteration (lower bound)"


def _paper_rho18(model: ClosedLoopModel, ld: Array, ts_s: float) -> float:
    """max over samples of ρ([I + Ld C B]⁻¹[I − Ld C B]) with C·B = Ts·M⁻¹."""
    eye = np.eye(model.j)
    ldcb = np.diag(ld)[None] @ (ts_s * model.minv)
    s = np.linalg.solve(eye + ldcb, eye - ldcb)
    return float(np.max(np.abs(np.linalg.eigvals(s))))


def _predict(imap: IterationMap, model: ClosedLoopModel, probe: Array, horizon: int) -> tuple[Array, float]:
    """log‖e_k‖ for k = 0..horizon of the linear model from the probe, and log‖e_0‖'s RMS offset.

    Works with the normalised vector and accumulates the logarithm of its norm, so divergent laws
    do not overflow."""
    x = model.g(probe) if imap.kind == "error" else probe.copy()
    logs = np.full(horizon + 1, -np.inf)

    def err_norm(v: Array) -> float:
        return _norm(v if imap.kind == "error" else model.g(v))

    e0 = err_norm(x)
    if e0 == 0.0:
        return logs, 0.0
    scale = _norm(x)
    x = x / scale
    log_scale = math.log(scale)
    logs[0] = math.log(e0)
    for k in range(1, horizon + 1):
        x = imap.apply(x)
        nx = _norm(x)
        if nx == 0.0 or not math.isfinite(nx):
            break
        ne = err_norm(x)
        logs[k] = log_scale + math.log(ne) if ne > 0 else -np.inf
        log_scale += math.log(nx)
        x = x / nx
    return logs, math.log(math.sqrt(probe.size))


def _long_growth(logs: Array, log_sqrt_size: float, long_horizon: int) -> float:
    """Last block mean over best block mean of the predicted RMSE, floored at one encoder LSB."""
    rms = np.exp(np.clip(logs[:long_horizon] - log_sqrt_size, -745.0, 700.0))
    rms = np.where(np.isfinite(logs[:long_horizon]), rms, 0.0)
    floored = np.maximum(rms, units.RAD_PER_COUNT)
    blk = min(BOUNDED_BLOCK, max(long_horizon // 2, 1))
    means = np.convolve(floored, np.ones(blk) / blk, mode="valid")
    return float(means[-1] / np.min(means)) if means.size else 1.0


def not_checked(model: ClosedLoopModel, ld_nms_per_rad: Array, ts_s: float, law: str, iterations: int = 10) -> ConvergenceReport:
    """The report of a law that gives no linear iteration map: nothing is predicted (``checked``
    False; ``ok`` is False and means nothing then, the summary writes it as null); the paper's
    condition (18), which needs only the model and Ld, is still given."""
    return ConvergenceReport(
        rho_max=math.nan,
        norm2=math.nan,
        paper_rho18=_paper_rho18(model, np.asarray(ld_nms_per_rad, dtype=float), ts_s),
        ok=False,
        map_kind="none",
        iterations=int(iterations),
        rho_method="not checked",
        norm_method="not checked",
        prediction=f"not checked: law {law} gives no linear iteration map",
        checked=False,
    )


def check_iteration_map(
    imap: IterationMap,
    model: ClosedLoopModel,
    ld_nms_per_rad: Array,
    ts_s: float,
    probe_torque_nm: Array | None = None,
    iterations: int = 10,
    long_horizon: int = LONG_HORIZON,
    perturbed: list[tuple[float, IterationMap, ClosedLoopModel]] | None = None,
) -> ConvergenceReport:
    """Check a law's iteration map before a run (module docstring).

    :param imap: the law's map (``LearningLaw.iteration_map``)
    :param model: the closed-loop model it was built on
    :param ld_nms_per_rad: (J,) the learning D gain, for the paper's condition (18)
    :param probe_torque_nm: (N, J) torque whose error starts the prediction (default: per joint a
        1 N·m sinusoid sin(2π t/T + j))
    :param iterations: the planned trials K (any size: the cost does not depend on it)
    :param long_horizon: trials of the long-run verdict (≤ SIMULATED_TRIALS)
    :param perturbed: (inertia scale, the law's map on that plant, that plant) for the long-run verdict
    """
    n, j = model.n, model.j
    if probe_torque_nm is None:
        t = np.arange(n)[:, None] * ts_s
        probe_torque_nm = np.sin(2 * np.pi * t / max(float(t[-1, 0]), ts_s) + np.arange(j)[None, :])
    probe = np.asarray(probe_torque_nm, dtype=float).reshape(n, j)
    long_horizon = min(int(long_horizon), SIMULATED_TRIALS)
    # a symmetric map (norm-optimal on its own model) is a contraction in the 2-norm by construction
    # (eigenvalues in (0, 1]): its long run needs no simulation, only the planned trials do
    horizon = min(int(iterations) if imap.symmetric else max(int(iterations), long_horizon), SIMULATED_TRIALS)
    logs, log_sqrt_size = _predict(imap, model, probe, horizon)
    log_ratio = logs - logs[0] if math.isfinite(logs[0]) else np.full_like(logs, -np.inf)

    # beyond the simulated trials: the mean rate of the last EXTRAPOLATION_WINDOW ones
    w = min(EXTRAPOLATION_WINDOW, horizon)
    tail = log_ratio[horizon - w : horizon + 1]
    log_rate = float((tail[-1] - tail[0]) / w) if w > 0 and np.all(np.isfinite(tail)) else -np.inf

    def ratio_at(k: int) -> float:
        if k <= horizon:
            lr = log_ratio[k]
        else:
            lr = log_ratio[horizon] + log_rate * (k - horizon)
        return math.exp(min(lr, 700.0)) if math.isfinite(lr) else 0.0

    K = max(int(iterations), 1)
    predicted = ratio_at(K)
    finite = log_ratio[1 : min(K, horizon) + 1]
    peak_log = float(np.max(finite)) if finite.size else -np.inf
    if K > horizon and log_rate > 0:
        peak_log = max(peak_log, log_ratio[horizon] + log_rate * (K - horizon))
    peak = math.exp(min(peak_log, 700.0)) if math.isfinite(peak_log) else 0.0
    prediction = (
        f"linear model simulated for {horizon} trials"
        if K <= horizon
        else f"linear model simulated for {horizon} trials, extrapolated to {K} at "
        f"{math.exp(max(min(log_rate, 700.0), -700.0)):.4g} per trial (mean of the last {w})"
    )

    # long-run verdict: predicted RMSE floored at one encoder LSB, block means over the horizon, on
    # the model and on the plants with scaled inertia
    growth = 1.0 if imap.symmetric else _long_growth(logs, log_sqrt_size, long_horizon)
    worst = "nominal"
    for scale, imap_s, model_s in perturbed or []:
        logs_s, _ = _predict(imap_s, model_s, probe, long_horizon)
        g_s = _long_growth(logs_s, log_sqrt_size, long_horizon)
        if g_s > growth:
            growth, worst = g_s, f"inertia x{scale:g}"
    long_bounded = bool(growth <= BOUNDED_LIMIT)

    r = _Restricted(imap, n, j)
    rho, rho_method = _spectral_radius(imap, r)
    nrm, norm_method = _norm2(imap, r, rho)
    r18 = _paper_rho18(model, np.asarray(ld_nms_per_rad, dtype=float), ts_s)
    return ConvergenceReport(
        rho_max=rho,
        norm2=nrm,
        paper_rho18=r18,
        ok=bool(rho < 1.0 and predicted < 1.0),
        map_kind=imap.kind,
        predicted_ratio=predicted,
        predicted_peak=peak,
        iterations=int(iterations),
        long_horizon=long_horizon,
        rho_method=rho_method,
        predicted_ratio_long=ratio_at(long_horizon),
        long_bounded=long_bounded,
        predicted_long_growth=growth,
        long_worst_case=worst,
        norm_method=norm_method,
        prediction=prediction,
    )
