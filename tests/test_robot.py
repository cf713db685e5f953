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
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from cli_util import run_cli
from fs_util import small_tmpfs
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


def test_a_disk_that_fills_ends_the_session_as_a_fault_with_every_record_true(tmp_path: Path) -> None:
    """The run folder on a small filesystem that the session's candump logs fill while a master
    steps the robot: the session ends as a fault (one line naming the log and the error, exit 3),
    the space reserve taken at the start holds the last records — the plant's session, the whole
    trace, the summary saying how it ended — and no process is left."""
    with small_tmpfs(tmp_path / "small", 400) as mnt:
        robot = RobotProcess(mnt / "robot")
        try:
            where = robot.ready()
            sent = 0
            with can.Bus(interface=where["interface"], channel=where["channel"]) as master:
                while robot.proc.poll() is None and sent < 20_000:  # ~1,000 periods of logs fill it
                    try:
                        master.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=b""))
                    except can.CanError:
                        break  # the hub went away with the robot
                    sent += 1
                    time.sleep(0.002)
            code = robot.wait()
        finally:
            robot.kill()
        assert code == 3, (robot.stdout, robot.stderr)
        assert not [pid for pid in where["pids"].values() if pid_alive(pid)]
        (line,) = [ln for ln in robot.stderr if ln.startswith("ilcrig: fault:")]
        assert "No space left on device" in line and "the robot stopped, every process of it ended" in line, line
        summary = json.loads((robot.out / "summary.json").read_text())
        assert summary["exit_code"] == 3
        end = summary["end"]
        assert end["reason"] == "fault" and end["disk_full"] is True and end["records"] in ("io.log", "fieldbus.log"), end
        r = summary["robot"]
        accounted = r["periods"] + r["periods_dropped"] + r["period_in_progress"] + r["syncs_waiting"] + r["syncs_unstepped"]
        assert r["syncs"] == accounted and r["periods"] > 0, r  # the session ended while a master streamed
        assert r["trace"]["error"] is None and r["trace"]["not_written"] == 0, r
        assert len(read_trace(robot.out / "trace.bin").records) == r["trace"]["records"] == r["periods"]
        assert f"{r['periods']} periods stepped" in robot.stdout[-1], robot.stdout[-1]


def test_a_monitor_that_loses_its_bus_ends_the_session_as_a_fault(tmp_path: Path) -> None:
    """The hub drops a reader that stopped reading (an ``ilcrig robot`` stopped with Ctrl-Z for
    long enough: its output buffer overflows) by closing its socket; the launcher, going on, found
    its io log and counts silently ended there. Played here by closing the io monitor's socket from
    outside while the robot runs (the launcher in this process): one fault line, exit 3, the
    summary says which channel's records stopped."""
    import io
    import socket
    import threading

    from clock_util import wait_for

    from host.rig.options import RobotOptions
    from host.rig.robot_launcher import RobotLauncher

    out, err = io.StringIO(), io.StringIO()
    launcher = RobotLauncher(RobotOptions(bus="hub", out=str(tmp_path / "robot")), stdout=out, stderr=err)
    closed: list[bool] = []

    def hub_drops_the_io_monitor() -> None:
        if wait_for(lambda: "Ctrl-C to stop" in out.getvalue(), 180.0):
            monitor = next(m for m in launcher.monitors if m.name == "io")
            monitor.bus._sock.shutdown(socket.SHUT_RDWR)  # type: ignore[attr-defined]  # the hub client's socket
            closed.append(True)

    outsider = threading.Thread(target=hub_drops_the_io_monitor)
    outsider.start()
    try:
        code = launcher.run()
    finally:
        outsider.join(timeout=200)
    assert closed and code == 3, (out.getvalue(), err.getvalue())
    (line,) = err.getvalue().splitlines()
    assert line.startswith("ilcrig: fault: the io channel's monitor lost its bus (") and line.endswith(
        "the session's records would stop there; the robot stopped, every process of it ended"
    ), line
    summary = json.loads((tmp_path / "robot" / "summary.json").read_text())
    assert summary["exit_code"] == 3 and summary["end"]["reason"] == "fault" and summary["end"]["records"] == "io monitor"
    assert not [name for name, pid in summary["processes"].items() if isinstance(pid, int) and pid_alive(pid)]


def test_a_bus_error_frame_the_monitors_hear_is_said_and_counted(robot: RobotProcess) -> None:
    """A frame damaged on the wire (a master's CAN controller sends the error frame; udp_multicast
    reports a datagram lost in the monitor's receiver so): the robot keeps stepping, but its
    candump log and bus counts miss a frame, and the console and the summary say so, once."""
    where = robot.ready()
    with can.Bus(interface=where["interface"], channel=where["channel"]) as master:
        for _ in range(2):
            master.send(can.Message(is_error_frame=True, arbitration_id=0x20000080, is_extended_id=True, data=bytes(8)))
        robot.wait_line(r"ilcrig robot: bus error frame on fieldbus")
    assert robot.stop(signal.SIGINT) == 130
    said = [line for line in robot.stderr if "bus error frame" in line]
    assert said == [
        "ilcrig robot: bus error frame on fieldbus (a frame damaged on the wire, or lost in the monitor's receiver): "
        "fieldbus.log and the bus counts of summary.json miss frames"
    ]
    summary = json.loads((robot.out / "summary.json").read_text())
    assert summary["bus"]["channels"]["fieldbus"]["error_frames"] == 2
    assert summary["bus"]["channels"]["io"]["error_frames"] == 0


#: drive 4's role command in the next test: once the other four nodes booted it puts a bus error
#: frame on the fieldbus (as a frame lost in the launcher's monitor would be reported) and then
#: never boots
_ERROR_THEN_STALL = """
import signal, sys
import can
from bus.transports.config import FIELDBUS, transport_from_name
args = sys.argv[1:]
bus = transport_from_name("hub", args[args.index("--hub") + 1]).open(FIELDBUS)
booted = set()
while booted != {1, 2, 3, 32}:
    msg = bus.recv()
    if msg is not None and not msg.is_error_frame and msg.arbitration_id - 0x700 in (1, 2, 3, 32) and bytes(msg.data) == b"\\x00":
        booted.add(msg.arbitration_id - 0x700)
bus.send(can.Message(is_error_frame=True, arbitration_id=0x20000080, is_extended_id=True, data=bytes(8)))
signal.pause()
"""


def test_a_bus_error_frame_while_the_nodes_boot_ends_the_start_as_a_fault(tmp_path: Path) -> None:
    """A frame lost while the nodes boot may have been a boot-up: the start ends at once as a fault
    (exit 3, one line naming the nodes not heard), not after the 120 s boot wait."""
    script = tmp_path / "error_then_stall.py"
    script.write_text(_ERROR_THEN_STALL)
    robot = RobotProcess(tmp_path / "robot", env={"ILCRIG_ROLE_CMD_DRIVE4": f"{sys.executable} {script}"})
    try:
        assert robot.wait(timeout_s=180) == 3
    finally:
        robot.kill()
    assert robot.stderr == [
        "ilcrig: fault: bus error frame on fieldbus while the nodes booted (frames lost or damaged; the boot-up of "
        "node(s) [4] may be among them); the robot stopped, every process of it ended"
    ]
    summary = json.loads((robot.out / "summary.json").read_text())
    assert summary["end"] == {"reason": "fault", "channel": "fieldbus", "error_frames": 1, "missing_nodes": [4]}
    assert summary["bus"]["channels"]["fieldbus"]["error_frames"] == 1
    assert not [name for name, pid in summary["processes"].items() if isinstance(pid, int) and pid_alive(pid)]


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
