"""The paper's claims judged on the finished runs of a sweep folder: :class:`SweepRuns` (the runs,
looked up by experiment), :func:`claims_for_law` (every claim for the paper's law or a law beyond
it) and :func:`paper_self_check` (the same rules applied to the paper's own numbers, which shows
the rules are calibrated).  The rules themselves are :mod:`host.studies.paper.verdicts` and
:mod:`host.studies.paper.convergence_verdicts`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from host.studies.paper import paper_data
from host.studies.paper.convergence_verdicts import (
    criterion_disturbance,
    criterion_long,
    criterion_settle,
    verdict_disturbance,
    verdict_long_bounded,
    verdict_settle,
)
from host.studies.paper.paper_data import TABLES
from host.studies.paper.plan import (
    BASELINE_LAW,
    DISTURBED,
    LAW_LABEL,
    LONG_TRIALS,
    PAPER_LAW,
    Experiment,
    RunData,
    all_experiments,
    load_run,
)
from host.studies.paper.verdicts import (
    CRITERION_CYCLES,
    CRITERION_PROFILES_ORDER,
    Verdict,
    criterion_beats,
    criterion_paths,
    criterion_profiles_similar,
    missing,
    verdict_beats,
    verdict_cycles,
    verdict_floor_raised,
    verdict_paths,
    verdict_profiles_order,
    verdict_profiles_similar,
)
from host.studies.settling import settle_iteration, settled_floor

logger = logging.getLogger(__name__)

__all__ = [
    "SweepRuns",
    "experiment",
    "claims_for_law",
    "paper_self_check",
    "settle_of",
    "disturbed_floor",
    "long_settle",
    "long_verdict",
    "long_verdicts",
]


def experiment(law: str, **kw: Any) -> Experiment:
    """The sweep's experiment of ``law`` with the given settings (path 1, 0.25 s, … otherwise)."""
    return Experiment(law=law, **kw)


_K = TypeVar("_K")


class SweepRuns:
    """Finished runs of a sweep folder, looked up by experiment."""

    def __init__(self, out: Path, iterations: int) -> None:
        self.out, self.iterations = out, iterations
        self.by_id: dict[str, RunData] = {}
        for e in all_experiments():
            r = load_run(out, e, iterations)
            if r is not None:
                self.by_id[e.id] = r

    def get(self, e: Experiment) -> RunData | None:
        """The finished run of ``e`` (it may have ended by a fault before its first trial)."""
        return self.by_id.get(e.id)

    def usable(self, e: Experiment) -> RunData | None:
        """The finished run of ``e`` if it has at least one trial (what a verdict can judge)."""
        r = self.by_id.get(e.id)
        return r if r is not None and r.summary["iterations"] else None

    def final(self, e: Experiment, metric: str) -> np.ndarray | None:
        """The last trial's per-joint ``metric`` of ``e`` (None: no run, or no trial)."""
        r = self.get(e)
        return None if r is None or not r.summary["iterations"] else r.metric(metric)[-1]

    def need(self, e: Experiment) -> RunData:
        """:meth:`get` where the caller has checked that the run exists.

        :raises LookupError: it does not.
        """
        r = self.get(e)
        if r is None:
            raise LookupError(f"experiment {e.id}: no finished run in {self.out}")
        return r

    def need_final(self, e: Experiment, metric: str) -> np.ndarray:
        """:meth:`final` where the caller has checked that the run exists.

        :raises LookupError: no finished run, or a run without a trial.
        """
        v = self.final(e, metric)
        if v is None:
            raise LookupError(f"experiment {e.id}: no finished run with a trial in {self.out}")
        return v

    def floors(self, e: Experiment) -> tuple[np.ndarray, np.ndarray]:
        """The errors a run converged to: (MaxE, MAE) per joint of its last trial, deg
        (:meth:`need_final`: the caller has checked that the run exists)."""
        return self.need_final(e, "max_abs_deg"), self.need_final(e, "mae_deg")

    def floors_by(self, exps: Mapping[_K, Experiment]) -> tuple[dict[_K, np.ndarray], dict[_K, np.ndarray]]:
        """:meth:`floors` of several runs keyed alike: (MaxE by key, MAE by key)."""
        floors = {k: self.floors(e) for k, e in exps.items()}
        return {k: f[0] for k, f in floors.items()}, {k: f[1] for k, f in floors.items()}


def settle_of(runs: SweepRuns, e: Experiment) -> int | None:
    """The settle iteration of ``e``'s run (None: not run, or no trial)."""
    run = runs.usable(e)
    return None if run is None else settle_iteration(run.metric("rmse_deg"))


def disturbed_floor(runs: SweepRuns, law: str, trials: int | None = None) -> np.ndarray | None:
    """The floor per joint, deg, of ``law``'s run with disturbance: its mean RMSE from the settle
    iteration of the same run without disturbance on (None: either run missing)."""
    run = runs.usable(experiment(law, disturbance=DISTURBED, trials=trials))
    settle = settle_of(runs, experiment(law, trials=trials))
    if run is None or settle is None:
        return None
    return settled_floor(run.metric("rmse_deg"), settle=settle).floor_deg


def long_settle(runs: SweepRuns, law: str) -> int | None:
    """The settle iteration of ``law``'s long runs: of its long run without disturbance over the
    paper's horizon (its first ``runs.iterations`` trials); None: that run is missing."""
    ref = runs.usable(experiment(law, trials=LONG_TRIALS))
    if ref is None:
        return None
    return settle_iteration(ref.metric("rmse_deg")[: runs.iterations])


def long_verdict(runs: SweepRuns, law: str, dist: str, claim: str = "the error stays bounded over a long run") -> Verdict:
    """The long-run verdict of ``law`` with disturbance ``dist`` (:func:`long_settle`)."""
    e = experiment(law, disturbance=dist, trials=LONG_TRIALS)
    run = runs.usable(e)
    if run is None:
        return missing(claim, e.id, criterion_long())
    settle = long_settle(runs, law)
    if settle is None:
        return missing(claim, f"{experiment(law, trials=LONG_TRIALS).id}, whose settle iteration it takes", criterion_long())
    return verdict_long_bounded(run.metric("rmse_deg"), settle, claim=claim)


def long_verdicts(runs: SweepRuns, law: str) -> dict[str, Verdict]:
    """The long-run verdict of ``law`` per disturbance ("none", DISTURBED) that was run."""
    return {
        dist: long_verdict(runs, law, dist)
        for dist in ("none", DISTURBED)
        if runs.usable(experiment(law, disturbance=dist, trials=LONG_TRIALS)) is not None
    }


def _verdict_finals(runs: SweepRuns, law: str, v: dict[str, Verdict]) -> None:
    """Tables 2, 4, 5, 6: the verdicts on the errors after learning."""
    label = LAW_LABEL.get(law, law)
    C = paper_data.CLAIMS
    a, b = experiment(law), experiment(BASELINE_LAW)
    if law != BASELINE_LAW:
        claim = C["table2"] if law == PAPER_LAW else f"{label} gives smaller MaxE and mean error than D-ILC on every joint"
        if runs.usable(a) and runs.usable(b):
            v["table2"] = verdict_beats(*runs.floors(a), *runs.floors(b), label, "D-ILC", claim)
        else:
            v["table2"] = missing(claim, f"{a.id}, {b.id}", criterion_beats(label, "D-ILC"))
    claim = C["table4"] if law == PAPER_LAW else f"with {label}, the converged errors are similar across the paths"
    ps = {p: experiment(law, path=p) for p in ("1", "2", "3", "4")}
    if all(runs.usable(e) for e in ps.values()):
        v["table4"] = verdict_paths(*runs.floors_by(ps), claim=claim)
    else:
        v["table4"] = missing(claim, "paths 1-4", criterion_paths())
    claim = C["table5"] if law == PAPER_LAW else f"with {label}, slower cycles give smaller errors on every joint"
    cs = {c: experiment(law, cycle_s=c) for c in (0.15, 0.25, 0.50)}
    if all(runs.usable(e) for e in cs.values()):
        v["table5"] = verdict_cycles(*runs.floors_by(cs), claim=claim)
    else:
        v["table5"] = missing(claim, "0.15/0.25/0.50 s", CRITERION_CYCLES)
    p5 = experiment(law, profile="poly5")
    for key in ("table6_similar", "table6_order"):
        claim = C[key] if law == PAPER_LAW else f"{label}: " + C[key].split(" (Table")[0]
        if not (runs.usable(a) and runs.usable(p5)):
            crit = criterion_profiles_similar() if key == "table6_similar" else CRITERION_PROFILES_ORDER
            v[key] = missing(claim, p5.id, crit)
        elif key == "table6_similar":
            v[key] = verdict_profiles_similar(*runs.floors(a), *runs.floors(p5), claim=claim)
        else:
            v[key] = verdict_profiles_order(runs.need_final(a, "mae_deg"), runs.need_final(p5, "mae_deg"), claim=claim)


def _verdict_histories(runs: SweepRuns, law: str, v: dict[str, Verdict]) -> None:
    """Fig. 8, Table 3 and the long runs: the verdicts on RMSE histories."""
    label = LAW_LABEL.get(law, law)
    C = paper_data.CLAIMS
    a, d = experiment(law), experiment(law, disturbance=DISTURBED)
    claim = C["fig8_settle"] if law == PAPER_LAW else f"{label} errors settle within about 4 iterations"
    v["fig8_settle"] = (
        verdict_settle(runs.need(a).metric("rmse_deg"), law=label, claim=claim)
        if runs.usable(a)
        else missing(claim, a.id, criterion_settle())
    )
    claim = C["table3"] if law == PAPER_LAW else f"with {label}, a disturbance raises the floor but the error stays bounded"
    v["table3"] = (
        verdict_disturbance(runs.need(a).metric("rmse_deg"), runs.need(d).metric("rmse_deg"), law=label, claim=claim)
        if runs.usable(a) and runs.usable(d)
        else missing(claim, f"{a.id}, {d.id}", criterion_disturbance())
    )
    for key, dist in (("long_none", "none"), ("long_dist", DISTURBED)):
        claim = C[key] if law == PAPER_LAW else C[key].replace("PD-ILC", label).split(" (Fig.")[0]
        v[key] = long_verdict(runs, law, dist, claim)
    t3 = v["table3"]
    if t3.holds is False and "unbounded" in t3.detail and v["long_dist"].holds:
        v["table3"] = Verdict(
            t3.claim,
            False,
            t3.detail + f"; but the {LONG_TRIALS}-trial disturbed run stays bounded, "
            "so this short-run growth is more likely trial-to-trial scatter than divergence",
            t3.criterion,
        )


def claims_for_law(runs: SweepRuns, law: str) -> dict[str, Verdict]:
    """Every claim evaluated for ``law`` (the paper's law or one beyond it) on the runs, keyed as
    :data:`host.studies.paper.paper_data.CLAIMS` (without ``fig8_dilc_rise``)."""
    v: dict[str, Verdict] = {}
    _verdict_finals(runs, law, v)
    _verdict_histories(runs, law, v)
    return v


def paper_self_check() -> dict[str, Verdict]:
    """The same rules applied to the paper's own numbers (shows they are calibrated)."""
    T2, T3, T4, T5, T6 = (TABLES[k] for k in ("table2", "table3", "table4", "table5", "table6"))
    return {
        "table2": verdict_beats(*T2.rows["PD-ILC"].floors, *T2.rows["D-ILC"].floors),
        "table3": verdict_floor_raised(T3.rows["none"].mean_err_deg, T3.rows["both"].mean_err_deg),
        "table4": verdict_paths({k: r.max_err_deg for k, r in T4.rows.items()}, {k: r.mean_err_deg for k, r in T4.rows.items()}),
        "table5": verdict_cycles(
            {float(k): r.max_err_deg for k, r in T5.rows.items()}, {float(k): r.mean_err_deg for k, r in T5.rows.items()}
        ),
        "table6_similar": verdict_profiles_similar(*T6.rows["poly4567"].floors, *T6.rows["poly5"].floors),
        "table6_order": verdict_profiles_order(T6.rows["poly4567"].mean_err_deg, T6.rows["poly5"].mean_err_deg),
    }
