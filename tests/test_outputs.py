"""Nothing lost: ``summary.json`` is replaced atomically and a failing write leaves the
previous one (and no temporary file); a full disk is a fault like the others — one line, exit code
3, the earlier results kept, the final summary and report written into the space reserve; a NaN
never reaches the summary; an interrupt is marked; a run killed after trial k keeps a recording
with k trials."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_util import sim_signalled_at_row

from bus import atomic as atomic_mod
from host.experiment.faults import FaultKind
from host.experiment.outputs import RESERVE_NAME, DiskFullError, RunFolder, check_out_dir, reserve_bytes
from host.experiment.summary import finite, write_summary

REPO = Path(__file__).resolve().parent.parent


def test_a_failing_write_keeps_the_previous_summary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_summary(tmp_path, {"iterations": [1], "completed": False})
    before = (tmp_path / "summary.json").read_text()

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic_mod.os, "fsync", full)  # the one atomic write (bus/atomic.py)
    with pytest.raises(DiskFullError, match="disk full"):
        write_summary(tmp_path, {"iterations": [1, 2], "completed": False})
    assert (tmp_path / "summary.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]  # no summary.json.tmp


def test_no_nan_reaches_the_summary(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert finite({"a": [1.0, float("nan")], "b": {"c": float("inf")}, "d": "x"}) == {
        "a": [1.0, None],
        "b": {"c": None},
        "d": "x",
    }
    write_summary(tmp_path, {"x": np.float64("nan"), "y": [np.inf]})
    assert json.loads((tmp_path / "summary.json").read_text()) == {"x": None, "y": [None]}
    assert "non-finite" in caplog.text


def test_the_space_reserve(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path, iterations=10, n_ticks=301)
    assert folder.reserve()
    # the reserve is two files without a name, held open: nothing in the folder, the space allocated;
    # its last part (room for one more summary) is kept until the report is written
    parts = [os.fstat(folder._fd), os.fstat(folder._fd_last)]
    assert [st.st_nlink for st in parts] == [0, 0] and sum(st.st_size for st in parts) == reserve_bytes(10, 301)
    assert all(st.st_blocks * 512 >= st.st_size for st in parts) and parts[1].st_size == 32 * 1024 + 10 * 1536
    assert reserve_bytes(10, 301) == 128 * 1024 + 10 * 1536 + 320 * 1024 + 301 * 1000
    assert list(tmp_path.iterdir()) == []
    folder.fail_writes_from_trial = 2
    folder.check_write(1)
    with pytest.raises(OSError) as exc:
        folder.check_write(2)
    assert exc.value.errno == errno.ENOSPC
    folder.release()
    assert folder._fd == -1 and folder._fd_last >= 0 and not (tmp_path / RESERVE_NAME).exists()
    folder.check_write(3)  # the reserve's space is what the final results are written into
    folder.release_last()
    assert folder._fd_last == -1
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(ValueError, match="exists and is not a folder"):
        check_out_dir(tmp_path / "f.txt", create=False)
    assert check_out_dir(tmp_path / "new" / "run", create=False) == tmp_path / "new" / "run"
    assert not (tmp_path / "new").exists()  # checked, not made


def sim_with_full_disk(out: Path, from_trial: int):  # type: ignore[no-untyped-def]
    from host.analysis.session import report_fault, run_session
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.sim.inprocess import InProcessBench

    cfg = build_config(None, {"iterations": 3, "cycle_s": 0.15})
    import io

    res = run_session(prepare(cfg), InProcessBench(cfg), out, mode="sim", stream=io.StringIO(), fail_writes_from_trial=from_trial)
    return res, report_fault(res, out / "summary.json")


@pytest.mark.slow
def test_full_disk_is_a_fault_with_the_results_kept(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    (out / "logs").mkdir(parents=True)  # where the injection record goes (as in `ilcrig run`)
    res, code = sim_with_full_disk(out, from_trial=1)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and len(err) == 1 and err[0].startswith("ilcrig: fault: disk full") and "[disk_full]" in err[0]
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] is False and len(s["iterations"]) == 2  # trial 1 completed: kept
    f = s["faults"][0]
    assert f["kind"] == FaultKind.DISK_FULL and f["trial"] == 2 and f["injected"]["kind"] == "diskfull"
    assert (out / "report.md").exists() and "**Fault** (disk_full)" in (out / "report.md").read_text()
    assert not (out / RESERVE_NAME).exists() and not (out / "summary.json.tmp").exists()


def _can_mount_tmpfs(path: Path, size: str) -> bool:
    if os.geteuid() != 0:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True).returncode == 0


@pytest.mark.slow
def test_a_really_full_disk(tmp_path: Path) -> None:
    """``ilcrig sim --out`` on a 1.5 MB tmpfs: the recording fills it during the run."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if not _can_mount_tmpfs(mnt, "1500k"):
        pytest.skip("needs root and tmpfs to make a small filesystem")
    try:
        res = subprocess.run(
            [sys.executable, "-m", "host.cli", "sim", "--iterations", "10", "--out", str(mnt / "run")],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=600,
        )
        assert res.returncode == 3, res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and "[disk_full]" in lines[0] and "Traceback" not in res.stderr
        s = json.loads((mnt / "run" / "summary.json").read_text())
        assert s["completed"] is False and s["faults"][0]["kind"] == "disk_full" and s["iterations"]
        assert not (mnt / "run" / "summary.json.tmp").exists() and not (mnt / "run" / RESERVE_NAME).exists()
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


@pytest.mark.slow
def test_learning_that_diverges_is_a_fault_and_no_nan_is_written(tmp_path: Path) -> None:
    """No feedback (α = 1 → Kp = 0) and an absurd learning gain: the check says it diverges, the
    run faults cleanly when the feed-forward leaves the drive's range; the summary is valid JSON."""
    from host.analysis.session import report_fault, run_session
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.sim.inprocess import InProcessBench

    cfg = build_config(None, {"law": "pd-ilc", "iterations": 3, "cycle_s": 0.15, "gains": {"alpha": 1.0, "lp": 1e12}})
    plan = prepare(cfg)
    assert not plan.check.ok
    import io

    res = run_session(plan, InProcessBench(cfg), tmp_path, mode="sim", stream=io.StringIO())
    assert report_fault(res) == 3
    text = (tmp_path / "summary.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    s = json.loads(text)
    assert s["faults"][0]["kind"] in ("learning_diverged", "emcy")


def test_a_signal_between_the_guarded_parts_of_a_step_is_marked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM's interrupt raised just after a trial was kept, outside the parts of the step that
    catch it (the narrow window that made ``ilcrig sim`` exit 130 with no marker): the run ends the
    same way — ``interrupted`` SIGTERM in the summary, the trial kept, exit code 143."""
    import io

    from host.analysis.session import report_fault, run_session
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.experiment.signal_shield import Interrupted
    from host.experiment.trial_loop import TrialLoop
    from host.sim.inprocess import InProcessBench

    guarded = TrialLoop._guarded
    calls = []

    def then_interrupted(self: TrialLoop, fn: object) -> object:
        out = guarded(self, fn)  # type: ignore[arg-type]
        calls.append(self.k)
        if self.k == 1 and calls.count(1) == 1:  # trial 0 kept: the signal comes before the law's update is guarded
            raise Interrupted(signal.SIGTERM)
        return out

    monkeypatch.setattr(TrialLoop, "_guarded", then_interrupted)
    cfg = build_config(None, {"iterations": 3, "cycle_s": 0.15})
    res = run_session(prepare(cfg), InProcessBench(cfg), tmp_path, mode="sim", stream=io.StringIO())
    assert res.interrupted == signal.SIGTERM and report_fault(res) == 143
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["completed"] is False and len(s["iterations"]) == 1


def _sigterm_at(monkeypatch: pytest.MonkeyPatch, module: object, name: str, *, before: bool = False) -> list[int]:
    """``module.name`` sends this process SIGTERM as it returns (``before``: as it is called);
    the list it returns counts the signals sent."""
    real = getattr(module, name)
    sent: list[int] = []

    def signalled(*args: object, **kwargs: object) -> object:
        if before:
            sent.append(os.kill(os.getpid(), signal.SIGTERM) or 1)
        out = real(*args, **kwargs)
        if not before:
            sent.append(os.kill(os.getpid(), signal.SIGTERM) or 1)
        return out

    monkeypatch.setattr(module, name, signalled)
    return sent


def test_a_signal_between_two_trials_of_ilcrig_sim_is_marked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM's interrupt raised after a trial was kept and its step returned, before the next
    step (the window where ``ilcrig sim`` left its folder unfinished and said only
    ``ilcrig: interrupted``): the run ends as inside a step — exit 143, ``interrupted`` SIGTERM in
    the summary, the kept trial and ``report.md`` there, nothing on the console's error stream."""
    import io

    from host.experiment.config import build_config
    from host.experiment.signal_shield import Interrupted
    from host.experiment.trial_loop import TrialLoop
    from host.sim.session import SimOptions, run_sim

    step = TrialLoop.step

    def then_interrupted(self: TrialLoop) -> object:
        out = step(self)
        if self.k == 1:
            raise Interrupted(signal.SIGTERM)
        return out

    monkeypatch.setattr(TrialLoop, "step", then_interrupted)
    out = tmp_path / "run"
    cfg = build_config(None, {"iterations": 3, "cycle_s": 0.15})
    assert run_sim(SimOptions(cfg, out), io.StringIO()) == 143
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["completed"] is False and len(s["iterations"]) == 1
    assert s["end_reason"] == "interrupted" and (out / "report.md").is_file()


def test_a_signal_while_ilcrig_sim_makes_its_folder_is_marked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM just after the run folder's recording was opened, before the first trial (the
    process died there, leaving a folder with a recording and no summary): exit 143, the summary
    says interrupted before the first trial, no trial."""
    import io

    import host.sim.session as sim_mod
    from host.experiment.config import build_config
    from host.sim.session import SimOptions, run_sim

    _sigterm_at(monkeypatch, sim_mod, "open_outputs")
    out = tmp_path / "run"
    assert run_sim(SimOptions(build_config(None, {"iterations": 2, "cycle_s": 0.15}), out), io.StringIO()) == 143
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["interrupted"]["position"] == "before_first_trial"
    assert s["iterations"] == [] and s["end_reason"] == "interrupted" and s["completed"] is False


def test_a_signal_while_a_host_makes_its_folder_is_marked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same for the run session of ``ilcrig host`` (:func:`host.analysis.session.run_session`
    under the role's signal handlers): SIGTERM after the recording was opened ends the run
    before its first trial with the summary saying so, never a half-made folder."""
    import io

    import host.analysis.session as session_mod
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.experiment.signal_shield import interrupt_on_signals
    from host.sim.inprocess import InProcessBench

    _sigterm_at(monkeypatch, session_mod, "open_outputs")
    cfg = build_config(None, {"iterations": 2, "cycle_s": 0.15})
    with interrupt_on_signals():
        res = session_mod.run_session(prepare(cfg), InProcessBench(cfg), tmp_path, mode="rig", stream=io.StringIO())
    assert res.interrupted == signal.SIGTERM and session_mod.report_fault(res) == 143
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["interrupted"]["position"] == "before_first_trial" and s["iterations"] == [] and s["completed"] is False


def test_a_signal_once_a_run_ended_leaves_its_records_as_they_are(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM while ``ilcrig sim`` writes the report of a run that completed: logged, not raised
    (the summary says completed, so the exit code is 0 and the report is written whole)."""
    import io

    import host.analysis.session as session_mod
    from host.experiment.config import build_config
    from host.sim.session import SimOptions, run_sim

    sent = _sigterm_at(monkeypatch, session_mod, "write_run_report", before=True)
    out = tmp_path / "run"
    cfg = build_config(None, {"iterations": 2, "cycle_s": 0.15})
    assert run_sim(SimOptions(cfg, out), io.StringIO()) == 0 and sent == [1]
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] is True and "interrupted" not in s and (out / "report.md").is_file()


def test_a_signal_as_the_runs_end_begins_is_marked_after_the_last_trial(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM's interrupt raised as the trial loop begins its end, after the last trial was kept
    (the window where a run marked ``completed`` ended without its final summary, or interrupted
    yet not completed): the run ends through its end once — exit 143, ``interrupted`` placed
    ``after_last_trial``, ``completed`` (every trial run and kept), the final summary and report."""
    import io

    import host.experiment.trial_loop as loop_mod
    from host.experiment.config import build_config
    from host.sim.session import SimOptions, run_sim

    sent = _sigterm_at(monkeypatch, loop_mod, "end_of_run", before=True)
    out = tmp_path / "run"
    assert run_sim(SimOptions(build_config(None, {"iterations": 2, "cycle_s": 0.15}), out), io.StringIO()) == 143
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["interrupted"]["position"] == "after_last_trial"
    assert s["end_reason"] == "interrupted" and s["completed"] is True and len(s["iterations"]) == 2
    assert (out / "report.md").is_file() and sent == [1]  # the first raised before it was counted; the second: logged


def test_sigterm_during_sim_is_marked(tmp_path: Path) -> None:
    """``ilcrig sim`` killed with SIGTERM after its first trial: exit 143, ``interrupted`` in the
    summary, the completed trial kept."""
    out = tmp_path / "run"
    code, err, _ = sim_signalled_at_row(out, "0", signal.SIGTERM)  # the row of trial 0
    assert code == 143, err
    # nothing on stderr (but a warning of the plan's convergence check, were there one)
    assert "Traceback" not in err
    assert [ln for ln in err.splitlines() if ln.strip() and "convergence check failed" not in ln] == []
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["completed"] is False and len(s["iterations"]) >= 1
    from fault_harness import recorded_trials

    assert recorded_trials(out / "recording.rrd") == list(range(len(s["iterations"])))
