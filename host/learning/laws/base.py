"""The context every law is built with and the base class of the built-in laws.

This module owns :class:`LawContext` (what a law may use, decided before the run: the same for every
law, project or plug-in) and :class:`BuiltinLaw`, the base class of the eight classic laws of
:mod:`host.learning.laws.pd` and :mod:`host.learning.laws.norm_optimal`.  A built-in law implements
the public protocol (:class:`host.learning.protocol.LawProtocol`) like any other law: its public
method is ``update(trial)``; its arithmetic is ``_update(u_k, e_k, tau_k) -> u_{k+1}`` on (N, J)
arrays — u the feed-forward (N·m), e = q_d − q the error (rad), τ the total torque the drive applied
(N·m).  Each knows its linear trial-to-trial map (:meth:`BuiltinLaw.iteration_map`) for the
convergence check of :mod:`host.learning.check`.  Sign convention, the paper's law and the gains:
``docs/learning-laws.md``.

The arithmetic of an update is fixed (the run's trace digest depends on it).

May import: numpy, :mod:`host.learning` (model, gains, check, protocol), :mod:`host.planning`, ``plant``.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from host.learning.check import IterationMap
from host.learning.gains import Gains
from host.learning.model import ClosedLoopModel
from host.learning.protocol import TrialData
from host.planning.joint_reference import JointReference
from plant.params import Geometry, MassModel

logger = logging.getLogger(__name__)

__all__ = ["BuiltinLaw", "LawContext"]

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


class BuiltinLaw(ABC):
    """One built-in law (module docstring): ``update(trial)`` of the public protocol on top of the
    law's arithmetic ``_update(u_k, e_k, tau_k)``."""

    #: the law's name (a key of :data:`host.learning.laws.table.PROJECT_LAWS`)
    name: str
    #: one line: what it is
    description: str

    def __init__(self, ctx: LawContext) -> None:
        self.ctx = ctx
        self.gains = ctx.gains
        self.ts_s = ctx.ts_s
        #: updates done so far
        self.updates = 0

    def update(self, trial: TrialData) -> Array:
        """Next feed-forward table (N, J), N·m, from a completed learning trial: the law's arithmetic
        on its feed-forward u_k (N·m), error e_k (rad) and total torque τ_k (N·m)."""
        out = self._update(trial.feedforward_nm, trial.error_rad, trial.torque_nm)
        self.updates += 1
        return out

    @abstractmethod
    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        """The law's arithmetic: u_{k+1} (N, J) N·m from u_k (N·m), e_k (rad), τ_k (N·m)."""

    @abstractmethod
    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        """The law's linear trial-to-trial map when the plant is ``model`` (the law's own operators —
        its filters, its norm-optimal gains — stay the ones it was built with)."""
