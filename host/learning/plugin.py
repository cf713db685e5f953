"""Any law by name, built for an experiment: the built-in laws as they are, a law from outside
(:class:`host.learning.protocol.LawProtocol`) behind :class:`PluginLaw`.

This module owns :func:`build_law` (what :func:`host.experiment.plan.prepare` calls) and
:class:`PluginLaw`, the adapter that gives a protocol law the interface the trial loop and the
convergence check use (:class:`host.learning.laws.LearningLaw`): it checks what the law returns
(shape (N, J), finite), turns an exception of the law's code into one :class:`LawError` (a fault
of the run, never a traceback) and reports the check as "not checked" for a law without an
iteration map.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from bus.errors import IlcrigError
from host.learning.check import IterationMap
from host.learning.laws import LAW_CLASSES, LawContext, LearningLaw
from host.learning.model import ClosedLoopModel
from host.learning.protocol import AUXILIARY, TrialData
from host.learning.registry import LawNameError, law_class

logger = logging.getLogger(__name__)

__all__ = ["LawError", "PluginLaw", "build_law"]

Array = npt.NDArray[np.float64]


class LawError(IlcrigError):
    """A law's own code failed or returned something that cannot be a feed-forward table."""


def build_law(name: str, ctx: LawContext) -> LearningLaw:
    """The law ``name`` (any name :mod:`host.learning.registry` resolves) built for ``ctx``.

    :raises ValueError: an unknown name, a plug-in that cannot be loaded, or a law that refuses
        the context (e.g. one of its options) — one line naming the law.
    """
    if name in LAW_CLASSES:
        return LAW_CLASSES[name](ctx)
    cls = law_class(name)
    if isinstance(cls, type) and issubclass(cls, LearningLaw):
        return cls(ctx)
    try:
        impl = cls(ctx)
    except ValueError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise LawNameError(f"law {name!r}: {first}") from None
    except Exception as exc:  # noqa: BLE001 - the law's constructor failed: one line
        raise LawNameError(f"law {name!r}: cannot be built: {type(exc).__name__}: {exc}") from None
    return PluginLaw(ctx, name, impl)


class PluginLaw(LearningLaw):
    """A :class:`host.learning.protocol.LawProtocol` law behind the internal law interface.

    :param ctx: the experiment's context (given to the law's constructor already)
    :param name: the name the law was asked for by
    :param impl: the law object
    """

    name = "plug-in"
    description = "a learning law from outside the package"

    def __init__(self, ctx: LawContext, name: str, impl: Any) -> None:
        super().__init__(ctx)
        self.impl = impl
        self.name = name
        self.description = str(getattr(impl, "description", "") or getattr(type(impl), "__doc__", "") or "").strip()
        aux = getattr(impl, "auxiliary_trials", 0) or 0
        if isinstance(aux, bool) or not isinstance(aux, int) or aux < 0:
            raise LawNameError(f"law {name!r}: auxiliary_trials must be an integer >= 0, got {aux!r}")
        if aux and not callable(getattr(impl, "auxiliary_input", None)):
            raise LawNameError(f"law {name!r}: auxiliary_trials = {aux} needs an auxiliary_input(trial, done) method")
        self.auxiliary_trials = aux
        self._n = None if ctx.reference is None else int(ctx.reference.q.shape[0])

    def _table(self, value: Any, what: str, shape: tuple[int, ...]) -> Array:
        try:
            out = np.array(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise LawError(f"law {self.name}: {what} returned no numeric array ({exc})") from None
        if out.shape != shape:
            raise LawError(f"law {self.name}: {what} returned shape {out.shape}, expected {shape} (N, J) in N·m")
        return out

    def learn(self, trial: TrialData) -> Array:
        out = self._call(trial)
        self.updates += 1
        return out

    def _call(self, trial: TrialData) -> Array:
        """The law's ``update(trial)``, checked (shape, finite values)."""
        try:
            value = self.impl.update(trial)
        except (IlcrigError, FloatingPointError):
            raise
        except Exception as exc:  # noqa: BLE001 - the law's code failed: one fault of the run
            raise LawError(f"law {self.name} failed in update after trial {trial.trial}: {type(exc).__name__}: {exc}") from exc
        out = self._table(value, "update", trial.error_rad.shape)
        if not np.all(np.isfinite(out)):
            raise FloatingPointError(f"law {self.name} produced a non-finite feed-forward")
        return out

    def _update(self, u_k: Array, e_k: Array, tau_k: Array) -> Array:
        """The internal interface's form: a trial from (u, e, τ) with the feedback τ − u."""
        return self._call(TrialData(self.updates, u_k, e_k, tau_k, tau_k - u_k, self.ts_s))

    def auxiliary_input(self, trial: TrialData, done: Sequence[TrialData]) -> Array:
        try:
            value = self.impl.auxiliary_input(trial, tuple(done))
        except (IlcrigError, FloatingPointError):
            raise
        except Exception as exc:  # noqa: BLE001 - the law's code failed: one fault of the run
            raise LawError(
                f"law {self.name} failed in auxiliary_input after trial {trial.trial}: {type(exc).__name__}: {exc}"
            ) from exc
        out = self._table(value, f"auxiliary_input ({AUXILIARY} trial {len(done) + 1})", trial.error_rad.shape)
        if not np.all(np.isfinite(out)):
            raise FloatingPointError(f"law {self.name} produced a non-finite auxiliary feed-forward")
        return out

    @property
    def has_iteration_map(self) -> bool:
        return callable(getattr(self.impl, "iteration_map", None))

    def iteration_map(self, model: ClosedLoopModel) -> IterationMap:
        if not self.has_iteration_map:
            raise NotImplementedError(f"law {self.name} gives no iteration map")
        imap = self.impl.iteration_map(model)
        if not isinstance(imap, IterationMap):
            raise LawError(f"law {self.name}: iteration_map returned {type(imap).__name__}, not an IterationMap")
        return imap
