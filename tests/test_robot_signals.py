"""A signal at a random moment of a robot session while a foreign master streams: every record true.

``ilcrig robot`` (hub transport) in a session of its own; once it is ready, the issue's streaming
master (``tests/streaming_master.py``: python canopen maps the PDOs, enables the four drives in CSP
by SDO, then RPDO1 + SYNC every 2–5 ms up to 565 SYNCs) starts beside it, and SIGINT or SIGTERM
reaches the robot at a random delay over the master's sequence (its set-up, its stream, after it).
After each example:

* exit code 128 + n, the summary's ``end`` that signal, no process of the session left; for
  SIGKILL of the launcher (also drawn), the janitor's ``end`` ``launcher_lost`` and the plant's
  session in the summary;
* every SYNC the plant saw is accounted for: ``syncs`` = ``periods`` + ``periods_dropped`` +
  ``period_in_progress`` + ``syncs_waiting`` + ``syncs_unstepped``; no robot fault, no overrun;
* the trace holds exactly the periods stepped, numbered 0, 1, …;
* the channel monitors saw at least the SYNCs the plant saw (``bus.syncs_on_bus``; they stop after
  the plant, so a master that goes on meanwhile adds SYNCs the plant never saw) and no frame was
  lost on the way.

And SIGKILL of the launcher itself, while the robot starts and after a master: the janitor ends
the summary (``launcher_lost``) with the plant's session, and the candump logs hold every frame.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_util import ROOT, start_in_session, wait_gone
from clock_util import wait_for
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from robot_util import RobotProcess

from plant.trace import read_trace

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

#: the delays drawn after the master starts, s: its sequence takes about 2–4 s on a quiet machine
MAX_DELAY_S = 4.0
EXAMPLES = int(os.environ.get("ILCRIG_ROBOT_SIGNAL_EXAMPLES", "4"))
_RUNS = itertools.count()


def _start_master(where: dict[str, Any]) -> subprocess.Popen[str]:
    """The streaming master (seed 1) against the robot announced as ``where``, in a session of its own."""
    argv = [sys.executable, str(ROOT / "tests" / "streaming_master.py"), where["interface"], where["channel"], "1"]
    return start_in_session(argv, env={**os.environ, "PYTHONPATH": str(ROOT)})


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(delay_s=st.floats(0.0, MAX_DELAY_S), signame=st.sampled_from(["SIGINT", "SIGTERM", "SIGKILL"]))
@example(delay_s=2.0, signame="SIGKILL")  # the launcher killed while the master streams, in every run
def test_at_random_a_signal_while_a_master_streams_leaves_every_record_true(tmp_path: Path, delay_s: float, signame: str) -> None:
    """SIGINT / SIGTERM reach the robot's launcher, which ends the session; SIGKILL kills the
    launcher (no handler runs), and the janitor ends the summary with the plant's session."""
    signum = signal.Signals[signame]
    out = tmp_path / f"robot{next(_RUNS)}"
    robot = RobotProcess(out)
    master: subprocess.Popen[str] | None = None
    pids: dict[str, int] = {}
    try:
        where = robot.ready()
        pids = where["pids"]
        master = _start_master(where)
        time.sleep(delay_s)  # the random moment itself
        if signum == signal.SIGKILL:
            robot.proc.kill()
            code = robot.wait()
            janitor_log = out / "logs" / "janitor.log"
            assert wait_for(lambda: "end launcher_lost" in _read(janitor_log), 60.0), _read(janitor_log)
        else:
            code = robot.stop(signum)
    finally:
        robot.kill()
        if master is not None:
            if master.poll() is None:
                os.killpg(master.pid, signal.SIGKILL)
            master.communicate()
    assert wait_gone(list(pids.values()), 30.0) == []
    summary = json.loads((out / "summary.json").read_text())
    if signum == signal.SIGKILL:
        assert code == -signal.SIGKILL
        end = summary["end"]
        assert (end["reason"], end["was"], end["noticed_by"]) == ("launcher_lost", "running", "janitor"), end
        assert summary["exit_code"] is None
    else:
        assert code == 128 + signum, robot.stderr
        assert summary["end"] == {"reason": "interrupted", "signal": signame}
    r = summary["robot"]
    assert r is not None, summary  # the plant's session, also when the janitor wrote it
    assert r["sync_overruns"] == 0, r
    if signum != signal.SIGKILL:
        assert r["fault"] is None and r["faults_total"] == 0, r
    accounted = r["periods"] + r["periods_dropped"] + r["period_in_progress"] + r["syncs_waiting"] + r["syncs_unstepped"]
    assert r["syncs"] == accounted, r
    records = read_trace(out / "trace.bin").records
    assert r["trace"]["records"] == len(records) == r["periods"]
    np.testing.assert_array_equal(records["period"], np.arange(r["periods"]))
    if signum != signal.SIGKILL:  # the janitor keeps the bus counts the launcher last wrote
        bus = summary["bus"]
        assert bus["syncs_on_bus"] >= r["syncs"], (bus["syncs_on_bus"], r["syncs"])
        assert all(ch["error_frames"] == 0 for ch in bus["channels"].values()), bus["channels"]


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


@pytest.mark.parametrize("when", ["starting", "after a master"])
def test_a_killed_robot_launcher_leaves_a_summary_that_says_so(tmp_path: Path, when: str) -> None:
    """SIGKILL of ``ilcrig robot`` itself (no handler runs): the drives die with it, the plant ends
    its session (SIGTERM), and the janitor ends the summary the launcher kept: ``end``
    ``launcher_lost``, what the robot was doing, the plant's session; the candump logs hold every
    frame the monitors had heard (flushed while the robot ran)."""
    out = tmp_path / "robot"
    robot = RobotProcess(out)
    pids: dict[str, int] = {}
    try:
        if when == "starting":
            wait_for(lambda: (out / "summary.json").exists(), 120.0)
        else:
            where = robot.ready()
            pids = where["pids"]
            master = _start_master(where)
            master_out, master_err = master.communicate(timeout=300)
            assert master.returncode == 0, master_err
        robot.proc.kill()
        assert robot.wait() == -signal.SIGKILL
        # the janitor's last act: its log says how the summary ended (the file exists before it is written)
        janitor_log = out / "logs" / "janitor.log"
        assert wait_for(lambda: "end launcher_lost" in _read(janitor_log), 60.0), sorted(p.name for p in (out / "logs").iterdir())
    finally:
        robot.kill()
    assert wait_gone(list(pids.values()), 30.0) == []
    summary = json.loads((out / "summary.json").read_text())
    end = summary["end"]
    assert end["reason"] == "launcher_lost" and end["noticed_by"] == "janitor", end
    assert summary["exit_code"] is None
    assert "end launcher_lost" in janitor_log.read_text(), janitor_log.read_text()
    if when == "starting":
        assert end["was"] == "starting", end
        return
    assert end["was"] == "running", end
    r = summary["robot"]
    assert r is not None and r["syncs"] == r["periods"] == int(master_out.split()[0]) == 565, (r, master_out)
    records = read_trace(out / "trace.bin").records
    assert len(records) == r["periods"], len(records)
    log = (out / "fieldbus.log").read_text().splitlines()
    assert sum(" 080#" in line for line in log) == 565
    cob_ids = {line.split()[2].split("#")[0] for line in log}
    assert cob_ids >= {"701", "702", "703", "704", "720"}, cob_ids  # the boot-ups
