"""``ilcrig robot`` with masters nobody here wrote: the example script (examples/robot_master.py,
python canopen's ``BaseNode402``) powers the robot, homes it, moves it point to point in profile
position and along a pick-and-place in CSP, and stops it with quick stop; the positions it reached
are checked from its TPDOs and from the plant, and the same script run again in process on virtual
buses gives the same period trace.
The session's outputs (summary, trace, candump logs) and Ctrl-C / SIGTERM (130 / 143); a killed
process of the robot: tests/test_fault_matrix.py.

Every wait is for an event (an output line, a frame, a process's exit); every process is cleaned up.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from cli_util import run_cli
from robot_util import DRIVES, RobotProcess, check_pick_and_place, pid_alive, run_example, run_example_in_process

from bus.canlog import read_log
from bus.objects import DRIVE_EDS_PATH
from plant.kinematics import inverse_kinematics
from plant.trace import read_trace, trace_digest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[RobotProcess]:
    r = RobotProcess(tmp_path / "robot", env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    try:
        yield r
    finally:
        r.kill()


def test_python_canopen_master_homes_moves_and_quick_stops_the_robot_deterministically(
    robot: RobotProcess, tmp_path: Path
) -> None:
    where = robot.ready()
    res = run_example(where["interface"], where["channel"], tmp_path)
    check_pick_and_place(res)

    assert robot.stop(signal.SIGTERM) == 143
    out = robot.out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["schema"] == "ilcrig.robot/1" and summary["end"]["reason"] == "interrupted"
    session = summary["robot"]
    assert session["periods"] == res["periods_total"] == session["syncs"]  # one period per SYNC, none lost
    assert session["faults"] == [] and session["state"] == "ready" and session["brakes"] == 0xF  # disabled: braked
    assert summary["bus"]["syncs_on_bus"] == session["syncs"]
    trace = read_trace(out / "trace.bin")
    assert len(trace.records) == session["periods"] and trace.ts_s == 1e-3
    # the streamed periods are in the trace: the robot passed over the pick and the place points
    z = np.array([inverse_kinematics(np.array([x, y, -0.68, th])) for x, y, th in ((-0.1, 0, 0), (0.1, 0.05, np.pi / 2))])
    for q in z:
        assert np.abs(trace.q_rad - q).max(axis=1).min() < 0.005
    assert any(msg.arbitration_id == 0x080 for msg in read_log(out / "fieldbus.log"))
    encoder_frames = sum(1 for msg in read_log(out / "io.log") if msg.arbitration_id == 0x101)
    assert encoder_frames == session["periods"]
    for name in ("plant", "drive1", "drive2", "drive3", "drive4"):
        assert "Traceback" not in (out / "logs" / f"{name}.log").read_text()
    # the same master script, in this process on virtual buses (homing method 35 instead of 37):
    # the same robot, period for period
    again, digest = run_example_in_process(tmp_path / "again", homing_method=35)
    assert again == res
    assert digest == trace_digest(trace.records)


def readme_master() -> str:
    """The python block of the README's section "Drive the robot from your own master"."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Drive the robot from your own master") :]
    return section[section.index("```python\n") + len("```python\n") : section.index("\n```\n")]


def test_the_readme_master_lowers_the_tool(robot: RobotProcess, tmp_path: Path) -> None:
    where = robot.ready()
    script = tmp_path / "master.py"
    script.write_text(readme_master())
    done = subprocess.run(
        [sys.executable, str(script), where["channel"], str(DRIVE_EDS_PATH)], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    import canopen

    net = canopen.Network()
    net.connect(interface=where["interface"], channel=where["channel"])
    try:
        plant = net.add_node(32, canopen.ObjectDictionary())
        tcp = [int.from_bytes(plant.sdo.upload(0x2452, j), "little", signed=True) * 1e-6 for j in (1, 2, 3, 4)]
    finally:
        net.disconnect()
    np.testing.assert_allclose(tcp[:3], (0.0, 0.0, -0.67), atol=1.5e-3)


def test_ctrl_c_stops_every_process_with_130(robot: RobotProcess) -> None:
    pids = robot.ready()["pids"]
    assert robot.stop(signal.SIGINT) == 130
    assert robot.stderr == ["ilcrig: interrupted (SIGINT); stopping 6 processes"]  # the hub, the plant, four drives
    assert not [name for name, pid in pids.items() if pid_alive(pid)]
    summary = json.loads((robot.out / "summary.json").read_text())
    assert summary["end"] == {"reason": "interrupted", "signal": "SIGINT"}
    assert summary["robot"]["periods"] == 0 and summary["robot"]["brakes"] == 0xF
    assert set(DRIVES) <= {int(n[-1]) for n in pids if n.startswith("drive")}


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--bus", "virtual"], "--bus virtual: the virtual transport works inside one process only"),
        (["--rt-priority", "5"], "--rt-priority 5: the priority of a real-time robot; add --realtime"),
        (["--no-idle-poll"], "--no-idle-poll: the CPUs are kept awake only in real time; add --realtime"),
        (["--bus", "nosuch"], "nosuch"),
        (["--param-dir", __file__], f"--param-dir {__file__}: not a folder"),
    ],
)
def test_bad_input_is_one_line_and_exit_2_before_anything_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, argv: list[str], message: str
) -> None:
    code, out, err = run_cli(capsys, "robot", "--out", str(tmp_path / "robot"), *argv)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("ilcrig: error: ") and message in err
    assert not (tmp_path / "robot").exists()
