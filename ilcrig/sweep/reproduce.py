"""``ilcrig reproduce``: the paper's experiments (Tables 2–6, Figs. 8 and 10) and the
beyond-the-paper comparison of learning laws, as a predefined sweep on the sweep engine.

This module owns the reproduce run: its points are the experiments of
:mod:`host.analysis.sweep_plan` (each named by its experiment id, so the sweep folder is the one the
report reads), run by :func:`ilcrig.sweep.engine.run_points` with their error arrays, followed by
the paper's report (:func:`host.analysis.report.write_sweep_report`) and the tidy table
(``results.parquet``), and the sweep folder's ``sweep.json`` of every sweep command
(:func:`record_call`).  The sweep folder::

    <out>/sweep.json                       what was run, wall times, interruptions
    <out>/runs/<experiment-id>/            summary.json, errors.npy, point.json (ilcrig.sweep.point)
    <out>/report.md, fig8.png, fig10.png, convergence_laws.png, long_runs.png   (host.analysis.report)
    <out>/results.parquet                  one row per experiment, trial and joint (ilcrig.sweep.table)
"""

from __future__ import annotations

import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bus.exit_codes import EXIT_INTERRUPTED
from host.analysis.report import write_sweep_report
from host.analysis.sweep_plan import Experiment, ReproduceError, experiment_list
from host.experiment.config import gains_table
from ilcrig.errors import InputError
from ilcrig.sweep.engine import Engine, SweepOutcome, run_points
from ilcrig.sweep.spec import Point
from ilcrig.sweep.table import write_table

logger = logging.getLogger(__name__)

__all__ = ["SWEEP_SCHEMA", "record_call", "reproduce_points", "reproduce", "write_sweep_json"]

SWEEP_SCHEMA = "ilcrig.sweep/1"
#: exit code of an interrupted command (host.experiment.console.EXIT_INTERRUPTED)


def reproduce_points(experiments: Sequence[Experiment], iterations: int) -> list[Point]:
    """The experiments as points (validated), named by their ids, in the plan's order (slowest first)."""
    points = []
    for i, e in enumerate(experiments):
        cfg = e.config(iterations)
        options = cfg.as_dict() | {"gains": gains_table(cfg.gains)}
        points.append(Point(e.id, i, options, {"experiment": e.id}, cfg))
    return points


def record_call(out: Path, doc: dict[str, Any], call: dict[str, Any], where: dict[str, Any], outcome: SweepOutcome) -> None:
    """Add one call of a sweep command to ``out/sweep.json``, atomically: the file becomes ``doc``
    with its ``history`` so far and this call's entry (``call``, the outcome's counts, ``where``,
    the wall time in s) at its end."""
    path = out / "sweep.json"
    try:
        prev = json.loads(path.read_text())
    except (OSError, ValueError):
        prev = {}
    history = list(prev.get("history", []))
    counts = {
        "ran": len(outcome.ran),
        "skipped": len(outcome.skipped),
        "errors": outcome.errors,
        "interrupted": outcome.interrupted,
    }
    history.append(call | counts | where | {"wall_s": round(outcome.wall_s, 3)})
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc | {"history": history}, indent=2, default=str))
    os.replace(tmp, path)


def write_sweep_json(out: Path, ids: Sequence[str], iterations: int, workers: str, outcome: SweepOutcome) -> None:
    """Add this reproduce call to ``out/sweep.json`` (:func:`record_call`)."""
    doc = {"schema": SWEEP_SCHEMA, "iterations": iterations, "experiments": list(ids)}
    record_call(out, doc, {"experiments": len(ids)}, {"jobs": workers, "iterations": iterations}, outcome)


def reproduce(
    out: Path,
    *,
    iterations: int = 10,
    only: str | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    fresh: bool = False,
    progress: bool = True,
    dashboard: bool | str = True,
) -> tuple[int, SweepOutcome]:
    """Run the reproduction into sweep folder ``out`` and write its report.

    Returns (exit code, outcome): 0, 1 if an experiment could not run (its error.txt says why),
    130 if interrupted (the finished experiments are kept; running again resumes).

    :raises InputError: bad arguments (before anything starts)."""
    if iterations < 1:
        raise InputError(f"--iterations must be >= 1, got {iterations}")
    try:
        experiments = experiment_list(only)
    except ReproduceError as exc:
        raise InputError(str(exc)) from None
    points = reproduce_points(experiments, iterations)  # every configuration validated before anything runs
    out = Path(out)
    with Engine(workers=workers, scheduler=scheduler, dashboard=dashboard) as engine:
        where = engine.describe()
        if engine.dashboard:
            sys.stderr.write(f"ilcrig reproduce: dashboard {engine.dashboard}\n")
        outcome = run_points(engine, out, points, save_errors=True, fresh=fresh, progress=progress, desc="reproduce")
    write_sweep_json(out, [p.id for p in points], iterations, where, outcome)
    if outcome.interrupted:
        return EXIT_INTERRUPTED, outcome
    write_sweep_report(out, iterations)
    write_table(out, points)
    return (1 if outcome.errors else 0), outcome


def reproduce_main(args: Any) -> int:
    """``ilcrig reproduce`` (args: out, jobs, scheduler, iterations, only, fresh, no_progress, no_dashboard)."""
    out = Path(getattr(args, "out", None) or "runs/reproduce")
    jobs = getattr(args, "jobs", None)
    scheduler = getattr(args, "scheduler", None)
    if jobs is not None and jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {jobs}")
    code, outcome = reproduce(
        out,
        iterations=10 if getattr(args, "iterations", None) is None else args.iterations,
        only=getattr(args, "only", None),
        workers=jobs if scheduler is None else None,
        scheduler=scheduler,
        fresh=bool(getattr(args, "fresh", False)),
        progress=not getattr(args, "no_progress", False),
        dashboard=not getattr(args, "no_dashboard", False),
    )
    if outcome.interrupted:
        sys.stderr.write(
            f"ilcrig: interrupted; {len(outcome.ran)} experiment(s) finished in this call are kept "
            f"in {out / 'runs'}; run again to resume\n"
        )
        return code
    on = f"{jobs or os.cpu_count()} worker(s)" if scheduler is None else scheduler
    sys.stdout.write(
        f"ilcrig reproduce: {len(outcome.ran)} run, {len(outcome.skipped)} already finished, "
        f"{outcome.wall_s:.1f} s on {on}; report: {out / 'report.md'}\n"
    )
    if outcome.errors:
        sys.stderr.write(
            f"ilcrig: {len(outcome.errors)} experiment(s) could not run: "
            f"{', '.join(sorted(outcome.errors))} (see their error.txt)\n"
        )
    return code
