"""The C firmware (``--firmware c``) in the multi-process rig and in a robot session: the same
results as the Python firmware, bit for bit (full tier).

* ``ilcrig run --firmware c``: four drive processes running the C core give the trace digest of
  the in-process experiment with the Python firmware (which ``ilcrig run`` with it gives too,
  tests/test_rig.py), and the summary records the firmware;
* the robot: examples/robot_master.py's session (homing, profile position, a CSP stream, quick
  stop) against the virtual robot (tests/robot_util.py: the plant node and four drive nodes in this
  process on virtual buses, SYNC-stepped) gives the same period trace with both firmwares.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import pytest
import robot_util
from cli_util import run_in_session

from firmware_model.drive import Drive
from firmware_model.firmware_select import c_available
from host.experiment.config import build_config
from host.experiment.plan import prepare
from host.experiment.trial_loop import run_experiment
from host.sim.inprocess import InProcessBench

pytestmark = [
    pytest.mark.multiprocess,
    pytest.mark.slow,
    pytest.mark.skipif(not c_available(), reason="the C firmware (firmware_model._fwcore) is not built"),
]

EXP = ["--iterations", "2", "--cycle", "0.15", "--disturbance", "both", "--seed", "3"]
EXP_CFG = {"iterations": 2, "cycle_s": 0.15, "disturbance": "both", "seed": 3}
REPO = Path(__file__).resolve().parent.parent


def test_rig_with_the_c_firmware_gives_the_python_digest(tmp_path: Path) -> None:
    cfg = build_config(None, EXP_CFG)
    python = run_experiment(prepare(cfg), InProcessBench(cfg, "python"), None, mode="sim").summary["trace_sha256"]
    out = tmp_path / "rig"
    res = run_in_session(
        [sys.executable, "-m", "host.cli", "run", *EXP, "--bus", "hub", "--firmware", "c", "--out", str(out)],
        300.0,
        REPO,
        what="rig",
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] is True and s["faults"] == []
    assert s["trace_sha256"] == python
    assert s["bench"]["firmware"] == "c"


def test_robot_csp_session_gives_the_same_trace_with_both_firmwares(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    results = {}
    for firmware in ("python", "c"):
        monkeypatch.setattr(robot_util, "Drive", functools.partial(Drive, firmware=firmware))
        results[firmware] = robot_util.run_example_in_process(tmp_path / firmware)
    (res_py, digest_py), (res_c, digest_c) = results["python"], results["c"]
    robot_util.check_pick_and_place(res_c)
    assert res_c == res_py
    assert digest_c == digest_py
