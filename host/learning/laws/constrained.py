"""``cno-ilc``: constrained norm-optimal ILC — the norm-optimal update as a quadratic programme with
the joint torque limit (and, if asked, a torque-rate limit) as constraints, solved by OSQP.

A project law (:data:`host.learning.laws.table.PROJECT_LAWS`) written against the public protocol
(:class:`host.learning.protocol.LawProtocol`, ``ilcrig.LearningLaw``): ``update(trial)``.

After learning trial k (feed-forward u_k, error e_k, feedback τ_fb,k) the change δu minimises

    Σ_n ‖e_k[n] − δq[n]‖² + r Σ_n ‖δu[n]‖²        (the norm-optimal cost, ``no-ilc``)

subject to, for every sample n and joint j (L = (1 − margin)·limit):

* the closed-loop model along the reference (:class:`host.learning.model.ClosedLoopModel`,
  x_{n+1} = A_n x_n + B_n δu_n, x = (δq, δq̇, δq_{n−1}), x_0 = 0) as equality constraints;
* the feed-forward: |u_k[n] + δu[n]| ≤ L;
* the total torque the drive will command, predicted: |τ_k[n] + δu[n] − Kp δq[n] − Kd (δq[n] −
  δq[n−1])/Ts| ≤ L, with τ_k = u_k + τ_fb,k the demand of trial k (before the drive's clamp);
* optionally the rate: |Δτ[n]| ≤ rate_limit·Ts.

Sparse state-space form: the variables are the states and inputs of every sample (16 per sample
for J = 4), so the matrices have O(N) non-zeros and OSQP's factorisation (QDLDL, AMD ordering) of
the banded KKT system is O(N) in time and memory — no lifted (NJ × NJ) matrix.  The matrices do
not change between trials (only the linear cost and the bounds): OSQP is set up once per model and
warm-started.  Variables are scaled (errors and positions in encoder counts, velocities in counts
per sample) so OSQP's tolerances mean fractions of a count.

The model: by default the one estimated from the first trial (as ``no-ilc-id``:
:mod:`host.learning.identification`; option ``model = "nominal"`` keeps the nominal one).  While no
constraint is active the step is the norm-optimal step; the convergence check uses that
(unconstrained) map.

Options (``[law_options]``): ``torque_limit_nm`` (default: the drives' joint torque limit),
``margin`` (fraction kept free below it for what the model does not predict, default 0.02),
``rate_limit_nm_per_s`` (default none), ``model`` (``identified`` | ``nominal``), ``weight`` (the
relative input weight w, default the experiment's ``gains.no_weight``).

OSQP is imported when the first QP is set up (naming the law costs nothing).

May import: numpy, scipy, osqp, ``bus``, :mod:`host.learning` (model, norm_optimal, identification,
check, protocol) and :mod:`host.learning.laws.base`.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from bus import units
from host.learning.check import IterationMap
from host.learning.identification import DynamicsEstimate
from host.learning.laws.base import LawContext
from host.learning.model import ClosedLoopModel
from host.learning.norm_optimal import NormOptimalStep
from host.learning.protocol import TrialData

logger = logging.getLogger(__name__)

__all__ = ["ConstrainedNormOptimal", "ConstrainedStep"]

Array = npt.NDArray[np.float64]

#: OSQP settings: tolerances in encoder counts (the scaled variables); a fixed iteration-based rho
#: adaptation keeps the solution the same in every run (no time-based decision)
OSQP_SETTINGS: dict[str, Any] = {
    "eps_abs": 1e-6,
    "eps_rel": 1e-6,
    "max_iter": 50_000,
    "polishing": True,
    "adaptive_rho_interval": 25,
    "verbose": False,
    "warm_starting": True,
}


def _number(options: Any, key: str, default: float | None) -> float | None:
    """The option ``key`` as a number (None when absent and without default)."""
    value = options.get(key, default)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"option {key} must be a number, got {value!r}")
    return float(value)


class ConstrainedStep:
    """The QP of one model (module docstring): set up once, solved per trial.

    :param model: the closed-loop model
    :param r_weight: the input weight r, rad²/(N·m)²
    :param limit_nm: L, the bound on |u| and on the predicted total torque, N·m
    :param rate_nm_per_sample: bound on the predicted total torque's change per sample (None: no bound)
    """

    def __init__(self, model: ClosedLoopModel, r_weight: float, limit_nm: float, rate_nm_per_sample: float | None) -> None:
        self.model, self.limit_nm, self.rate = model, float(limit_nm), rate_nm_per_sample
        n, j = model.n, model.j
        s = 3 * j
        c = units.RAD_PER_COUNT
        ts = model.ts_s
        h2 = 0.5 * ts * ts
        self.n, self.j, self.c = n, j, c
        nx = (n - 1) * s
        self.nx, self.nz = nx, nx + n * j

        def xi(k: Any, i: Any) -> Any:
            return np.asarray((np.asarray(k) - 1) * s + np.asarray(i))

        def ui(k: Any, i: Any) -> Any:
            return np.asarray(nx + np.asarray(k) * j + np.asarray(i))

        rows: list[Array] = []
        cols: list[Array] = []
        vals: list[Array] = []

        def add(r: Any, col: Any, v: Any) -> None:
            r, col, v = np.broadcast_arrays(np.asarray(r), np.asarray(col), np.asarray(v, dtype=float))
            rows.append(r.ravel())
            cols.append(col.ravel())
            vals.append(v.ravel())

        minv = model.minv  # (N, J, J)
        fq, fp = model.fq, model.fp
        ks = np.arange(n - 1)  # dynamics rows for x_{k+1}, k = 0..N-2
        ii = np.arange(j)
        # x_{k+1}: +I
        add(ks[:, None] * s + np.arange(s)[None, :], xi(ks[:, None] + 1, np.arange(s)[None, :]), 1.0)
        # -A_k x_k (k >= 1)
        kk = ks[1:]
        m_k = minv[kk]  # (K, J, J)
        rq, rv, rp = kk[:, None, None] * s + ii[None, :, None], kk[:, None, None] * s + j + ii[None, :, None], None
        cq = xi(kk[:, None, None], ii[None, None, :])
        cv = xi(kk[:, None, None], j + ii[None, None, :])
        cp = xi(kk[:, None, None], 2 * j + ii[None, None, :])
        eye = np.eye(j)[None]
        add(rq, cq, -(eye + h2 * m_k * fq[None, None, :]))
        add(rq, cv, -eye)
        add(rq, cp, -(h2 * m_k * fp[None, None, :]))
        add(rv, cq, -(ts * ts * m_k * fq[None, None, :]))
        add(rv, cv, -eye)
        add(rv, cp, -(ts * ts * m_k * fp[None, None, :]))
        rp = kk[:, None] * s + 2 * j + ii[None, :]
        add(rp, xi(kk[:, None], ii[None, :]), -1.0)
        # -B_k u_k
        m_all = minv[ks]
        rq_all = ks[:, None, None] * s + ii[None, :, None]
        cu = ui(ks[:, None, None], ii[None, None, :])
        add(rq_all, cu, -(h2 / c) * m_all)
        add(rq_all + j, cu, -(ts * ts / c) * m_all)
        n_dyn = (n - 1) * s
        # predicted total torque change: du + fq*c*q + fp*c*qp (rows n_dyn + k*J + i)
        kt = np.arange(n)
        add(n_dyn + kt[:, None] * j + ii[None, :], ui(kt[:, None], ii[None, :]), 1.0)
        k1 = np.arange(1, n)
        add(n_dyn + k1[:, None] * j + ii[None, :], xi(k1[:, None], ii[None, :]), (fq * c)[None, :])
        add(n_dyn + k1[:, None] * j + ii[None, :], xi(k1[:, None], 2 * j + ii[None, :]), (fp * c)[None, :])
        n_tau = n * j
        # the feed-forward: du (rows n_dyn + n_tau + k*J + i)
        base_ff = n_dyn + n_tau
        add(base_ff + kt[:, None] * j + ii[None, :], ui(kt[:, None], ii[None, :]), 1.0)
        n_rows = base_ff + n * j
        self._rate_base = None
        if rate_nm_per_sample is not None:
            # the change of the predicted torque from sample k-1 to k: rows of torque k minus torque k-1
            tau = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_rows, self.nz))[
                n_dyn : n_dyn + n_tau
            ]
            diff = (tau[j:] - tau[:-j]).tocoo()
            add(n_rows + diff.row, diff.col, diff.data)
            self._rate_base = n_rows
            n_rows += (n - 1) * j
        self.n_dyn, self.n_tau, self.base_ff, self.n_rows = n_dyn, n_tau, base_ff, n_rows
        a_mat = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_rows, self.nz))
        self.r_scaled = float(r_weight) / (c * c)
        p_diag = np.zeros(self.nz)
        p_diag[xi(np.arange(1, n)[:, None], ii[None, :]).ravel()] = 1.0
        p_diag[nx:] = self.r_scaled
        self._q_index = xi(np.arange(1, n)[:, None], ii[None, :])  # (N-1, J) positions of δq̂
        import osqp

        self.solver = osqp.OSQP()
        self.solver.setup(
            sp.diags(p_diag, format="csc"), np.zeros(self.nz), a_mat, np.zeros(n_rows), np.zeros(n_rows), **OSQP_SETTINGS
        )
        self.nnz = int(a_mat.nnz)
        self.last_status = "not solved"
        self.last_iterations = 0

    def __call__(self, u_nm: Array, e_rad: Array, demand_nm: Array) -> Array:
        """δu (N, J) N·m for the feed-forward ``u_nm``, its error ``e_rad`` and total-torque demand
        ``demand_nm`` (each (N, J)); the step that keeps ``u_nm`` inside the limit when the QP has no
        solution (logged)."""
        n, j, lim = self.n, self.j, self.limit_nm
        q = np.zeros(self.nz)
        q[self._q_index.ravel()] = -(np.asarray(e_rad)[1:] / self.c).ravel()
        lo = np.zeros(self.n_rows)
        hi = np.zeros(self.n_rows)
        tau = np.asarray(demand_nm, dtype=float).ravel()
        uu = np.asarray(u_nm, dtype=float).ravel()
        lo[self.n_dyn : self.n_dyn + self.n_tau] = -lim - tau
        hi[self.n_dyn : self.n_dyn + self.n_tau] = lim - tau
        lo[self.base_ff : self.base_ff + n * j] = -lim - uu
        hi[self.base_ff : self.base_ff + n * j] = lim - uu
        if self._rate_base is not None and self.rate is not None:
            dtau = (np.asarray(demand_nm)[1:] - np.asarray(demand_nm)[:-1]).ravel()
            lo[self._rate_base :] = -self.rate - dtau
            hi[self._rate_base :] = self.rate - dtau
        self.solver.update(q=q, l=lo, u=hi)
        res = self.solver.solve(raise_error=False)
        self.last_status = str(res.info.status)
        self.last_iterations = int(res.info.iter)
        if res.x is None or self.last_status not in ("solved", "solved inaccurate"):
            logger.warning("constrained step: OSQP %s: the feed-forward is clipped to the limit instead", self.last_status)
            return np.clip(u_nm, -lim, lim) - u_nm
        return np.asarray(res.x[self.nx :], dtype=float).reshape(n, j)


class ConstrainedNormOptimal:
    """Constrained norm-optimal ILC (module docstring)."""

    name = "cno-ilc"
    description = "norm-optimal ILC as a QP with the joint torque limit (and rate) as constraints (OSQP)"

    def __init__(self, ctx: LawContext) -> None:
        opts = dict(ctx.options)
        unknown = set(opts) - {"torque_limit_nm", "margin", "rate_limit_nm_per_s", "model", "weight"}
        if unknown:
            raise ValueError(
                f"unknown option(s) {', '.join(sorted(unknown))} (cno-ilc takes torque_limit_nm, margin, "
                "rate_limit_nm_per_s, model, weight)"
            )
        limit = _number(opts, "torque_limit_nm", ctx.torque_limit_nm)
        if limit is None or not limit > 0:
            raise ValueError(f"option torque_limit_nm must be > 0 N·m, got {limit!r}")
        margin = float(_number(opts, "margin", 0.02) or 0.0)
        if not 0.0 <= margin < 1.0:
            raise ValueError(f"option margin must be in [0, 1), got {margin}")
        rate = _number(opts, "rate_limit_nm_per_s", None)
        if rate is not None and not rate > 0:
            raise ValueError(f"option rate_limit_nm_per_s must be > 0, got {rate}")
        self.model_kind = opts.get("model", "identified")
        if self.model_kind not in ("identified", "nominal"):
            raise ValueError(f"option model must be 'identified' or 'nominal', got {self.model_kind!r}")
        self.weight = float(_number(opts, "weight", ctx.gains.spec.no_weight) or 0.0)
        if not self.weight > 0:
            raise ValueError(f"option weight must be > 0, got {self.weight}")
        self.ctx = ctx
        self.limit_nm = limit * (1.0 - margin)
        self.rate_nm_per_sample = None if rate is None else float(rate) * ctx.ts_s
        self.updates = 0
        self._step: ConstrainedStep | None = None
        self._estimate: DynamicsEstimate | None = None
        self._unconstrained: NormOptimalStep | None = None
        if self.model_kind == "identified":
            if ctx.reference is None or ctx.mass_model is None or ctx.geometry is None:
                raise ValueError("model 'identified' needs the reference, the nominal mass model and the geometry")
            self._estimate = DynamicsEstimate(ctx.mass_model, ctx.geometry, ctx.ts_s)
        else:
            self._step = self._build(ctx.model)

    def _build(self, model: ClosedLoopModel) -> ConstrainedStep:
        scale = float(np.max(model.column_norms_sq()))
        return ConstrainedStep(model, self.weight * scale + 1e-300, self.limit_nm, self.rate_nm_per_sample)

    def update(self, trial: TrialData) -> Array:
        """u_{k+1} = u_k + δu of the QP (module docstring)."""
        if self._step is None:
            ref = self.ctx.reference
            assert ref is not None and self._estimate is not None
            self._estimate.add_trial(ref.q, trial.error_rad, trial.torque_nm)
            self._step = self._build(self.ctx.model.corrected(self._estimate.mass_matrices(ref.q)))
        demand = trial.feedforward_nm + trial.feedback_nm
        du = self._step(trial.feedforward_nm, trial.error_rad, demand)
        self.updates += 1
        return np.asarray(trial.feedforward_nm + du, dtype=float)

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        """The map while no constraint is active: norm-optimal, e_{k+1} = (I − G(GᵀG + rI)⁻¹Gᵀ) e_k,
        with the step of the law's own (nominal) model."""
        if self._unconstrained is None:
            self._unconstrained = NormOptimalStep(self.ctx.model, self.weight)
        step = self._unconstrained
        return IterationMap("error", apply=lambda e: e + model.g(step(e)), symmetric=model is step.model)
