"""One experiment with all its outputs, as ``ilcrig sim`` and ``ilcrig host`` run it.

This module owns what both commands do around :func:`host.experiment.trial_loop.run_experiment`: the run
folder's space reserve (:class:`host.experiment.outputs.RunFolder`), the Rerun recording
(:mod:`host.analysis.recording`, written trial by trial), one console row per trial,
every trial's signals as numpy files (:mod:`host.experiment.arrays`), ``report.md`` with its
convergence plot after the last completed trial — also after a fault or an
interrupt (:mod:`host.analysis.run_report`); a report that cannot be written (a full disk) is the
run's fault when it has none (``summary.json`` then says so) — and the closing line with its exit
code: one line ``ilcrig: fault: …`` and 3 after a fault, 130 / 143 after SIGINT / SIGTERM.
"""

from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path
from typing import TextIO

from bus.exit_codes import EXIT_FAULT, EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED
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
from host.experiment.summary import write_summary
from host.experiment.trial_loop import run_experiment

logger = logging.getLogger(__name__)

__all__ = ["finish_run_report", "run_session", "report_fault"]


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
    if live is not None:
        stream.write(live.open_viewer() + "\n")
    print_header(stream)
    res = run_experiment(
        plan, bench, out, mode=mode, on_trial=lambda m, role: print_row(stream, m, role), recorder=recorder, folder=folder
    )
    finish_run_report(out, res, folder)
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
        return (
            EXIT_TERMINATED
            if res.interrupted == signal.SIGTERM
            else EXIT_INTERRUPTED
            if res.interrupted == signal.SIGINT
            else 128 + res.interrupted
        )
    if res.fault_record is not None:
        sys.stderr.write(fault_line(res.fault_record, kept, summary_path=summary_path) + "\n")
        sys.stderr.flush()
        return EXIT_FAULT
    if res.fault:
        sys.stderr.write(f"ilcrig: fault: {res.fault} (torque removed; {kept} trials kept)\n")
        return EXIT_FAULT
    return EXIT_OK
