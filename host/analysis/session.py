"""One experiment with all its outputs, as ``ilcrig sim``, ``ilcrig host`` and the API run it.

This module owns the one run-outputs path of every run (:func:`open_outputs`, used by
:func:`run_session` and by the in-process :class:`host.sim.session.SimSession`) and what the
commands do around :func:`host.experiment.trial_loop.run_experiment`: the run folder's space reserve
(:class:`host.experiment.outputs.RunFolder`), the Rerun recording (:mod:`host.analysis.recording`,
written trial by trial), one console row per trial, every trial's signals as numpy files
(:mod:`host.experiment.arrays`), ``report.md`` with its convergence plot after the last completed
trial — also after a fault or an interrupt (:mod:`host.analysis.run_report`); a report that cannot be written (a full disk) is the
run's fault when it has none (``summary.json`` then says so) — and the closing line with its exit
code: one line ``ilcrig: fault: …`` and 3 after a fault, 130 / 143 after SIGINT / SIGTERM.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from bus.exit_codes import EXIT_FAULT, EXIT_OK, exit_code_of_signal
from host.analysis.recording import RunRecorder
from host.analysis.run_report import write_run_report
from host.experiment.arrays import Recorders, TrialArrays
from host.experiment.bench import Bench
from host.experiment.console import print_header, print_row
from host.experiment.fault_placement import record_output_fault
from host.experiment.faults import fault_line
from host.experiment.loop_state import ExperimentResult
from host.experiment.outputs import OutputError, RunFolder, output_error
from host.experiment.plan import Plan
from host.experiment.signal_shield import deferred_interrupts
from host.experiment.summary import write_summary
from host.experiment.trial_loop import run_experiment

logger = logging.getLogger(__name__)

__all__ = ["RunOutputs", "finish_run_report", "open_outputs", "run_session", "report_fault"]


@dataclass(frozen=True)
class RunOutputs:
    """The outputs of a run in its folder: the space reserve, the trial recorder (Rerun recording +
    trials/*.npz), and, with ``view``, the live stream's address and the line that tells how to see
    it (both None without ``view``)."""

    folder: RunFolder
    recorder: Recorders
    live_url: str | None = None
    live_line: str | None = None


def open_outputs(
    plan: Plan,
    out: Path,
    *,
    view: bool = False,
    fail_writes_from_trial: int | None = None,
    fail_spec: str | None = None,
) -> RunOutputs:
    """The run folder ``out`` (checked by the caller) with its space reserve, the Rerun recording
    (live to a viewer with ``view``, :mod:`host.analysis.live_view`) and the trials' arrays.

    :param fail_writes_from_trial: fault injection: the outputs' writes fail with ``ENOSPC`` from
        this trial's on (−1: from the first summary on; ``--inject diskfull@K``)
    :param fail_spec: the ``--inject`` spec of that injection (for its record)
    """
    live = None
    if view:
        from host.analysis.live_view import LiveView

        live = LiveView()
    folder = RunFolder(out, plan.cfg.iterations, plan.n_ticks)
    folder.reserve()
    folder.fail_writes_from_trial = fail_writes_from_trial
    folder.fail_spec = fail_spec
    recorder = Recorders(
        RunRecorder(out / "recording.rrd", recording_id=out.name, config_summary=plan.cfg.as_dict(), folder=folder, live=live),
        TrialArrays(out, folder),
    )
    if live is None:
        return RunOutputs(folder, recorder)
    return RunOutputs(folder, recorder, live.url, live.open_viewer())


def run_session(
    plan: Plan,
    bench: Bench,
    out: Path,
    *,
    mode: str,
    stream: TextIO,
    fail_writes_from_trial: int | None = None,
    view: bool = False,
    fail_spec: str | None = None,
) -> ExperimentResult:
    """Run ``plan`` on ``bench`` with a recording in ``out`` and a console row per trial; write
    ``report.md`` when at least one trial completed.

    :param fail_writes_from_trial: fault injection: the outputs' writes fail with ``ENOSPC`` from
        this trial's on (−1: from the first summary on; ``--inject diskfull@K``)
    :param fail_spec: the ``--inject`` spec of that injection (for its record)
    :param view: the recording also goes live to a Rerun viewer (:mod:`host.analysis.live_view`)
    """
    held: KeyboardInterrupt | None = None
    try:
        with deferred_interrupts():  # a signal while the folder is made: the run ends marked, not half made
            outputs = open_outputs(plan, out, view=view, fail_writes_from_trial=fail_writes_from_trial, fail_spec=fail_spec)
            if outputs.live_line is not None:
                stream.write(outputs.live_line + "\n")
            print_header(stream)
    except KeyboardInterrupt as exc:  # raised as the block ended: the outputs are made
        held = exc
    res = run_experiment(
        plan,
        bench,
        out,
        mode=mode,
        on_trial=lambda m, role: print_row(stream, m, role),
        recorder=outputs.recorder,
        folder=outputs.folder,
        interrupted=held,
    )
    finish_run_report(out, res, outputs.folder)
    return res


def finish_run_report(out: Path, res: ExperimentResult, folder: RunFolder | None = None) -> None:
    """``report.md`` with its convergence plot (when a trial completed, or the run faulted or was
    interrupted); one that cannot be written (a full disk) is the run's fault when it has none: the
    summary says so, written into the last part of the reserve. Gives the reserve back."""
    if res.summary["iterations"] or res.summary["faults"] or res.interrupted:
        try:
            write_run_report(out, res.summary)  # report.md + convergence plot next to the summary
        except OSError as err:
            logger.error("report.md could not be written: %s", err)
            if record_output_fault(res, output_error(str(out / "report.md"), err)) is not None:
                if folder is not None:
                    folder.release_last()  # the room kept for this last word
                try:
                    write_summary(out, res.summary)
                except OutputError as exc:
                    logger.error("the summary could not say so either: %s", exc)
    if folder is not None:
        folder.release_last()


def report_fault(res: ExperimentResult, summary_path: Path | None = None) -> int:
    """The exit code of a finished run; a fault gets its one line on stderr."""
    kept = len(res.summary["iterations"])
    if res.interrupted is not None:
        return exit_code_of_signal(res.interrupted)
    if res.fault_record is not None:
        sys.stderr.write(fault_line(res.fault_record, kept, summary_path=summary_path) + "\n")
        sys.stderr.flush()
        return EXIT_FAULT
    if res.fault:
        sys.stderr.write(f"ilcrig: fault: {res.fault} (torque removed; {kept} trials kept)\n")
        return EXIT_FAULT
    return EXIT_OK
