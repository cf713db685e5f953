"""``ilcrig tune``: gains tuned with Optuna, each trial's experiments run on the sweep engine.

This module owns the search space (:class:`Param`: ``KEY=LOW:HIGH[:log|:int]``), the objective
(:class:`Objective`), the study (Optuna, kept in the tuning folder as SQLite: ``study.db``, so a
tuning run resumes) and its outputs: ``best.toml`` (an experiment file of the best gains, for
``ilcrig sim --config``), ``report.md`` with ``tuning.png``, ``results.parquet`` and every point's
folder in ``runs/`` (:mod:`ilcrig.sweep.point`).

**Objective** (minimised), per experiment: J = mean over the joints of the final RMSE (the last
learning trial's, deg) + ``settle_weight`` × the settle iteration (the first trial from which every
joint stays within 2× of its final RMSE, :func:`host.analysis.settling.settle_iteration`); a run
ended by a fault (a diverging law, a drive fault) gives J = inf.  With Monte Carlo plants
(``plants`` > 0: the draws of the spec's ``[monte_carlo.draw]``, sample 0 … plants − 1) a trial
runs one experiment per plant and its value is the mean (or the worst, ``aggregate = "max"``) of
their J; after each plant the running value is reported to Optuna's median pruner, which stops a
trial that is worse than the median of the earlier ones at the same number of plants.  With
``require_check`` the convergence check must hold: gains that fail it are not
run and get J = inf (the check's ``ok``: spectral radius < 1 and a predicted error ratio < 1 after
the experiment's trials, :mod:`host.learning.check`).

**The starting point** (the base options' values of the tuned keys: the hand-picked gains) is the
study's first trial, so the best value is never worse than the hand-picked one.  The study runs
until it holds ``budget`` trials (an interrupted trial is run again on resume, from its finished
points).

Spec file: the sections of :mod:`ilcrig.sweep.spec` and

.. code-block:: toml

    [tune]
    "gains.alpha" = { low = 1.5, high = 8.0 }
    "gains.lp_norm" = { low = 2e-4, high = 4e-3, log = true }
    "gains.lead" = { low = 1, high = 4, int = true }
    budget = 40

    [objective]
    settle_weight = 0.001   # deg per trial
    plants = 20             # Monte Carlo plants per trial (the [monte_carlo.draw] distributions)
    aggregate = "mean"      # or "max"
    require_check = true
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from host.analysis.figures import figure, save_png
from host.analysis.markdown import fmt, md_table
from host.analysis.settling import settle_iteration
from ilcrig.errors import InputError
from ilcrig.sweep.engine import TASK_GROUP, Engine, interrupt_on_sigterm, point_doc
from ilcrig.sweep.point import commit, is_finished, load_point, run_dir
from ilcrig.sweep.spec import Point, SweepSpec, check_key, parse_value, set_key
from ilcrig.sweep.table import metrics_of, write_table

logger = logging.getLogger(__name__)

__all__ = ["Param", "Objective", "Tuner", "TuneOutcome", "tune_main", "STUDY_NAME", "STUDY_FILE", "BEST_FILE", "toml_text"]

STUDY_NAME = "ilcrig-tune"
STUDY_FILE = "study.db"
BEST_FILE = "best.toml"
DEFAULT_BUDGET = 30
#: the command-line flag of a tunable gain (for the printed options); others go by ``best.toml``
GAIN_FLAGS = {
    "alpha": "--alpha",
    "beta": "--beta",
    "lp": "--lp",
    "ld": "--ld",
    "lp_norm": "--lp-norm",
    "ld_norm": "--ld-norm",
    "q_cutoff_hz": "--q-cutoff-hz",
    "pdq_cutoff_hz": "--pdq-cutoff-hz",
    "lead": "--lead",
}


@dataclass(frozen=True)
class Param:
    """One tuned key and its range (``log``: sampled on a log scale; ``integer``: whole numbers)."""

    key: str
    low: float
    high: float
    log: bool = False
    integer: bool = False

    @classmethod
    def parse(cls, text: str) -> Param:
        """``KEY=LOW:HIGH[:log|:int]``.

        :raises InputError: one line naming the option."""
        key, eq, rest = text.partition("=")
        parts = rest.split(":") if eq else []
        flags = {p.strip() for p in parts[2:]}
        if len(parts) < 2 or flags - {"log", "int"}:
            raise InputError(f"--param {text!r}: expected KEY=LOW:HIGH[:log|:int]")
        return cls.of(
            key.strip(),
            {"low": parse_value(parts[0]), "high": parse_value(parts[1]), "log": "log" in flags, "int": "int" in flags},
            "--param",
        )

    @classmethod
    def of(cls, key: str, table: Mapping[str, Any], where: str) -> Param:
        """A ``[tune]`` entry ``{low, high[, log][, int]}``."""
        check_key(key, where)
        if key.startswith("plant."):
            raise InputError(f"{where} {key}: plant factors are drawn (Monte Carlo), not tuned")
        bad = set(table) - {"low", "high", "log", "int"}
        low, high = table.get("low"), table.get("high")
        if bad or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in (low, high)):
            raise InputError(f"{where} {key}: a range is {{low, high[, log = true][, int = true]}} with numbers")
        assert isinstance(low, (int, float)) and isinstance(high, (int, float))
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise InputError(f"{where} {key}: needs low < high, got {low} .. {high}")
        log, integer = bool(table.get("log", False)), bool(table.get("int", False))
        if log and low <= 0:
            raise InputError(f"{where} {key}: a log range needs low > 0")
        if integer and not (float(low).is_integer() and float(high).is_integer()):
            raise InputError(f"{where} {key}: an integer range needs whole numbers")
        return cls(key, float(low), float(high), log, integer)

    def distribution(self) -> Any:
        import optuna

        if self.integer:
            return optuna.distributions.IntDistribution(int(self.low), int(self.high), log=self.log)
        return optuna.distributions.FloatDistribution(self.low, self.high, log=self.log)

    def contains(self, value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and self.low <= value <= self.high

    def describe(self) -> str:
        kind = ", log" if self.log else ""
        return f"`{self.key}` in [{fmt(self.low, 4)}, {fmt(self.high, 4)}]{kind}{', integer' if self.integer else ''}"


@dataclass(frozen=True)
class Objective:
    """J of one experiment and of a trial over its plants (module docstring)."""

    settle_weight: float = 0.0
    plants: int = 0
    aggregate: str = "mean"
    require_check: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.settle_weight) and self.settle_weight >= 0):
            raise InputError(f"settle_weight must be a number >= 0, got {self.settle_weight}")
        if self.plants < 0:
            raise InputError(f"plants must be >= 0, got {self.plants}")
        if self.aggregate not in ("mean", "max"):
            raise InputError(f"aggregate must be 'mean' or 'max', got {self.aggregate!r}")

    def of_summary(self, summary: Mapping[str, Any] | None) -> float:
        """J of one run's summary (inf: it could not run, faulted or has no finite RMSE)."""
        m = metrics_of(dict(summary) if summary is not None else None)
        final = m["final_rmse_deg"]
        if m["error"] is not None or m["fault"] or final is None or not np.all(np.isfinite(final)):
            return math.inf
        value = float(np.mean(final))
        if self.settle_weight:
            value += self.settle_weight * settle_iteration(m["rmse_deg"])
        return value

    def combine(self, values: Sequence[float]) -> float:
        """A trial's value over its plants."""
        if not values:
            return math.inf
        return float(np.mean(values)) if self.aggregate == "mean" else float(np.max(values))

    def describe(self) -> str:
        text = "J = mean over joints of the final RMSE (deg)"
        if self.settle_weight:
            text += f" + {self.settle_weight:g} × settle iteration"
        if self.plants:
            text += f"; {'mean' if self.aggregate == 'mean' else 'worst'} over {self.plants} Monte Carlo plants"
        if self.require_check:
            text += "; gains whose convergence check fails are infeasible (J = inf)"
        return text + "; a run ended by a fault: J = inf"

    def as_dict(self) -> dict[str, Any]:
        return {
            "settle_weight": self.settle_weight,
            "plants": self.plants,
            "aggregate": self.aggregate,
            "require_check": self.require_check,
        }


@dataclass
class TuneOutcome:
    """What a :meth:`Tuner.run` call did."""

    completed: int = 0
    best_value: float = math.inf
    best_params: dict[str, Any] = field(default_factory=dict)
    best_trial: int | None = None
    start_value: float | None = None
    interrupted: bool = False
    wall_s: float = 0.0
    points_ran: int = 0


@dataclass
class _Running:
    """A trial in flight: its points, their values so far, its futures."""

    trial: Any
    points: list[Point]
    values: dict[str, float] = field(default_factory=dict)
    futures: list[Any] = field(default_factory=list)


class Tuner:
    """One tuning folder: the study, its points, its outputs (module docstring).

    :param out: the tuning folder (``study.db``, ``runs/``, ``best.toml``, ``report.md``)
    :param spec: base options and Monte Carlo draws (``[base]``, ``[monte_carlo]``)
    :param params: the tuned keys
    """

    def __init__(
        self, out: Path, spec: SweepSpec, params: Sequence[Param], objective: Objective, budget: int, sampler_seed: int = 0
    ) -> None:
        if not params:
            raise InputError("nothing to tune: give --param KEY=LOW:HIGH (or a [tune] section)")
        keys = [p.key for p in params]
        if len(set(keys)) != len(keys):
            raise InputError(f"a key is tuned twice: {', '.join(keys)}")
        if budget < 1:
            raise InputError(f"--budget must be >= 1, got {budget}")
        if objective.plants and not spec.draws:
            raise InputError("--plants needs the distributions of the plants: a spec with [monte_carlo.draw]")
        tuned_and_drawn = set(keys) & {d.key for d in spec.draws}
        if tuned_and_drawn:
            raise InputError(f"{', '.join(sorted(tuned_and_drawn))}: tuned and drawn")
        self.out = Path(out)
        self.spec, self.params, self.objective, self.budget = spec, list(params), objective, budget
        self.sampler_seed = sampler_seed
        self.base = spec.base_options()
        self.start = self._start_values()
        Point.of(self._options(self.start, None))  # the starting point is a valid experiment
        self.study: Any = None

    # -- the experiments of a trial ------------------------------------------------------------

    def _start_values(self) -> dict[str, Any]:
        from host.experiment.config import build_config

        cfg = build_config(None, self.base).as_dict()
        start = {}
        for p in self.params:
            head, _, tail = p.key.partition(".")
            value = (cfg.get(head) or {}).get(tail) if tail else cfg.get(head)
            if value is None:
                raise InputError(f"{p.key} has no starting value (the hand-picked gains): give it with --set {p.key}=VALUE")
            if not p.contains(value):
                raise InputError(f"the starting value {p.key} = {value} lies outside its range {p.low:g} .. {p.high:g}")
            start[p.key] = int(value) if p.integer else float(value)
        return start

    def _options(self, params: Mapping[str, Any], sample: int | None) -> dict[str, Any]:
        opts: dict[str, Any] = {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.base.items()}
        for k, v in params.items():
            set_key(opts, k, v)
        if sample is not None:
            for k, v in self.spec.draw(sample).items():
                set_key(opts, k, v)
        return opts

    def trial_points(self, params: Mapping[str, Any]) -> list[Point]:
        """The experiments of a trial with ``params``: one, or one per Monte Carlo plant."""
        samples: list[int | None] = list(range(self.objective.plants)) if self.objective.plants else [None]
        pts = []
        for i, s in enumerate(samples):
            labels = dict(params) | ({} if s is None else self.spec.draw(s) | {"sample": s})
            pts.append(Point.of(self._options(params, s), index=i, labels=labels))
        return pts

    # -- the study -----------------------------------------------------------------------------

    def open_study(self) -> Any:
        """Create or load the study in ``out/study.db``; a new one gets the starting point as its
        first trial.

        :raises InputError: the folder's study tunes other keys or another objective."""
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self.out.mkdir(parents=True, exist_ok=True)
        storage = f"sqlite:///{(self.out / STUDY_FILE).resolve()}"
        sampler = optuna.samplers.TPESampler(seed=self.sampler_seed, n_startup_trials=max(4, len(self.params) * 2))
        pruner = optuna.pruners.MedianPruner(n_startup_trials=4, n_warmup_steps=1)
        study = optuna.create_study(
            storage=storage, study_name=STUDY_NAME, direction="minimize", sampler=sampler, pruner=pruner, load_if_exists=True
        )
        identity = {
            "params": [[p.key, p.low, p.high, p.log, p.integer] for p in self.params],
            "objective": self.objective.as_dict(),
            "base": json_safe(self.base),
            "draws": [[d.key, d.dist, list(d.params)] for d in self.spec.draws] if self.objective.plants else [],
            "seed": self.spec.seed if self.objective.plants else None,
        }
        stored = study.user_attrs.get("identity")
        if stored is None:
            study.set_user_attr("identity", identity)
            study.enqueue_trial(self.start, user_attrs={"start": True})
        elif stored != json_safe(identity):
            raise InputError(
                f"{self.out / STUDY_FILE} holds a study of other keys, base options or objective; "
                "tune in another --out folder (or delete it)"
            )
        self._recover_interrupted(study)
        self.study = study
        return study

    def _recover_interrupted(self, study: Any) -> None:
        """Trials left running by a run that was killed: failed, and their parameters queued again."""
        import optuna

        for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
            study.tell(t.number, state=optuna.trial.TrialState.FAIL)
            study.set_user_attr(f"interrupted_{t.number}", True)
            study.enqueue_trial(t.params, user_attrs={"start": True} if t.user_attrs.get("start") else {})

    def finished(self) -> list[Any]:
        """The study's trials that count towards the budget (not the interrupted ones)."""
        import optuna

        done = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED, optuna.trial.TrialState.FAIL)
        attrs = self.study.user_attrs
        return [t for t in self.study.get_trials(deepcopy=False, states=done) if not attrs.get(f"interrupted_{t.number}")]

    def _ask(self) -> _Running:
        trial = self.study.ask({p.key: p.distribution() for p in self.params})
        params = {p.key: trial.params[p.key] for p in self.params}
        return _Running(trial, self.trial_points(params))

    def _infeasible(self, run: _Running) -> str | None:
        """Why the trial's gains are not run (``require_check``: the convergence check fails)."""
        if not self.objective.require_check:
            return None
        from ilcrig.experiment import Experiment

        host_log = logging.getLogger("host")  # the plan's warnings about these gains: the reason says it
        level = host_log.level
        host_log.setLevel(logging.ERROR)
        try:
            check = Experiment(**run.points[0].options).check
        except InputError as exc:
            return str(exc)
        finally:
            host_log.setLevel(level)
        if check.checked and not check.ok:
            return (
                f"convergence check fails (spectral radius {check.rho_max:.4f}, predicted error ratio after "
                f"{check.iterations} trials {check.predicted_ratio:.3g})"
            )
        return None

    # -- running -------------------------------------------------------------------------------

    def run(self, engine: Engine, progress: bool = True) -> TuneOutcome:
        """Run trials until the study holds ``budget`` of them (Ctrl-C / SIGTERM: interrupted, the
        trials in flight queued again for the next call)."""
        import optuna
        from distributed import as_completed
        from tqdm import tqdm

        if self.study is None:
            self.open_study()
        outcome = TuneOutcome()
        t0 = time.perf_counter()
        todo = self.budget - len(self.finished())
        bar = tqdm(total=max(todo, 0), desc="tune", unit="trial", file=sys.stderr, disable=not progress, dynamic_ncols=True)
        workers = max(1, engine.n_workers)
        in_flight: dict[int, _Running] = {}
        by_future: dict[Any, tuple[_Running, Point]] = {}
        ac = as_completed([], loop=engine.client.loop)
        started = 0

        def finish(run: _Running, state: Any = None, value: float | None = None) -> None:
            for f in run.futures:
                if f in by_future:
                    by_future.pop(f)
                    with contextlib.suppress(Exception):
                        f.cancel()
            in_flight.pop(run.trial.number, None)
            if state is optuna.trial.TrialState.PRUNED:
                self.study.tell(run.trial, state=state)
            else:
                self.study.tell(run.trial, value)
            outcome.completed += 1
            bar.update(1)
            with contextlib.suppress(ValueError):
                bar.set_postfix_str(f"best J {self.study.best_value:.4g}", refresh=False)

        def add_value(run: _Running, p: Point, value: float) -> None:
            run.values[p.id] = value
            done = [run.values[q.id] for q in run.points if q.id in run.values]
            if len(done) == len(run.points):
                finish(run, value=self.objective.combine(done))
                return
            run.trial.report(self.objective.combine(done), len(done))
            if run.trial.should_prune():
                finish(run, state=optuna.trial.TrialState.PRUNED)

        def start_trial() -> None:
            run = self._ask()
            run.trial.set_user_attr("points", [p.id for p in run.points])
            in_flight[run.trial.number] = run
            why = self._infeasible(run)
            if why is not None:
                run.trial.set_user_attr("infeasible", why)
                finish(run, value=math.inf)
                return
            for p in run.points:
                folder = run_dir(self.out, p.id)
                if is_finished(folder, p.config, False):
                    rec = load_point(folder)
                    add_value(run, p, self.objective.of_summary(rec.summary if rec else None))
                    if run.trial.number not in in_flight:
                        return
                    continue
                fut = engine.submit(
                    engine_point_function(), p.id, p.options, False, key=(TASK_GROUP, p.id, f"trial-{run.trial.number}")
                )
                run.futures.append(fut)
                by_future[fut] = (run, p)
                ac.add(fut)

        try:
            with interrupt_on_sigterm():
                try:
                    while True:
                        while started < todo and sum(len(r.points) - len(r.values) for r in in_flight.values()) < workers:
                            started += 1
                            start_trial()
                        if not by_future:
                            if started >= todo:
                                break
                            continue  # every point of the trials started so far was finished before
                        fut = next(ac)
                        if fut not in by_future:
                            continue  # a point of a pruned trial
                        run, p = by_future.pop(fut)
                        try:
                            result = fut.result()
                        except Exception as exc:  # noqa: BLE001 - KilledWorker: the point's error
                            result = {"id": p.id, "error": f"{type(exc).__name__}: {exc}", "summary": None, "wall_s": 0.0}
                        commit(self.out, p.id, point_doc(p) | {"trial": run.trial.number}, result)
                        outcome.points_ran += 1
                        add_value(run, p, self.objective.of_summary(result.get("summary")))
                except KeyboardInterrupt:
                    outcome.interrupted = True
                    self._requeue(in_flight.values(), engine)
        finally:
            bar.close()
            outcome.wall_s = time.perf_counter() - t0
        self._fill_best(outcome)
        return outcome

    def _requeue(self, runs: Any, engine: Engine) -> None:
        import optuna

        futures = [f for r in runs for f in r.futures]
        with contextlib.suppress(Exception):
            engine.client.cancel(futures, force=True)
        for r in list(runs):
            self.study.tell(r.trial, state=optuna.trial.TrialState.FAIL)
            self.study.set_user_attr(f"interrupted_{r.trial.number}", True)
            self.study.enqueue_trial(r.trial.params, user_attrs={"start": True} if r.trial.user_attrs.get("start") else {})

    def _fill_best(self, outcome: TuneOutcome) -> None:
        import optuna

        complete = [t for t in self.study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))]
        finite = [t for t in complete if t.value is not None and math.isfinite(t.value)]
        if finite:
            best = min(finite, key=lambda t: (t.value, t.number))
            outcome.best_value, outcome.best_params, outcome.best_trial = float(best.value), dict(best.params), best.number
        starts = [t for t in complete if t.user_attrs.get("start")]
        if starts:
            outcome.start_value = float(starts[0].value) if starts[0].value is not None else None

    # -- outputs -------------------------------------------------------------------------------

    def best_options(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """The experiment of the best gains (the robot as built: no Monte Carlo draw)."""
        return self._options(params, None)

    def write_best(self, outcome: TuneOutcome) -> Path | None:
        """``best.toml``: the experiment file of the best gains (None: no finite trial yet)."""
        if outcome.best_trial is None:
            return None
        opts = self.best_options(outcome.best_params)
        head = [
            f"# ilcrig tune: the best of {len(self.finished())} trials in {STUDY_FILE} (trial {outcome.best_trial}, "
            f"J = {outcome.best_value:.6g}"
            + (f"; the starting point: J = {outcome.start_value:.6g}" if outcome.start_value is not None else "")
            + ")",
            f"# objective: {self.objective.describe()}",
            f"# run it: ilcrig sim --config {self.out / BEST_FILE}",
        ]
        path = self.out / BEST_FILE
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text("\n".join(head) + "\n" + toml_text(opts), encoding="utf-8")
        os.replace(tmp, path)
        return path

    def write_outputs(self, outcome: TuneOutcome) -> Path:
        """``best.toml``, ``results.parquet`` (every point of every trial) and ``report.md`` with
        ``tuning.png`` (J per trial and the best so far)."""
        import optuna

        self.write_best(outcome)
        trials = self.study.get_trials(deepcopy=False)
        points: dict[str, Point] = {}
        for t in trials:
            if t.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED) and t.params:
                for p in self.trial_points({q.key: t.params[q.key] for q in self.params if q.key in t.params}):
                    points.setdefault(p.id, Point(p.id, len(points), p.options, p.labels | {"study_trial": t.number}, p.config))
        write_table(self.out, list(points.values()))
        return self._report(outcome, trials)

    def _report(self, outcome: TuneOutcome, trials: Sequence[Any]) -> Path:
        import optuna

        done = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
        lines = [
            f"# ilcrig tune — {self.out.name}",
            "",
            f"{len(self.finished())} of {self.budget} trials in `{STUDY_FILE}` "
            f"({sum(t.state == optuna.trial.TrialState.PRUNED for t in trials)} pruned).",
            "",
            f"- objective: {self.objective.describe()}",
            "- tuned: " + "; ".join(p.describe() for p in self.params),
            "- base: " + ", ".join(f"`{k}` = {v!r}" for k, v in sorted(self.base.items()) if not isinstance(v, dict)),
            "",
        ]
        if outcome.best_trial is not None:
            start = ", ".join(f"{k} = {fmt(v, 4)}" for k, v in self.start.items())
            best = ", ".join(f"{k} = {fmt(v, 4)}" for k, v in outcome.best_params.items())
            lines += [
                "## Best against the starting point",
                "",
                *md_table(
                    ["", "gains", "J"],
                    [
                        ["starting point (hand-picked)", start, fmt(outcome.start_value, 4)],
                        [f"best (trial {outcome.best_trial})", best, fmt(outcome.best_value, 4)],
                    ],
                ),
                "",
                f"`ilcrig sim --config {BEST_FILE}` runs the best gains ({BEST_FILE} in this folder).",
                "",
            ]
        if done:
            fig, ax = figure(1, 1, 8, 4)
            a = ax[0, 0]
            num = np.array([t.number for t in done])
            val = np.array([t.value if t.value is not None and math.isfinite(t.value) else np.nan for t in done])
            a.plot(num, val, "o", label="J of the trial")
            best_so_far = np.fmin.accumulate(np.where(np.isfinite(val), val, np.inf))
            a.step(num, np.where(np.isfinite(best_so_far), best_so_far, np.nan), where="post", label="best so far")
            a.set_xlabel("trial")
            a.set_ylabel("J")
            if np.nanmin(val) > 0 and np.nanmax(val) / np.nanmin(val) > 10:
                a.set_yscale("log")
            a.grid(True, alpha=0.3)
            a.legend()
            save_png(fig, self.out / "tuning.png")
            lines += ["## Trials", "", "![J per trial](tuning.png)", ""]
        rows = []
        for t in sorted(trials, key=lambda t: (t.value is None or not math.isfinite(t.value), t.value or 0.0, t.number)):
            state = t.state.name.lower() + (" (start)" if t.user_attrs.get("start") else "")
            if t.user_attrs.get("infeasible"):
                state += f": {t.user_attrs['infeasible']}"
            rows.append(
                [str(t.number)]
                + [fmt(t.params.get(p.key), 4) for p in self.params]
                + [fmt(t.value, 4) if t.value is not None else "—", state]
            )
        lines += md_table(["trial"] + [f"`{p.key}`" for p in self.params] + ["J", "state"], rows) + [""]
        path = self.out / "report.md"
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
        os.replace(tmp, path)
        return path

    def cli_options(self, params: Mapping[str, Any]) -> str:
        """The best gains as command-line options of ``ilcrig sim`` (where a flag exists)."""
        words = []
        for k, v in params.items():
            head, _, tail = k.partition(".")
            if head == "gains" and tail in GAIN_FLAGS:
                words += [GAIN_FLAGS[tail], repr(v)]
            else:
                words.append(f"[{head}] {tail} = {v!r}" if tail else f"{k} = {v!r}")
        return " ".join(words)


def engine_point_function() -> Any:
    """The point function of the engine (a test may have put a wrapper in its place)."""
    import ilcrig.sweep.engine

    return ilcrig.sweep.engine.POINT_FUNCTION


def json_safe(obj: Any) -> Any:
    """``obj`` as JSON types (what Optuna stores as a user attribute)."""
    import json

    return json.loads(json.dumps(obj, default=str))


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"TOML has no {v}")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    raise ValueError(f"no TOML value for {v!r}")


def toml_text(options: Mapping[str, Any]) -> str:
    """Experiment options as an experiment file (top-level keys, then ``[gains]``, ``[law_options]``,
    ``[plant]``); ``None`` values are left out (the default)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in options.items() if not isinstance(v, dict) and v is not None]
    for table in ("gains", "law_options", "plant"):
        values = {k: v for k, v in (options.get(table) or {}).items() if v is not None}
        if values:
            lines += ["", f"[{table}]"] + [f"{k} = {_toml_value(v)}" for k, v in values.items()]
    return "\n".join(lines) + "\n"


def _tune_settings(spec: SweepSpec, args: argparse.Namespace) -> tuple[list[Param], Objective, int]:
    tune = dict(spec.extra.get("tune") or {})
    budget = tune.pop("budget", DEFAULT_BUDGET)
    params = [Param.of(k, v, "[tune]") if isinstance(v, Mapping) else _bad_tune(k) for k, v in tune.items()]
    for text in getattr(args, "param", None) or []:
        p = Param.parse(text)
        params = [q for q in params if q.key != p.key] + [p]
    obj = dict(spec.extra.get("objective") or {})
    bad = set(obj) - {"settle_weight", "plants", "aggregate", "require_check"}
    if bad:
        raise InputError(
            f"[objective]: unknown key(s) {', '.join(sorted(bad))}; choose from settle_weight, plants, aggregate, require_check"
        )
    for key in ("settle_weight", "plants", "aggregate", "require_check"):
        if getattr(args, key, None) is not None:
            obj[key] = getattr(args, key)
    if getattr(args, "budget", None) is not None:
        budget = args.budget
    if isinstance(budget, bool) or not isinstance(budget, int):
        raise InputError(f"budget must be an integer, got {budget!r}")
    try:
        objective = Objective(
            settle_weight=float(obj.get("settle_weight", 0.0)),
            plants=int(obj.get("plants", 0)),
            aggregate=str(obj.get("aggregate", "mean")),
            require_check=bool(obj.get("require_check", False)),
        )
    except (TypeError, ValueError) as exc:
        raise InputError(f"[objective]: {exc}") from None
    return params, objective, budget


def _bad_tune(key: str) -> Param:
    raise InputError(f"[tune] {key}: a range is {{low, high[, log = true][, int = true]}}")


def tune_main(args: argparse.Namespace, spec: SweepSpec, engine: Engine) -> int:
    """``ilcrig tune`` with its spec and (not started) engine: open (or resume) the study, run it to
    its budget, write the outputs and print the best gains."""
    if spec.vary:
        raise InputError("ilcrig tune takes no --vary / [vary]: the tuned keys are --param / [tune]")
    params, objective, budget = _tune_settings(spec, args)
    out = Path(args.out) if getattr(args, "out", None) else Path("runs") / time.strftime("tune-%Y%m%d-%H%M%S")
    tuner = Tuner(out, spec, params, objective, budget, sampler_seed=getattr(args, "sampler_seed", 0) or 0)
    tuner.open_study()
    with engine:
        sys.stderr.write(
            f"ilcrig tune: {', '.join(p.key for p in params)}; {budget} trials "
            f"({len(tuner.finished())} in the study already) on {engine.describe()}; folder {out}\n"
        )
        if engine.dashboard:
            sys.stderr.write(f"ilcrig tune: dashboard {engine.dashboard}\n")
        outcome = tuner.run(engine, progress=not getattr(args, "no_progress", False))
    report = tuner.write_outputs(outcome)
    if outcome.interrupted:
        sys.stderr.write(f"ilcrig: interrupted; the study in {out / STUDY_FILE} is kept; run the same command again to resume\n")
        return 130
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
