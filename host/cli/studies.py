"""The study commands of the command line: ``ilcrig sweep``, ``ilcrig tune``, ``ilcrig reproduce``.

This module owns their options and what they do with them, self-contained so the command line
only calls it: :func:`add_sweep_parser`, :func:`add_tune_parser` and :func:`add_reproduce_parser`
each add one subcommand with all its options and its handler (:func:`sweep_main`,
:func:`tune_main`, :func:`reproduce_main`): build the points, run them on the engine, write the
table and the report, and print one closing line.  Bad input is a :class:`bus.errors.InputError`
(one line, exit code 2) raised before anything starts, among it an ``--out`` that holds a run or
another study (:func:`host.studies.sweep_record.check_study_folder`); an interrupted sweep returns
130 / 143 (SIGINT / SIGTERM; the handlers of :mod:`host.experiment.signal_shield` cover the whole
command, a signal once the points ran is only logged while the records are written) and a lost
scheduler or a cluster without workers returns 5 (``EXIT_CLUSTER_LOST``), one line each, with every
finished point kept for the resume.

May import: what ``host.cli`` may (:mod:`host.studies` and, for ``reproduce``,
:mod:`host.studies.paper`).  The studies are imported when a handler runs, so building the command
line's parser imports none of them.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bus.errors import InputError
from bus.exit_codes import EXIT_CLUSTER_LOST, exit_code_of_signal
from host.cli.options import options_of
from host.experiment.signal_shield import end_of_run, interrupt_on_signals

if TYPE_CHECKING:  # the handlers import the studies when they run: building the parser stays cheap
    from collections.abc import Sequence

    from host.studies.engine import Engine, SweepOutcome
    from host.studies.spec import Point, SweepSpec
    from host.studies.tune import Tuner

logger = logging.getLogger(__name__)

__all__ = [
    "add_sweep_parser",
    "add_tune_parser",
    "add_reproduce_parser",
    "sweep_main",
    "tune_main",
    "reproduce_main",
    "spec_of_args",
    "engine_of_args",
]


def spec_of_args(args: argparse.Namespace) -> SweepSpec:
    """The sweep spec of ``--spec`` with ``--set``, ``--vary`` and ``--config`` merged in."""
    from host.studies.spec import SweepSpec

    spec = SweepSpec.from_toml(args.spec) if getattr(args, "spec", None) else SweepSpec()
    spec.add_cli(getattr(args, "set", None) or [], getattr(args, "vary", None) or [], getattr(args, "config", None))
    samples = getattr(args, "samples", None)
    if samples is not None:
        if samples < 1 or not spec.draws:
            raise InputError(f"--samples {samples}: needs >= 1 and a spec with [monte_carlo.draw]")
        spec.samples = samples
    return spec


def engine_of_args(args: argparse.Namespace) -> Engine:
    """The engine of ``--workers`` / ``--scheduler`` / ``--dashboard`` / ``--no-dashboard`` /
    ``--wait-workers``."""
    from host.studies.engine import Engine

    dashboard: bool | str = True
    if getattr(args, "no_dashboard", False):
        dashboard = False
    elif getattr(args, "dashboard", None):
        dashboard = args.dashboard
    return Engine(
        workers=getattr(args, "workers", None),
        scheduler=getattr(args, "scheduler", None),
        dashboard=dashboard,
        wait_workers_s=_wait_workers(args),
    )


def _wait_workers(args: argparse.Namespace) -> float:
    from host.studies.engine import WAIT_WORKERS_S

    wait = getattr(args, "wait_workers", None)
    return WAIT_WORKERS_S if wait is None else float(wait)


def _spec_doc(spec: SweepSpec) -> dict[str, Any]:
    """What ``sweep.json`` says of the spec (a resume must give the same)."""
    return {
        "base": spec.base_options(),
        "vary": spec.vary,
        "monte_carlo": {
            "samples": spec.samples,
            "seed": spec.seed,
            "draw": {d.key: {d.dist: list(d.params)} for d in spec.draws},
        },
    }


def _record(out: Path, spec: SweepSpec, ids: list[str], where: str, outcome: SweepOutcome, command: str) -> None:
    """Add this call to ``out/sweep.json`` (the spec, the points, the history of calls), atomically."""
    from host.studies.sweep_record import SWEEP_SCHEMA, record_call

    doc = {"schema": SWEEP_SCHEMA, "spec": _spec_doc(spec), "points": ids}
    record_call(out, doc, {"command": command, "points": len(ids)}, {"on": where}, outcome)


def _say_cluster_lost(command: str, outcome: SweepOutcome, out: Path) -> int:
    """One line for a lost scheduler or a cluster without workers; returns ``EXIT_CLUSTER_LOST``."""
    sys.stderr.write(
        f"ilcrig {command}: {outcome.cluster_lost}; {len(outcome.ran)} point(s) finished in this call are kept in "
        f"{out}; run the same command again to resume (only the unfinished points run)\n"
    )
    return EXIT_CLUSTER_LOST


def sweep_main(args: argparse.Namespace) -> int:
    """``ilcrig sweep``: run the points of the spec, write ``results.parquet`` and ``report.md``."""
    from host.studies.sweep_record import check_study_folder

    spec = spec_of_args(args)
    points = spec.points()  # every point validated before anything starts
    from host.experiment.outputs import default_run_folder, release_unused_folder

    claimed = not getattr(args, "out", None)
    out = Path(args.out) if not claimed else default_run_folder("sweep", claim=True)
    check_study_folder(out, "sweep", _spec_doc(spec))  # one study, one folder: a resume or a new folder
    keys = ", ".join(spec.varied_keys) or "nothing varied"
    try:
        with interrupt_on_signals():  # Ctrl-C / SIGTERM: what finished is kept, the records say so
            return _sweep_points(args, spec, points, out, keys)
    finally:
        if claimed:  # ended before its first record (e.g. Ctrl-C while the cluster started): no empty folder left
            release_unused_folder(out)


def _sweep_points(args: argparse.Namespace, spec: SweepSpec, points: list[Point], out: Path, keys: str) -> int:
    """The part of :func:`sweep_main` under its signal handlers."""
    from host.studies.engine import run_points
    from host.studies.report import write_report
    from host.studies.table import TABLE_FILE, write_table

    with engine_of_args(args) as engine:
        where = engine.describe()
        sys.stderr.write(f"ilcrig sweep: {len(points)} point(s) ({keys}) on {where}; folder {out}\n")
        if engine.dashboard:
            sys.stderr.write(f"ilcrig sweep: dashboard {engine.dashboard}\n")
        outcome = run_points(
            engine,
            out,
            points,
            save_errors=bool(getattr(args, "save_errors", False)),
            fresh=bool(getattr(args, "fresh", False)),
            progress=not getattr(args, "no_progress", False),
            desc="sweep",
        )
        end_of_run()  # the records from here: a signal now is logged, not raised
    _record(out, spec, [p.id for p in points], where, outcome, "sweep")
    if outcome.cluster_lost:
        return _say_cluster_lost("sweep", outcome, out / "runs")
    if outcome.signum is not None:
        sys.stderr.write(
            f"ilcrig: interrupted; {len(outcome.ran)} point(s) finished in this call are kept in {out / 'runs'}; "
            "run the same command again to resume\n"
        )
        return exit_code_of_signal(outcome.signum)
    write_table(out, points)
    report = write_report(out, spec, points, outcome.wall_s)
    sys.stdout.write(
        f"ilcrig sweep: {len(outcome.ran)} run, {len(outcome.skipped)} already finished, {outcome.wall_s:.1f} s; "
        f"table: {out / TABLE_FILE}; report: {report}\n"
    )
    if outcome.errors:
        sys.stderr.write(f"ilcrig: {len(outcome.errors)} point(s) could not run (see their error.txt in {out / 'runs'})\n")
        return 1
    return 0


def tune_main(args: argparse.Namespace) -> int:
    """``ilcrig tune``: open (or resume) the study in ``--out``, run it to its budget on the engine,
    write the outputs and print the best gains."""
    from host.studies.sweep_record import check_study_folder
    from host.studies.tune import Tuner
    from host.studies.tune_params import TuneOverrides, tune_settings

    spec = spec_of_args(args)
    engine = engine_of_args(args)
    if spec.vary:
        raise InputError("ilcrig tune takes no --vary / [vary]: the tuned keys are --param / [tune]")
    params, objective, budget = tune_settings(spec, options_of(TuneOverrides, args, params=tuple(args.param or ())))
    from host.experiment.outputs import default_run_folder

    out = Path(args.out) if getattr(args, "out", None) else default_run_folder("tune", claim=True)
    check_study_folder(out, "tune")  # one study, one folder: study.db resumes, anything else is refused
    tuner = Tuner(out, spec, params, objective, budget, sampler_seed=getattr(args, "sampler_seed", 0) or 0)
    tuner.open_study()
    with interrupt_on_signals():  # Ctrl-C / SIGTERM: the study keeps every finished trial
        return _tune_study(args, engine, tuner, out, params, budget)


def _tune_study(args: argparse.Namespace, engine: Engine, tuner: Tuner, out: Path, params: Sequence[Any], budget: int) -> int:
    """The part of :func:`tune_main` under its signal handlers."""
    from host.studies.tune import BEST_FILE, STUDY_FILE

    with engine:
        sys.stderr.write(
            f"ilcrig tune: {', '.join(p.key for p in params)}; {budget} trials "
            f"({len(tuner.finished())} in the study already) on {engine.describe()}; folder {out}\n"
        )
        if engine.dashboard:
            sys.stderr.write(f"ilcrig tune: dashboard {engine.dashboard}\n")
        outcome = tuner.run(engine, progress=not getattr(args, "no_progress", False))
        end_of_run()  # the records from here: a signal now is logged, not raised
    report = tuner.write_outputs(outcome)
    if outcome.cluster_lost:
        sys.stderr.write(
            f"ilcrig tune: {outcome.cluster_lost}; the study in {out / STUDY_FILE} is kept; "
            "run the same command again to resume\n"
        )
        return EXIT_CLUSTER_LOST
    if outcome.signum is not None:
        sys.stderr.write(f"ilcrig: interrupted; the study in {out / STUDY_FILE} is kept; run the same command again to resume\n")
        return exit_code_of_signal(outcome.signum)
    if outcome.best_trial is None:
        sys.stderr.write("ilcrig tune: no trial gave a finite objective (every run faulted or was infeasible)\n")
        return 1
    start = f" (starting point {outcome.start_value:.6g})" if outcome.start_value is not None else ""
    sys.stdout.write(
        f"ilcrig tune: best J = {outcome.best_value:.6g}{start}, trial {outcome.best_trial} of {len(tuner.finished())}; "
        f"{outcome.wall_s:.1f} s\n"
        f"best gains: {tuner.cli_options(outcome.best_params)}\n"
        f"run them: ilcrig sim --config {out / BEST_FILE}\n"
        f"report: {report}\n"
    )
    return 0


def reproduce_main(args: argparse.Namespace) -> int:
    """``ilcrig reproduce``: the paper's sweep (:func:`host.studies.paper.reproduce.reproduce`) with
    ``--out``, ``--jobs``, ``--scheduler``, ``--iterations``, ``--only``, ``--fresh``,
    ``--no-progress``, ``--no-dashboard``."""

    out = Path(getattr(args, "out", None) or "runs/reproduce")
    jobs = getattr(args, "jobs", None)
    scheduler = getattr(args, "scheduler", None)
    if jobs is not None and jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {jobs}")
    with interrupt_on_signals():  # Ctrl-C / SIGTERM: the finished experiments are kept, the records say so
        return _reproduce(args, out, jobs, scheduler)


def _reproduce(args: argparse.Namespace, out: Path, jobs: int | None, scheduler: str | None) -> int:
    """The part of :func:`reproduce_main` under its signal handlers."""
    from host.studies.paper.reproduce import reproduce

    code, outcome = reproduce(
        out,
        iterations=10 if getattr(args, "iterations", None) is None else args.iterations,
        only=getattr(args, "only", None),
        workers=jobs if scheduler is None else None,
        scheduler=scheduler,
        fresh=bool(getattr(args, "fresh", False)),
        progress=not getattr(args, "no_progress", False),
        dashboard=not getattr(args, "no_dashboard", False),
        wait_workers_s=_wait_workers(args),
    )
    if outcome.cluster_lost:
        return _say_cluster_lost("reproduce", outcome, out / "runs")
    if outcome.signum is not None:
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


# -- the options ---------------------------------------------------------------------------------


def _add_engine_args(p: argparse.ArgumentParser, workers_flag: str = "--workers") -> None:
    """Where the points run: a local cluster (``workers_flag``) or ``--scheduler``; progress, dashboard."""
    p.add_argument(
        workers_flag,
        type=int,
        default=None,
        dest="jobs" if workers_flag == "--jobs" else "workers",
        metavar="N",
        help="worker processes of the local Dask cluster, on 127.0.0.1 (default: number of cores)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="tcp://HOST:PORT",
        help="run on an existing Dask cluster (`dask scheduler` + `dask worker` on a private network; docs/sweeps.md)",
    )
    p.add_argument(
        "--wait-workers",
        type=float,
        default=None,
        metavar="S",
        help="how long to wait for a worker when the cluster has none, then exit 5 (default 60 s)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-dashboard", action="store_true", help="no dashboard: the local cluster opens no HTTP listener at all")
    p.add_argument(
        "--dashboard", default=None, metavar="127.0.0.1:PORT", help="the local cluster's dashboard address (loopback only)"
    )


def _add_spec_args(p: argparse.ArgumentParser, sections: str = "[base], [vary], [monte_carlo]") -> None:
    """The points' options: a spec file, an experiment file, ``--set`` and ``--vary``."""
    p.add_argument("--spec", metavar="TOML", help=f"spec file: {sections} (docs/sweeps.md)")
    p.add_argument("--config", metavar="TOML", help="experiment file under the spec's [base] (keys as `ilcrig sim --config`)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="an option of every point (repeatable), e.g. law=pd-ilc-q, gains.alpha=3, plant.mass_scale=1.1",
    )


def add_reproduce_parser(sub: Any) -> argparse.ArgumentParser:
    """Add ``reproduce`` to the subcommands ``sub`` (with :func:`reproduce_main` as its handler)."""
    xp: argparse.ArgumentParser = sub.add_parser(
        "reproduce", help="run the paper's experiments (Tables 2-6, Figs. 8 and 10) and beyond"
    )
    xp.add_argument("--out", default="runs/reproduce", help="sweep folder (default runs/reproduce); reused to resume")
    _add_engine_args(xp, "--jobs")
    xp.add_argument("--iterations", type=int, default=10, help="trials per experiment (default 10)")
    xp.add_argument("--only", default=None, help="comma-separated subset: table2,table3,table4,table5,table6,figs,beyond")
    xp.add_argument("--fresh", action="store_true", help="ignore finished experiments in --out and redo all")
    xp.set_defaults(func=reproduce_main)
    return xp


def add_sweep_parser(sub: Any) -> argparse.ArgumentParser:
    """Add ``sweep`` to the subcommands ``sub`` (with :func:`sweep_main` as its handler)."""
    wp: argparse.ArgumentParser = sub.add_parser(
        "sweep", help="run a grid / Monte Carlo sweep of experiments on Dask (docs/sweeps.md)"
    )
    _add_spec_args(wp)
    wp.add_argument(
        "--vary",
        action="append",
        metavar="KEY=V1,V2,…",
        help="values of one option (repeatable: the product of all), e.g. gains.alpha=2,3,4 or law=pd-ilc,pd-ilc-q",
    )
    wp.add_argument(
        "--samples",
        type=int,
        default=None,
        metavar="N",
        help="Monte Carlo samples per grid point (the spec's [monte_carlo] samples)",
    )
    wp.add_argument("--out", default=None, help="sweep folder (default runs/sweep-<time>); reused to resume")
    wp.add_argument("--save-errors", action="store_true", help="keep each point's error signals (errors.npy)")
    wp.add_argument("--fresh", action="store_true", help="run every point again, finished or not")
    _add_engine_args(wp)
    wp.set_defaults(func=sweep_main)
    return wp


def add_tune_parser(sub: Any) -> argparse.ArgumentParser:
    """Add ``tune`` to the subcommands ``sub`` (with :func:`tune_main` as its handler)."""
    tp: argparse.ArgumentParser = sub.add_parser("tune", help="tune gains with Optuna on the sweep engine (docs/sweeps.md)")
    _add_spec_args(tp, "[base], [tune], [objective], [monte_carlo]")
    tp.add_argument(
        "--param",
        action="append",
        metavar="KEY=LOW:HIGH[:log|:int]",
        help="a gain to tune and its range (repeatable), e.g. gains.alpha=1.5:6 or gains.lp_norm=1e-4:5e-3:log",
    )
    tp.add_argument("--budget", type=int, default=None, help="trials of the study in all, resumed ones included (default 30)")
    tp.add_argument(
        "--settle-weight",
        type=float,
        default=None,
        metavar="DEG",
        help="objective = final RMSE (deg, mean over joints) + this × the settle iteration (default 0)",
    )
    tp.add_argument(
        "--plants", type=int, default=None, help="Monte Carlo plants per trial (the spec's draws; default 0: the robot as built)"
    )
    tp.add_argument("--aggregate", choices=("mean", "max"), default=None, help="over the plants: mean or worst (default mean)")
    tp.add_argument(
        "--require-check",
        action="store_true",
        default=None,
        help="gains whose convergence check fails (spectral radius or predicted error ratio >= 1) are infeasible, not run",
    )
    tp.add_argument("--sampler-seed", type=int, default=0, help="seed of Optuna's sampler (default 0)")
    tp.add_argument(
        "--out", default=None, help="tuning folder: study.db, runs/, best.toml (default runs/tune-<time>); reused to resume"
    )
    _add_engine_args(tp)
    tp.set_defaults(func=tune_main)
    return tp
