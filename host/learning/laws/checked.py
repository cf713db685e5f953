"""Any law by name, built for an experiment and run inside one checked wrapper.

This module owns :func:`build_law` (what :func:`host.experiment.plan.prepare` calls), the wrapper
:class:`CheckedLaw` and :class:`LawError`.  Every law — a project law of
:data:`host.learning.laws.table.PROJECT_LAWS`, a plug-in, a ``module:Class``, a class registered in
the process — implements the one public protocol (:class:`host.learning.protocol.LawProtocol`) and
is built and run the same way: ``cls(ctx)``, then :class:`CheckedLaw` around it.  The wrapper is
what the trial loop and the convergence check use:

* ``update(trial)`` (the trial loop's ``learn``) and ``auxiliary_input(trial, done)``: what the law
  returns is checked — a numeric (N, J) array (else :class:`LawError`), finite values (else
  ``FloatingPointError``: the trial loop's "the law diverged" fault); an exception of the law's own
  code becomes one :class:`LawError` naming the law, with the law's traceback kept as ``__cause__``;
* ``auxiliary_trials`` (checked once, at build time), ``name``, ``description``, ``source`` (where
  the law came from, :func:`host.learning.registry.law_source`; summary.json's ``law_source``);
* :meth:`CheckedLaw.check`: the convergence check of :mod:`host.learning.check` on the law's
  ``iteration_map`` — "not checked" for a law without one;
* :meth:`CheckedLaw.rehearse_first_update`: the first update once on a copy of a project law
  (``ilcrig run``: first-use imports paid before the nodes watch the host).

May import: :mod:`host.learning` (check, model, protocol, registry) and :mod:`host.learning.laws.base`.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from bus.errors import IlcrigError
from host.learning.check import (
    LONG_HORIZON,
    ROBUST_INERTIA_SCALES,
    ConvergenceReport,
    IterationMap,
    check_iteration_map,
    not_checked,
)
from host.learning.laws.base import LawContext
from host.learning.model import ClosedLoopModel
from host.learning.names import PROJECT_LAW_NAMES
from host.learning.protocol import AUXILIARY, TrialData
from host.learning.registry import LawNameError, law_class, law_source

logger = logging.getLogger(__name__)

__all__ = ["CheckedLaw", "LawError", "build_law"]

Array = npt.NDArray[np.float64]


class LawError(IlcrigError):
    """A law's own code failed or returned something that cannot be a feed-forward table (one line
    naming the law; the law's own exception, if any, is the ``__cause__``)."""


def build_law(name: str, ctx: LawContext) -> CheckedLaw:
    """The law ``name`` (any name :mod:`host.learning.registry` resolves) built for ``ctx``, in its
    checked wrapper.

    :raises LawNameError: an unknown name, a plug-in that cannot be loaded, or a law that refuses
        the context (e.g. one of its options) — one line naming the law (an ``InputError``).
    """
    cls = law_class(name)
    try:
        impl = cls(ctx)
    except ValueError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise LawNameError(first if first.startswith(f"law {name!r}") else f"law {name!r}: {first}") from None
    except Exception as exc:  # noqa: BLE001 - the law's constructor failed: one line
        raise LawNameError(f"law {name!r}: cannot be built: {type(exc).__name__}: {exc}") from None
    return CheckedLaw(name, impl, ctx)


def _own_name(impl: Any, asked: str) -> str:
    """The law's own ``name`` attribute when it has one (a class resolved by ``module:Class`` or
    registered keeps its name), else the name it was asked for (also when the own name is a project
    law's and the law is not that one, e.g. a subclass of it)."""
    own = getattr(impl, "name", None)
    if not isinstance(own, str) or not own.strip() or (own in PROJECT_LAW_NAMES and own != asked):
        return asked
    return own


class CheckedLaw:
    """One law as an experiment runs it (module docstring).

    :param asked: the name the law was asked for by (``--law``, the configuration)
    :param impl: the law object (any class of the public protocol)
    :param ctx: the context it was built with
    """

    def __init__(self, asked: str, impl: Any, ctx: LawContext) -> None:
        self.impl = impl
        self.ctx = ctx
        self.gains = ctx.gains
        self.ts_s = ctx.ts_s
        #: the name the law was asked for by
        self.asked = asked
        #: the name shown in the plan line, the faults and the messages
        self.name = _own_name(impl, asked)
        self.description = str(getattr(impl, "description", "") or (type(impl).__doc__ or "")).strip()
        #: where the law came from (:func:`host.learning.registry.law_source`)
        self.source: dict[str, str] = law_source(asked)
        aux = getattr(impl, "auxiliary_trials", 0) or 0
        if isinstance(aux, bool) or not isinstance(aux, int) or aux < 0:
            raise LawNameError(f"law {asked!r}: auxiliary_trials must be an integer >= 0, got {aux!r}")
        if aux and not callable(getattr(impl, "auxiliary_input", None)):
            raise LawNameError(f"law {asked!r}: auxiliary_trials = {aux} needs an auxiliary_input(trial, done) method")
        #: extra rollouts the law needs after each learning trial (:mod:`host.learning.protocol`)
        self.auxiliary_trials: int = aux
        #: updates done so far
        self.updates = 0

    def __repr__(self) -> str:
        return f"CheckedLaw({self.name!r}, {type(self.impl).__module__}.{type(self.impl).__qualname__})"

    # -- the law's calls, checked -------------------------------------------------------------------

    def _table(self, value: Any, what: str, shape: tuple[int, ...]) -> Array:
        """``value`` as a finite float64 (N, J) table (a copy: the law may reuse its own arrays)."""
        try:
            out = np.array(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise LawError(f"law {self.name}: {what} returned no numeric array ({exc})") from exc
        if out.shape != shape:
            raise LawError(f"law {self.name}: {what} returned shape {out.shape}, expected {shape} (N, J) in N·m")
        if not np.all(np.isfinite(out)):
            raise FloatingPointError(f"law {self.name} produced a non-finite feed-forward ({what})")
        return out

    def update(self, trial: TrialData) -> Array:
        """The next learning trial's feed-forward (N, J) N·m: the law's ``update(trial)``, checked.

        :raises LawError: the law's code failed (its exception is the ``__cause__``) or returned no
            (N, J) numeric array
        :raises FloatingPointError: the law returned a non-finite value (the law diverged)
        """
        try:
            value = self.impl.update(trial)
        except (IlcrigError, FloatingPointError):
            raise
        except Exception as exc:  # noqa: BLE001 - the law's code failed: one fault of the run
            raise LawError(f"law {self.name} failed in update after trial {trial.trial}: {type(exc).__name__}: {exc}") from exc
        out = self._table(value, "update", trial.error_rad.shape)
        self.updates += 1
        return out

    #: the trial loop's name for :meth:`update`
    learn = update

    def auxiliary_input(self, trial: TrialData, done: Sequence[TrialData]) -> Array:
        """The feed-forward (N, J) N·m of the next auxiliary rollout after the learning trial
        ``trial`` (``done``: the auxiliary trials of this step so far), checked as :meth:`update`."""
        if not self.auxiliary_trials:
            raise NotImplementedError(f"law {self.name} runs no auxiliary trials")
        try:
            value = self.impl.auxiliary_input(trial, tuple(done))
        except (IlcrigError, FloatingPointError):
            raise
        except Exception as exc:  # noqa: BLE001 - the law's code failed: one fault of the run
            raise LawError(
                f"law {self.name} failed in auxiliary_input after trial {trial.trial}: {type(exc).__name__}: {exc}"
            ) from exc
        return self._table(value, f"auxiliary_input ({AUXILIARY} trial {len(done) + 1})", trial.error_rad.shape)

    # -- the convergence check -------------------------------------------------------------------

    @property
    def has_iteration_map(self) -> bool:
        """Whether the law gives its trial-to-trial map (``iteration_map``); every classic law does."""
        return callable(getattr(self.impl, "iteration_map", None))

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        """The law's linear trial-to-trial map on the plant ``model``.

        :raises NotImplementedError: the law gives none
        :raises LawError: it returned something else than an :class:`IterationMap`
        """
        if not self.has_iteration_map:
            raise NotImplementedError(f"law {self.name} gives no iteration map")
        imap = self.impl.iteration_map(model)
        if not isinstance(imap, IterationMap):
            raise LawError(f"law {self.name}: iteration_map returned {type(imap).__name__}, not an IterationMap")
        return imap

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

    # -- the rig's rehearsal ---------------------------------------------------------------------

    def rehearse_first_update(self, u0_nm: Array) -> None:
        """Run a project law's first update once, on a copy of it, with zero error and torque: what
        the update imports or compiles on first use (``scipy.signal`` for the zero-phase filters, the
        numba kernels of the lifted-model sweeps, OSQP) is paid here, before ``ilcrig run``'s nodes
        watch the host's heartbeat.  Paid after the first trial instead, an import or a compilation
        holds the GIL in long stretches, and on a busy machine the host's heartbeat thread missed
        the nodes' consumer time.  The law itself is untouched (same results); a law from outside
        the project is left alone (a copy of it could act outside itself), as is one whose copy or
        update fails here (the real update reports that in its place)."""
        if self.source.get("source") != "built-in":
            return
        u0 = np.array(u0_nm, dtype=float)
        zeros = np.zeros_like(u0)
        trial = TrialData(0, u0, zeros, zeros, zeros - u0, self.ts_s)
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                copy.deepcopy(self.impl).update(trial)
        except Exception as exc:  # noqa: BLE001 - a rehearsal; the real update raises in its place
            logger.debug("law %s: first update not rehearsed: %s", self.name, exc)
