"""A signal at a random moment of a robot session while a foreign master streams: every record true.

``ilcrig robot`` (hub transport) in a session of its own; once it is ready, the issue's streaming
master (``tests/streaming_master.py``: python canopen maps the PDOs, enables the four drives in CSP
by SDO, then RPDO1 + SYNC every 2–5 ms up to 565 SYNCs) starts beside it, and SIGINT or SIGTERM
reaches the robot at a random delay over the master's sequence (its set-up, its stream, after it).
After each example:

* exit code 128 + n, the summary's ``end`` that signal, no process of the session left;
* every SYNC the plant saw is accounted for: ``syncs`` = ``periods`` + ``periods_dropped`` +
  ``period_in_progress`` + ``syncs_waiting`` + ``syncs_unstepped``; no robot fault, no overrun;
* the trace holds exactly the periods stepped, numbered 0, 1, …;
* the channel monitors saw at least the SYNCs the plant saw (``bus.syncs_on_bus``; they stop after
  the plant, so a master that goes on meanwhile adds SYNCs the plant never saw) and no frame was
  lost on the way.
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

import numpy as np
import pytest
from cli_util import ROOT, start_in_session, wait_gone
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from robot_util import RobotProcess

from plant.trace import read_trace

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

#: the delays drawn after the master starts, s: its sequence takes about 2–4 s on a quiet machine
MAX_DELAY_S = 4.0
EXAMPLES = int(os.environ.get("ILCRIG_ROBOT_SIGNAL_EXAMPLES", "4"))
_RUNS = itertools.count()


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(delay_s=st.floats(0.0, MAX_DELAY_S), signum=st.sampled_from([signal.SIGINT, signal.SIGTERM]))
def test_at_random_a_signal_while_a_master_streams_leaves_every_record_true(tmp_path: Path, delay_s: float, signum: int) -> None:
    out = tmp_path / f"robot{next(_RUNS)}"
    robot = RobotProcess(out)
    master: subprocess.Popen[str] | None = None
    pids: dict[str, int] = {}
    try:
        where = robot.ready()
        pids = where["pids"]
        master = start_in_session(
            [sys.executable, str(ROOT / "tests" / "streaming_master.py"), where["interface"], where["channel"], "1"],
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        time.sleep(delay_s)  # the random moment itself
        code = robot.stop(signum)
    finally:
        robot.kill()
        if master is not None:
            if master.poll() is None:
                os.killpg(master.pid, signal.SIGKILL)
            master.communicate()
    assert code == 128 + signum, robot.stderr
    assert wait_gone(list(pids.values()), 10.0) == []
    summary = json.loads((out / "summary.json").read_text())
    assert summary["end"] == {"reason": "interrupted", "signal": signal.Signals(signum).name}
    r = summary["robot"]
    assert r["fault"] is None and r["faults_total"] == 0 and r["sync_overruns"] == 0, r
    accounted = r["periods"] + r["periods_dropped"] + r["period_in_progress"] + r["syncs_waiting"] + r["syncs_unstepped"]
    assert r["syncs"] == accounted, r
    records = read_trace(out / "trace.bin").records
    assert r["trace"]["records"] == len(records) == r["periods"]
    np.testing.assert_array_equal(records["period"], np.arange(r["periods"]))
    bus = summary["bus"]
    assert bus["syncs_on_bus"] >= r["syncs"], (bus["syncs_on_bus"], r["syncs"])
    assert all(ch["error_frames"] == 0 for ch in bus["channels"].values()), bus["channels"]
