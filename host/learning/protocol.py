"""The public protocol of a learning law: what a law receives after each trial and what it returns.

This module owns :class:`TrialData` (one completed trial as a law sees it) and
:class:`LawProtocol` (the ``typing.Protocol`` a law from outside the package implements; the
public API re-exports it as ``ilcrig.LearningLaw``).  Every law implements it: the project's laws
of :mod:`host.learning.laws` (the classic ones through their base class
``host.learning.laws.base.BuiltinLaw``) as well as a plug-in's; each runs inside the one checked
wrapper :class:`host.learning.laws.checked.CheckedLaw`.

A law is a class built once per experiment with the experiment's
:class:`host.learning.laws.base.LawContext` (gains, Ts, the nominal closed-loop model along the
reference, the reference, the initial feed-forward u₀, the joint torque limit, the law's options).
After each trial the trial loop calls ``update(trial)`` and downloads what it returns as the next
trial's feed-forward table (N, J) in N·m.  Optional members, used when present:

* ``name`` / ``description`` (str): shown in the plan line and ``ilcrig laws``;
* ``iteration_map(model) -> IterationMap``: the law's linear trial-to-trial map on a closed-loop
  model (:class:`host.learning.model.ClosedLoopModel`), for the convergence check before the run.
  A law without it is run with the check reported as "not checked";
* ``auxiliary_trials`` (int ≥ 0, default 0) and ``auxiliary_input(trial, done) -> array``: the law
  needs that many extra rollouts after each learning trial (e.g. the model-free gradient laws); the
  loop runs each with the feed-forward ``auxiliary_input`` returns (``done``: the auxiliary trials
  of this step so far), counts them as trials (results, summary, reports, the trace digest) and then
  calls ``update`` with the learning trial, the auxiliary trials attached in
  :attr:`TrialData.auxiliary`.  When the planned trials leave no room for a whole step
  (``auxiliary_trials`` + 1 more), no auxiliary trial runs and ``update`` gets the trial without
  them.

Units: feed-forward and torques in N·m, errors e = q_d − q in rad, (N, J) arrays, time along axis 0.

May import: numpy only (the public API re-exports this module's names).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

logger = logging.getLogger(__name__)

__all__ = ["TrialData", "LawProtocol", "AUXILIARY", "LEARNING"]

Array = npt.NDArray[np.float64]

#: the role of a trial whose error the law learns from
LEARNING = "learning"
#: the role of an extra rollout a law asked for (``auxiliary_trials``)
AUXILIARY = "auxiliary"


@dataclass(frozen=True)
class TrialData:
    """One completed trial as a law receives it.

    :ivar trial: the trial's index in the run (every rollout counts, auxiliary ones too)
    :ivar feedforward_nm: (N, J) the feed-forward table played in the trial, N·m
    :ivar error_rad: (N, J) e = q_d − q measured by the encoders, rad
    :ivar torque_nm: (N, J) total torque the drives applied (feed-forward + feedback, after the
        drive's clamp at the torque limit), N·m
    :ivar feedback_nm: (N, J) the drives' feedback torque Kp·e + Kd·ė as recorded, N·m
    :ivar ts_s: control period, s
    :ivar role: :data:`LEARNING` or :data:`AUXILIARY`
    :ivar auxiliary: the auxiliary trials run after this learning trial, in the order they ran
    """

    trial: int
    feedforward_nm: Array
    error_rad: Array
    torque_nm: Array
    feedback_nm: Array
    ts_s: float
    role: str = LEARNING
    auxiliary: tuple[TrialData, ...] = ()

    @property
    def n_ticks(self) -> int:
        """N, the samples of the trial."""
        return int(self.error_rad.shape[0])


@runtime_checkable
class LawProtocol(Protocol):
    """A learning law (module docstring): built as ``cls(ctx)`` with a
    :class:`host.learning.laws.base.LawContext`; after each learning trial ``update(trial)`` returns the
    next feed-forward (N, J) in N·m.  Optional: ``name``, ``description``,
    ``iteration_map(model)``, ``auxiliary_trials`` with ``auxiliary_input(trial, done)``."""

    def update(self, trial: TrialData) -> npt.ArrayLike:
        """The feed-forward of the next learning trial, (N, J) N·m."""
        ...
