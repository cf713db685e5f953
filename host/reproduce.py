"""``ilcrig reproduce``: the paper's experiments (Tables 2–6, Figs. 8 and 10) and the
beyond-the-paper comparison of learning laws, run as a resumable parallel sweep.

This module owns the experiment list (which configuration stands behind which table row), the
sweep runner and the run-folder layout of a sweep::

    <out>/sweep.json                       what was run, wall times, interruptions
    <out>/runs/<experiment-id>/summary.json   the run's summary (host.experiment schema)
    <out>/runs/<experiment-id>/errors.npy     (K, N, 4) float32 joint errors q_d − q, rad, per trial
    <out>/runs/<experiment-id>/error.txt      only if the experiment could not start (e.g. infeasible)
    <out>/report.md, fig8.png, fig10.png, convergence_laws.png, long_runs.png   (host.report)

Every experiment is one ``prepare`` + ``run_experiment`` on an :class:`~host.compose.InProcessBench`
in a worker process of a ``ProcessPoolExecutor`` (spawned, SIGINT ignored in the workers so the
parent alone decides).  An experiment whose folder holds a finished summary (``"completed": true``
or a recorded fault — both are deterministic results) with the same configuration and its
``errors.npy`` is not run again unless ``--fresh``.  Ctrl-C (or SIGTERM) cancels what has not
started, terminates the workers, keeps every finished experiment and returns 130.

Beyond the paper: the same tables for ``q-ilc`` and ``no-ilc``, every law on path 1 with and
without disturbance, and every law for a fixed ``LONG_TRIALS`` = 40 trials (long-run stability).

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
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from host.config import ExperimentConfig, build_config
from host.names import LAWS

logger = logging.getLogger(__name__)

__all__ = [
    "Experiment", "TableRow", "GROUPS", "PAPER_LAW", "BASELINE_LAW", "BEYOND_LAWS", "PROFILE", "LONG_TRIALS",
    "SWEEP_SCHEMA", "ReproduceError", "group_experiments", "experiment_list", "table_rows",
    "all_experiments", "run_dir_of", "is_finished", "load_run", "RunData", "run_sweep", "reproduce_main",
    "EXIT_INTERRUPTED", "SweepOutcome",
]

SWEEP_SCHEMA = "ilcrig.sweep/1"
EXIT_INTERRUPTED = 130

#: the paper's law, its baseline, and the laws shown beyond the paper's tables
PAPER_LAW = "pd-ilc"
BASELINE_LAW = "d-ilc"
BEYOND_LAWS: tuple[str, ...] = ("q-ilc", "no-ilc")
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
LONG_TRIALS = 40


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
        """Folder name, e.g. ``pd-ilc_p1_250ms_poly4567_none`` (``…_k40`` for a fixed 40 trials)."""
        base = f"{self.law}_p{self.path}_{round(self.cycle_s * 1000)}ms_{self.profile}_{self.disturbance}"
        return base if self.trials is None else f"{base}_k{self.trials}"

    def config(self, iterations: int) -> ExperimentConfig:
        return build_config(None, {"law": self.law, "path": self.path, "cycle_s": self.cycle_s,
                                   "profile": self.profile, "disturbance": self.disturbance,
                                   "iterations": self.trials if self.trials is not None else iterations})

    def describe(self) -> str:
        return (f"{self.law}, path {self.path}, {self.cycle_s:g} s, {self.profile}, "
                f"disturbance {self.disturbance}" + ("" if self.trials is None else f", {self.trials} trials"))


@dataclass(frozen=True)
class TableRow:
    """A row of one of our tables: the experiment behind it and the paper row it stands beside."""

    table: str  # "table2" ...
    label: str
    experiment: Experiment
    paper_key: str | None  # key into host.paper_data.TABLES[table].rows; None = beyond the paper
    law: str


def _base(law: str, **kw: Any) -> Experiment:
    return Experiment(law=law, **kw)


def table_rows(table: str, laws: Sequence[str] | None = None) -> list[TableRow]:
    """The rows of our version of a paper table for the given laws (default: the paper's)."""
    rows: list[TableRow] = []
    if table == "table2":
        for law in (laws or (PAPER_LAW, BASELINE_LAW)):
            key = {PAPER_LAW: "PD-ILC", BASELINE_LAW: "D-ILC"}.get(law)
            rows.append(TableRow(table, law.upper(), _base(law), key, law))
        return rows
    for law in (laws or (PAPER_LAW,)):
        paper = law == PAPER_LAW
        if table == "table3":
            for dist, label in (("none", "no disturbance"), (DISTURBED, "disturbance")):
                rows.append(TableRow(table, f"{law.upper()}, {label}", _base(law, disturbance=dist),
                                     dist if paper else None, law))
        elif table == "table4":
            for p in PATHS:
                rows.append(TableRow(table, f"{law.upper()}, path {p}", _base(law, path=p), p if paper else None, law))
        elif table == "table5":
            for c in CYCLES_S:
                rows.append(TableRow(table, f"{law.upper()}, {c:.2f} s", _base(law, cycle_s=c),
                                     f"{c:.2f}" if paper else None, law))
        elif table == "table6":
            for prof in PROFILES_T6:
                label = "4-5-6-7" if prof == "poly4567" else "5th order"
                rows.append(TableRow(table, f"{law.upper()}, {label}", _base(law, profile=prof),
                                     prof if paper else None, law))
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
        exps = [_base(law, disturbance=d) for law in LAWS for d in ("none", DISTURBED)]
        exps += [_base(law, disturbance=d, trials=LONG_TRIALS) for law in LAWS for d in ("none", DISTURBED)]
        for t in ("table3", "table4", "table5", "table6"):
            exps += [r.experiment for r in table_rows(t, BEYOND_LAWS)]
        return exps
    raise ReproduceError(f"unknown --only group {group!r}; choose from {', '.join(GROUPS)}")


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
    cost = {"q-ilc": 3.0, "no-ilc": 2.0}
    return sorted(seen.values(), key=lambda e: (-e.cycle_s * cost.get(e.law, 1.0) * (e.trials or 10) / 10, e.id))


def all_experiments() -> list[Experiment]:
    return experiment_list(None)


# ----------------------------------------------------------------------------------------- run folders

def run_dir_of(out: Path, exp: Experiment) -> Path:
    return Path(out) / "runs" / exp.id


def _config_json(cfg: ExperimentConfig) -> dict[str, Any]:
    return json.loads(json.dumps(cfg.as_dict()))


def _read_summary(run_dir: Path) -> dict[str, Any] | None:
    try:
        return json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None


def is_finished(run_dir: Path, cfg: ExperimentConfig) -> bool:
    """True if ``run_dir`` holds a finished run (completed, or ended by a recorded fault) of
    exactly ``cfg`` together with its errors file."""
    s = _read_summary(Path(run_dir))
    if s is None or not (s.get("completed") or s.get("faults")):
        return False
    stored = {k: v for k, v in s.get("config", {}).items() if k not in ("n_ticks", "trial_s")}
    if stored != _config_json(cfg):
        return False
    return (Path(run_dir) / "errors.npy").is_file()


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
    summary = _read_summary(d)
    assert summary is not None
    return RunData(exp, summary, np.load(d / "errors.npy"))


# ------------------------------------------------------------------------------------------- worker

def _worker_init() -> None:
    """Workers leave SIGINT to the parent (which terminates them) and die quietly on SIGTERM."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _run_one(exp: Experiment, iterations: int, run_dir: str) -> dict[str, Any]:
    """Run one experiment into ``run_dir`` (in a worker process). Never raises."""
    from host.compose import InProcessBench
    from host.experiment import prepare, run_experiment

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


def run_sweep(out: Path, experiments: Sequence[Experiment], iterations: int, jobs: int, fresh: bool,
              progress: bool = True) -> SweepOutcome:
    """Run the experiments that are not finished in ``out`` (all of them if ``fresh``)."""
    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    todo, skipped = [], []
    for e in experiments:
        if not fresh and is_finished(run_dir_of(out, e), e.config(iterations)):
            skipped.append(e.id)
        else:
            todo.append(e)
    logger.info("reproduce: %d experiments, %d already finished, %d to run on %d processes",
                len(experiments), len(skipped), len(todo), jobs)
    outcome = SweepOutcome(ran=[], skipped=skipped, errors={}, interrupted=False, wall_s=0.0)
    if not todo:
        return outcome
    from tqdm import tqdm

    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), desc="reproduce", unit="exp", file=sys.stderr, disable=not progress,
               dynamic_ncols=True)
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


def _write_sweep_json(out: Path, experiments: Sequence[Experiment], iterations: int, jobs: int,
                      outcome: SweepOutcome) -> None:
    path = out / "sweep.json"
    try:
        prev = json.loads(path.read_text())
    except (OSError, ValueError):
        prev = {}
    history = list(prev.get("history", []))
    history.append({"experiments": len(experiments), "ran": len(outcome.ran), "skipped": len(outcome.skipped),
                    "errors": outcome.errors, "interrupted": outcome.interrupted, "jobs": jobs,
                    "iterations": iterations, "wall_s": round(outcome.wall_s, 3)})
    doc = {"schema": SWEEP_SCHEMA, "iterations": iterations, "experiments": [e.id for e in experiments],
           "history": history}
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
        sys.stderr.write(f"ilcrig: interrupted; {len(outcome.ran)} experiment(s) finished in this call are kept "
                         f"in {out / 'runs'}; run again to resume\n")
        return EXIT_INTERRUPTED
    from host.report import write_sweep_report

    report = write_sweep_report(out, iterations)
    sys.stdout.write(f"ilcrig reproduce: {len(outcome.ran)} run, {len(outcome.skipped)} already finished, "
                     f"{outcome.wall_s:.1f} s on {jobs} process(es); report: {report}\n")
    if outcome.errors:
        sys.stderr.write(f"ilcrig: {len(outcome.errors)} experiment(s) could not run: "
                         f"{', '.join(sorted(outcome.errors))} (see their error.txt)\n")
        return 1
    return 0

