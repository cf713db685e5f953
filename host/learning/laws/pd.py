"""The PD-type built-in laws: the paper's law, its open-loop and Q-filtered forms.

This module owns, on the PD learning term Lp·lead(e_k) + Ld·lead(ė_k) (lead m samples):

    pd-ilc     u_{k+1} = τ_k + Lp·lead(e_k) + Ld·lead(ė_k)              the paper's law (total torque)
    pd-ilc-q   u_{k+1} = u_0 + Q(τ_k − u_0 + Lp·lead(e_k) + Ld·lead(ė_k))  its robust form (zero-phase Q)
    pd-ol      u_{k+1} = u_k + Lp·lead(e_k) + Ld·lead(ė_k)              open-loop PD-type
    p-ol       u_{k+1} = u_k + Lp·lead(e_k)                             open-loop P-type
    d-ilc      u_{k+1} = u_k + Ld·lead(ė_k)                             Arimoto D-type (paper's baseline)
    q-ilc      u_{k+1} = Q(u_k + Lp·lead(e_k) + Ld·lead(ė_k))           robust Q-filtered PD-type

u in N·m, e = q_d − q in rad, τ the total torque in N·m, (N, J) arrays.  The arithmetic is fixed
(the run's trace digest depends on it).

May import: numpy, :mod:`host.learning` (signals, model, check) and :mod:`host.learning.laws.base`.
"""

from __future__ import annotations

import logging
from abc import abstractmethod
from collections.abc import Callable
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from host.learning.check import IterationMap
from host.learning.laws.base import BuiltinLaw, LawContext
from host.learning.model import ClosedLoopModel
from host.learning.signals import ZeroPhaseFilter, backward_difference, backward_difference_t, lead, lead_t

logger = logging.getLogger(__name__)

__all__ = ["DIlc", "POl", "PdIlc", "PdIlcQ", "PdOl", "QIlc"]

Array = npt.NDArray[np.float64]


class _PdType(BuiltinLaw):
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
