"""The sweep commands of the command line: ``ilcrig sweep``, ``ilcrig tune``, ``ilcrig reproduce``.

This module owns what those commands do with their parsed options (``host.cli`` defines the options
and calls :func:`sweep_main`, :func:`tune_main`, :func:`reproduce_main`): build the points, run them
on the engine, write the table and the report, and print one closing line.  Bad input is an
:class:`ilcrig.InputError` (one line, exit code 2) raised before anything starts; an interrupted
sweep returns 130 with every finished point kept.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from ilcrig.errors import InputError
from ilcrig.sweep.engine import Engine, SweepOutcome, run_points
from ilcrig.sweep.report import write_report
from ilcrig.sweep.reproduce import EXIT_INTERRUPTED, SWEEP_SCHEMA, record_call, reproduce_main
from ilcrig.sweep.spec import SweepSpec
from ilcrig.sweep.table import TABLE_FILE, write_table

logger = logging.getLogger(__name__)

__all__ = ["sweep_main", "tune_main", "reproduce_main", "spec_of_args", "engine_of_args"]


def spec_of_args(args: argparse.Namespace) -> SweepSpec:
    """The sweep spec of ``--spec`` with ``--set``, ``--vary`` and ``--config`` merged in."""
    spec = SweepSpec.from_toml(args.spec) if getattr(args, "spec", None) else SweepSpec()
    spec.add_cli(getattr(args, "set", None) or [], getattr(args, "vary", None) or [], getattr(args, "config", None))
    samples = getattr(args, "samples", None)
    if samples is not None:
        if samples < 1 or not spec.draws:
            raise InputError(f"--samples {samples}: needs >= 1 and a spec with [monte_carlo.draw]")
        spec.samples = samples
    return spec


def engine_of_args(args: argparse.Namespace) -> Engine:
    """The engine of ``--workers`` / ``--scheduler`` / ``--dashboard`` / ``--no-dashboard``."""
    dashboard: bool | str = True
    if getattr(args, "no_dashboard", False):
        dashboard = False
    elif getattr(args, "dashboard", None):
        dashboard = args.dashboard
    return Engine(workers=getattr(args, "workers", None), scheduler=getattr(args, "scheduler", None), dashboard=dashboard)


def _record(out: Path, spec: SweepSpec, ids: list[str], where: str, outcome: SweepOutcome, command: str) -> None:
    """Add this call to ``out/sweep.json`` (the spec, the points, the history of calls), atomically."""
    doc = {
        "schema": SWEEP_SCHEMA,
        "spec": {
            "base": spec.base_options(),
            "vary": spec.vary,
            "monte_carlo": {
                "samples": spec.samples,
                "seed": spec.seed,
                "draw": {d.key: {d.dist: list(d.params)} for d in spec.draws},
            },
        },
        "points": ids,
    }
    record_call(out, doc, {"command": command, "points": len(ids)}, {"on": where}, outcome)


def sweep_main(args: argparse.Namespace) -> int:
    """``ilcrig sweep``: run the points of the spec, write ``results.parquet`` and ``report.md``."""
    spec = spec_of_args(args)
    points = spec.points()  # every point validated before anything starts
    out = Path(args.out) if getattr(args, "out", None) else Path("runs") / time.strftime("sweep-%Y%m%d-%H%M%S")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, not a folder")
    keys = ", ".join(spec.varied_keys) or "nothing varied"
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
    _record(out, spec, [p.id for p in points], where, outcome, "sweep")
    if outcome.interrupted:
        sys.stderr.write(
            f"ilcrig: interrupted; {len(outcome.ran)} point(s) finished in this call are kept in {out / 'runs'}; "
            "run the same command again to resume\n"
        )
        return EXIT_INTERRUPTED
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
    """``ilcrig tune`` (:mod:`ilcrig.sweep.tune`)."""
    from ilcrig.sweep.tune import tune_main as _tune

    return _tune(args, spec_of_args(args), engine_of_args(args))
