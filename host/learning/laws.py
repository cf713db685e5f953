"""The learning laws: one class per law, a registry keyed by the names of
:mod:`host.learning.names`, and :func:`make_law`.

Every law is ``update(u_k, e_k, tau_k) -> u_{k+1}`` on (N, J) arrays — u the feed-forward (N·m),
e = q_d − q the error (rad), τ the total torque the drive applied (N·m) — and knows its linear
trial-to-trial map (:meth:`LearningLaw.iteration_map`) for the convergence check of
:mod:`host.learning.check`.  Sign convention, the paper's law and the gains: ``docs/learning-laws.md``.

    pd-ilc     u_{k+1} = τ_k + Lp·lead(e_k) + Ld·lead(ė_k)              the paper's law (total torque)
    pd-ilc-q   u_{k+1} = u_0 + Q(τ_k − u_0 + Lp·lead(e_k) + Ld·lead(ė_k))  its robust form (zero-phase Q)
    pd-ol      u_{k+1} = u_k + Lp·lead(e_k) + Ld·lead(ė_k)              open-loop PD-type
    p-ol       u_{k+1} = u_k + Lp·lead(e_k)                             open-loop P-type
    d-ilc      u_{k+1} = u_k + Ld·lead(ė_k)                             Arimoto D-type (paper's baseline)
    q-ilc      u_{k+1} = Q(u_k + Lp·lead(e_k) + Ld·lead(ė_k))           robust Q-filtered PD-type
    no-ilc     u_{k+1} = u_k − (GᵀG + r I)⁻¹Gᵀ e_k                      norm-optimal (Riccati form)
    no-ilc-id  u_1 = estimated inverse dynamics along q_d; then norm-optimal on the estimated model

The arithmetic of an update is fixed (the run's trace digest depends on it).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from host.learning.check import (
    LONG_HORIZON,
    ROBUST_INERTIA_SCALES,
    ConvergenceReport,
    IterationMap,
    check_iteration_map,
    not_checked,
)
from host.learning.gains import Gains
from host.learning.identification import DynamicsEstimate
from host.learning.model import ClosedLoopModel
from host.learning.names import LAWS
from host.learning.norm_optimal import NormOptimalStep
from host.learning.protocol import TrialData
from host.learning.signals import ZeroPhaseFilter, backward_difference, backward_difference_t, lead, lead_t
from host.planning.joint_reference import JointReference
from plant.params import Geometry, MassModel

logger = logging.getLogger(__name__)

__all__ = ["LawContext", "LearningLaw", "LAW_CLASSES", "make_law"]

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LawContext:
    """What a law may use, decided before the run.

    :param gains: the resolved gains (feedback Kp, Kd in the drive; learning Lp, Ld)
    :param ts_s: control period, s
    :param model: the nominal closed loop along the reference (:class:`ClosedLoopModel`)
    :param reference: the joint reference (for laws that estimate the dynamics)
    :param u0_nm: (N, J) the initial feed-forward, N·m (None: the first u_k a law sees)
    :param mass_model: the host's nominal mass model (prior of the estimated model)
    :param geometry: the robot geometry
    :param torque_limit_nm: the drives' joint torque limit (they clamp the total torque there), N·m
    :param options: the law's own options (the experiment's ``[law_options]`` table), name → value
    """

    gains: Gains
    ts_s: float
    model: ClosedLoopModel
    reference: JointReference | None = None
    u0_nm: Array | None = None
    mass_model: MassModel | None = None
    geometry: Geometry | None = None
    torque_limit_nm: float | None = None
    options: Mapping[str, Any] = field(default_factory=dict)


class LearningLaw(ABC):
    """One learning law (see the module docstring for the list)."""

    #: the law's name (a key of :data:`host.learning.names.LAWS`)
    name: str
    #: one line: what it is
    description: str
    #: extra rollouts the law needs after each learning trial (protocol: host.learning.protocol)
    auxiliary_trials: int = 0

    def __init__(self, ctx: LawContext) -> None:
        self.ctx = ctx
        self.gains = ctx.gains
        self.ts_s = ctx.ts_s
        #: updates done so far
        self.updates = 0

    def update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        """Next feed-forward table (N, J), N·m.

        :param u_k: (N, J) feed-forward applied in trial k, N·m
        :param e_k: (N, J) error q_d − q measured in trial k, rad
        :param tau_k: (N, J) total torque applied in trial k (feed-forward + feedback), N·m
        :raises FloatingPointError: the law produced a non-finite value
        """
        out = self._update(u_k, e_k, tau_k)
        self.updates += 1
        if not np.all(np.isfinite(out)):
            raise FloatingPointError(f"law {self.name} produced a non-finite feed-forward")
        return out

    def learn(self, trial: TrialData) -> Array:
        """Next feed-forward table (N, J), N·m, from a completed learning trial (the trial loop's
        call; the built-in laws use its feed-forward, error and total torque, :meth:`update`)."""
        return self.update(trial.feedforward_nm, trial.error_rad, trial.torque_nm)

    def auxiliary_input(self, trial: TrialData, done: Sequence[TrialData]) -> Array:
        """The feed-forward (N, J) N·m of the next auxiliary rollout after the learning trial
        ``trial`` (``done``: the auxiliary trials of this step so far); only for a law whose
        :attr:`auxiliary_trials` is > 0."""
        raise NotImplementedError(f"law {self.name} runs no auxiliary trials")

    @abstractmethod
    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        """The law's arithmetic."""

    @property
    def has_iteration_map(self) -> bool:
        """Whether the law gives its trial-to-trial map (:meth:`iteration_map`); every built-in law does."""
        return True

    @abstractmethod
    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        """The law's linear trial-to-trial map when the plant is ``model`` (the law's own operators —
        its filters, its norm-optimal gains — stay the ones it was built with)."""

    def check(
        self,
        model: ClosedLoopModel | None = None,
        probe_torque: Array | None = None,
        iterations: int = 10,
        long_horizon: int = LONG_HORIZON,
        inertia_scales: tuple[float, ...] = ROBUST_INERTIA_SCALES,
    ) -> ConvergenceReport:
        """The convergence check of :mod:`host.learning.check` on ``model`` (default: the law's), with
        the long-run verdict also on the plant whose inertia is scaled by each of ``inertia_scales``;
        "not checked" for a law that gives no iteration map (:attr:`has_iteration_map`)."""
        mdl = model if model is not None else self.ctx.model
        if not self.has_iteration_map:
            logger.info("law %s gives no iteration map: convergence not checked", self.name)
            return not_checked(mdl, self.gains.ld, self.ts_s, self.name, iterations)
        perturbed = []
        for scale in inertia_scales:
            plant = mdl.corrected(mdl.inertia * scale)
            perturbed.append((scale, self.iteration_map(plant), plant))
        return check_iteration_map(
            self.iteration_map(mdl), mdl, self.gains.ld, self.ts_s, probe_torque, iterations, long_horizon, perturbed
        )


# ------------------------------------------------------------------------------ PD-type laws


class _PdType(LearningLaw):
    """Laws built on the PD learning term Lp·lead(e) + Ld·lead(ė) with a lead of m samples."""

    use_p: ClassVar[bool] = True
    use_d: ClassVar[bool] = True

    def pd_term(self, e: Array) -> Array:
        """Lp·lead(e, m) + Ld·lead(ė, m) (N·m) for the error e (rad)."""
        g, m, ts = self.gains, self.gains.spec.lead, self.ts_s
        out = np.zeros_like(e)
        if self.use_p:
            out += g.lp * lead(e, m)
        if self.use_d:
            out += g.ld * lead(backward_difference(e, ts), m)
        return out

    def pd_term_t(self, y: Array) -> Array:
        """Transpose of :meth:`pd_term`."""
        g, m, ts = self.gains, self.gains.spec.lead, self.ts_s
        out = np.zeros_like(y)
        if self.use_p:
            out += lead_t(g.lp * y, m)
        if self.use_d:
            out += backward_difference_t(lead_t(g.ld * y, m), ts)
        return out

    def _lead_coupling(self) -> Array | None:
        """The gain (J,) from e[n+1] to the correction at u[n] (None when the lead is > 1: then the
        map is not causal); with lead 0 nothing couples e[n+1] to u[n]."""
        m = self.gains.spec.lead
        if m > 1:
            return None
        c = np.zeros(len(self.gains.lp))
        if m == 1:
            if self.use_p:
                c = c + self.gains.lp
            if self.use_d:
                c = c + self.gains.ld / self.ts_s
        return c

    def _causal_diagonal(self, model: ClosedLoopModel) -> Callable[[], Array] | None:
        """The diagonal blocks of a causal error map (None when the map is not causal)."""
        c = self._lead_coupling()
        if c is None:
            return None
        coupling = c

        def blocks() -> Array:
            # e_{k+1}[n] = e_k[n] + G_{n,n−1}·c·e_k[n] + (earlier samples): I + G_{n,n−1} diag(c), n ≥ 1
            return np.eye(model.j)[None] + model.first_markov()[:-1] * coupling[None, None, :]

        return blocks


class PdIlc(_PdType):
    name = "pd-ilc"
    description = "the paper's open-closed-loop PD law, total-torque form"

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        return tau_k + self.pd_term(e_k)

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        # e_{k+1} = (I + G(K + L)) e_k
        def apply_t(y: Array) -> Array:
            gy = model.g_t(y)
            return y + model.k_t(gy) + self.pd_term_t(gy)

        return IterationMap(
            "error",
            apply=lambda e: e + model.g(model.k(e) + self.pd_term(e)),
            apply_t=apply_t,
            diagonal=self._causal_diagonal(model),
        )


class PdOl(_PdType):
    name = "pd-ol"
    description = "open-loop PD-type: the paper's law accumulating the feed-forward only"

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        return u_k + self.pd_term(e_k)

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        # e_{k+1} = (I + G L) e_k
        return IterationMap(
            "error",
            apply=lambda e: e + model.g(self.pd_term(e)),
            apply_t=lambda y: y + self.pd_term_t(model.g_t(y)),
            diagonal=self._causal_diagonal(model),
        )


class POl(PdOl):
    name = "p-ol"
    description = "open-loop P-type (Arimoto P-type)"
    use_d = False


class DIlc(PdOl):
    name = "d-ilc"
    description = "classical Arimoto D-type, the paper's baseline"
    use_p = False


class _QFiltered(_PdType):
    """PD-type laws with a zero-phase Q filter: input maps x_{k+1} = Q(I + M G) x_k."""

    def __init__(self, ctx: LawContext) -> None:
        super().__init__(ctx)
        self.q = ZeroPhaseFilter(self._cutoff_hz(), ctx.gains.spec.q_order, ctx.ts_s)

    @abstractmethod
    def _cutoff_hz(self) -> float:
        """The Q filter's cut-off, Hz."""

    def _m(self, model: ClosedLoopModel, e: Array) -> Array:
        return self.pd_term(e)

    def _m_t(self, model: ClosedLoopModel, y: Array) -> Array:
        return self.pd_term_t(y)

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        def apply(x: Array) -> Array:
            return self.q(x + self._m(model, model.g(x)))

        def apply_t(y: Array) -> Array:
            w = self.q.transpose(y)
            return w + model.g_t(self._m_t(model, w))

        return IterationMap("input", apply=apply, apply_t=apply_t)


class QIlc(_QFiltered):
    name = "q-ilc"
    description = "robust PD-type with a zero-phase Q filter on the whole feed-forward"

    def _cutoff_hz(self) -> float:
        return self.gains.spec.q_cutoff_hz

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        return self.q(u_k + self.pd_term(e_k))


class PdIlcQ(_QFiltered):
    name = "pd-ilc-q"
    description = "the paper's law (total torque) with a zero-phase Q filter on what it learns"

    def __init__(self, ctx: LawContext) -> None:
        super().__init__(ctx)
        self._u0 = None if ctx.u0_nm is None else np.array(ctx.u0_nm, dtype=float, copy=True)

    def _cutoff_hz(self) -> float:
        return self.gains.spec.pdq_cutoff_hz

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        if self._u0 is None:
            self._u0 = np.array(u_k, dtype=float, copy=True)
        # the learned part τ_k − u_0 (the feedback of trial k and what was learned before) is filtered;
        # the initial feed-forward (e.g. the nominal inverse dynamics) is kept as it is
        return self._u0 + self.q(tau_k - self._u0 + self.pd_term(e_k))

    def _m(self, model: ClosedLoopModel, e: Array) -> Array:
        return model.k(e) + self.pd_term(e)

    def _m_t(self, model: ClosedLoopModel, y: Array) -> Array:
        return model.k_t(y) + self.pd_term_t(y)


# ------------------------------------------------------------------------------ norm-optimal


class NoIlc(LearningLaw):
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
            raise ValueError("law no-ilc-id needs the reference, the nominal mass model and the geometry")
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


#: the registry: law name → class (the names are :data:`host.learning.names.LAWS`)
LAW_CLASSES: dict[str, type[LearningLaw]] = {cls.name: cls for cls in (PdIlc, PdIlcQ, PdOl, POl, DIlc, QIlc, NoIlc, NoIlcId)}
if set(LAW_CLASSES) != set(LAWS):  # pragma: no cover - a programming error, caught by every test
    raise ImportError(f"law registry {sorted(LAW_CLASSES)} differs from host.learning.names.LAWS {sorted(LAWS)}")


def make_law(name: str, ctx: LawContext) -> LearningLaw:
    """Build the law ``name`` (one of :data:`host.learning.names.LAWS`) for the context ``ctx``."""
    try:
        cls = LAW_CLASSES[name]
    except KeyError:
        raise ValueError(f"unknown law {name!r}; choose one of {', '.join(LAWS)}") from None
    return cls(ctx)
