"""A signal at a random moment of a user command's start: said in one line, exit 128 + n, nothing left.

``ilcrig run`` and ``ilcrig robot`` as a user starts them (a session of their own, as a terminal
would); SIGINT or SIGTERM comes at a random delay after the command holds its signals — the moment
its ``/proc/<pid>/status`` shows SIGTERM caught, :func:`host.cli.main`'s first statement — over the
imports of the command modules, the parsing, the planning, the processes' start and the nodes'
boot. Before the fix a SIGINT there printed Python's traceback and a SIGTERM ended the command
silently (killed by the signal, nothing said). After each example:

* exit code 128 + n, and stderr's first line ``ilcrig: interrupted (SIGNAME)…``;
* no traceback on stdout or stderr;
* no process the command started is left (every one carries the example's environment tag);
* no run folder, or one whose summary says that signal interrupted it.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import time
import uuid
from pathlib import Path

import pytest
from cli_util import ilcrig_argv, start_in_session, wait_gone
from clock_util import wait_for
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

#: the delays drawn after the command holds its signals, s: its start-up (imports, planning, the
#: processes' start, the nodes' boot) takes several seconds on a quiet 2-core machine
MAX_DELAY_S = 3.0
#: examples per run of the test (CI: 8; a long run: ``ILCRIG_START_SIGNAL_EXAMPLES=200``)
EXAMPLES = int(os.environ.get("ILCRIG_START_SIGNAL_EXAMPLES", "8"))
#: the environment variable every process of an example carries (children inherit it)
TAG = "ILCRIG_TEST_START_TAG"
_RUNS = itertools.count()
#: the command lines under test, after ``ilcrig``
COMMANDS = {
    "run": ["run", "--iterations", "2", "--cycle", "0.15", "--bus", "hub"],
    "robot": ["robot"],
}


def _catches_sigterm(pid: int) -> bool:
    """Whether process ``pid`` has a handler for SIGTERM (its status's SigCgt mask)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    for line in status.splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


def _tagged(tag: str) -> list[int]:
    """Live processes whose environment holds ``TAG=tag``."""
    needle = f"{TAG}={tag}".encode()
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if needle in (d / "environ").read_bytes().split(b"\0") and " Z " not in (d / "stat").read_text():
                found.append(int(d.name))
        except OSError:
            continue
    return found


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(
    command=st.sampled_from(sorted(COMMANDS)),
    delay_s=st.floats(0.0, MAX_DELAY_S),
    signum=st.sampled_from([signal.SIGINT, signal.SIGTERM]),
)
def test_at_random_a_signal_while_a_command_starts_is_said_and_leaves_nothing(
    tmp_path: Path, command: str, delay_s: float, signum: int
) -> None:
    out = tmp_path / f"{command}{next(_RUNS)}"
    tag = uuid.uuid4().hex
    proc = start_in_session(ilcrig_argv(*COMMANDS[command], "--out", str(out)), env={**os.environ, TAG: tag})
    try:
        # main() holds the signals from its first statement
        assert wait_for(lambda: _catches_sigterm(proc.pid) or proc.poll() is not None, 60.0)
        assert proc.poll() is None, proc.communicate()
        time.sleep(delay_s)  # the random moment itself
        os.kill(proc.pid, signum)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
        left = wait_gone(_tagged(tag), 10.0)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, (proc.returncode, stdout[-2000:], stderr[-2000:])
    assert stderr.startswith(f"ilcrig: interrupted ({name})"), stderr[-2000:]
    assert "Traceback" not in stdout + stderr, stderr[-4000:]
    assert left == [], left
    if out.exists():
        summary = json.loads((out / "summary.json").read_text())
        marker = summary["end"] if command == "robot" else summary["interrupted"]
        assert marker["signal"] == name, marker
        if command == "run":
            assert summary["end_reason"] == "interrupted" and summary["completed"] is False
