"""The experiment plan of ``ilcrig reproduce``: which configuration stands behind which row of
the paper's Tables 2–6, Figs. 8 and 10, and the beyond-the-paper comparison of learning laws;
the experiments' folders in the sweep folder and the loading of finished runs (a finished run:
:func:`host.studies.point.is_finished`).

Motion law: the paper's Tables 2–5 use its 4-5-6-7 polynomial law (Table 6 compares it with the
5th-order law), so every paper-table experiment here uses ``profile = "poly4567"`` — Table 6 then
compares 4567 and 5 on the same footing.

Beyond the paper: the same tables for ``pd-ilc-q``, ``q-ilc``, ``no-ilc``, ``no-ilc-id`` and the
plug-in laws ``cno-ilc`` (constrained norm-optimal) and ``adjoint-ilc`` (model-free gradient), every
law on path 1 with and without disturbance, every law for a fixed ``LONG_TRIALS`` = 200 trials
(long-run stability), and the torque-limit comparison at ``LIMIT_CYCLE_S`` (:data:`LIMIT_LAWS`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.experiment.config import ExperimentConfig, build_config
from host.experiment.outputs import read_summary
from host.learning.names import LAWS
from host.studies.point import is_finished

logger = logging.getLogger(__name__)

__all__ = [
    "LAW_LABEL",
    "Experiment",
    "TableRow",
    "GROUPS",
    "PAPER_LAW",
    "BASELINE_LAW",
    "BEYOND_LAWS",
    "PLUGIN_LAWS",
    "LIMIT_LAWS",
    "LIMIT_CYCLE_S",
    "limit_experiments",
    "PROFILE",
    "LONG_TRIALS",
    "DISTURBED",
    "ReproduceError",
    "group_experiments",
    "experiment_list",
    "table_rows",
    "all_experiments",
    "run_dir_of",
    "load_run",
    "RunData",
]


#: display names of the learning laws, in the order the reports list them
LAW_LABEL = {
    "pd-ilc": "PD-ILC",
    "pd-ilc-q": "PD-ILC-Q",
    "d-ilc": "D-ILC",
    "q-ilc": "Q-ILC",
    "no-ilc": "NO-ILC",
    "no-ilc-id": "NO-ILC-ID",
    "pd-ol": "PD-OL",
    "p-ol": "P-OL",
    "cno-ilc": "CNO-ILC",
    "adjoint-ilc": "ADJOINT-ILC",
}

#: the paper's law, its baseline, and the laws shown beyond the paper's tables
PAPER_LAW = "pd-ilc"
BASELINE_LAW = "d-ilc"
#: ilcrig's laws registered as plug-ins (entry points ilcrig.laws), written against the public protocol
PLUGIN_LAWS: tuple[str, ...] = ("cno-ilc", "adjoint-ilc")
BEYOND_LAWS: tuple[str, ...] = ("pd-ilc-q", "q-ilc", "no-ilc", "no-ilc-id") + PLUGIN_LAWS
#: the torque-limit comparison: at this cycle (4-5-6-7 law) the emulated robot needs more than the
#: drives' 264.6 N·m while the nominal model passes the feasibility check (0.15 s, the paper's Table 5
#: row, peaks at about 200 N·m); the laws compared there
LIMIT_CYCLE_S = 0.125
LIMIT_LAWS: tuple[str, ...] = ("pd-ilc", "no-ilc-id", "cno-ilc")
#: motion law of every paper-table experiment (the paper's 4-5-6-7 polynomial law)
PROFILE = "poly4567"
#: base condition of the paper: path 1, 0.25 s single journey
BASE_PATH = "1"
BASE_CYCLE_S = 0.25
#: --only groups
GROUPS: tuple[str, ...] = ("table2", "table3", "table4", "table5", "table6", "figs", "beyond")
PATHS: tuple[str, ...] = ("1", "2", "3", "4")
CYCLES_S: tuple[float, ...] = (0.25, 0.15, 0.50)  # the paper's row order in Table 5
PROFILES_T6: tuple[str, ...] = ("poly4567", "poly5")
#: the paper's disturbed case ("repetitive and non-repetitive", §5.2)
DISTURBED = "both"
#: trials of the long-run stability experiments (beyond the paper's horizon of about 10)
LONG_TRIALS = 200


class ReproduceError(ValueError):
    """Bad ``reproduce`` arguments (unknown --only group, --jobs < 1, ...)."""


@dataclass(frozen=True)
class Experiment:
    """One configuration of the sweep (all other settings are the project defaults).

    ``trials`` fixes the number of trials (the long-run stability experiments); ``None`` takes the
    sweep's ``--iterations``."""

    law: str
    path: str = BASE_PATH
    cycle_s: float = BASE_CYCLE_S
    profile: str = PROFILE
    disturbance: str = "none"
    trials: int | None = None

    @property
    def id(self) -> str:
        """Folder name, e.g. ``pd-ilc_p1_250ms_poly4567_none`` (``…_k200`` for a fixed 200 trials)."""
        base = f"{self.law}_p{self.path}_{round(self.cycle_s * 1000)}ms_{self.profile}_{self.disturbance}"
        return base if self.trials is None else f"{base}_k{self.trials}"

    def config(self, iterations: int) -> ExperimentConfig:
        return build_config(
            None,
            {
                "law": self.law,
                "path": self.path,
                "cycle_s": self.cycle_s,
                "profile": self.profile,
                "disturbance": self.disturbance,
                "iterations": self.trials if self.trials is not None else iterations,
            },
        )

    def describe(self) -> str:
        return f"{self.law}, path {self.path}, {self.cycle_s:g} s, {self.profile}, disturbance {self.disturbance}" + (
            "" if self.trials is None else f", {self.trials} trials"
        )


@dataclass(frozen=True)
class TableRow:
    """A row of one of our tables: the experiment behind it and the paper row it stands beside."""

    table: str  # "table2" ...
    label: str
    experiment: Experiment
    paper_key: str | None  # key into host.studies.paper.paper_data.TABLES[table].rows; None = beyond the paper
    law: str


def _base(law: str, **kw: Any) -> Experiment:
    return Experiment(law=law, **kw)


def table_rows(table: str, laws: Sequence[str] | None = None) -> list[TableRow]:
    """The rows of our version of a paper table for the given laws (default: the paper's)."""
    rows: list[TableRow] = []
    if table == "table2":
        for law in laws or (PAPER_LAW, BASELINE_LAW):
            key = {PAPER_LAW: "PD-ILC", BASELINE_LAW: "D-ILC"}.get(law)
            rows.append(TableRow(table, law.upper(), _base(law), key, law))
        return rows
    for law in laws or (PAPER_LAW,):
        paper = law == PAPER_LAW
        if table == "table3":
            for dist, label in (("none", "no disturbance"), (DISTURBED, "disturbance")):
                rows.append(
                    TableRow(table, f"{law.upper()}, {label}", _base(law, disturbance=dist), dist if paper else None, law)
                )
        elif table == "table4":
            for p in PATHS:
                rows.append(TableRow(table, f"{law.upper()}, path {p}", _base(law, path=p), p if paper else None, law))
        elif table == "table5":
            for c in CYCLES_S:
                rows.append(
                    TableRow(table, f"{law.upper()}, {c:.2f} s", _base(law, cycle_s=c), f"{c:.2f}" if paper else None, law)
                )
        elif table == "table6":
            for prof in PROFILES_T6:
                label = "4-5-6-7" if prof == "poly4567" else "5th order"
                rows.append(TableRow(table, f"{law.upper()}, {label}", _base(law, profile=prof), prof if paper else None, law))
        else:
            raise ReproduceError(f"unknown table {table!r}")
    return rows


def group_experiments(group: str) -> list[Experiment]:
    """The experiments one ``--only`` group needs."""
    if group in ("table2", "table3", "table4", "table5", "table6"):
        return [r.experiment for r in table_rows(group)]
    if group == "figs":  # Figs. 8 and 10: PD-ILC and D-ILC without and with disturbance
        return [_base(law, disturbance=d) for law in (PAPER_LAW, BASELINE_LAW) for d in ("none", DISTURBED)]
    if group == "beyond":
        laws = LAWS + PLUGIN_LAWS
        exps = [_base(law, disturbance=d) for law in laws for d in ("none", DISTURBED)]
        exps += [_base(law, disturbance=d, trials=LONG_TRIALS) for law in laws for d in ("none", DISTURBED)]
        exps += limit_experiments()
        for t in ("table3", "table4", "table5", "table6"):
            exps += [r.experiment for r in table_rows(t, BEYOND_LAWS)]
        return exps
    raise ReproduceError(f"unknown --only group {group!r}; choose from {', '.join(GROUPS)}")


def limit_experiments() -> list[Experiment]:
    """The torque-limit comparison: :data:`LIMIT_LAWS` at :data:`LIMIT_CYCLE_S` and at 0.15 s."""
    return [_base(law, cycle_s=c) for c in (LIMIT_CYCLE_S, 0.15) for law in LIMIT_LAWS]


def _parse_only(only: str | Iterable[str] | None) -> list[str]:
    if only is None:
        return list(GROUPS)
    names = [s.strip() for s in (only.split(",") if isinstance(only, str) else only) if s.strip()]
    if not names:
        raise ReproduceError("--only needs at least one group")
    bad = [n for n in names if n not in GROUPS]
    if bad:
        raise ReproduceError(f"unknown --only group(s) {', '.join(bad)}; choose from {', '.join(GROUPS)}")
    return names


def experiment_list(only: str | Iterable[str] | None = None) -> list[Experiment]:
    """The de-duplicated experiments of the selected groups (default: all), in a stable order
    with the slowest (longest cycles, model-based laws) first so the pool finishes evenly."""
    seen: dict[str, Experiment] = {}
    for g in _parse_only(only):
        for e in group_experiments(g):
            seen.setdefault(e.id, e)
    cost = {"q-ilc": 1.5, "pd-ilc-q": 1.5, "no-ilc": 1.2, "no-ilc-id": 1.2, "cno-ilc": 3.0}
    return sorted(seen.values(), key=lambda e: (-e.cycle_s * cost.get(e.law, 1.0) * (e.trials or 10) / 10, e.id))


def all_experiments() -> list[Experiment]:
    return experiment_list(None)


# ----------------------------------------------------------------------------------------- run folders


def run_dir_of(out: Path, exp: Experiment) -> Path:
    return Path(out) / "runs" / exp.id


@dataclass
class RunData:
    """A finished experiment as the report needs it."""

    experiment: Experiment
    summary: dict[str, Any]
    errors_rad: np.ndarray  # (K, N, 4) float32, q_d − q per trial

    def metric(self, name: str) -> np.ndarray:
        """(K, 4) per-trial metric, deg: ``rmse_deg``, ``max_abs_deg`` or ``mae_deg``."""
        return np.array([it[name] for it in self.summary["iterations"]], dtype=float).reshape(-1, 4)

    @property
    def fault(self) -> str | None:
        f = self.summary.get("faults") or []
        return f[0]["message"] if f else None


def load_run(out: Path, exp: Experiment, iterations: int) -> RunData | None:
    """The finished run of ``exp`` in sweep folder ``out`` with ``iterations`` trials, or None."""
    d = run_dir_of(out, exp)
    if not is_finished(d, exp.config(iterations)):
        return None
    summary = read_summary(d)
    assert summary is not None
    return RunData(exp, summary, np.load(d / "errors.npy"))
