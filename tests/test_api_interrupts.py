"""Nothing lost, nothing silent: whatever ends an in-process run of the API — the law's exception
after a random trial, a KeyboardInterrupt from the law's update or from the caller's loop body, an
exception of the caller's own code in the ``with`` block — every completed trial is in every view of
the run (the Session's ``Results``, ``ilcrig.load(out)``, ``summary.json``'s iterations, the
``trials/`` files, the recording's committed trials) bit for bit, the summary's ``end_reason`` says
how it ended, and an interrupt reaches the caller as ``KeyboardInterrupt`` (never swallowed).

Fast: in process, short trials (``cycle_s`` 0.15 s), at most 4 trials per run."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_util import ROOT, run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import ilcrig

ARRAYS = ("error_rad", "actual_rad", "feedforward_nm", "feedback_nm", "torque_nm", "rmse_deg", "peak_torque_nm")


class UserError(RuntimeError):
    """The caller's own exception."""


class ScriptedLaw:
    """A P-type law (u + 0.5·Lp·e[n+1]) that fails as told: after trial ``after`` its update raises
    ``exc`` (a law error, or a KeyboardInterrupt)."""

    name = "scripted-p"

    def __init__(self, after: int | None, exc: BaseException | None) -> None:
        self.after, self.exc = after, exc
        self.lp: Any = None

    def update(self, trial: ilcrig.TrialData) -> Any:
        if self.after is not None and trial.trial == self.after and self.exc is not None:
            raise self.exc
        lp = 0.5 * np.full(trial.error_rad.shape[1], 40.0)
        return trial.feedforward_nm + lp * ilcrig.signals.lead(trial.error_rad, 1)


def run_scenario(out: Path, iterations: int, kind: str, at: int) -> tuple[ilcrig.Results, BaseException | None]:
    """One session of ``iterations`` trials ended as ``kind`` says at trial ``at``; its Results and
    what reached the caller."""
    law = ScriptedLaw(
        at if kind in ("law_error", "law_interrupt") else None,
        ZeroDivisionError("scripted") if kind == "law_error" else KeyboardInterrupt() if kind == "law_interrupt" else None,
    )
    exp = ilcrig.Experiment(law=law, iterations=iterations, cycle_s=0.15)
    raised: BaseException | None = None
    session = exp.start(out)
    try:
        with session as s:
            for trial in s:
                if trial.trial == at and kind == "body_interrupt":
                    raise KeyboardInterrupt
                if trial.trial == at and kind == "user_exception":
                    raise UserError("the caller's code failed\nsecond line")
    except (KeyboardInterrupt, UserError) as exc:
        raised = exc
    return session.results, raised


def assert_views_agree(out: Path, res: ilcrig.Results, kept: int) -> dict[str, Any]:
    summary = json.loads((out / "summary.json").read_text())
    loaded = ilcrig.load(out)
    files = sorted(p.name for p in (out / "trials").glob("trial-*.npz"))
    assert len(res) == len(loaded) == len(summary["iterations"]) == len(files) == kept
    assert files == [f"trial-{k:05d}.npz" for k in range(kept)]
    assert summary["recording"]["trials"] == list(range(kept))
    assert res.digest == loaded.digest == summary["trace_sha256"]
    for a, b in zip(res.trials, loaded.trials, strict=True):
        assert a.trial == b.trial and a.role == b.role
        for name in ARRAYS:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for k, it in enumerate(summary["iterations"]):
        peak = np.max(np.abs(loaded[k].feedforward_nm), axis=0)
        np.testing.assert_array_equal(it["peak_feedforward_nm"], peak)
        assert it["peak_torque_nm"] == list(loaded[k].peak_torque_nm)
    return summary


@st.composite
def scenarios(draw: st.DrawFn) -> tuple[int, str, int]:
    iterations = draw(st.integers(2, 4))
    kind = draw(st.sampled_from(["none", "law_error", "law_interrupt", "body_interrupt", "user_exception"]))
    # a law's update runs after trials 0 … iterations-2; the caller's body sees every trial
    last = iterations - 2 if kind.startswith("law") else iterations - 1
    return iterations, kind, draw(st.integers(0, last))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
def test_every_completed_trial_is_in_every_view(scenario: tuple[int, str, int]) -> None:
    iterations, kind, at = scenario
    folder = Path(tempfile.mkdtemp(prefix="ilcrig-interrupts-"))
    try:
        out = folder / "run"
        res, raised = run_scenario(out, iterations, kind, at)
        kept = iterations if kind == "none" else at + 1
        summary = assert_views_agree(out, res, kept)
        expected = {
            "none": "completed",
            "law_error": "law_error",
            "law_interrupt": "interrupted",
            "body_interrupt": "interrupted",
            "user_exception": "user_exception",
        }[kind]
        after_the_end = kind in ("body_interrupt", "user_exception") and at == iterations - 1
        if after_the_end:
            expected = "completed"  # the run had completed (every trial kept) before the caller's code raised
        assert summary["end_reason"] == expected == res.end_reason
        if kind in ("law_interrupt", "body_interrupt"):
            assert isinstance(raised, KeyboardInterrupt)  # never swallowed
            assert after_the_end or summary["interrupted"]["signal"] == "SIGINT"
        elif kind == "user_exception":
            assert isinstance(raised, UserError)
        else:
            assert raised is None
        if kind == "user_exception" and not after_the_end:
            assert summary["user_exception"] == {"type": "UserError", "message": "the caller's code failed", "after_trial": at}
        if kind == "law_error":
            assert summary["faults"] and "scripted" in summary["faults"][0]["message"]
            log = (out / "logs" / "law-error.log").read_text()
            assert "ZeroDivisionError: scripted" in log and "in update" in log  # the law's own traceback
        assert summary["completed"] == (kind == "none" or after_the_end)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def test_a_law_error_keeps_the_trial_in_the_session_without_a_folder() -> None:
    res, raised = run_scenario_nofolder()
    assert raised is None and len(res) == 2 and res.end_reason == "law_error" and res.fault


def run_scenario_nofolder() -> tuple[ilcrig.Results, BaseException | None]:
    exp = ilcrig.Experiment(law=ScriptedLaw(1, ValueError("late")), iterations=4, cycle_s=0.15)
    with exp.start() as s:
        trials = list(s)
    assert [t.trial for t in trials] == [0, 1]  # the trial before the failing update is returned too
    return s.results, None


def test_api_edges() -> None:
    with pytest.raises(ilcrig.InputError, match=r"unknown key 'cycle' \(did you mean cycle_s\?\)"):
        ilcrig.Experiment(cycle=0.15)
    with pytest.raises(ilcrig.InputError, match="no-such-run-folder"):
        ilcrig.load("no-such-run-folder")
    with pytest.raises(ilcrig.InputError, match="law: a name, a law class or a law instance"):
        ilcrig.Experiment(law=3.5)
    assert "cycle_s" in (ilcrig.Experiment.__init__.__doc__ or ilcrig.Experiment.__doc__ or "")
    exp = ilcrig.Experiment(law=ScriptedLaw(None, None), iterations=1, cycle_s=0.15)
    with pytest.raises(ilcrig.InputError, match="a law instance, which runs in this process only"):
        ilcrig.RigRun(exp)  # an Experiment is taken; an instance cannot run on the rig


class TermLaw:
    """A law whose first update receives SIGTERM (as from ``kill``)."""

    name = "term-p"

    def update(self, trial: ilcrig.TrialData) -> Any:
        os.kill(os.getpid(), signal.SIGTERM)
        return trial.feedforward_nm


def test_sigterm_during_an_update_is_raised_after_the_views_agree(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law=TermLaw(), iterations=3, cycle_s=0.15)
    session = exp.start(tmp_path / "run")
    with pytest.raises(KeyboardInterrupt) as caught, session as s:
        for _ in s:
            pass
    assert getattr(caught.value, "signum", None) == signal.SIGTERM
    summary = assert_views_agree(tmp_path / "run", session.results, 1)
    assert summary["end_reason"] == "interrupted" and summary["interrupted"]["signal"] == "SIGTERM"


FAILING_LAW = """
class Failing:
    name = "failing"

    def __init__(self, ctx):
        pass

    def update(self, trial):
        return helper(trial)


def helper(trial):
    raise ArithmeticError("the law author's bug")
"""


def test_the_law_authors_traceback_is_in_the_runs_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "failing_law_mod.py").write_text(FAILING_LAW)
    monkeypatch.syspath_prepend(str(tmp_path))
    codes = []
    for debug in ([], ["--debug"]):
        out = tmp_path / f"run{len(codes)}"
        with caplog.at_level(logging.DEBUG, logger="host.experiment.trial_loop"):
            code, _, err = run_cli(
                capsys,
                *debug,
                "sim",
                "--law",
                "failing_law_mod:Failing",
                "--iterations",
                "3",
                "--cycle",
                "0.15",
                "--out",
                str(out),
            )
        codes.append(code)
        log = (out / "logs" / "law-error.log").read_text()
        assert 'in helper\n    raise ArithmeticError("the law author\'s bug")' in log  # the law's own frames, always
        assert "law failing failed in update after trial 0" in err
        summary = json.loads((out / "summary.json").read_text())
        assert summary["end_reason"] == "law_error" and len(summary["iterations"]) == 1
    assert codes == [3, 3]  # the same exit code with and without --debug
    assert any("in helper" in (r.exc_text or "") or "in helper" in r.getMessage() for r in caplog.records)


@pytest.mark.slow
def test_the_law_authors_traceback_on_the_terminal_with_debug(tmp_path: Path) -> None:
    (tmp_path / "failing_law_mod.py").write_text(FAILING_LAW)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]))
    runs = []
    for debug in ([], ["--debug"]):
        argv = [sys.executable, "-m", "host.cli", *debug, "sim", "--law", "failing_law_mod:Failing", "--iterations", "2"]
        argv += ["--cycle", "0.15", "--out", str(tmp_path / f"run{len(runs)}")]
        runs.append(subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300))
    assert [r.returncode for r in runs] == [3, 3]
    assert "in helper" not in runs[0].stderr and "in helper" in runs[1].stderr


def test_leaving_a_trials_loop_early_is_a_stop_not_an_exception(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law="pd-ol", iterations=3, cycle_s=0.15)
    for trial in exp.trials(out=tmp_path / "run"):
        if trial.trial == 1:
            break
    res = ilcrig.load(tmp_path / "run")
    assert len(res) == 2 and res.end_reason == "stopped" and "user_exception" not in res.summary
    peaks = [it["peak_feedforward_nm"] for it in res.summary["iterations"]]
    np.testing.assert_array_equal(res.peak_feedforward_nm, peaks)


#: a fresh interpreter: a signal sent while ``scipy.signal`` is being imported during a step (the
#: run's own handler installed), as a Ctrl-C could land; then a second run in the same interpreter
_IMPORT_SIGNAL_SCRIPT = """
import os, signal, sys
import ilcrig

class Hook:
    sent = False

    def find_spec(self, name, path=None, target=None):
        # once, halfway through scipy.signal's own import, and only inside a step (the run's handler)
        if name == "scipy.signal.bsplines" and not Hook.sent and signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
            Hook.sent = True
            os.kill(os.getpid(), signal.SIGTERM)
        return None

sys.meta_path.insert(0, Hook())
for run in ("first", "second"):
    try:
        res = ilcrig.Experiment(law="no-ilc-id", iterations=2, cycle_s=0.15).run()
        print(run, "end", res.summary["end_reason"], "faults", len(res.summary["faults"]))
    except KeyboardInterrupt:
        print(run, "interrupted")
"""


@pytest.mark.slow  # a fresh interpreter and two runs: 3-5 s
def test_a_signal_cannot_land_inside_the_laws_first_import(tmp_path: Path) -> None:
    """What the law's update imports on first use (``scipy.signal`` for ``no-ilc-id``) is imported
    when the session is made, before its first step: a signal during a step (where the run's own
    handler raises it) never lands inside that import, which would leave ``scipy.signal`` half made
    in the interpreter and fail a later run's update (``NameError`` in the law)."""
    proc = subprocess.run(
        [sys.executable, "-c", _IMPORT_SIGNAL_SCRIPT], cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["first end completed faults 0", "second end completed faults 0"], proc.stderr
