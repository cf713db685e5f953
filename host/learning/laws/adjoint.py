"""``adjoint-ilc``: model-free gradient ILC by the adjoint (time-reversal) experiment, with an exact
line search measured on the plant.

A project law (:data:`host.learning.laws.table.PROJECT_LAWS`) written against the public protocol
(:class:`host.learning.protocol.LawProtocol`, ``ilcrig.LearningLaw``): ``update(trial)``.  No
model is used: every quantity comes from rollouts of the plant around the current feed-forward.

A learning step after learning trial k (feed-forward u_k, error e_k) takes two auxiliary rollouts
(``auxiliary_trials = 2``; each is a trial of the run — recorded, reported and in the digest):

1. **gradient**: u_k + s₁·T e_k, with T the time reversal along the trial (e[n] → e[N−1−n]) and s₁
   scaling the peak to ``perturbation_nm``.  Its error differs from e_k by G(s₁ T e_k), G the plant's
   map from a feed-forward change to an error change around u_k, so g = T(e₁ − e_k)/s₁ = T G T e_k.
   For a time-invariant plant with a symmetric transfer matrix (collocated torques and joint angles
   with a symmetric inertia and diagonal drive gains, as here) T G T = Gᵀ: g is the gradient Gᵀe_k of
   ½‖e‖² with respect to u.  Along the reference the inertia varies slowly, so g is that gradient
   approximately (Huo, Freeman, Liu: model-free gradient ILC; Ye et al.: the adjoint experiment).
2. **line search**: u_k + s₂·d with d = −g, s₂ scaling the peak to ``perturbation_nm``; its error
   gives G d = (e₂ − e_k)/s₂ and the exact step along d, α = −⟨e_k, G d⟩/‖G d‖² (clipped at ≥ 0).

Then u_{k+1} = u_k + α·d: steepest descent with an exact line search, monotone in ‖e‖ while the
plant is linear around u_k.  It converges fast in the directions G amplifies most (low
frequencies) and slowly in the others; each step costs three trials.  When the planned trials leave
no room for a step the feed-forward is kept.  The law is not linear in e (the step depends on the
data): there is no iteration map, and the convergence check says "not checked".

Options (``[law_options]``): ``perturbation_nm`` (peak of each auxiliary perturbation, N·m, default
5.0).

May import: numpy, :mod:`host.learning.protocol` and :mod:`host.learning.laws.base`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from host.learning.laws.base import LawContext
from host.learning.protocol import TrialData

logger = logging.getLogger(__name__)

__all__ = ["AdjointGradient"]

Array = npt.NDArray[np.float64]


def _peak_scale(x: Array, peak_nm: float) -> float:
    """The factor that brings the peak of |x| to ``peak_nm`` (0 for x = 0)."""
    top = float(np.max(np.abs(x), initial=0.0))
    return peak_nm / top if top > 0.0 else 0.0


class AdjointGradient:
    """Model-free gradient ILC (module docstring)."""

    name = "adjoint-ilc"
    description = "model-free gradient ILC: the adjoint (time-reversal) experiment and a measured line search"
    #: rollouts per learning step: the gradient, then the line search
    auxiliary_trials = 2

    def __init__(self, ctx: LawContext) -> None:
        unknown = set(ctx.options) - {"perturbation_nm"}
        if unknown:
            raise ValueError(f"unknown option(s) {', '.join(sorted(unknown))} (adjoint-ilc takes perturbation_nm)")
        peak = ctx.options.get("perturbation_nm", 5.0)
        if isinstance(peak, bool) or not isinstance(peak, (int, float)) or not peak > 0:
            raise ValueError(f"option perturbation_nm must be a number > 0 N·m, got {peak!r}")
        self.perturbation_nm = float(peak)
        #: per learning step: the line-search step α and the measured ‖G d‖ (for the documentation / tests)
        self.steps: list[float] = []

    def _gradient(self, trial: TrialData, first: TrialData) -> tuple[Array, float]:
        """g ≈ Gᵀe_k from the gradient rollout, and the perturbation's scale s₁."""
        s1 = _peak_scale(trial.error_rad, self.perturbation_nm)
        if s1 == 0.0:
            return np.zeros_like(trial.error_rad), 0.0
        return (first.error_rad - trial.error_rad)[::-1] / s1, s1

    def auxiliary_input(self, trial: TrialData, done: Sequence[TrialData]) -> Array:
        """Rollout 1: u_k + s₁·T e_k; rollout 2: u_k + s₂·d, d = −g."""
        u = trial.feedforward_nm
        if not done:
            return u + _peak_scale(trial.error_rad, self.perturbation_nm) * trial.error_rad[::-1]
        g, _ = self._gradient(trial, done[0])
        return u - _peak_scale(g, self.perturbation_nm) * g

    def update(self, trial: TrialData) -> Array:
        """u_{k+1} = u_k + α·d (module docstring); u_k when the step's rollouts did not run."""
        u = trial.feedforward_nm
        if len(trial.auxiliary) < self.auxiliary_trials:
            return np.array(u, dtype=float, copy=True)
        g, _ = self._gradient(trial, trial.auxiliary[0])
        d = -g
        s2 = _peak_scale(d, self.perturbation_nm)
        if s2 == 0.0:
            self.steps.append(0.0)
            return np.array(u, dtype=float, copy=True)
        gd = (trial.auxiliary[1].error_rad - trial.error_rad) / s2
        den = float(np.sum(gd * gd))
        alpha = max(-float(np.sum(trial.error_rad * gd)) / den, 0.0) if den > 0.0 else 0.0
        self.steps.append(alpha)
        logger.info("adjoint-ilc step after trial %d: alpha %.4g", trial.trial, alpha)
        return np.asarray(u + alpha * d, dtype=float)
