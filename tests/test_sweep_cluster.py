"""Sweeps that say what happened: one study, one folder (a run's folder or another sweep's is
refused, exit 2); ``--no-dashboard`` opens no HTTP listener; a cluster without workers and a lost
scheduler are one line and exit 5 (``EXIT_CLUSTER_LOST``), never point errors, and resumable."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_util import run_cli, start_in_session
from test_sweep import DASK, GUARD_S, ROOT, TINY, _cli, _listening, _start, _stop

from bus.errors import InputError
from bus.exit_codes import EXIT_CLUSTER_LOST, EXIT_USAGE
from host.studies.spec import SweepSpec
from host.studies.sweep_record import check_study_folder

# ------------------------------------------------------------------------- one study, one folder


def _a_run(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text("{}")
    (folder / "report.md").write_text("# the run's own report\n")
    return folder


def test_check_study_folder(tmp_path: Path) -> None:
    spec = {"base": {"iterations": 2}, "vary": {"gains.alpha": [2, 3]}}
    check_study_folder(tmp_path / "new", "sweep", spec)  # a new folder
    (tmp_path / "empty").mkdir()
    check_study_folder(tmp_path / "empty", "tune")
    run = _a_run(tmp_path / "run")
    for kind in ("sweep", "tune"):
        with pytest.raises(InputError, match=r"--out .*run: holds a run \(summary.json, report.md\)"):
            check_study_folder(run, kind, spec)
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "report.md").write_text("x")  # a sweep's own report is no run
    (sweep / "sweep.json").write_text(json.dumps({"spec": {"base": {"iterations": 2}, "vary": {"gains.alpha": (2, 3)}}}))
    check_study_folder(sweep, "sweep", spec)  # the same spec: a resume
    with pytest.raises(InputError, match="holds a sweep of another spec"):
        check_study_folder(sweep, "sweep", spec | {"vary": {"gains.alpha": [2, 4]}})
    with pytest.raises(InputError, match=r"holds a sweep \(sweep.json\)"):
        check_study_folder(sweep, "tune")
    study = tmp_path / "study"
    study.mkdir()
    (study / "study.db").write_bytes(b"")
    check_study_folder(study, "tune")  # a resume (the tuner checks the study's identity)
    with pytest.raises(InputError, match=r"holds a tuning study \(study.db\)"):
        check_study_folder(study, "sweep", spec)
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        check_study_folder(tmp_path / "file", "sweep", spec)


def test_sweep_and_tune_refuse_a_run_folder_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _a_run(tmp_path / "run")
    before = sorted(p.name for p in run.iterdir())
    for argv in (
        ["sweep", "--out", str(run), *TINY, "--vary", "gains.alpha=2,3"],
        ["tune", "--out", str(run), *TINY, "--param", "gains.alpha=1.5:6", "--budget", "2"],
    ):
        code, out, err = run_cli(capsys, *argv)
        assert code == EXIT_USAGE and out == ""
        assert err.count("\n") == 1 and err.startswith(f"ilcrig: error: --out {run}: holds a run"), err
    assert sorted(p.name for p in run.iterdir()) == before
    assert (run / "report.md").read_text() == "# the run's own report\n"


def test_sweep_refuses_another_sweeps_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from host.cli.studies import _spec_doc

    spec = SweepSpec()
    spec.add_cli(["iterations=2", "cycle_s=0.15"], ["gains.alpha=2,3"])
    out = tmp_path / "sweep"
    out.mkdir()
    (out / "sweep.json").write_text(json.dumps({"spec": _spec_doc(spec), "history": []}))
    code, _, err = run_cli(capsys, "sweep", "--out", str(out), *TINY, "--vary", "gains.alpha=2,4")
    assert code == EXIT_USAGE and "holds a sweep of another spec" in err and err.count("\n") == 1
    check_study_folder(out, "sweep", _spec_doc(spec))  # the same command resumes


# ----------------------------------------------------------------------- --no-dashboard, Dask


def _answers_http(port: int) -> bool:
    """True if something on 127.0.0.1:``port`` answers an HTTP request."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.settimeout(2)
        s.sendall(b"GET /health HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
        try:
            return s.recv(5).startswith(b"HTTP/")
        except (TimeoutError, ConnectionError):
            return False


@pytest.mark.slow
@pytest.mark.multiprocess
def test_no_dashboard_opens_no_http_listener() -> None:
    """Every listener of the local cluster (this process: scheduler and nannies; the workers) on
    loopback; with the dashboard one of them answers HTTP, with ``dashboard=False`` none."""
    from host.studies.engine import Engine

    for dashboard, http in ((True, True), (False, False)):
        with Engine(workers=1, dashboard=dashboard) as engine:
            assert engine.n_workers == 1
            sockets = _listening([os.getpid()])
            assert sockets and all(ip == "127.0.0.1" for _, ip, _ in sockets), sockets
            assert 8787 not in {port for _, _, port in sockets} or dashboard
            answering = [port for _, _, port in sockets if _answers_http(port)]
            assert bool(answering) is http, (dashboard, sockets, answering)
            if not dashboard:
                assert engine.dashboard is None


# ------------------------------------------------------------------ a cluster lost or without workers


@pytest.fixture
def scheduler(tmp_path: Path) -> Iterator[tuple[str, list[subprocess.Popen[bytes]], dict[str, str]]]:
    """``dask scheduler`` on 127.0.0.1 (no workers); yields (address, processes — the test may add
    workers —, the environment a worker needs to hold points)."""
    env = os.environ | {"PYTHONPATH": str(ROOT / "tests")}
    sfile = tmp_path / "scheduler.json"
    cmd = [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address", "127.0.0.1:0"]
    procs = [_start([*cmd, "--scheduler-file", str(sfile)], tmp_path / "scheduler.log", env)]
    try:
        deadline = time.monotonic() + GUARD_S
        while not sfile.is_file() or "address" not in sfile.read_text():
            assert procs[0].poll() is None and time.monotonic() < deadline, (tmp_path / "scheduler.log").read_text()
            time.sleep(0.1)
        time.sleep(0.2)
        yield json.loads(sfile.read_text())["address"], procs, env
    finally:
        _stop(procs)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_cluster_without_workers_is_said_and_exit_5(
    tmp_path: Path, scheduler: tuple[str, list[subprocess.Popen[bytes]], dict[str, str]]
) -> None:
    address, _, _ = scheduler
    out = tmp_path / "sweep"
    t0 = time.monotonic()
    p = _cli("sweep", "--out", str(out), "--scheduler", address, "--wait-workers", "3", "--no-progress", *TINY)
    assert p.returncode == EXIT_CLUSTER_LOST, p.stderr
    assert time.monotonic() - t0 < 60
    assert f"ilcrig: the cluster at {address} has no workers; waiting up to 3 s for one" in p.stderr
    assert f"ilcrig sweep: no worker joined the cluster at {address} within 3 s; 0 point(s)" in p.stderr
    assert "Traceback" not in p.stderr and p.stdout == ""
    assert not list(out.glob("runs/*/error.txt"))
    (call,) = json.loads((out / "sweep.json").read_text())["history"]
    assert call["cluster_lost"] and call["errors"] == {} and call["ran"] == 0


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_lost_scheduler_is_exit_5_not_point_errors_and_resumes(
    tmp_path: Path, scheduler: tuple[str, list[subprocess.Popen[bytes]], dict[str, str]]
) -> None:
    """One point finished, the other held by the worker (tests/sweep_hold.py); the scheduler
    SIGKILLed: exit 5 in one line, the finished point kept, no error stored; the resume on a new
    cluster runs the other point only."""
    from test_sweep import HELD, HELD_SPEC

    address, procs, env = scheduler
    hold = tmp_path / "hold"
    env = env | {"ILCRIG_TEST_HOLD": HELD.id, "ILCRIG_TEST_HOLD_DIR": str(hold)}
    worker = [str(DASK), "worker", address, "--nthreads", "1", "--host", "127.0.0.1", "--dashboard-address", "127.0.0.1:0"]
    procs.append(_start(worker, tmp_path / "worker.log", env))
    out = tmp_path / "sweep"
    args = ["sweep", "--out", str(out), "--scheduler", address, "--no-progress"]
    args += [a for s in HELD_SPEC for a in ("--set", s)] + ["--vary", "gains.alpha=2,3"]
    client = start_in_session([sys.executable, "tests/sweep_hold.py", *args], env=env)
    try:
        deadline = time.monotonic() + GUARD_S
        while not ((hold / HELD.id / "held").is_file() and any(out.glob("runs/*/summary.json"))):
            assert client.poll() is None, client.communicate()
            assert time.monotonic() < deadline, "the sweep neither finished one point nor held the other"
            time.sleep(0.1)
        os.killpg(procs[0].pid, signal.SIGKILL)
        stdout, stderr = client.communicate(timeout=GUARD_S)
    finally:
        if client.poll() is None:
            os.killpg(client.pid, signal.SIGKILL)
            client.wait()
    assert client.returncode == EXIT_CLUSTER_LOST, stderr
    assert "ilcrig sweep: lost the connection to the scheduler" in stderr and "run the same command again" in stderr
    assert "Traceback" not in stderr and "could not run" not in stderr and stdout == ""
    assert not list(out.glob("runs/*/error.txt"))
    finished = [d.name for d in out.glob("runs/*") if (d / "summary.json").is_file()]
    assert len(finished) == 1 and HELD.id not in finished, finished
    (call,) = json.loads((out / "sweep.json").read_text())["history"]
    assert call["cluster_lost"] and call["errors"] == {} and call["ran"] == 1
    _stop(procs)
    procs.clear()
    # the resume, on a new cluster: the held point only
    p = _cli("sweep", "--out", str(out), "--workers", "1", "--no-progress", "--no-dashboard", *args[6:])
    assert p.returncode == 0, p.stderr
    assert "1 run, 1 already finished" in p.stdout


def test_every_dask_recipe_in_the_docs_binds_every_listener_to_the_chosen_address() -> None:
    """docs/sweeps.md: each ``dask scheduler`` / ``dask worker`` command binds its connections
    (``--host``) and its HTTP server (``--dashboard-address``, else Dask listens on every
    interface) to one address."""
    import re

    text = (ROOT / "docs" / "sweeps.md").read_text().replace("\n", " ")
    recipes = [m.group(1).strip() for m in re.finditer(r"(dask (?:scheduler|worker)\b[^`#]*)", text)]
    recipes = [r for r in recipes if "--" in r]
    assert len(recipes) >= 4, recipes
    for r in recipes:
        host = re.search(r"--host (\S+)", r)
        http = re.search(r"--dashboard-address (\S+):\d+", r)
        assert host and http and host.group(1) == http.group(1), r
        assert "0.0.0.0" not in r and "--listen-address" not in r, r
