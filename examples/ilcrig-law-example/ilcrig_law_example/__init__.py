"""An example learning law for ilcrig, installed as a plug-in (entry point ``leaky-p`` of the group
``ilcrig.laws``).

``LeakyP``: u_{k+1} = u_0 + λ·(u_k − u_0) + γ·Lp·lead(e_k) — Arimoto's P-type law with a forgetting
factor λ toward the initial feed-forward u_0 (robust to non-repeating disturbances, at the price of a
non-zero error floor), the learning gain γ·Lp (Lp: ilcrig's learning P gain per joint, N·m/rad) and a
one-sample lead (the torque of sample n first shows in the error at n + 1).

Options (``[law_options]`` / ``--law-options``): ``gain`` γ (default 1.0), ``forgetting`` λ (default 1.0).
"""

from __future__ import annotations

import numpy as np

import ilcrig
from ilcrig.signals import lead, lead_t

__all__ = ["LeakyP"]


class LeakyP:
    """P-type ILC with a forgetting factor (module docstring)."""

    name = "leaky-p"
    description = "example plug-in: P-type ILC with a forgetting factor toward u0"

    def __init__(self, ctx: ilcrig.LawContext) -> None:
        unknown = set(ctx.options) - {"gain", "forgetting"}
        if unknown:
            raise ValueError(f"unknown option(s) {', '.join(sorted(unknown))} (leaky-p takes gain, forgetting)")
        self.gain = float(ctx.options.get("gain", 1.0))
        self.forgetting = float(ctx.options.get("forgetting", 1.0))
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"option forgetting must be in (0, 1], got {self.forgetting}")
        self.lp = self.gain * np.asarray(ctx.gains.lp, dtype=float)  # (J,) N·m/rad
        self.u0 = None if ctx.u0_nm is None else np.array(ctx.u0_nm, dtype=float)

    def update(self, trial: ilcrig.TrialData) -> np.ndarray:
        """The next feed-forward (N, J) N·m from the trial's feed-forward and error."""
        u = trial.feedforward_nm
        u0 = self.u0 if self.u0 is not None else np.zeros_like(u)
        return u0 + self.forgetting * (u - u0) + self.lp * lead(trial.error_rad, 1)

    def iteration_map(self, model: ilcrig.ClosedLoopModel) -> ilcrig.IterationMap:
        """x_{k+1} = (λI + L G) x_k on x = u − u* (an input map: with λ < 1 the fixed point is not
        zero error); with λ = 1 the error map e_{k+1} = (I + G L) e_k."""
        lp, lam = self.lp, self.forgetting
        if lam == 1.0:
            return ilcrig.IterationMap(
                "error",
                apply=lambda e: e + model.g(lp * lead(e, 1)),
                apply_t=lambda y: y + lead_t(lp * model.g_t(y), 1),
            )
        return ilcrig.IterationMap(
            "input",
            apply=lambda x: lam * x + lp * lead(model.g(x), 1),
            apply_t=lambda y: lam * y + model.g_t(lead_t(lp * y, 1)),
        )
