"""``ilcrig tune``: gains tuned with Optuna, each trial's experiments run on the sweep engine.

This module owns :class:`Tuner`: the study (Optuna, kept in the tuning folder as SQLite:
``study.db``, so a tuning run resumes), its trials run on the engine, and its outputs:
``best.toml`` (an experiment file of the best gains, for ``ilcrig sim --config``), ``report.md``
with ``tuning.png``, ``results.parquet`` and every point's folder in ``runs/``
(:mod:`host.studies.point`).

**Objective** (minimised), per experiment: J = mean over the joints of the final RMSE (the last
learning trial's, deg) + ``settle_weight`` × the settle iteration (the first trial from which every
joint stays within 2× of its final RMSE, :func:`host.studies.settling.settle_iteration`); a run
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

**Reproducibility**: on one worker the sampler seed fixes the study trial by trial; on more, a
trial's gains are asked while others run and the sampler (and the pruner) learn only from the
finished ones, so the sequence depends on the order the points finish in (docs/sweeps.md §4,
measured there).

The settings (the tuned keys, the objective, the budget) are :mod:`host.studies.tune_params`'s; a
trial's points run on the engine's one submit loop (:class:`host.studies.engine.PointQueue`).
``best.toml`` is written by the experiment file writer, :func:`host.experiment.config.options_toml`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bus.atomic import atomic_write
from bus.errors import InputError
from host.analysis.figures import figure, save_png
from host.analysis.markdown import fmt, md_table
from host.experiment.config import options_toml
from host.experiment.signal_shield import interrupt_on_signals, signum_of
from host.studies.engine import ClusterLost, Engine, PointQueue, point_doc
from host.studies.point import is_finished, load_point, plan_of, run_dir
from host.studies.spec import Point, SweepSpec, set_key
from host.studies.table import write_table
from host.studies.tune_params import Objective, Param

logger = logging.getLogger(__name__)

__all__ = ["Tuner", "TuneOutcome", "STUDY_NAME", "STUDY_FILE", "BEST_FILE", "json_safe"]

STUDY_NAME = "ilcrig-tune"
STUDY_FILE = "study.db"
BEST_FILE = "best.toml"
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


@dataclass
class TuneOutcome:
    """What a :meth:`Tuner.run` call did."""

    completed: int = 0
    best_value: float = math.inf
    best_params: dict[str, Any] = field(default_factory=dict)
    best_trial: int | None = None
    start_value: float | None = None
    #: the signal that interrupted it (SIGINT for Ctrl-C, SIGTERM); None: not interrupted
    signum: int | None = None
    cluster_lost: str | None = None
    wall_s: float = 0.0
    points_ran: int = 0

    @property
    def interrupted(self) -> bool:
        """A signal ended it (:attr:`signum`)."""
        return self.signum is not None


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
        host_log = logging.getLogger("host")  # the plan's warnings about these gains: the reason says it
        level = host_log.level
        host_log.setLevel(logging.ERROR)
        try:
            check = plan_of(run.points[0].options).check
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
        from tqdm import tqdm

        if self.study is None:
            self.open_study()
        outcome = TuneOutcome()
        t0 = time.perf_counter()
        todo = self.budget - len(self.finished())
        try:
            with interrupt_on_signals():
                if todo > 0:
                    engine.await_workers()
        except ClusterLost as exc:
            outcome.cluster_lost = str(exc)
            self._fill_best(outcome)
            return outcome
        except KeyboardInterrupt as exc:
            outcome.signum = signum_of(exc)
            self._fill_best(outcome)
            return outcome
        bar = tqdm(total=max(todo, 0), desc="tune", unit="trial", file=sys.stderr, disable=not progress, dynamic_ncols=True)
        workers = max(1, engine.n_workers)
        in_flight: dict[int, _Running] = {}
        queue = PointQueue(engine, self.out)
        started = 0

        def finish(run: _Running, state: Any = None, value: float | None = None) -> None:
            queue.drop(run.futures)
            in_flight.pop(run.trial.number, None)
            if state is optuna.trial.TrialState.PRUNED:
                self.study.tell(run.trial, state=state)
            else:
                self.study.tell(run.trial, value)
            outcome.completed += 1
            bar.update(1)
            with contextlib.suppress(ValueError):  # no completed trial yet
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
                doc = point_doc(p) | {"trial": run.trial.number}
                run.futures.append(queue.submit(p, tag=f"trial-{run.trial.number}", doc=doc, owner=run))

        try:
            with interrupt_on_signals():
                try:
                    while True:
                        while started < todo and sum(len(r.points) - len(r.values) for r in in_flight.values()) < workers:
                            started += 1
                            start_trial()
                        if not len(queue):
                            if started >= todo:
                                break
                            continue  # every point of the trials started so far was finished before
                        p, result, run = queue.next()  # written into its folder; a pruned trial's are dropped
                        outcome.points_ran += 1
                        add_value(run, p, self.objective.of_summary(result.get("summary")))
                except KeyboardInterrupt as exc:
                    outcome.signum = signum_of(exc)
                    queue.cancel()
                    self._requeue(in_flight.values())
                except ClusterLost as exc:  # the trials in flight run again on resume
                    outcome.cluster_lost = str(exc)
                    queue.cancel()
                    self._requeue(in_flight.values())
        finally:
            bar.close()
            outcome.wall_s = time.perf_counter() - t0
        self._fill_best(outcome)
        return outcome

    def _requeue(self, runs: Any) -> None:
        """The trials in flight (their points cancelled): failed, and their parameters queued again."""
        import optuna

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
        return atomic_write(self.out / BEST_FILE, "\n".join(head) + "\n" + options_toml(opts))

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
        return atomic_write(self.out / "report.md", "\n".join(lines) + "\n")

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


def json_safe(obj: Any) -> Any:
    """``obj`` as JSON types (what Optuna stores as a user attribute)."""
    import json

    return json.loads(json.dumps(obj, default=str))
