"""The report of a sweep: ``report.md`` with its figures, in the sweep folder.

This module owns the report of ``ilcrig sweep`` (``ilcrig reproduce`` has the paper's report,
:mod:`host.studies.paper.report`): what was swept, how many points finished, the final RMSE (the last
learning trial's, per joint) across the grid (``grid.png``: against the first varied key, one line
per combination of the others; with Monte Carlo draws the median over the samples and the 5–95 %
band), the distribution over the Monte Carlo plants (``montecarlo.png``: a histogram per joint,
one per grid point, and the quantiles as a table), and the points.
"""

from __future__ import annotations

import itertools
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from host.analysis.figures import figure, save_png
from host.analysis.markdown import JOINTS, fmt, md_table
from host.studies.spec import Point, SweepSpec
from host.studies.table import TABLE_FILE, final_metrics

logger = logging.getLogger(__name__)

__all__ = ["write_report", "MAX_LISTED_POINTS", "MAX_LINES"]

#: the report lists every point up to this many (the table has them all)
MAX_LISTED_POINTS = 200
#: at most this many lines (grid) or histograms (Monte Carlo) per panel
MAX_LINES = 8
QUANTILES = (0.05, 0.5, 0.95)


def _value_text(v: Any) -> str:
    return fmt(v, 4) if isinstance(v, float) else str(v)


def _grid_key(p: Point, keys: Sequence[str]) -> tuple[Any, ...]:
    return tuple(p.labels.get(k) for k in keys)


def _final(m: dict[str, Any]) -> np.ndarray | None:
    return None if m["final_rmse_deg"] is None or m["fault"] else np.asarray(m["final_rmse_deg"], dtype=float)


def _groups(
    spec: SweepSpec, points: Sequence[Point], metrics: dict[str, dict[str, Any]]
) -> dict[tuple[Any, ...], list[np.ndarray]]:
    """Grid point (values of the varied keys) → the final RMSE (4,) of each finished sample."""
    keys = list(spec.vary)
    groups: dict[tuple[Any, ...], list[np.ndarray]] = {}
    for p in points:
        f = _final(metrics[p.id])
        groups.setdefault(_grid_key(p, keys), [])
        if f is not None:
            groups[_grid_key(p, keys)].append(f)
    return groups


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def plot_grid(path: Path, spec: SweepSpec, groups: dict[tuple[Any, ...], list[np.ndarray]]) -> Path | None:
    """Final RMSE per joint against the first varied key (``path``), or None with nothing to plot."""
    keys = list(spec.vary)
    if not keys or not any(groups.values()):
        return None
    x_key, rest = keys[0], keys[1:]
    x_vals = list(spec.vary[x_key])
    numeric = all(_is_number(v) for v in x_vals)
    xs = np.array(x_vals, dtype=float) if numeric else np.arange(len(x_vals), dtype=float)
    combos = list(itertools.product(*(spec.vary[k] for k in rest)))[:MAX_LINES]
    fig, ax = figure(2, 2, 11, 7)
    for j in JOINTS:
        a = ax[(j - 1) // 2, (j - 1) % 2]
        for combo in combos:
            med, lo, hi = [], [], []
            for xv in x_vals:
                vals = groups.get((xv, *combo), [])
                col = np.array([v[j - 1] for v in vals]) if vals else np.array([np.nan])
                q = np.nanquantile(col, QUANTILES) if np.isfinite(col).any() else np.full(3, np.nan)
                lo.append(q[0])
                med.append(q[1])
                hi.append(q[2])
            label = ", ".join(f"{k} = {_value_text(v)}" for k, v in zip(rest, combo)) or None
            line = a.plot(xs, med, marker="o", label=label)[0]
            if spec.samples > 1:
                a.fill_between(xs, lo, hi, color=line.get_color(), alpha=0.2)
        a.set_title(f"joint {j}")
        a.set_xlabel(x_key)
        a.set_ylabel("final RMSE [deg]" + (" (median, 5–95 %)" if spec.samples > 1 else ""))
        if numeric and len(xs) > 2 and xs.min() > 0 and xs.max() / xs.min() > 20:
            a.set_xscale("log")
        if not numeric:
            a.set_xticks(xs)
            a.set_xticklabels([str(v) for v in x_vals], rotation=30)
        a.set_yscale("log")
        a.grid(True, which="both", alpha=0.3)
        if rest and j == 1:
            a.legend(fontsize=7)
    return save_png(fig, path)


def plot_monte_carlo(path: Path, spec: SweepSpec, groups: dict[tuple[Any, ...], list[np.ndarray]]) -> Path | None:
    """Histograms of the final RMSE over the Monte Carlo plants, per joint (``path``)."""
    finite = [v for vals in groups.values() for v in vals if np.all(np.isfinite(v)) and np.all(v > 0)]
    if not finite:
        return None
    allv = np.array(finite)
    fig, ax = figure(2, 2, 11, 7)
    for j in JOINTS:
        a = ax[(j - 1) // 2, (j - 1) % 2]
        col = allv[:, j - 1]
        bins = np.geomspace(col.min() * 0.95, col.max() * 1.05, 30) if col.max() > col.min() else 10
        for key, vals in list(groups.items())[:MAX_LINES]:
            v = np.array([x[j - 1] for x in vals if np.all(np.isfinite(x)) and np.all(x > 0)])
            if not len(v):
                continue
            label = ", ".join(f"{k} = {_value_text(x)}" for k, x in zip(spec.vary, key)) or f"{len(v)} plants"
            a.hist(v, bins=bins, alpha=0.55, label=label)
        if col.max() > col.min():
            a.set_xscale("log")
        a.set_title(f"joint {j}")
        a.set_xlabel("final RMSE [deg]")
        a.set_ylabel("plants")
        a.grid(True, alpha=0.3)
        if j == 1:
            a.legend(fontsize=7)
    return save_png(fig, path)


def _describe(spec: SweepSpec, base: dict[str, Any]) -> list[str]:
    lines = []
    if base:
        shown = ", ".join(f"`{k}` = {v!r}" for k, v in sorted(base.items()) if k not in ("gains", "law_options", "plant"))
        for table in ("gains", "law_options", "plant"):
            for k, v in sorted((base.get(table) or {}).items()):
                shown += f", `{table}.{k}` = {v!r}"
        lines.append(f"- base: {shown.lstrip(', ')}")
    for k, vals in spec.vary.items():
        lines.append(f"- varied `{k}`: {', '.join(_value_text(v) for v in vals)}")
    for d in spec.draws:
        lines.append(f"- drawn `{d.key}` ~ {d.dist}({', '.join(str(x) for x in d.params)})")
    if spec.samples:
        lines.append(f"- Monte Carlo: {spec.samples} samples per grid point, seed {spec.seed}")
    return lines


def write_report(out: Path, spec: SweepSpec, points: Sequence[Point], wall_s: float | None = None) -> Path:
    """Write ``out/report.md`` and its figures for the finished points of ``points``."""
    out = Path(out)
    metrics = final_metrics(out, points)
    done = [p for p in points if metrics[p.id]["error"] is None]
    faults = [p for p in done if metrics[p.id]["fault"]]
    errors = [p for p in points if metrics[p.id]["error"] not in (None, "not run")]
    lines = [
        f"# ilcrig sweep — {out.name}",
        "",
        f"{len(points)} points: {len(done)} finished ({len(faults)} of them ended by a fault), "
        f"{len(errors)} could not run, {len(points) - len(done) - len(errors)} not run yet"
        + (f"; {wall_s:.1f} s in the last call" if wall_s is not None else "")
        + f". Every point, trial and joint: `{TABLE_FILE}`.",
        "",
        "Final RMSE = the RMSE of a point's last learning trial, per joint, in degrees.",
        "",
    ]
    lines += _describe(spec, spec.base_options()) + [""]
    groups = _groups(spec, points, metrics)
    if spec.vary:
        lines += ["## Final RMSE across the grid", ""]
        fig = plot_grid(out / "grid.png", spec, groups)
        lines += [f"![final RMSE across the grid]({fig.name})", ""] if fig else ["no finished point to plot", ""]
        header = [f"`{k}`" for k in spec.vary] + [f"RMSE j{j}" for j in JOINTS] + (["plants"] if spec.samples else [])
        rows = []
        for key, vals in groups.items():
            med = np.median(np.array(vals), axis=0) if vals else [None] * 4
            rows.append([_value_text(v) for v in key] + [fmt(v) for v in med] + ([str(len(vals))] if spec.samples else []))
        lines += md_table(header, rows[:MAX_LISTED_POINTS]) + [""]
        if spec.samples:
            lines += ["(the median over each grid point's Monte Carlo plants)", ""]
    if spec.samples:
        lines += [f"## Monte Carlo: the final RMSE over {spec.samples} plants per grid point", ""]
        fig = plot_monte_carlo(out / "montecarlo.png", spec, groups)
        lines += [f"![final RMSE over the plants]({fig.name})", ""] if fig else ["no finished point to plot", ""]
        header = [f"`{k}`" for k in spec.vary] + ["plants", "faults"]
        header += [f"j{j} {lab}" for j in JOINTS for lab in ("median", "95 %", "max")]
        rows = []
        by_key: dict[tuple[Any, ...], list[Point]] = {}
        for p in points:
            by_key.setdefault(_grid_key(p, list(spec.vary)), []).append(p)
        for key, pts in by_key.items():
            finished = groups.get(key) or []
            table = np.array(finished) if finished else np.full((1, 4), np.nan)
            n_fault = sum(1 for p in pts if metrics[p.id]["fault"])
            row = [_value_text(v) for v in key] + [str(len(groups.get(key) or [])), str(n_fault)]
            for j in JOINTS:
                col = table[:, j - 1]
                ok = np.isfinite(col).any()
                row += [
                    fmt(float(np.nanmedian(col))) if ok else "—",
                    fmt(float(np.nanquantile(col, 0.95))) if ok else "—",
                    fmt(float(np.nanmax(col))) if ok else "—",
                ]
            rows.append(row)
        lines += md_table(header, rows[:MAX_LISTED_POINTS]) + [""]
    lines += ["## Points", ""]
    if len(points) > MAX_LISTED_POINTS:
        lines += [f"{len(points)} points: see `{TABLE_FILE}`.", ""]
    else:
        keys = spec.varied_keys
        header = ["point"] + [f"`{k}`" for k in keys] + [f"RMSE j{j}" for j in JOINTS] + ["status", "digest"]
        rows = []
        for p in points:
            m = metrics[p.id]
            f = m["final_rmse_deg"]
            status = m["error"] or (f"fault: {m['fault']}" if m["fault"] else "completed")
            rows.append(
                [p.id]
                + [_value_text(p.labels.get(k)) for k in keys]
                + [fmt(v) for v in (f if f is not None else [None] * 4)]
                + [status, (m["digest"] or "")[:16]]
            )
        lines += md_table(header, rows) + [""]
    path = out / "report.md"
    tmp = out / "report.md.tmp"
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path
