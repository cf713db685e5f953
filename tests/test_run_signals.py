"""A signal at a random moment of ``ilcrig run`` leaves every record true.

The real multi-process rig (tests/fault_harness.py); SIGTERM or SIGINT goes to the launcher from a
timer started at its status line, at a random delay over the rest of the run (the nodes' bring-up,
the trials, the end, the processes' stop). After each example:

* no process of the run is left;
* a summary, with an ``end_reason``; exit 0 only for a completed run without an ``interrupted``
  marker; exit 130 / 143 only with the marker of that signal and ``end_reason`` interrupted;
* the summary's trials = the console's rows = the trials' arrays = the recording's trials.
"""

from __future__ import annotations

import itertools
import os
import signal
import threading
from pathlib import Path
from typing import Any

import pytest
from fault_harness import recorded_trials, run_rig
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

#: trials of each run (a run that kept them all is ``completed``, whatever its exit code)
ITERATIONS = 2
#: the delays drawn after the status line, s: a 2-trial run ends about 4 s after it (quiet machine)
MAX_DELAY_S = 4.5
_RUNS = itertools.count()


def _send(pid: int, signum: int) -> None:
    try:
        os.kill(pid, signum)
    except ProcessLookupError:
        pass  # the run had ended


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(delay_s=st.floats(0.0, MAX_DELAY_S), signum=st.sampled_from([signal.SIGTERM, signal.SIGINT]))
def test_at_random_a_signal_over_ilcrig_run_leaves_every_record_true(tmp_path: Path, delay_s: float, signum: int) -> None:
    out = tmp_path / f"run{next(_RUNS)}"
    timers: list[threading.Timer] = []

    def on_line(line: str, proc: Any) -> None:
        if not timers and line.startswith("ilcrig run:"):
            timers.append(threading.Timer(delay_s, _send, (proc.pid, signum)))
            timers[0].start()

    try:
        o = run_rig(out, iterations=ITERATIONS, on_line=on_line)
    finally:
        for t in timers:
            t.cancel()
            t.join()
    assert timers and o.left == [], (o.stdout, o.stderr)
    s = o.summary
    assert s is not None and "end_reason" in s, (o.code, o.stderr)
    name = signal.Signals(signum).name
    if o.code == 0:
        assert s["completed"] is True and "interrupted" not in s and s["end_reason"] == "completed"
    else:
        assert o.code == 128 + signum, (o.code, o.stderr)
        assert s["interrupted"]["signal"] == name and s["end_reason"] == "interrupted", s.get("interrupted")
    kept = len(s["iterations"])
    assert s["completed"] is (kept == ITERATIONS), (kept, s.get("interrupted"))  # every trial run and kept
    rows = [ln for ln in o.stdout.splitlines() if len(ln.split()) == 9 and ln.split()[0].isdigit()]
    assert len(rows) == kept, o.stdout
    assert len(list((out / "trials").glob("trial-*.npz"))) == kept
    if (out / "recording.rrd").exists():
        assert recorded_trials(out / "recording.rrd") == list(range(kept))
    else:
        assert kept == 0
