"""Running ``ilcrig`` in tests: in-process (the exit code and what it printed) and as a process in
a session of its own (:func:`ilcrig_argv`, :func:`run_cli_process`: it and every process it started
gone on return);
any command started in a session of its own (:func:`start_in_session`), or run there, its group
killed on a hang (:func:`run_in_session`); a process
asked to stop, killed if it does not (:func:`stop_process`); ``ilcrig sim`` signalled at a row of its
table (:func:`sim_signalled_at_row`); whether a process still runs (:func:`pid_alive`) and waiting
until processes are gone (:func:`wait_gone`)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest
from clock_util import wait_for

from host.cli import main


def pid_alive(pid: int) -> bool:
    """True while a process with ``pid`` exists and is not a zombie (it runs no more)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return False


def wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    """Wait until no pid of ``pids`` is alive; returns the ones still alive at the deadline."""
    wait_for(lambda: not any(map(pid_alive, pids)), timeout_s)
    return [p for p in pids if pid_alive(p)]


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``main(argv)``; (exit code, stdout, stderr) — argparse's own errors exit by SystemExit."""
    try:
        code = main(list(argv))
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


ROOT = Path(__file__).resolve().parent.parent


def ilcrig_argv(*args: str) -> list[str]:
    """The command line of ``ilcrig ARGS`` as a process of this interpreter (``python -m host.cli``)."""
    return [sys.executable, "-m", "host.cli", *args]


def start_in_session(cmd: list[str], cwd: Path = ROOT, env: Mapping[str, str] | None = None) -> subprocess.Popen[str]:
    """``cmd`` started in a session of its own (its whole group can be killed), from ``cwd``, its
    stdout and stderr piped as text."""
    pipe = subprocess.PIPE
    return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=pipe, stderr=pipe, text=True, start_new_session=True)


def run_cli_process(args: list[str], guard_s: float, env: Mapping[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """``ilcrig ARGS`` in its own session, from the project folder (with ``env`` if given); returns
    once it and every process it started ended (killed after ``guard_s``, a guard against a hang)."""
    proc = start_in_session(ilcrig_argv(*args), env=env)
    try:
        out, err = proc.communicate(timeout=guard_s)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    group_gone(proc.pid, guard_s)  # e.g. a local cluster's workers end with the command
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def run_in_session(
    cmd: list[str], timeout_s: float, cwd: Path = ROOT, what: str | None = None
) -> subprocess.CompletedProcess[str]:
    """``cmd`` in a session of its own, from ``cwd``; its whole group killed and the test failed
    (``what`` timed out, by default the command) if it takes longer than ``timeout_s``."""
    proc = start_in_session(cmd, cwd)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{what or cmd} timed out:\n{out}\n{err}")
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def stop_process(proc: subprocess.Popen[Any], sig: int = signal.SIGTERM, wait_s: float = 10.0) -> None:
    """Send ``sig`` to ``proc`` and wait ``wait_s`` for it to end; kill it if it does not."""
    proc.send_signal(sig)
    try:
        proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def group_gone(pgid: int, guard_s: float) -> None:
    """Wait until no process of group ``pgid`` is left (a local cluster's workers end with its
    command); fail after ``guard_s``."""
    deadline = time.monotonic() + guard_s
    while True:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        if time.monotonic() > deadline:
            os.killpg(pgid, signal.SIGKILL)
            pytest.fail(f"processes of the command (group {pgid}) survived it")
        time.sleep(0.1)


def sim_signalled_at_row(out: Path, row: str, sig: int) -> tuple[int, str, int]:
    """``ilcrig sim --iterations 200 --cycle 0.15 --out out``, sent ``sig`` when it prints the
    table row of trial ``row``; (exit code, stderr, its pid). The process is always reaped."""
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "host.cli", "sim", "--iterations", "200", "--cycle", "0.15", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.split()[:1] == [row]:
                proc.send_signal(sig)
                break
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err, proc.pid
