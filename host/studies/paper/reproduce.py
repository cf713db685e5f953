"""``ilcrig reproduce``: the paper's experiments (Tables 2–6, Figs. 8 and 10) and the
beyond-the-paper comparison of learning laws, as a predefined sweep on the sweep engine.

This module owns the reproduce run: its points are the experiments of
:mod:`host.studies.paper.plan` (each named by its experiment id, so the sweep folder is the one the
report reads), run by :func:`host.studies.engine.run_points` with their error arrays, followed by
the paper's report (:func:`host.studies.paper.report.write_sweep_report`) and the tidy table
(``results.parquet``), and this call in the sweep folder's ``sweep.json``
(:func:`host.studies.sweep_record.record_call`).  The sweep folder::

    <out>/sweep.json                       what was run, wall times, interruptions
    <out>/runs/<experiment-id>/            summary.json, errors.npy, point.json (host.studies.point)
    <out>/report.md, fig8.png, fig10.png, convergence_laws.png, long_runs.png   (host.studies.paper.report)
    <out>/results.parquet                  one row per experiment, trial and joint (host.studies.table)
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from bus.errors import InputError
from bus.exit_codes import EXIT_CLUSTER_LOST, exit_code_of_signal
from host.experiment.config import gains_table
from host.experiment.signal_shield import end_of_run
from host.studies.engine import WAIT_WORKERS_S, Engine, SweepOutcome, run_points
from host.studies.paper.plan import Experiment, ReproduceError, experiment_list
from host.studies.paper.report import write_sweep_report
from host.studies.spec import Point
from host.studies.sweep_record import SWEEP_SCHEMA, check_study_folder, record_call
from host.studies.table import write_table

logger = logging.getLogger(__name__)

__all__ = ["reproduce_points", "reproduce", "write_sweep_json"]


def reproduce_points(experiments: Sequence[Experiment], iterations: int) -> list[Point]:
    """The experiments as points (validated), named by their ids, in the plan's order (slowest first)."""
    points = []
    for i, e in enumerate(experiments):
        cfg = e.config(iterations)
        options = cfg.as_dict() | {"gains": gains_table(cfg.gains)}
        points.append(Point(e.id, i, options, {"experiment": e.id}, cfg))
    return points


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
    wait_workers_s: float = WAIT_WORKERS_S,
) -> tuple[int, SweepOutcome]:
    """Run the reproduction into sweep folder ``out`` and write its report.

    Returns (exit code, outcome): 0, 1 if an experiment could not run (its error.txt says why),
    130 / 143 if interrupted by SIGINT / SIGTERM, 5 if the cluster was lost (the finished experiments are kept; running again
    resumes).

    :raises InputError: bad arguments (before anything starts)."""
    if iterations < 1:
        raise InputError(f"--iterations must be >= 1, got {iterations}")
    try:
        experiments = experiment_list(only)
    except ReproduceError as exc:
        raise InputError(str(exc)) from None
    points = reproduce_points(experiments, iterations)  # every configuration validated before anything runs
    out = Path(out)
    check_study_folder(out, "sweep")  # a run's or a tuning study's folder is refused
    with Engine(workers=workers, scheduler=scheduler, dashboard=dashboard, wait_workers_s=wait_workers_s) as engine:
        where = engine.describe()
        if engine.dashboard:
            sys.stderr.write(f"ilcrig reproduce: dashboard {engine.dashboard}\n")
        outcome = run_points(engine, out, points, save_errors=True, fresh=fresh, progress=progress, desc="reproduce")
        end_of_run()  # the records from here: a signal now is logged, not raised
    write_sweep_json(out, [p.id for p in points], iterations, where, outcome)
    if outcome.cluster_lost:
        return EXIT_CLUSTER_LOST, outcome
    if outcome.signum is not None:
        return exit_code_of_signal(outcome.signum), outcome
    write_sweep_report(out, iterations)
    write_table(out, points)
    return (1 if outcome.errors else 0), outcome
