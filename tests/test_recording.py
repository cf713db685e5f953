"""recording.rrd of a run (host.analysis.recording): layout, values that reproduce the summary's metrics,
the 3D view, the recorder's calls into Rerun (none per sample or per trial), and `ilcrig view`
without a display / without a recording.  What recording costs in time is a benchmark:
benchmarks/recording_cost.py."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pyarrow as pa
import pytest

from host.cli import main

N_ITER = 3


def read_rrd(path: Path) -> dict[tuple[str, bool], list[pa.RecordBatch]]:
    """All chunks of the first recording, by (entity path, static)."""
    from rerun.chunk import RrdReader

    out: dict[tuple[str, bool], list[pa.RecordBatch]] = {}
    for c in RrdReader(path).stream():
        out.setdefault((c.entity_path, c.is_static), []).append(c.to_record_batch())
    return out


def series(chunks: dict, entity: str, index: str = "trial_time") -> tuple[np.ndarray, np.ndarray]:
    """(times, values (rows, width)) of a Scalars entity, sorted by time; duration → s."""
    t, v = [], []
    for rb in chunks[(entity, False)]:
        col = rb.column(index)
        t.append(col.cast(pa.int64()).to_numpy() * (1e-9 if index == "trial_time" else 1))
        v.append(np.array(rb.column("Scalars:scalars").to_pylist(), dtype=float))
    tt, vv = np.concatenate(t), np.concatenate(v)
    o = np.argsort(tt, kind="stable")
    return tt[o], vv[o]


def iterations(chunks: dict, entity: str) -> tuple[np.ndarray, np.ndarray]:
    """(times, values (rows, K)) of the per-iteration entities ``entity/iter{k}``, k = 0..K−1."""
    k_max = max(int(e.rsplit("/iter", 1)[1]) for e, _ in chunks if e.startswith(entity + "/iter"))
    cols = [series(chunks, f"{entity}/iter{k}") for k in range(k_max + 1)]
    return cols[0][0], np.concatenate([v for _, v in cols], axis=1)


def static_value(chunks: dict, entity: str, column: str) -> Any:
    return chunks[(entity, True)][-1].column(column).to_pylist()[-1]


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, dict]:
    out = tmp_path_factory.mktemp("rec") / "run-a"
    code = main(["sim", "--iterations", str(N_ITER), "--cycle", "0.15", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    return out, summary, read_rrd(out / "recording.rrd")


@pytest.mark.slow
def test_recording_layout_and_ids(sim_run) -> None:
    out, summary, chunks = sim_run
    from rerun.chunk import RrdReader

    recs = RrdReader(out / "recording.rrd").recordings()
    assert [(r.application_id, r.recording_id) for r in recs] == [("ilcrig", "run-a")]
    assert len(RrdReader(out / "recording.rrd").blueprints()) == 1  # the default blueprint
    n = summary["config"]["n_ticks"]
    entities = {e for e, _ in chunks}
    for j in range(1, 5):
        t, v = series(chunks, f"/joint{j}/reference")
        assert v.shape == (n, 1)
        np.testing.assert_allclose(t, np.arange(n) * 1e-3, atol=1e-12)
        for q in ("actual", "error", "torque_ff", "torque_fb"):
            t, v = iterations(chunks, f"/joint{j}/{q}")
            assert v.shape == (n, N_ITER), q  # N ticks, one entity per iteration
            for k in range(N_ITER):
                names = static_value(chunks, f"/joint{j}/{q}/iter{k}", "SeriesLines:names")
                assert names == [f"{q} iter {k} [{'deg' if q in ('actual', 'error') else 'N·m'}]"]
        for key in ("rmse_deg", "maxe_deg"):
            assert f"/metrics/{key}/joint{j}" in entities
    assert ("/robot", True) in chunks  # ViewCoordinates
    assert "ViewCoordinates:xyz" in chunks[("/robot", True)][0].schema.names


@pytest.mark.slow
def test_logged_errors_reproduce_summary_metrics(sim_run) -> None:
    _, summary, chunks = sim_run
    for j in range(1, 5):
        _, e = iterations(chunks, f"/joint{j}/error")
        _, ref = series(chunks, f"/joint{j}/reference")
        _, act = iterations(chunks, f"/joint{j}/actual")
        np.testing.assert_allclose(ref - act, e, atol=1e-9)  # e = q_d − q (deg)
        for k, it in enumerate(summary["iterations"]):
            rmse = float(np.sqrt(np.mean(e[:, k] ** 2)))
            maxe = float(np.max(np.abs(e[:, k])))
            assert rmse == pytest.approx(it["rmse_deg"][j - 1], rel=1e-12)
            assert maxe == pytest.approx(it["max_abs_deg"][j - 1], rel=1e-12)
        for key, field in (("rmse_deg", "rmse_deg"), ("maxe_deg", "max_abs_deg")):
            it_idx, v = series(chunks, f"/metrics/{key}/joint{j}", index="iteration")
            assert it_idx.tolist() == list(range(N_ITER))  # one row per iteration
            assert v[:, 0].tolist() == [it[field][j - 1] for it in summary["iterations"]]


@pytest.mark.slow
def test_3d_first_and_last_trial(sim_run) -> None:
    _, summary, chunks = sim_run
    n = summary["config"]["n_ticks"]
    m = len(np.unique(np.r_[np.arange(0, n, 5), n - 1]))
    for which in ("first", "last"):
        for name, col, width in (
            ("arms", "LineStrips3D:strips", 4),
            ("sub_platforms", "LineStrips3D:strips", 3),
            ("tool", "Points3D:positions", 1),
        ):
            rbs = chunks[(f"/robot/{which}/{name}", False)]
            rows = [r for rb in rbs for r in rb.column(col).to_pylist()]
            # "first" once; "last" after every trial (the newest rows win in the viewer)
            assert len(rows) == m * (1 if which == "first" else N_ITER) and all(len(r) == width for r in rows)
        assert (f"/robot/{which}/tcp_path", True) in chunks
    # the arms start at the motor axes (R = 0.2 m) and the tool follows the reference path
    arms = chunks[("/robot/first/arms", False)][0].column("LineStrips3D:strips").to_pylist()[0]
    for strip in arms:
        assert np.hypot(strip[0][0], strip[0][1]) == pytest.approx(0.2, abs=1e-6) and strip[0][2] == 0.0
        assert np.linalg.norm(np.subtract(strip[2], strip[1])) == pytest.approx(0.6, abs=1e-5)  # outer arm l_b
    ref_path = np.array(static_value(chunks, "/robot/reference_path", "LineStrips3D:strips")[0])  # (N, 3)
    tool = np.array(
        [r[0] for rb in chunks[("/robot/last/tool", False)] for r in rb.column("Points3D:positions").to_pylist()][-m:]
    )
    dist = np.min(np.linalg.norm(tool[:, None, :] - ref_path[None, :, :], axis=2), axis=1)
    assert dist.max() < 0.01  # within 1 cm of the path (errors are a fraction of a degree)


class _CallLog:
    """Stands in front of a RunRecorder's Rerun stream and notes the name of every method called."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.calls: list[str] = []

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._stream, name)
        if not callable(attr):
            return attr

        def call(*args: Any, **kwargs: Any) -> Any:
            self.calls.append(name)
            return attr(*args, **kwargs)

        return call


def _record(folder: Path, n: int, trials: int) -> tuple[list[list[str]], list[str]]:
    """Record ``trials`` synthetic trials of ``n`` samples (a reachable pose, small errors);
    returns the stream calls made by each log_trial call and by close."""
    from host.analysis.recording import RunRecorder
    from host.learning.metrics import trial_metrics
    from host.planning.joint_reference import JointReference
    from plant.kinematics import inverse_kinematics

    q0 = inverse_kinematics(np.array([0.0, 0.0, -0.65, 0.0]))
    q = np.tile(q0, (n, 1))
    ref = JointReference(t=np.arange(n) * 1e-3, q=q, qd=np.zeros((n, 4)), qdd=np.zeros((n, 4)))
    rec = RunRecorder(folder / "recording.rrd", config_summary={"iterations": trials})
    log = _CallLog(rec._rec)
    rec._rec = log  # type: ignore[assignment]
    per_trial: list[list[str]] = []
    for k in range(trials):
        before = len(log.calls)
        e = np.full((n, 4), 1e-3 / (k + 1)) * np.sin(np.arange(n) / 7.0)[:, None]
        traces = [SimpleNamespace(q_rad=q[:, j] - e[:, j], tau_fb_nm=np.full(n, 0.1 * j)) for j in range(4)]
        u = np.full((n, 4), float(k))
        rec.log_trial(k, ref, traces, u, e, trial_metrics(k, e, u))
        per_trial.append(log.calls[before:])
    before = len(log.calls)
    rec.close()
    assert rec.error is None
    return per_trial, log.calls[before:]


def test_recorder_calls_do_not_grow_with_samples_or_trials(tmp_path: Path) -> None:
    """The recording grows trial by trial (a killed run keeps every completed trial), with a
    fixed number of calls into the Rerun stream per trial, ending with a flush: none per sample,
    the same for 51 samples as for 2001, the same for every trial after the first; close makes
    the same calls for 2 trials as for 6."""
    small_trials, small_close = _record(tmp_path / "small", 51, 2)
    large_trials, large_close = _record(tmp_path / "large", 2001, 6)
    assert small_trials[0] == large_trials[0]
    assert small_trials[1:] == large_trials[1:2] and all(c == large_trials[1] for c in large_trials[1:])
    for calls in large_trials:
        assert calls.count("send_record_batch") >= 1 and calls[-1] == "flush"
        assert len(calls) < 100
    assert small_close == large_close and small_close[-2:] == ["flush", "disconnect"]
    chunks = read_rrd(tmp_path / "large" / "recording.rrd")
    for k in range(6):
        t, v = series(chunks, f"/joint1/error/iter{k}")
        assert v.shape == (2001, 1)
        np.testing.assert_allclose(t, np.arange(2001) * 1e-3, atol=1e-12)
    assert ("/robot/last/tool", False) in chunks  # the 3D view was written too


def test_log_trial_rejects_bad_shapes(tmp_path: Path) -> None:
    from host.analysis.recording import RunRecorder
    from host.analysis.recording_segments import RecordingError
    from host.learning.metrics import trial_metrics
    from host.planning.joint_reference import JointReference

    n = 11
    ref = JointReference(t=np.arange(n) * 1e-3, q=np.full((n, 4), 0.5), qd=np.zeros((n, 4)), qdd=np.zeros((n, 4)))
    rec = RunRecorder(tmp_path / "x" / "recording.rrd")
    with pytest.raises(RecordingError, match="expected 4 traces"):
        rec.log_trial(0, ref, [], np.zeros((n, 4)), np.zeros((n, 4)), trial_metrics(0, np.zeros((n, 4)), np.zeros((n, 4))))
    rec.close()
    rec.close()  # idempotent
    assert rec.error is None and rec.recording_id == "x"
    from rerun.chunk import RrdReader

    assert [r.recording_id for r in RrdReader(tmp_path / "x" / "recording.rrd").recordings()] == ["x"]


def _fake_viewer(tmp_path: Path, native: str) -> list[str]:
    """A stand-in for ``rerun``: as the native viewer it runs ``native`` (shell); as the web viewer
    it says Rerun's line with a URL and ends a moment later."""
    script = tmp_path / "fake-rerun"
    script.write_text(
        "#!/bin/sh\n"
        'case " $* " in *" --web-viewer "*)\n'
        '  echo "INFO Hosting a web-viewer at http://127.0.0.1:1 - connect at http://127.0.0.1:1?url=x"; sleep 0.5; exit 0;;\n'
        "esac\n"
        f"{native}\n"
    )
    script.chmod(0o755)
    return [str(script)]


def test_view_without_a_viewer_prints_the_command(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from importlib.metadata import version

    from host.analysis import viewer

    (tmp_path / "recording.rrd").write_bytes(b"")
    monkeypatch.setattr(viewer, "viewer_command", lambda: None)
    spawned: list[Any] = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: spawned.append(a))
    out, err = io.StringIO(), io.StringIO()
    assert viewer.view_run(tmp_path, stdout=out, stderr=err) == 0
    text = out.getvalue()
    assert f"rerun {(tmp_path / 'recording.rrd').resolve()}" in text
    assert f"pip install rerun-sdk=={version('rerun-sdk')}" in text
    assert "opened" not in text and not spawned and err.getvalue() == ""


def test_view_with_display_opens_a_native_viewer_that_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from host.analysis import viewer

    (tmp_path / "recording.rrd").write_bytes(b"")
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(viewer, "NATIVE_SETTLE_S", 0.5)
    monkeypatch.setattr(viewer, "viewer_command", lambda: _fake_viewer(tmp_path, 'echo "$1" > "$0.args"; exec sleep 5'))
    out = io.StringIO()
    assert viewer.view_run(tmp_path, stdout=out, stderr=io.StringIO()) == 0
    assert out.getvalue().startswith("ilcrig view: opened ")
    assert (tmp_path / "fake-rerun.args").read_text().strip() == str((tmp_path / "recording.rrd").resolve())


def test_view_native_viewer_exiting_at_once_falls_back_to_the_web_viewer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from host.analysis import viewer

    (tmp_path / "recording.rrd").write_bytes(b"")
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(viewer, "viewer_command", lambda: _fake_viewer(tmp_path, "exit 101"))
    out, err = io.StringIO(), io.StringIO()
    assert viewer.view_run(tmp_path, stdout=out, stderr=err) == 0
    assert "opened" not in out.getvalue()
    assert "the native viewer exited at once (exit code 101" in err.getvalue()
    assert "in Rerun's web viewer on 127.0.0.1: open http://127.0.0.1:1?url=x" in out.getvalue()


@pytest.mark.multiprocess
def test_view_headless_serves_the_web_viewer_on_loopback(tmp_path: Path) -> None:
    """No display: the real Rerun web viewer, its URL printed, answering an HTTP GET on loopback;
    Ctrl-C ends the command and the viewer."""
    import os
    import signal
    import urllib.request

    import psutil

    (tmp_path / "recording.rrd").write_bytes(b"")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "host.cli", "view", str(tmp_path)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    viewers: list[psutil.Process] = []
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        assert "in Rerun's web viewer on 127.0.0.1: open http://127.0.0.1:" in line, (line, proc.stderr and proc.stderr.read())
        url = line.split("open ", 1)[1].strip()
        viewers = psutil.Process(proc.pid).children(recursive=True)
        listening = [c.laddr for v in viewers for c in v.net_connections(kind="inet") if c.status == "LISTEN"]
        assert listening and all(a.ip == "127.0.0.1" for a in listening), listening
        with urllib.request.urlopen(url, timeout=10) as resp:  # noqa: S310 - a loopback http URL
            assert resp.status == 200 and resp.read(100)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 130, err
        assert "Traceback" not in err and "opened" not in err
        _, alive = psutil.wait_procs(viewers, timeout=10)  # the viewer ends with the command
        assert not [v for v in alive if v.status() != psutil.STATUS_ZOMBIE]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        for v in viewers:  # whatever the test's outcome, no viewer outlives it
            with contextlib.suppress(psutil.NoSuchProcess):
                v.kill()


def test_view_missing_recording_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["view", str(tmp_path / "nope")])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ilcrig: error: no recording at ")


def test_view_of_a_run_without_a_recording_says_how_it_ended(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run folder whose run ended before a recording was made (here: the summary of a run
    interrupted before its first trial): one line naming what its summary says, exit 2."""
    from host.experiment.summary import write_summary

    marker = {"signal": "SIGTERM", "position": "before_first_trial", "trial": 0, "tick": None}
    summary = {"iterations": [], "completed": False, "end_reason": "interrupted", "interrupted": marker, "faults": []}
    write_summary(tmp_path, summary)
    code = main(["view", str(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.splitlines() == [
        f"ilcrig: error: no recording at {tmp_path / 'recording.rrd'}: the run kept 0 trials (interrupted by SIGTERM); "
        f"summary: {tmp_path / 'summary.json'}"
    ]


def test_import_host_does_not_import_rerun() -> None:
    code = (
        "import sys, host, host.analysis.recording, host.cli, host.experiment.trial_loop; "
        "sys.exit(1 if 'rerun' in sys.modules else 0)"
    )
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0
