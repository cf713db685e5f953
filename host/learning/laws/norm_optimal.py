"""The norm-optimal built-in laws (the Riccati step of :mod:`host.learning.norm_optimal`).

This module owns:

    no-ilc     u_{k+1} = u_k − (GᵀG + r I)⁻¹Gᵀ e_k                      norm-optimal (Riccati form)
    no-ilc-id  u_1 = estimated inverse dynamics along q_d; then norm-optimal on the estimated model

u in N·m, e = q_d − q in rad, (N, J) arrays.  The arithmetic is fixed (the run's trace digest
depends on it).

May import: numpy, :mod:`host.learning` (norm_optimal, identification, model, check) and
:mod:`host.learning.laws.base`.
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt

from host.learning.check import IterationMap
from host.learning.identification import DynamicsEstimate
from host.learning.laws.base import BuiltinLaw, LawContext
from host.learning.model import ClosedLoopModel
from host.learning.norm_optimal import NormOptimalStep

logger = logging.getLogger(__name__)

__all__ = ["NoIlc", "NoIlcId"]

Array = npt.NDArray[np.float64]


class NoIlc(BuiltinLaw):
    name = "no-ilc"
    description = "norm-optimal ILC on the nominal model (Riccati form)"

    def __init__(self, ctx: LawContext) -> None:
        super().__init__(ctx)
        self.step = NormOptimalStep(ctx.model, ctx.gains.spec.no_weight)

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        return u_k + self.step(e_k)

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        step = self.step
        # e_{k+1} = (I + G_plant L_no) e_k; on the law's own model I − G(GᵀG + rI)⁻¹Gᵀ: symmetric,
        # eigenvalues r/(σ² + r) in (0, 1]
        return IterationMap("error", apply=lambda e: e + model.g(step(e)), symmetric=model is step.model)


class NoIlcId(NoIlc):
    name = "no-ilc-id"
    description = "norm-optimal ILC on a model estimated from the measured trials"

    #: trials whose data the estimate uses (then the model is frozen)
    ESTIMATION_TRIALS = 1

    def __init__(self, ctx: LawContext) -> None:
        super().__init__(ctx)
        if ctx.reference is None or ctx.mass_model is None or ctx.geometry is None:
            raise ValueError("needs the reference, the nominal mass model and the geometry")
        self.estimate = DynamicsEstimate(ctx.mass_model, ctx.geometry, ctx.ts_s)

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        ref = self.ctx.reference
        assert ref is not None
        if self.updates >= self.ESTIMATION_TRIALS:
            return u_k + self.step(e_k)
        self.estimate.add_trial(ref.q, e_k, tau_k)
        # corrected feed-forward: the estimated inverse dynamics along the reference, at the middle
        # of each hold interval (the torque u[n] acts over [t_n, t_n + Ts])
        t_ref = self.estimate.inverse_dynamics(ref.q, ref.qd, ref.qdd)
        u_next = t_ref.copy()
        u_next[:-1] = 0.5 * (t_ref[:-1] + t_ref[1:])
        # the model of the following norm-optimal steps: the estimated inertia along the reference
        # (the Coulomb friction's slope is left out: its linearisation holds only for velocity
        # errors far below the smoothing velocity, and with it the updates scatter more at the floor)
        model = self.ctx.model.corrected(self.estimate.mass_matrices(ref.q))
        self.step = NormOptimalStep(model, self.gains.spec.no_weight)
        return u_next
