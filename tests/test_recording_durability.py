"""A recording that survives whatever the summary survives (host/analysis/recording.py,
host/experiment/outputs.py, host/rig/janitor.py): ``recording.rrd`` opens with rerun's own reader
(``RrdReader``) and holds exactly the summary's trials after a write cut short at any byte, a
failing write (cut back, written again later), a kill between the recording and the summary (cut
back by whoever outlives the host: the launcher, or the janitor after a killed launcher), and a
full disk at each phase of a run on a real small filesystem (tmpfs, as root; skipped otherwise).
The space reserve never outlives the process that holds it, even after SIGKILL."""

from __future__ import annotations

import errno
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from cli_util import sim_signalled_at_row
from fault_harness import recorded_trials
from fs_util import small_tmpfs

from host.analysis.recording import RunRecorder
from host.analysis.recording_segments import TRAILER_BYTES, SegmentFile, cut_back

REPO = Path(__file__).resolve().parent.parent


def _trial_args(k: int, n: int = 41) -> tuple[Any, ...]:
    from host.learning.metrics import trial_metrics
    from host.planning.joint_reference import JointReference
    from plant.kinematics import inverse_kinematics

    q = np.tile(inverse_kinematics(np.array([0.0, 0.0, -0.65, 0.0])), (n, 1))
    ref = JointReference(t=np.arange(n) * 1e-3, q=q, qd=np.zeros((n, 4)), qdd=np.zeros((n, 4)))
    e = np.full((n, 4), 1e-3 / (k + 1))
    traces = [SimpleNamespace(q_rad=q[:, j] - e[:, j], tau_fb_nm=np.full(n, 0.1 * j)) for j in range(4)]
    return k, ref, traces, np.full((n, 4), float(k)), e, trial_metrics(k, e, e)


def record_trials(path: Path, trials: int, **kw: Any) -> tuple[RunRecorder, list[int]]:
    """A recorder with ``trials`` synthetic trials written; returns it (open) and the committed
    byte count after each trial."""
    rec = RunRecorder(path, config_summary={"iterations": trials + 1}, **kw)
    sizes = []
    for k in range(trials):
        rec.log_trial(*_trial_args(k))
        sizes.append(rec.committed()["bytes"])
    return rec, sizes


def test_a_write_cut_short_anywhere_leaves_the_earlier_trials(tmp_path: Path) -> None:
    """Every state a kill can leave the last append in — its body written in part behind the gap,
    then the previous segment's trailer written in part into the gap — reads back as the trials
    before it, or with the new trial once everything is written; never a file rerun refuses (a
    complete trailer at the end of the file, which rerun would trust, never happens)."""
    rec, sizes = record_trials(tmp_path / "recording.rrd", 3, join=False)
    data = (tmp_path / "recording.rrd").read_bytes()
    assert len(data) == sizes[-1] and data[-12:-4] != b"RRF2FOOT"  # the last trailer is held back
    start = sizes[-2]  # trial 2 was appended here: first its body behind a gap, then the old trailer
    trailer, body = data[start : start + TRAILER_BYTES], data[start + TRAILER_BYTES :]
    assert trailer[-12:-4] == b"RRF2FOOT"
    gap = b"\0" * TRAILER_BYTES
    states = [data[:start]]  # killed before the first byte
    states += [data[:start] + gap + body[:cut] for cut in (1, 15, 16, len(body) // 2, len(body) - 1, len(body))]
    for i, state in enumerate(states):
        p = tmp_path / f"cut{i}.rrd"
        p.write_bytes(state)
        assert recorded_trials(p) == [0, 1], i
    for cut in (1, 5, 16, TRAILER_BYTES - 1):  # the trailer written in part: the new trial is whole already
        p = tmp_path / f"trailer{cut}.rrd"
        p.write_bytes(data[:start] + trailer[:cut] + gap[cut:] + body)
        assert recorded_trials(p) in ([0, 1], [0, 1, 2]), cut  # readable; the summary, written after, decides
    assert recorded_trials(tmp_path / "recording.rrd") == [0, 1, 2]
    rec.close()


def test_a_failing_write_is_cut_back_and_written_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "recording.rrd"
    rec, sizes = record_trials(path, 1, join=False)
    real = os.pwrite
    calls = {"n": 0}

    def full_disk(fd: int, data: Any, offset: int) -> int:
        calls["n"] += 1
        if calls["n"] == 1:  # half the body written, then ENOSPC
            real(fd, bytes(data)[: len(data) // 2], offset)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", full_disk)
    from host.experiment.outputs import DiskFullError

    with pytest.raises(DiskFullError, match="disk full: cannot write trial 1 of the recording"):
        rec.log_trial(*_trial_args(1))
    assert path.stat().st_size == sizes[0] and rec.committed()["trials"] == [0] and recorded_trials(path) == [0]
    rec.log_trial(*_trial_args(1))  # again: the bytes kept are written now
    rec.log_trial(*_trial_args(1))  # a third time: it is in the file already, nothing is written
    rec.close()
    assert rec.committed()["trials"] == [0, 1] and recorded_trials(path) == [0, 1]


def test_cut_back_to_the_summarys_trials(tmp_path: Path) -> None:
    path = tmp_path / "recording.rrd"
    rec, sizes = record_trials(path, 3, join=False)
    rec.close()
    assert recorded_trials(path) == [0, 1, 2]
    assert cut_back(path, sizes[1]) and path.stat().st_size == sizes[1] and recorded_trials(path) == [0, 1]
    assert not cut_back(path, sizes[1])  # nothing beyond it any more
    # a recording joined into one stream at the end of its run is left alone
    joined, _ = record_trials(tmp_path / "joined.rrd", 2)
    joined.close()
    assert joined.committed()["joined"] and not cut_back(tmp_path / "joined.rrd", 100)
    assert recorded_trials(tmp_path / "joined.rrd") == [0, 1]


def test_segments_need_rerun_041s_layout() -> None:
    with pytest.raises(ValueError, match="did not return a complete stream"):
        SegmentFile.split(b"RRF2" + bytes(64))


# ---------------------------------------------------------------------------------------
# the reserve and the janitor
# ---------------------------------------------------------------------------------------


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    """A 4 MB tmpfs (as root), unmounted after the test."""
    with small_tmpfs(tmp_path / "small", 4096) as mnt:
        yield mnt


def test_the_reserve_never_outlives_its_process(small_fs: Path) -> None:
    """A process holding the reserve is killed with SIGKILL: no file is left and the space is free."""
    free0 = shutil.disk_usage(small_fs).free
    code = (
        "import sys, time; from host.experiment.outputs import RunFolder; "
        f"f = RunFolder({str(small_fs)!r}, 10, 501); assert f.reserve(); print('held', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "held\n"
        from host.experiment.outputs import reserve_bytes

        assert free0 - shutil.disk_usage(small_fs).free >= reserve_bytes(10, 501)  # really allocated
        assert list(small_fs.iterdir()) == []  # and without a name
    finally:
        proc.kill()
        proc.wait()
    assert shutil.disk_usage(small_fs).free == free0 and list(small_fs.iterdir()) == []


def _run_folder(tmp_path: Path) -> tuple[Path, list[int]]:
    """A run folder as a killed host may leave it: the recording one trial ahead of the summary, a
    trial file the summary does not hold, a temporary file of an atomic write."""
    out = tmp_path / "run"
    (out / "logs").mkdir(parents=True)
    (out / "trials").mkdir()
    rec, sizes = record_trials(out / "recording.rrd", 3, join=False)
    rec._file.close()  # killed: no close(), the last trailer never written
    summary = {"iterations": [{"k": 0}, {"k": 1}], "recording": {"file": "recording.rrd", "bytes": sizes[1], "trials": [0, 1]}}
    (out / "summary.json").write_text(json.dumps(summary))
    for k in range(3):
        (out / "trials" / f"trial-{k:05d}.npz").write_bytes(b"x")
    (out / "summary.json.tmp").write_text("{")
    return out, sizes


def test_the_janitor_settles_the_folder_after_a_killed_launcher(tmp_path: Path) -> None:
    out, _ = _run_folder(tmp_path)
    host = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # stands in for the host
    janitor = subprocess.Popen(
        [sys.executable, "-m", "host.cli.janitor", "--out", str(out), "--wait", str(host.pid)], cwd=REPO, stdin=subprocess.PIPE
    )
    try:
        assert janitor.stdin is not None
        janitor.stdin.close()  # the launcher is gone (no "done")
        time.sleep(0.2)
        assert recorded_trials(out / "recording.rrd") == [0, 1, 2]  # it waits for the host first
        host.kill()
        assert janitor.wait(timeout=60) == 0
    finally:
        host.kill()
        host.wait()
        janitor.kill()
        janitor.wait()
    assert recorded_trials(out / "recording.rrd") == [0, 1]
    assert sorted(p.name for p in (out / "trials").iterdir()) == ["trial-00000.npz", "trial-00001.npz"]
    assert not (out / "summary.json.tmp").exists()
    log = (out / "logs" / "janitor.log").read_text()
    assert "janitor: the launcher was killed; cut" in log
    # the host had not ended the run (no end_reason): the summary says the launcher was lost
    s = json.loads((out / "summary.json").read_text())
    assert s["end_reason"] == "launcher_lost" and s["launcher_lost"]["trials_kept"] == 2
    assert "janitor: the launcher was killed; marked the summary: end_reason launcher_lost, 2 trial(s) kept" in log


def test_the_janitor_leaves_the_summary_of_a_run_that_had_ended(tmp_path: Path) -> None:
    from host.rig.janitor import mark_launcher_lost

    out, _ = _run_folder(tmp_path)
    s = json.loads((out / "summary.json").read_text()) | {"end_reason": "completed"}
    (out / "summary.json").write_text(json.dumps(s))
    assert mark_launcher_lost(out) is None
    assert json.loads((out / "summary.json").read_text()) == s


def test_a_janitor_told_done_touches_nothing(tmp_path: Path) -> None:
    out, sizes = _run_folder(tmp_path)
    from host.rig.janitor import start_janitor

    janitor = start_janitor(out, os.getpid())
    assert janitor is not None
    janitor.done()
    assert janitor.proc.returncode == 0
    assert (out / "recording.rrd").stat().st_size > sizes[1] and (out / "summary.json.tmp").exists()


# ---------------------------------------------------------------------------------------
# a full disk at each phase of a run, on a real small filesystem
# ---------------------------------------------------------------------------------------


def _fill(where: Path) -> None:
    """Eat every free byte of ``where``'s filesystem (a ballast file; once)."""
    if (where / "ballast").exists():
        return
    fd = os.open(where / "ballast", os.O_WRONLY | os.O_CREAT, 0o600)
    try:
        for size in (65536, 4096, 512, 1):
            try:
                while True:
                    os.write(fd, b"\0" * size)
            except OSError:
                pass
    finally:
        os.close(fd)


PHASES = ("before_first_trial", "recording", "arrays", "report")


@pytest.mark.slow
@pytest.mark.parametrize("phase", PHASES)
def test_a_full_disk_at_each_phase_keeps_a_readable_recording(
    small_fs: Path, phase: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``ilcrig sim``'s session on a 4 MB tmpfs, filled to the last byte at one phase: before the
    first trial (after the reserve is taken), while trial 1's recording is written, while trial 1's
    arrays are written, while the report is written (after the last trial). Exit code 3, one line,
    the recording read by RrdReader holds exactly the summary's trials, no leftover."""
    from host.analysis import run_report, session
    from host.analysis.session import report_fault, run_session
    from host.experiment import arrays, trial_loop
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.sim.inprocess import InProcessBench

    out = small_fs / "run"
    out.mkdir()
    cfg = build_config(None, {"iterations": 3, "cycle_s": 0.15})
    plan = prepare(cfg)
    if phase == "before_first_trial":
        real_write = trial_loop.write_summary

        def write_first(out_dir: Path, summary: dict, **kw: Any) -> None:
            if not summary["iterations"]:
                _fill(small_fs)
            real_write(out_dir, summary, **kw)

        monkeypatch.setattr(trial_loop, "write_summary", write_first)
    elif phase == "recording":
        real_log = RunRecorder.log_trial

        def log_trial(self: RunRecorder, k: int, *a: Any, **kw: Any) -> None:
            if k == 1:
                _fill(small_fs)
            real_log(self, k, *a, **kw)

        monkeypatch.setattr(RunRecorder, "log_trial", log_trial)
        monkeypatch.setattr(RunRecorder, "_check_space", lambda self, k: None)  # let the write itself fail
    elif phase == "arrays":
        real_save = arrays._save

        def save(path: Path, *a: Any, **kw: Any) -> None:
            if path.name == "trial-00001.npz":
                _fill(small_fs)
            real_save(path, *a, **kw)

        monkeypatch.setattr(arrays, "_save", save)
    else:
        real_report = run_report.write_run_report

        def report(run_dir: Path, summary: dict) -> Path:
            _fill(small_fs)
            return real_report(run_dir, summary)

        monkeypatch.setattr(session, "write_run_report", report)
    res = run_session(plan, InProcessBench(cfg), out, mode="sim", stream=io.StringIO())
    code = report_fault(res, out / "summary.json")
    err = capsys.readouterr().err.splitlines()
    assert code == 3 and len(err) == 1 and "[disk_full]" in err[0], err
    s = json.loads((out / "summary.json").read_text())
    f = s["faults"][0]
    kept = {"before_first_trial": 0, "recording": 2, "arrays": 2, "report": 3}[phase]
    position = {"before_first_trial": "before_first_trial", "report": "after_last_trial"}.get(phase, "between_trials")
    assert (f["kind"], f["position"], len(s["iterations"])) == ("disk_full", position, kept), f
    assert s["recording"]["trials"] == list(range(kept))
    assert recorded_trials(out / "recording.rrd") == list(range(kept))
    names = {p.name for p in out.rglob("*")}
    assert not {n for n in names if n.endswith(".tmp") or "reserve" in n}, names
    if kept:
        assert sorted(p.name for p in (out / "trials").glob("trial-*.npz")) == [f"trial-{k:05d}.npz" for k in range(kept)]
    os.unlink(small_fs / "ballast")


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_rig_run_on_a_disk_that_fills_in_a_trial(tmp_path: Path) -> None:
    """``ilcrig run`` on a small tmpfs: the candump logs fill it during a trial; the run ends with a
    disk_full fault, the recording (written into the reserve's room) holds exactly the summary's
    trials, nothing is left behind. Sized from a run of the same experiment: a few trials fit."""
    from host.experiment.outputs import reserve_bytes

    size_k = (reserve_bytes(6, 301) + 1_400_000) // 1024  # the reserve and ~2 trials' logs, recording and arrays
    with small_tmpfs(tmp_path / "small", size_k) as mnt:
        from fault_harness import kill_session, run_rig

        o = run_rig(mnt / "run", iterations=6)
        try:
            assert o.code == 3, (o.stdout[-1500:], o.stderr)
            assert len(o.lines) == 1 and "[disk_full]" in o.lines[0] and o.left == []
            assert o.fault is not None and o.fault["kind"] == "disk_full"
            kept = o.kept
            assert 0 < kept < 6 and o.summary is not None
            assert o.summary["recording"]["trials"] == list(range(kept)) == recorded_trials(mnt / "run" / "recording.rrd")
            names = {p.name for p in (mnt / "run").rglob("*")}
            assert not {n for n in names if n.endswith(".tmp") or "reserve" in n}, names
        finally:
            kill_session(o)


def test_a_killed_sim_never_leaves_an_unreadable_recording(tmp_path: Path) -> None:
    """``ilcrig sim`` killed with SIGKILL in the middle of its trials (no process outlives it): the
    recording opens with RrdReader and holds the summary's trials, or one more (killed between
    the two writes; the launcher or the janitor cut that back in ``ilcrig run``); the API reads
    the run as ``writer_lost``, not as one still going."""
    out = tmp_path / "run"
    pid = sim_signalled_at_row(out, "3", signal.SIGKILL)[2]
    s = json.loads((out / "summary.json").read_text())
    k = len(s["iterations"])
    assert recorded_trials(out / "recording.rrd") in (list(range(k)), list(range(k + 1)))
    from host.rig.janitor import settle_run_folder

    settle_run_folder(out)
    assert recorded_trials(out / "recording.rrd") == list(range(k))
    # nobody outlived it to end the summary; its writer's identity says the run is not still going
    assert s["end_reason"] is None and s["writer"]["pid"] == pid
    import ilcrig

    res = ilcrig.load(out)
    assert (res.end_reason, res.completed, len(res.trials)) == ("writer_lost", False, k)
