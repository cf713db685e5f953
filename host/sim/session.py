"""The in-process experiment, one trial per step: the capability behind ``ilcrig sim`` and the
public API's :class:`ilcrig.Experiment` / :class:`ilcrig.Session`.

This module owns :class:`SimSession` (the composition root of an in-process run: the plan, the
in-process bench :class:`host.sim.inprocess.InProcessBench`, the trial loop
:class:`host.experiment.trial_loop.TrialLoop`, the run's outputs through the one run-outputs path
:func:`host.analysis.session.open_outputs`, the console lines, gains changed between trials, and
``report.md`` at the end) and :func:`run_sim`, the whole run of ``ilcrig sim``.  Bad input is
:class:`bus.errors.InputError`.

The drives' firmware (``--firmware``) is checked here before anything is made
(:func:`firmware_model.firmware_select.check_firmware`).

May import: ``bus``, ``plant``, ``firmware_model`` (the firmware's selection here, the drives
through :mod:`host.sim.inprocess`), and ``host`` below the rig (planning, learning, nodes,
experiment, analysis).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from bus.errors import InputError
from firmware_model.firmware_select import DEFAULT_FIRMWARE, check_firmware
from host.analysis.session import RunOutputs, finish_run_report, open_outputs, report_fault
from host.experiment.config import ExperimentConfig, build_config, gains_table
from host.experiment.console import print_header, print_plan, print_row
from host.experiment.loop_state import ExperimentResult, TrialOutcome
from host.experiment.outputs import SUMMARY_NAME, RunFolder, check_out_dir, default_run_folder
from host.experiment.plan import Plan, plan_with_gains, rehearse_first_update
from host.experiment.signal_shield import deferred_interrupts, interrupt_on_signals
from host.experiment.trial_loop import TrialLoop
from host.learning.metrics import TrialMetrics

logger = logging.getLogger(__name__)

__all__ = ["SimOptions", "SimSession", "run_sim"]


def _first_line(exc: BaseException) -> str:
    """The one line of an exception's message (its type's name when it has none)."""
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


class SimSession:
    """An in-process run of ``plan``, one trial per :meth:`step` (also an iterator of the trials'
    outcomes and a context manager: leaving it ends the run with the bench's safe state, the final
    summary and, with a run folder, ``report.md``).

    :param out: the run folder (checked here: :class:`InputError` before anything is made); None:
        nothing is written
    :param stream: the console lines (plan, header, one row per trial); None: silent
    :param view: stream the recording live to a Rerun viewer (needs ``out``)
    :param firmware: the drives' control-period implementation (``--firmware``: ``python``, ``c``, ``pil``)
    :raises InputError: a bad run folder, ``view`` without one, or a firmware this installation
        cannot run
    """

    def __init__(
        self,
        plan: Plan,
        out: str | Path | None = None,
        *,
        stream: TextIO | None = None,
        view: bool = False,
        firmware: str = DEFAULT_FIRMWARE,
    ) -> None:
        from host.sim.inprocess import InProcessBench

        self.out = Path(out) if out is not None else None
        self.stream = stream
        check_firmware(firmware)  # before anything is made
        if view and self.out is None:
            raise InputError("view: the live view streams the run's recording; give a run folder (out)")
        # what the law's update imports on first use (scipy.signal, ...) is imported now, in
        # ``ilcrig sim`` while signals are held: an interrupt raised inside an import leaves that
        # module half made in this interpreter, and an API caller's next run would fail on it
        rehearse_first_update(plan.law, plan.u0)
        outputs: RunOutputs | None = None
        if self.out is not None:
            check_out_dir(self.out, iterations=plan.cfg.iterations, n_ticks=plan.n_ticks, new_run=True)
        if stream is not None:
            print_plan(stream, "sim", plan)
        if self.out is not None:
            outputs = open_outputs(plan, self.out, view=view)
            if outputs.live_line is not None and stream is not None:
                stream.write(outputs.live_line + "\n")
                stream.flush()
        if stream is not None:
            print_header(stream)
        #: the live stream's address (``rerun+http://127.0.0.1:PORT/proxy``) with ``view``, else None
        self.live_url: str | None = outputs.live_url if outputs is not None else None
        self._folder: RunFolder | None = outputs.folder if outputs is not None else None
        self.runner = TrialLoop(
            plan,
            InProcessBench(plan.cfg, firmware),
            self.out,
            mode="sim",
            on_trial=self._row if stream is not None else None,
            recorder=outputs.recorder if outputs is not None else None,
            folder=self._folder,
        )
        self._reported = False

    def _row(self, m: TrialMetrics, role: str) -> None:
        assert self.stream is not None
        print_row(self.stream, m, role)

    def __enter__(self) -> SimSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[TrialOutcome]:
        while (o := self.step()) is not None:
            yield o

    @property
    def plan(self) -> Plan:
        """The plan in force (its gains change with :meth:`set_gains`)."""
        return self.runner.plan

    @property
    def done(self) -> bool:
        return self.runner.done

    @property
    def result(self) -> ExperimentResult:
        """The trial loop's result so far (summary, fault, interrupt)."""
        return self.runner.result

    def step(self) -> TrialOutcome | None:
        """Run the next trial (a learning trial, or an auxiliary rollout its law asked for); None
        when the run is over (every trial ran, or a fault or an interrupt ended it)."""
        outcome = self.runner.step()
        if outcome is None or self.runner.finished:
            self.close()
        return outcome

    def end_by_user(self, exc: BaseException) -> ExperimentResult:
        """End the run for an exception of the caller's code (the API's ``with`` block; a
        :class:`KeyboardInterrupt` is an interrupt): every kept trial stays, the summary says why
        (:meth:`host.experiment.trial_loop.TrialLoop.end_by_user`), then :meth:`close`."""
        self.runner.end_by_user(exc)
        return self.close()

    def set_gains(self, **changes: Any) -> None:
        """Change the gains before the next trial (``[gains]`` keys: ``alpha``, ``beta``, ``lp``, …).

        :raises InputError: a bad key or value, a feedback gain outside the drive's range, or a
            change between a learning trial and its auxiliary trials.
        """
        cfg = self.plan.cfg
        base = {k: v for k, v in cfg.as_dict().items() if k != "gains"}
        try:
            new = build_config(None, base | {"gains": gains_table(cfg.gains) | changes})
            self.runner.set_gains(plan_with_gains(self.plan, new.gains))
        except (ValueError, RuntimeError) as exc:
            raise InputError(_first_line(exc)) from None

    def close(self) -> ExperimentResult:
        """End the run (bench closed, final summary; with a run folder also ``report.md``), once."""
        res = self.runner.finish()
        if self.out is not None and not self._reported:
            self._reported = True
            finish_run_report(self.out, res, self._folder)
        return res


@dataclass(frozen=True)
class SimOptions:
    """What ``ilcrig sim`` runs: the validated experiment, its run folder, the live view, the drives'
    firmware."""

    config: ExperimentConfig
    #: the run folder (None: a fresh ``runs/sim-<time>``, :func:`host.experiment.outputs.default_run_folder`)
    out: Path | None
    view: bool = False
    firmware: str = DEFAULT_FIRMWARE


def run_sim(opts: SimOptions, stream: TextIO) -> int:
    """``ilcrig sim``: the whole experiment in this process with its outputs in ``opts.out``, the
    console lines and the closing line on ``stream``; returns the exit code (a fault: its one line
    on stderr, :func:`host.analysis.session.report_fault`).

    :raises InputError: an infeasible experiment or a bad run folder, before the folder is made
    """
    from host.experiment.console import prepared
    from host.experiment.plan import check_config_limits

    cfg = opts.config
    check_config_limits(cfg)  # the trial length and the memory first: an out-of-range --cycle is said as such
    named = opts.out if opts.out is not None else default_run_folder("sim", claim=False)
    check_out_dir(named, iterations=cfg.iterations, n_ticks=cfg.n_ticks, create=False)
    plan = prepared(cfg)  # refused with one line before the run folder is made
    with interrupt_on_signals():
        try:
            with deferred_interrupts():  # a signal while the folder is made: raised once the run can end
                out = opts.out if opts.out is not None else default_run_folder("sim", claim=True)
                session = SimSession(plan, out, stream=stream, view=opts.view, firmware=opts.firmware)
            for _ in session:
                pass
        except KeyboardInterrupt as exc:
            # a signal before the first trial or between the guarded parts of two trials (after a
            # trial was kept and printed, before the next one runs): the same end as inside them
            session.end_by_user(exc)
        res = session.close()
    s = res.summary
    stream.write(
        f"{s['ticks']} ticks in {s['wall_s']:.2f} s ({s['ticks_per_s']:.0f} ticks/s); "
        f"trace_sha256 {s['trace_sha256'][:16]}…; summary: {out / SUMMARY_NAME}\n"
    )
    return report_fault(res, out / SUMMARY_NAME)
