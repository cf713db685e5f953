"""The settings of ``ilcrig tune``: the search space and the objective.

This module owns :class:`Param` (one tuned key and its range: ``KEY=LOW:HIGH[:log|:int]`` on the
command line, ``{low, high[, log][, int]}`` in ``[tune]``), :class:`Objective` (J of one run's
summary and of a trial over its plants; defined in :mod:`host.studies.tune`'s docstring) and
:func:`tune_settings` (the spec's ``[tune]`` and ``[objective]`` under the command line's options,
:class:`TuneOverrides`).

Spec file: the sections of :mod:`host.studies.spec` and

.. code-block:: toml

    [tune]
    "gains.alpha" = { low = 1.5, high = 8.0 }
    "gains.lp_norm" = { low = 2e-4, high = 4e-3, log = true }
    "gains.lead" = { low = 1, high = 4, int = true }
    budget = 40

    [objective]
    settle_weight = 0.001   # deg per trial
    plants = 20             # Monte Carlo plants per trial (the [monte_carlo.draw] distributions)
    aggregate = "mean"      # or "max"
    require_check = true

May import what :mod:`host.studies` may import, and optuna (lazily).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from bus.errors import InputError
from host.analysis.markdown import fmt
from host.studies.settling import settle_iteration
from host.studies.spec import SweepSpec, check_key, parse_value
from host.studies.table import metrics_of

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_BUDGET", "OBJECTIVE_KEYS", "Objective", "Param", "TuneOverrides", "tune_settings"]

#: trials of a study when neither ``[tune] budget`` nor ``--budget`` says
DEFAULT_BUDGET = 30


@dataclass(frozen=True)
class Param:
    """One tuned key and its range (``log``: sampled on a log scale; ``integer``: whole numbers)."""

    key: str
    low: float
    high: float
    log: bool = False
    integer: bool = False

    @classmethod
    def parse(cls, text: str) -> Param:
        """``KEY=LOW:HIGH[:log|:int]``.

        :raises InputError: one line naming the option."""
        key, eq, rest = text.partition("=")
        parts = rest.split(":") if eq else []
        flags = {p.strip() for p in parts[2:]}
        if len(parts) < 2 or flags - {"log", "int"}:
            raise InputError(f"--param {text!r}: expected KEY=LOW:HIGH[:log|:int]")
        return cls.of(
            key.strip(),
            {"low": parse_value(parts[0]), "high": parse_value(parts[1]), "log": "log" in flags, "int": "int" in flags},
            "--param",
        )

    @classmethod
    def of(cls, key: str, table: Mapping[str, Any], where: str) -> Param:
        """A ``[tune]`` entry ``{low, high[, log][, int]}``."""
        check_key(key, where)
        if key.startswith("plant."):
            raise InputError(f"{where} {key}: plant factors are drawn (Monte Carlo), not tuned")
        bad = set(table) - {"low", "high", "log", "int"}
        low, high = table.get("low"), table.get("high")
        if bad or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in (low, high)):
            raise InputError(f"{where} {key}: a range is {{low, high[, log = true][, int = true]}} with numbers")
        assert isinstance(low, (int, float)) and isinstance(high, (int, float))
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise InputError(f"{where} {key}: needs low < high, got {low} .. {high}")
        log, integer = bool(table.get("log", False)), bool(table.get("int", False))
        if log and low <= 0:
            raise InputError(f"{where} {key}: a log range needs low > 0")
        if integer and not (float(low).is_integer() and float(high).is_integer()):
            raise InputError(f"{where} {key}: an integer range needs whole numbers")
        return cls(key, float(low), float(high), log, integer)

    def distribution(self) -> Any:
        import optuna

        if self.integer:
            return optuna.distributions.IntDistribution(int(self.low), int(self.high), log=self.log)
        return optuna.distributions.FloatDistribution(self.low, self.high, log=self.log)

    def contains(self, value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and self.low <= value <= self.high

    def describe(self) -> str:
        kind = ", log" if self.log else ""
        return f"`{self.key}` in [{fmt(self.low, 4)}, {fmt(self.high, 4)}]{kind}{', integer' if self.integer else ''}"


@dataclass(frozen=True)
class Objective:
    """J of one experiment and of a trial over its plants (module docstring)."""

    settle_weight: float = 0.0
    plants: int = 0
    aggregate: str = "mean"
    require_check: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.settle_weight) and self.settle_weight >= 0):
            raise InputError(f"settle_weight must be a number >= 0, got {self.settle_weight}")
        if self.plants < 0:
            raise InputError(f"plants must be >= 0, got {self.plants}")
        if self.aggregate not in ("mean", "max"):
            raise InputError(f"aggregate must be 'mean' or 'max', got {self.aggregate!r}")

    def of_summary(self, summary: Mapping[str, Any] | None) -> float:
        """J of one run's summary (inf: it could not run, faulted or has no finite RMSE)."""
        m = metrics_of(dict(summary) if summary is not None else None)
        final = m["final_rmse_deg"]
        if m["error"] is not None or m["fault"] or final is None or not np.all(np.isfinite(final)):
            return math.inf
        value = float(np.mean(final))
        if self.settle_weight:
            value += self.settle_weight * settle_iteration(m["rmse_deg"])
        return value

    def combine(self, values: Sequence[float]) -> float:
        """A trial's value over its plants."""
        if not values:
            return math.inf
        return float(np.mean(values)) if self.aggregate == "mean" else float(np.max(values))

    def describe(self) -> str:
        text = "J = mean over joints of the final RMSE (deg)"
        if self.settle_weight:
            text += f" + {self.settle_weight:g} × settle iteration"
        if self.plants:
            text += f"; {'mean' if self.aggregate == 'mean' else 'worst'} over {self.plants} Monte Carlo plants"
        if self.require_check:
            text += "; gains whose convergence check fails are infeasible (J = inf)"
        return text + "; a run ended by a fault: J = inf"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


#: the keys of ``[objective]`` (the fields of :class:`Objective`)
OBJECTIVE_KEYS = ("settle_weight", "plants", "aggregate", "require_check")


@dataclass(frozen=True)
class TuneOverrides:
    """What the command line sets over the spec's ``[tune]`` and ``[objective]`` (None: not given).

    :ivar params: the ``--param`` ranges as given (``KEY=LOW:HIGH[:log|:int]``)
    :ivar budget: ``--budget``, trials of the study in all
    :ivar settle_weight: ``--settle-weight``, deg per trial
    :ivar plants: ``--plants``
    :ivar aggregate: ``--aggregate``
    :ivar require_check: ``--require-check``
    """

    params: tuple[str, ...] = ()
    budget: int | None = None
    settle_weight: float | None = None
    plants: int | None = None
    aggregate: str | None = None
    require_check: bool | None = None


def tune_settings(spec: SweepSpec, overrides: TuneOverrides) -> tuple[list[Param], Objective, int]:
    """The tuned keys, the objective and the budget of ``ilcrig tune``: the spec's ``[tune]`` and
    ``[objective]`` with the command line's options over them.

    :raises InputError: a bad range, objective key or budget (one line)."""
    tune = dict(spec.extra.get("tune") or {})
    budget = tune.pop("budget", DEFAULT_BUDGET)
    params = [Param.of(k, v, "[tune]") if isinstance(v, Mapping) else _bad_tune(k) for k, v in tune.items()]
    for text in overrides.params:
        p = Param.parse(text)
        params = [q for q in params if q.key != p.key] + [p]
    obj = dict(spec.extra.get("objective") or {})
    bad = set(obj) - set(OBJECTIVE_KEYS)
    if bad:
        raise InputError(f"[objective]: unknown key(s) {', '.join(sorted(bad))}; choose from {', '.join(OBJECTIVE_KEYS)}")
    for key in OBJECTIVE_KEYS:
        if getattr(overrides, key) is not None:
            obj[key] = getattr(overrides, key)
    if overrides.budget is not None:
        budget = overrides.budget
    if isinstance(budget, bool) or not isinstance(budget, int):
        raise InputError(f"budget must be an integer, got {budget!r}")
    try:
        objective = Objective(
            settle_weight=float(obj.get("settle_weight", 0.0)),
            plants=int(obj.get("plants", 0)),
            aggregate=str(obj.get("aggregate", "mean")),
            require_check=bool(obj.get("require_check", False)),
        )
    except (TypeError, ValueError) as exc:
        raise InputError(f"[objective]: {exc}") from None
    return params, objective, budget


def _bad_tune(key: str) -> Param:
    raise InputError(f"[tune] {key}: a range is {{low, high[, log = true][, int = true]}}")
