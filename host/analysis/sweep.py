"""``ilcrig reproduce``: the paper's experiments (Tables 2–6, Figs. 8 and 10) and the
beyond-the-paper comparison of learning laws, run as a resumable parallel sweep.

This module owns the sweep runner; the experiment list and the run folders are
:mod:`host.analysis.sweep_plan`. A sweep folder::

    <out>/sweep.json                       what was run, wall times, interruptions
    <out>/runs/<experiment-id>/summary.json   the run's summary (host.experiment.trials schema)
    <out>/runs/<experiment-id>/errors.npy     (K, N, 4) float32 joint errors q_d − q, rad, per trial
    <out>/runs/<experiment-id>/error.txt      only if the experiment could not start (e.g. infeasible)
    <out>/report.md, fig8.png, fig10.png, convergence_laws.png, long_runs.png   (host.analysis.report)

Every experiment is one ``prepare`` + ``run_experiment`` on an :class:`~host.experiment.inprocess.InProcessBench`
in a worker process of a ``ProcessPoolExecutor`` (spawned, SIGINT ignored in the workers so the
parent alone decides).  An experiment whose folder holds a finished summary (``"completed": true``
or a recorded fault — both are deterministic results) with the same configuration and its
``errors.npy`` is not run again unless ``--fresh``.  Ctrl-C (or SIGTERM) cancels what has not
started, terminates the workers, keeps every finished experiment and returns 130.

Beyond the paper: the same tables for ``q-ilc`` and ``no-ilc``, every law on path 1 with and
without disturbance, and every law for a fixed ``LONG_TRIALS`` = 200 trials (long-run stability).

Motion law: the paper's Tables 2–5 use its 4-5-6-7 polynomial law (Table 6 compares it with the
5th-order law), so every paper-table experiment here uses ``profile = "poly4567"`` — Table 6 then
compares 4567 and 5 on the same footing.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import signal
import sys
import time
import traceback
from collections.abc import Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.analysis.report import write_sweep_report
from host.analysis.sweep_plan import (
    Experiment,
    ReproduceError,
    experiment_list,
    is_finished,
    run_dir_of,
)
from host.experiment.console import EXIT_INTERRUPTED

logger = logging.getLogger(__name__)

__all__ = [
    "SWEEP_SCHEMA",
    "run_sweep",
    "reproduce_main",
    "SweepOutcome",
]

SWEEP_SCHEMA = "ilcrig.sweep/1"


# ------------------------------------------------------------------------------------------- worker


def _worker_init() -> None:
    """Workers leave SIGINT to the parent (which terminates them) and die quietly on SIGTERM."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _run_one(exp: Experiment, iterations: int, run_dir: str) -> dict[str, Any]:
    """Run one experiment into ``run_dir`` (in a worker process). Never raises."""
    from host.experiment.inprocess import InProcessBench
    from host.experiment.plan import prepare
    from host.experiment.trials import run_experiment

    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    for stale in ("error.txt", "errors.npy"):
        (d / stale).unlink(missing_ok=True)
    t0 = time.perf_counter()
    try:
        cfg = exp.config(iterations)
        plan = prepare(cfg)
        res = run_experiment(plan, InProcessBench(cfg), d, mode="sim")
        errs = np.stack(res.errors).astype(np.float32) if res.errors else np.zeros((0, plan.n_ticks, 4), np.float32)
        with open(d / "errors.npy.tmp", "wb") as fh:
            np.save(fh, errs)
        os.replace(d / "errors.npy.tmp", d / "errors.npy")
        return {"id": exp.id, "wall_s": time.perf_counter() - t0, "fault": res.fault, "error": None}
    except Exception as exc:  # infeasible task, bug: record it, keep the sweep going
        msg = f"{type(exc).__name__}: {exc}"
        (d / "error.txt").write_text(msg + "\n\n" + traceback.format_exc())
        return {"id": exp.id, "wall_s": time.perf_counter() - t0, "fault": None, "error": msg}


# -------------------------------------------------------------------------------------------- sweep


@dataclass
class SweepOutcome:
    ran: list[str]
    skipped: list[str]
    errors: dict[str, str]
    interrupted: bool
    wall_s: float


def _raise_interrupt(signum: int, frame: Any) -> None:  # SIGTERM → same path as Ctrl-C
    raise KeyboardInterrupt


def _stop_pool(ex: ProcessPoolExecutor, futures: Iterable[Future]) -> None:
    """Cancel what has not started, terminate the workers and reap them (no orphans)."""
    for f in futures:
        f.cancel()
    procs = list((getattr(ex, "_processes", None) or {}).values())
    for p in procs:
        try:
            p.terminate()
        except (OSError, AttributeError):
            pass
    ex.shutdown(wait=True, cancel_futures=True)
    for p in procs:
        p.join(timeout=5.0)
        if p.is_alive():  # pragma: no cover - terminate ignored
            p.kill()
            p.join(timeout=5.0)


def run_sweep(
    out: Path, experiments: Sequence[Experiment], iterations: int, jobs: int, fresh: bool, progress: bool = True
) -> SweepOutcome:
    """Run the experiments that are not finished in ``out`` (all of them if ``fresh``)."""
    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    todo, skipped = [], []
    for e in experiments:
        if not fresh and is_finished(run_dir_of(out, e), e.config(iterations)):
            skipped.append(e.id)
        else:
            todo.append(e)
    logger.info(
        "reproduce: %d experiments, %d already finished, %d to run on %d processes",
        len(experiments),
        len(skipped),
        len(todo),
        jobs,
    )
    outcome = SweepOutcome(ran=[], skipped=skipped, errors={}, interrupted=False, wall_s=0.0)
    if not todo:
        return outcome
    from tqdm import tqdm

    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), desc="reproduce", unit="exp", file=sys.stderr, disable=not progress, dynamic_ncols=True)
    ctx = multiprocessing.get_context("spawn")
    ex = ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=ctx, initializer=_worker_init)
    futures: dict[Future, Experiment] = {}
    old_term = signal.getsignal(signal.SIGTERM)
    in_main = _in_main_thread()
    if in_main:
        signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        for e in todo:
            futures[ex.submit(_run_one, e, iterations, str(run_dir_of(out, e)))] = e
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            for f in done:
                e = futures[f]
                try:
                    r = f.result()
                except Exception as exc:  # a worker died (BrokenProcessPool, ...)
                    r = {"id": e.id, "error": f"{type(exc).__name__}: {exc}", "fault": None, "wall_s": 0.0}
                outcome.ran.append(e.id)
                if r.get("error"):
                    outcome.errors[e.id] = r["error"]
                    bar.write(f"ilcrig reproduce: {e.id} failed: {r['error']}", file=sys.stderr)
                bar.set_postfix_str(e.id, refresh=False)
                bar.update(1)
        ex.shutdown(wait=True)
    except KeyboardInterrupt:
        outcome.interrupted = True
        _stop_pool(ex, futures)
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, old_term)
        bar.close()
        outcome.wall_s = time.perf_counter() - t0
    return outcome


def _in_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _write_sweep_json(out: Path, experiments: Sequence[Experiment], iterations: int, jobs: int, outcome: SweepOutcome) -> None:
    path = out / "sweep.json"
    try:
        prev = json.loads(path.read_text())
    except (OSError, ValueError):
        prev = {}
    history = list(prev.get("history", []))
    history.append(
        {
            "experiments": len(experiments),
            "ran": len(outcome.ran),
            "skipped": len(outcome.skipped),
            "errors": outcome.errors,
            "interrupted": outcome.interrupted,
            "jobs": jobs,
            "iterations": iterations,
            "wall_s": round(outcome.wall_s, 3),
        }
    )
    doc = {"schema": SWEEP_SCHEMA, "iterations": iterations, "experiments": [e.id for e in experiments], "history": history}
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=2))
    os.replace(tmp, path)


def reproduce_main(args: argparse.Namespace) -> int:
    """Entry point of ``ilcrig reproduce`` (args: out, jobs, iterations, only, fresh).

    Returns 0, 1 if an experiment could not run (its error.txt says why), 130 if interrupted."""
    out = Path(getattr(args, "out", None) or "runs/reproduce")
    jobs = getattr(args, "jobs", None)
    jobs = (os.cpu_count() or 1) if jobs is None else jobs
    iterations = getattr(args, "iterations", None)
    iterations = 10 if iterations is None else iterations
    if jobs < 1:
        raise ReproduceError(f"--jobs must be >= 1, got {jobs}")
    if iterations < 1:
        raise ReproduceError(f"--iterations must be >= 1, got {iterations}")
    experiments = experiment_list(getattr(args, "only", None))
    for e in experiments:  # validate every configuration before anything runs
        e.config(iterations)
    outcome = run_sweep(out, experiments, iterations, jobs, bool(getattr(args, "fresh", False)))
    _write_sweep_json(out, experiments, iterations, jobs, outcome)
    if outcome.interrupted:
        sys.stderr.write(
            f"ilcrig: interrupted; {len(outcome.ran)} experiment(s) finished in this call are kept "
            f"in {out / 'runs'}; run again to resume\n"
        )
        return EXIT_INTERRUPTED

    report = write_sweep_report(out, iterations)
    sys.stdout.write(
        f"ilcrig reproduce: {len(outcome.ran)} run, {len(outcome.skipped)} already finished, "
        f"{outcome.wall_s:.1f} s on {jobs} process(es); report: {report}\n"
    )
    if outcome.errors:
        sys.stderr.write(
            f"ilcrig: {len(outcome.errors)} experiment(s) could not run: "
            f"{', '.join(sorted(outcome.errors))} (see their error.txt)\n"
        )
        return 1
    return 0
