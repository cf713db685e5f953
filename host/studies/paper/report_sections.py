"""The paper's sections of the sweep report as markdown lines: Tables 2–6 beside the paper's
numbers, Figs. 8 and 10 with their first/final RMSE and settle iteration, and the repeatable /
non-repeatable split of the error (:mod:`host.studies.paper.report` puts them together)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from host.analysis.markdown import JOINTS, Floats, fmt, md_table
from host.studies.paper import paper_data
from host.studies.paper.claims import SweepRuns, experiment
from host.studies.paper.figures import plot_fig8
from host.studies.paper.paper_data import PAPER_SETTLE_ITERATIONS, TABLES, paper_value
from host.studies.paper.plan import BASELINE_LAW, DISTURBED, LAW_LABEL, PAPER_LAW, table_rows
from host.studies.settling import SPLIT_TRIALS, settle_iteration, split_repeatable

logger = logging.getLogger(__name__)

__all__ = ["table_section", "fig_section", "split_section"]

_ERR_HEADER = ["case", "source"] + [f"MaxE j{j}" for j in JOINTS] + [f"mean j{j}" for j in JOINTS]


def _metric_cells(values: Floats | None, paper: bool = False) -> list[str]:
    if values is None:
        return ["not run"] + [""] * 3
    return [paper_value(v) if paper else fmt(v) for v in values]


def table_section(key: str, runs: SweepRuns, extra_laws: Sequence[str]) -> list[str]:
    """Paper table ``key`` (MaxE and mean error after learning): the paper's rows, ours, and the
    rows of ``extra_laws`` that were run."""
    t = TABLES[key]
    if not any(runs.get(r.experiment) for r in table_rows(key) + table_rows(key, extra_laws)):
        return [f"## Table {t.number} — {t.caption}", "", f"not run in this sweep folder (`--only {key}`)", ""]
    rows = []
    for r in table_rows(key):
        if r.paper_key is not None:
            p = t.rows[r.paper_key]
            rows.append([p.case, "paper"] + _metric_cells(p.max_err_deg, True) + _metric_cells(p.mean_err_deg, True))
        run = runs.get(r.experiment)
        note = f" (fault: {run.fault})" if run is not None and run.fault else ""
        rows.append(
            [r.label + note, "ilcrig"]
            + _metric_cells(runs.final(r.experiment, "max_abs_deg"))
            + _metric_cells(runs.final(r.experiment, "mae_deg"))
        )
    for r in table_rows(key, extra_laws):
        if runs.get(r.experiment) is None:
            continue
        rows.append(
            [r.label, "ilcrig, beyond"]
            + _metric_cells(runs.final(r.experiment, "max_abs_deg"))
            + _metric_cells(runs.final(r.experiment, "mae_deg"))
        )
    return [f"## Table {t.number} — {t.caption}", ""] + md_table(_ERR_HEADER, rows) + [""]


def fig_section(runs: SweepRuns, out: Path, fig: str, dist: str) -> list[str]:
    """Fig. 8 (``dist`` = "none") or Fig. 10: the figure ``out/fig`` and the first / final RMSE of
    PD-ILC and D-ILC beside the paper's, for Fig. 8 with the settle iteration."""
    both = {law: runs.get(experiment(law, disturbance=dist)) for law in (PAPER_LAW, BASELINE_LAW)}
    pair = {k: r for k, r in both.items() if r is not None and r.summary["iterations"]}
    num = "8" if dist == "none" else "10"
    lines = [f"## Fig. {num} — RMSE vs iteration, {'no disturbance' if dist == 'none' else 'with disturbance'}", ""]
    if not pair:
        return lines + ["not run", ""]
    plot_fig8(
        out / fig, pair, f"Fig. {num}: RMSE vs iteration, path 1, 0.25 s{'' if dist == 'none' else ', disturbance ' + dist}"
    )
    lines += [f"![Fig. {num}]({fig})", ""]
    rows = []
    for law, run in pair.items():
        r = run.metric("rmse_deg")
        label = LAW_LABEL[law]
        if dist == "none" and label in paper_data.FIG8_RMSE_DEG:
            p = paper_data.FIG8_RMSE_DEG[label]
            said = str(PAPER_SETTLE_ITERATIONS) if law == PAPER_LAW else "—"
            rows.append([label, "paper"] + [paper_value(x) for x in p["initial"]] + [paper_value(x) for x in p["final"]] + [said])
        settle = [str(settle_iteration(r))] if dist == "none" else []
        rows.append([label, "ilcrig"] + [fmt(x) for x in r[0]] + [fmt(x) for x in r[-1]] + settle)
    header = ["law", "source"] + [f"first j{j}" for j in JOINTS] + [f"final j{j}" for j in JOINTS]
    header += ["settle k"] if dist == "none" else []
    lines += md_table(header, rows)
    return lines + [""]


def split_section(runs: SweepRuns) -> list[str]:
    """The repeatable and non-repeatable error of every law on path 1 with and without disturbance."""
    rows = []
    for law in (PAPER_LAW, BASELINE_LAW) + tuple(name for name in LAW_LABEL if name not in (PAPER_LAW, BASELINE_LAW)):
        for dist in ("none", DISTURBED):
            run = runs.get(experiment(law, disturbance=dist))
            if run is None or run.errors_rad.shape[0] == 0:
                continue
            rep, nonrep = split_repeatable(run.errors_rad)
            rows.append([LAW_LABEL.get(law, law), dist] + [fmt(x) for x in rep] + [fmt(x) for x in nonrep])
    if not rows:
        return []
    n = min(SPLIT_TRIALS, runs.iterations)
    return (
        [
            f"### Repeatable vs non-repeatable error (path 1, 0.25 s; RMS over the last {n} trials, deg)",
            "",
            "Repeatable = the mean error of the last trials (learnable); non-repeatable = the residual around it "
            "(changes from trial to trial; no learning law can remove it, a law with high gain at high "
            "frequency amplifies it). Without disturbance the non-repeatable part is only what learning still "
            "changes between the last trials.",
            "",
        ]
        + md_table(["law", "disturbance"] + [f"rep. j{j}" for j in JOINTS] + [f"non-rep. j{j}" for j in JOINTS], rows)
        + [""]
    )
