"""One experiment with all its outputs, as ``ilcrig sim`` and ``ilcrig host`` run it.

This module owns what both commands do around :func:`host.experiment.loop.run_experiment`: the
Rerun recording (:mod:`host.analysis.recording`), one console row per trial, ``report.md`` with its
convergence plot after the last completed trial (:mod:`host.analysis.report`), and the closing fault
line with its exit code.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TextIO

from host.analysis.recording import RunRecorder
from host.analysis.run_report import write_run_report
from host.experiment.console import EXIT_FAULT, EXIT_OK, print_header, print_row
from host.experiment.loop import Bench, ExperimentResult, run_experiment
from host.experiment.plan import Plan

__all__ = ["run_session", "report_fault"]


def run_session(plan: Plan, bench: Bench, out: Path, *, mode: str, stream: TextIO) -> ExperimentResult:
    """Run ``plan`` on ``bench`` with a recording in ``out`` and a console row per trial; write
    ``report.md`` when at least one trial completed."""
    print_header(stream)
    recorder = RunRecorder(out / "recording.rrd", recording_id=out.name, config_summary=plan.cfg.as_dict())
    res = run_experiment(plan, bench, out, mode=mode, on_trial=lambda m: print_row(stream, m), recorder=recorder)
    if res.summary["iterations"]:
        write_run_report(out, res.summary)  # report.md + convergence plot next to the summary
    return res


def report_fault(res: ExperimentResult) -> int:
    """The exit code of a finished run; a fault gets its one line on stderr."""
    if res.fault:
        sys.stderr.write(f"ilcrig: fault: {res.fault} (torque removed; {len(res.summary['iterations'])} "
                         "trials kept)\n")
        return EXIT_FAULT
    return EXIT_OK
