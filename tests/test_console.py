"""A command whose console goes away (host/cli/console.py) or whose terminal hangs up (SIGHUP,
host/experiment/signal_shield.py, host/rig/interrupts.py), played from outside: a pipe read
until its reader has what it wants and closed, a pseudo-terminal closed under a running command
(the kernel then sends SIGHUP to the command, as when a terminal window is closed or an ssh
connection drops), with SIGHUP ignored as ``nohup`` leaves it. After each: the exit code, the
summary and the trials it kept, no traceback and no process left."""

from __future__ import annotations

import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bus.exit_codes import EXIT_HANGUP, EXIT_OK

ILCRIG = [sys.executable, "-m", "host.cli"]


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _on_a_terminal(argv: list[str], hang_up_after: bytes, *, nohup: bool = False, timeout_s: float = 300) -> tuple[int, bytes]:
    """Run ``argv`` on a new pseudo-terminal (its controlling terminal), read its output until
    ``hang_up_after`` appeared, then close the terminal. Returns the wait status (as
    :func:`os.waitpid`: a signal's death is not an exit code) and what the terminal showed."""
    pid, fd = pty.fork()
    if pid == 0:  # the child: the command, on the terminal  # pragma: no cover - replaced by exec
        if nohup:
            signal.signal(signal.SIGHUP, signal.SIG_IGN)
        os.execv(argv[0], argv)
    seen = b""
    try:
        deadline = time.monotonic() + timeout_s
        while hang_up_after not in seen:
            assert time.monotonic() < deadline, f"no {hang_up_after!r} on the terminal: {seen[-500:]!r}"
            if select.select([fd], [], [], 1.0)[0]:
                try:
                    seen += os.read(fd, 65536)
                except OSError:  # the command ended and its side of the terminal is gone
                    break
        os.close(fd)  # the hang-up: SIGHUP (and SIGCONT) to the terminal's foreground process group
        fd = -1
        waited = 0
        while waited == 0:
            assert time.monotonic() < deadline, "the command did not end after the hang-up"
            waited, status = os.waitpid(pid, os.WNOHANG)
            time.sleep(0.05)
        pid = 0
        return status, seen
    finally:
        if fd >= 0:
            os.close(fd)
        if pid:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)


def test_a_sim_whose_reader_stops_reading_runs_to_its_end(tmp_path: Path) -> None:
    """``ilcrig sim … | head -3``: the pipe breaks after three lines; the run completes every trial,
    its summary says so, exit code 0, nothing on stderr (it was an internal error, exit 1, with a
    summary that named no end)."""
    out = tmp_path / "run"
    argv = [*ILCRIG, "sim", "--iterations", "40", "--out", str(out)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stderr is not None
        lines = [proc.stdout.readline() for _ in range(3)]
        assert lines[0].startswith("ilcrig sim: law ")
        proc.stdout.close()  # the reader is gone
        err = proc.stderr.read()
        assert proc.wait(timeout=300) == EXIT_OK, err
        assert err == ""
        s = _summary(out)
        assert (s["completed"], s["end_reason"], len(s["iterations"])) == (True, "completed", 40)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_sim_whose_terminal_hangs_up_ends_interrupted_with_its_trials(tmp_path: Path) -> None:
    """The terminal closed while ``ilcrig sim`` runs: SIGHUP ends the run like SIGTERM — exit code
    129, the summary interrupted by SIGHUP with every trial finished before it (the process was
    killed by the signal, its summary naming no end)."""
    out = tmp_path / "run"
    status, seen = _on_a_terminal([*ILCRIG, "sim", "--iterations", "300", "--out", str(out)], b"\n   2 ")
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == EXIT_HANGUP, (status, seen[-300:])
    s = _summary(out)
    assert (s["completed"], s["end_reason"], s["interrupted"]["signal"]) == (False, "interrupted", "SIGHUP")
    kept = len(s["iterations"])
    assert 2 <= kept < 300
    assert [row["k"] for row in s["iterations"]] == list(range(kept))
    assert b"Traceback" not in seen


def test_a_sim_under_nohup_outlives_its_terminal(tmp_path: Path) -> None:
    """SIGHUP ignored (``nohup ilcrig sim …``): the terminal's hang-up does not end the run, its
    lines go nowhere, every trial is kept, exit code 0."""
    out = tmp_path / "run"
    status, _ = _on_a_terminal([*ILCRIG, "sim", "--iterations", "30", "--out", str(out)], b"\n   1 ", nohup=True)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == EXIT_OK
    s = _summary(out)
    assert (s["completed"], s["end_reason"], len(s["iterations"])) == (True, "completed", 30)


@pytest.mark.multiprocess
@pytest.mark.parametrize("nohup", [False, True])
def test_a_rig_run_whose_terminal_hangs_up(tmp_path: Path, nohup: bool) -> None:
    """``ilcrig run`` on a terminal that is closed after trial 2: the launcher stops the host with
    SIGHUP and the summary says SIGHUP, as exit code 129 does (the launcher's line to the gone
    terminal made it exit 1, and the host said SIGTERM). Under ``nohup`` the run goes on to its end
    (the host, which writes the trial rows to that terminal, died of EIO: a fault, exit 3). No
    process of the run is left."""
    out = tmp_path / "run"
    argv = [*ILCRIG, "run", "--iterations", "12", "--cycle", "0.15", "--out", str(out)]
    status, seen = _on_a_terminal(argv, b"\n   2 ", nohup=nohup)
    s = _summary(out)
    if nohup:
        assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == EXIT_OK, (status, seen[-300:])
        assert (s["completed"], s["end_reason"], len(s["iterations"]), s["faults"]) == (True, "completed", 12, [])
    else:
        assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == EXIT_HANGUP, (status, seen[-300:])
        assert (s["completed"], s["end_reason"], s["interrupted"]["signal"]) == (False, "interrupted", "SIGHUP")
        assert 3 <= len(s["iterations"]) < 12
    left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
    assert left == []


def test_a_console_that_cannot_show_a_character_gets_it_escaped(tmp_path: Path) -> None:
    """A console whose encoding is ASCII (``PYTHONIOENCODING=ascii``, a Latin-1 locale): the lines
    with µ, ≥ or the digest's … are written with those escaped, the run's exit code is its own (the
    closing line made it an internal error, exit 1, after the run)."""
    env = os.environ | {"PYTHONIOENCODING": "ascii"}
    res = subprocess.run(
        [*ILCRIG, "sim", "--iterations", "2", "--out", str(tmp_path / "run")], capture_output=True, env=env, timeout=300
    )
    assert res.returncode == EXIT_OK, res.stderr
    assert res.stderr == b""
    closing = res.stdout.decode("ascii").splitlines()[-1]
    assert f"trace_sha256 {_summary(tmp_path / 'run')['trace_sha256'][:16]}\\u2026; summary: " in closing
