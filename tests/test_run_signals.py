"""A signal at a random moment of ``ilcrig run`` leaves every record true.

The real multi-process rig (tests/fault_harness.py); SIGTERM, SIGINT or SIGHUP goes to the launcher from a
timer started at its status line, at a random delay over the rest of the run (the nodes' bring-up,
the trials, the end, the processes' stop). After each example:

* no process of the run is left;
* a summary, with an ``end_reason``; exit 0 only for a completed run without an ``interrupted``
  marker; exit 130 / 143 / 129 only with the marker of that signal and ``end_reason`` interrupted;
* the summary's trials = the console's rows = the trials' arrays = the recording's trials.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import threading
from pathlib import Path
from typing import Any

import pytest
from clock_util import wait_for
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
@given(delay_s=st.floats(0.0, MAX_DELAY_S), signum=st.sampled_from([signal.SIGTERM, signal.SIGINT, signal.SIGHUP]))
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
    assert s["end_reason"] in ("completed", "interrupted"), s["end_reason"]
    rows = [ln for ln in o.stdout.splitlines() if len(ln.split()) == 9 and ln.split()[0].isdigit()]
    assert len(rows) == kept, o.stdout
    assert len(list((out / "trials").glob("trial-*.npz"))) == kept
    if (out / "recording.rrd").exists():
        assert recorded_trials(out / "recording.rrd") == list(range(kept))
    else:
        assert kept == 0


def _quit_masks(pid: int) -> str:
    """Whether process ``pid`` blocks or ignores SIGQUIT (``/proc/PID/status``), for a message."""
    try:
        fields = dict(ln.split(":\t", 1) for ln in Path(f"/proc/{pid}/status").read_text().splitlines() if ":\t" in ln)
    except OSError as err:
        return f"{pid}: {err}"
    bit = 1 << (signal.SIGQUIT - 1)
    return f"{pid}: SIGQUIT blocked {bool(int(fields['SigBlk'], 16) & bit)}, ignored {bool(int(fields['SigIgn'], 16) & bit)}"


def test_a_launcher_that_dies_of_sigquit_leaves_a_summary_that_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-\\ (SIGQUIT) to the launcher after trial 1's row: it dies of the signal and takes its
    roles with it (their death signal); its janitor settles the folder and marks the summary, whose
    ``end_reason`` stayed empty as in a run still going: ``launcher_lost``, with the trials kept.
    The law (tests/rig_scripted_law.py) holds its update after trial 1 until the signal comes, so
    the signal falls inside the run however late this test reads the row (on a loaded machine the
    run had ended before it: exit 0)."""
    from rig_scripted_law import SCRIPT_ENV

    out = tmp_path / "run"
    sent: list[int] = []
    monkeypatch.setenv(SCRIPT_ENV, json.dumps({"kind": "update_signal", "at": 1, "dir": str(tmp_path)}))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(Path(__file__).parent), os.environ.get("PYTHONPATH")) if p))

    def on_line(line: str, proc: Any) -> None:
        if not sent and line.startswith("   1 "):
            sent.append(proc.pid)
            masks.append(_quit_masks(proc.pid))
            _send(proc.pid, signal.SIGQUIT)

    masks: list[str] = []
    o = run_rig(out, "--law", "rig_scripted_law:RigScriptedLaw", iterations=8, on_line=on_line)
    assert sent and o.code == -signal.SIGQUIT and o.left == [], (o.code, o.stderr, masks, _quit_masks(os.getpid()))
    log = out / "logs" / "janitor.log"

    def janitor_said() -> bool:  # its last act, once the host is gone: the summary is marked before
        with contextlib.suppress(OSError):
            return "marked the summary: end_reason launcher_lost" in log.read_text()
        return False

    assert wait_for(janitor_said, 60.0), "the janitor never said it marked the summary"
    s = json.loads((out / "summary.json").read_text())
    kept = len(s["iterations"])
    assert s["end_reason"] == "launcher_lost" and s["launcher_lost"]["trials_kept"] == kept
    assert s["completed"] is False and kept == 2  # trials 0 and 1: trial 2 waits for the held update
    assert len(list((out / "trials").glob("trial-*.npz"))) == kept
