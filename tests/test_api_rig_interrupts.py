"""Nothing lost, nothing silent on the rig: whatever ends a run of the API on the rig
(:class:`ilcrig.RigRun`) — the law's exception at a random update, SIGINT or SIGTERM to the run
(the launcher) at a random event (a trial's row in the summary, or the start of a law's update),
an exception of the caller's own code or a KeyboardInterrupt inside ``with RigRun(...)`` — every
completed trial is in every view of the run: the trials the API yielded, its ``results``,
``ilcrig.load(out)``, ``summary.json``'s iterations, the ``trials/`` files and the recording's
committed trials, bit for bit; and ``end_reason`` says how the run ended.  Paced to the wall clock
(``realtime=True``, drawn too), the run holds the PM QoS CPU latency request where it may (root:
the kernel's target reads 0 µs at the trial's row) and, however it ended, the target is what it was
before once the run is over; the summary records the request or why there was none.

The events are waited for, never slept for: a trial's row is the API yielding it (the summary lists
it), an update's start the file the scripted law (tests/rig_scripted_law.py) writes before it
waits for the signal.  Full tier (each example starts a rig): few examples, short trials, at most
3 trials."""

from __future__ import annotations

import json
import os
import shutil
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from rig_scripted_law import SCRIPT_ENV

import ilcrig
from host.rig.cpu_latency import CPU_LATENCY_PATH, cpu_latency_target_us

# alone: it reads the kernel's CPU latency target, which a real-time run beside it would hold (pyproject.toml)
pytestmark = [pytest.mark.slow, pytest.mark.multiprocess, pytest.mark.alone]

ARRAYS = ("error_rad", "actual_rad", "feedforward_nm", "feedback_nm", "torque_nm", "rmse_deg", "peak_torque_nm")
LAW = "rig_scripted_law:RigScriptedLaw"
#: the longest the test waits for an event of the rig, s
WAIT_S = 300.0
#: the signals sent to the run, by name
SIGNALS = {"SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM}


class UserError(RuntimeError):
    """The caller's own exception."""


def wait_for(path: Path, run: ilcrig.RigRun) -> None:
    """Until ``path`` exists (the law's update has started); fails if the rig ended first."""
    t0 = time.monotonic()
    while not path.exists():
        assert run.returncode is None, f"the rig ended before {path.name}"
        assert time.monotonic() - t0 < WAIT_S, f"no {path.name} within {WAIT_S:g} s"
        time.sleep(0.01)


def latency_target_us() -> int | None:
    """The kernel's CPU latency target, µs (None where the PM QoS device cannot be read)."""
    try:
        return cpu_latency_target_us()
    except OSError:
        return None


def run_scenario(
    folder: Path, iterations: int, kind: str, at: int, signame: str, realtime: bool = False
) -> tuple[list[ilcrig.TrialResult], ilcrig.Results, BaseException | None, int | None, int | None]:
    """One rig run ended as ``kind`` says at trial ``at``: the trials the API yielded, its results,
    what reached the caller, the launcher's exit code, the kernel's CPU latency target at trial ``at``'s
    row (µs; None where it cannot be read)."""
    exp = ilcrig.Experiment(law=LAW, iterations=iterations, cycle_s=0.15)
    seen: list[ilcrig.TrialResult] = []
    raised: BaseException | None = None
    during: int | None = None
    os.environ[SCRIPT_ENV] = json.dumps({"kind": kind, "at": at, "dir": str(folder)})  # the rig inherits it
    try:
        run = ilcrig.RigRun(exp, folder / "run", bus="hub", timeout_s=WAIT_S, realtime=realtime)
    finally:
        del os.environ[SCRIPT_ENV]
    try:
        with run:
            for trial in run:
                seen.append(trial)
                if trial.trial != at:
                    continue
                during = latency_target_us()
                if kind == "row_signal":  # the trial's row is in the summary: the signal now
                    os.kill(run.proc.pid, SIGNALS[signame])
                elif kind == "update_signal":  # the law's update after this trial has started
                    wait_for(folder / f"update-{at}", run)
                    os.kill(run.proc.pid, SIGNALS[signame])
                elif kind == "body_interrupt":
                    raise KeyboardInterrupt
                elif kind == "user_exception":
                    raise UserError("the caller's code failed\nsecond line")
    except (KeyboardInterrupt, UserError) as exc:
        raised = exc
    return seen, run.results, raised, run.returncode, during


def assert_views_agree(out: Path, seen: list[ilcrig.TrialResult], res: ilcrig.Results) -> dict[str, Any]:
    """Every view holds the same trials, bit for bit; the summary."""
    summary = json.loads((out / "summary.json").read_text())
    loaded = ilcrig.load(out)
    kept = len(summary["iterations"])
    files = sorted(p.name for p in (out / "trials").glob("trial-*.npz"))
    assert files == [f"trial-{k:05d}.npz" for k in range(kept)]
    assert len(res) == len(loaded) == kept
    assert summary["recording"]["trials"] == list(range(kept))
    assert res.digest == loaded.digest == summary["trace_sha256"]
    # what the API yielded while the rig ran is a prefix of the kept trials (a trial kept while the
    # caller's code raised is not yielded any more), equal bit for bit
    assert [t.trial for t in seen] == list(range(len(seen))) and len(seen) <= kept
    for a, b, c in zip(seen, res.trials, loaded.trials, strict=False):
        assert a.trial == b.trial == c.trial and a.role == b.role == c.role
        for name in ARRAYS:
            np.testing.assert_array_equal(getattr(a, name), getattr(c, name), err_msg=name)
            np.testing.assert_array_equal(getattr(b, name), getattr(c, name), err_msg=name)
    for k, it in enumerate(summary["iterations"]):
        np.testing.assert_array_equal(it["peak_feedforward_nm"], np.max(np.abs(loaded[k].feedforward_nm), axis=0))
    return summary


@st.composite
def scenarios(draw: st.DrawFn) -> tuple[int, str, int, str, bool]:
    iterations = draw(st.integers(2, 3))
    kind = draw(st.sampled_from(["law_error", "update_signal", "row_signal", "body_interrupt", "user_exception"]))
    # a law's update runs after trials 0 … iterations-2; a signal after a trial's row must have a trial
    # after it; the caller's body sees every trial
    last = iterations - 1 if kind in ("body_interrupt", "user_exception") else iterations - 2
    return iterations, kind, draw(st.integers(0, last)), draw(st.sampled_from(sorted(SIGNALS))), draw(st.booleans())


def assert_latency_request_ended(summary: dict[str, Any], before: int | None, during: int | None) -> None:
    """A real-time run held the CPU latency request where it may, and nothing of it outlived the run."""
    record = summary["bench"]["timing"]["scheduling"]["cpu_latency"]
    if not os.access(CPU_LATENCY_PATH, os.W_OK):
        assert set(record) == {"reason"}
        return
    assert record == {"latency_us": 0}
    if before is None or before == 0:
        return  # another holder (a tuned profile, a cyclictest) keeps the target at 0 already
    assert during == 0  # in force at the trial's row
    assert latency_target_us() == before  # the run is over, however it ended: the kernel's target as before


@settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenario=scenarios())
@example(scenario=(2, "law_error", 0, "SIGINT", False))
@example(scenario=(3, "update_signal", 1, "SIGTERM", True))
@example(scenario=(3, "user_exception", 1, "SIGINT", True))
@example(scenario=(2, "user_exception", 1, "SIGINT", False))  # after the last trial: the run stays completed
def test_every_completed_trial_is_in_every_view_on_the_rig(scenario: tuple[int, str, int, str, bool]) -> None:
    iterations, kind, at, signame, realtime = scenario
    folder = Path(tempfile.mkdtemp(prefix="ilcrig-rig-interrupts-"))
    try:
        before = latency_target_us()
        seen, res, raised, code, during = run_scenario(folder, iterations, kind, at, signame, realtime)
        out = folder / "run"
        summary = assert_views_agree(out, seen, res)
        if realtime:
            assert_latency_request_ended(summary, before, during)
        kept = len(summary["iterations"])
        if kind in ("law_error", "update_signal"):
            assert kept == at + 1  # the trial before the update is kept, none after it
        else:
            assert at + 1 <= kept <= iterations
        assert res.end_reason == summary["end_reason"]
        if kind == "law_error":
            assert summary["end_reason"] == "law_error" and "scripted" in summary["faults"][0]["message"]
            assert "ZeroDivisionError: scripted" in (out / "logs" / "law-error.log").read_text()
        elif kind in ("update_signal", "row_signal"):
            assert summary["end_reason"] == "interrupted" or (kept == iterations and summary["completed"])
            if summary["end_reason"] == "interrupted":
                assert summary["interrupted"]["signal"] == signame
                assert code == {"SIGINT": 130, "SIGTERM": 143}[signame]
        elif kind == "body_interrupt":
            assert isinstance(raised, KeyboardInterrupt)  # never swallowed
            assert summary["end_reason"] == "interrupted" or summary["completed"]
        elif kind == "user_exception":
            assert isinstance(raised, UserError)
            if not summary["completed"]:
                assert summary["end_reason"] == "user_exception"
                assert summary["user_exception"] == {
                    "type": "UserError",
                    "message": "the caller's code failed",
                    "after_trial": kept - 1,
                }
            else:
                assert summary["end_reason"] == "completed" and kept == iterations
        if kind not in ("body_interrupt", "user_exception"):
            assert raised is None
        assert summary["completed"] == (kept == iterations and summary["end_reason"] in ("completed", "interrupted"))
    finally:
        shutil.rmtree(folder, ignore_errors=True)
