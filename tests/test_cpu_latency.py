"""The PM QoS CPU latency request of a real-time session (host/rig/cpu_latency.py): what it writes,
that Linux has it in force while the file is held and drops it when the holder closes it or dies,
every reason it is left out, and the record a launcher keeps of it."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from cli_util import wait_gone
from clock_util import wait_for
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from host.rig import cpu_latency
from host.rig.cpu_latency import CPU_LATENCY_PATH, CpuLatencyRequest, cpu_latency_target_us, request_cpu_latency
from host.rig.realtime import scheduling_mechanisms, scheduling_text


def _device_writable() -> bool:
    return os.path.exists(CPU_LATENCY_PATH) and os.access(CPU_LATENCY_PATH, os.W_OK)


# alone: the kernel's CPU latency target is the machine's, and a real-time run beside it would hold it (pyproject.toml)
pytestmark = pytest.mark.alone

needs_device = pytest.mark.skipif(not _device_writable(), reason=f"{CPU_LATENCY_PATH} missing or not writable (root's)")


def test_the_request_is_a_native_s32_of_the_latency_written_once(tmp_path: Path) -> None:
    path = tmp_path / "qos"
    path.write_bytes(b"")
    request = CpuLatencyRequest(0, str(path))
    assert request.held and path.read_bytes() == struct.pack("=i", 0)
    request.release()
    request.release()  # again: nothing
    assert not request.held
    with pytest.raises(ValueError, match="latency_us"):
        CpuLatencyRequest(-1, str(path))


def test_every_reason_the_request_is_left_out_is_recorded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert request_cpu_latency(frozenset(), True) == (None, {"reason": "--no-idle-poll"})
    assert request_cpu_latency(frozenset({"cpu-latency"}), False) == (None, {"reason": "ILCRIG_RT_WITHOUT=cpu-latency"})
    missing = str(tmp_path / "none")
    assert request_cpu_latency(frozenset(), False, missing) == (None, {"reason": f"this system has no {missing}"})
    device = tmp_path / "qos"
    device.write_bytes(b"")

    def refused(*_args: object) -> int:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(cpu_latency.os, "open", refused)
    assert request_cpu_latency(frozenset(), False, str(device)) == (None, {"reason": "not permitted (root's)"})


def test_the_record_names_the_mechanism_in_both_scheduling_classes() -> None:
    held = {"policy": "normal", "reason": "--rt-priority 0", "roles": ["plant"], "fair": {"slice_us": 100.0}}
    held |= {"idle_poll": {"loops": 0, "reason": "not beside normal scheduling"}, "cpu_latency": {"latency_us": 0}}
    assert scheduling_mechanisms(held) == ["scheduler slice 100 µs", "idle CPUs polling (PM QoS 0 µs)"]
    text = scheduling_text(held)
    assert ", no SCHED_IDLE busy loops (not beside normal scheduling), idle CPUs polling (PM QoS CPU latency 0 µs)" in text
    refused = held | {"cpu_latency": {"reason": "not permitted (root's)"}}
    assert scheduling_mechanisms(refused) == ["scheduler slice 100 µs"]
    text = scheduling_text(refused)
    assert ", idle CPUs may halt (not beside normal scheduling), no PM QoS CPU latency request (not permitted (root's))" in text


@needs_device
def test_linux_has_the_request_in_force_while_held_and_drops_it_when_the_holder_dies() -> None:
    """Read back from the device: 0 µs while a request holds it; the target before it again after
    :meth:`CpuLatencyRequest.release`, and after the holder is killed with SIGKILL (nothing outlives
    a launcher, however it ends). Another holder on the machine (a ``tuned`` profile, a running
    ``cyclictest``) makes the target 0 already: nothing to see then."""
    before = cpu_latency_target_us()
    if before == 0:
        pytest.skip("another PM QoS request holds the CPU latency at 0 µs")
    request = CpuLatencyRequest(0)
    try:
        assert cpu_latency_target_us() == 0
    finally:
        request.release()
    assert cpu_latency_target_us() == before
    code = "from host.rig.cpu_latency import CpuLatencyRequest as R; r = R(0); print('held', flush=True); input()"
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        assert cpu_latency_target_us() == 0
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
        deadline = time.monotonic() + 30
        while cpu_latency_target_us() != before and time.monotonic() < deadline:
            time.sleep(0.01)  # the kernel closes a killed process's files as it exits
        assert cpu_latency_target_us() == before
    finally:
        holder.kill()
        holder.wait()


def children_of(pid: int) -> list[int]:
    """The child processes of ``pid`` (none once it has ended)."""
    try:
        return [int(k) for k in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


#: who is signalled in a real-time robot session: the launcher, or one of the processes it started
ROBOT_TARGETS = ("launcher", "hub", "plant", "drive1", "drive2", "drive3", "drive4")
SIGNALS = {"SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM, "SIGKILL": signal.SIGKILL}


@pytest.mark.slow
@pytest.mark.multiprocess
@needs_device
@settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(who=st.sampled_from(ROBOT_TARGETS), signame=st.sampled_from(sorted(SIGNALS)), starting=st.booleans())
@example(who="launcher", signame="SIGKILL", starting=False)
@example(who="launcher", signame="SIGINT", starting=True)
@example(who="drive3", signame="SIGTERM", starting=False)
@example(who="hub", signame="SIGINT", starting=False)  # the hub's end, not a drive that lost its bus with it
def test_however_a_real_time_robot_ends_the_request_ends_with_it(who: str, signame: str, starting: bool) -> None:
    """``ilcrig robot --realtime --rt-priority 0`` (an ordinary user's scheduling, the request held)
    ended by a drawn signal to the launcher (at its announcement, or while it starts up: as soon as
    it has started its first process) or to one of its processes (at the announcement): it ends in time with the
    exit code the signal calls for, no process of it is left, the summary says how it ended, and the
    kernel's CPU latency target is what it was before the session."""
    from robot_util import RobotProcess  # the robot's test helpers (tests/robot_util.py: canopen, numpy)

    before = cpu_latency_target_us()
    if before == 0:
        pytest.skip("another PM QoS request holds the CPU latency at 0 µs")
    out = Path(tempfile.mkdtemp(prefix="ilcrig-rt-ends-"))
    robot = RobotProcess(out / "robot", "--realtime", "--rt-priority", "0", env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    sig = SIGNALS[signame]
    try:
        pids: dict[str, int] = {}
        if who == "launcher" and starting:
            # it has started its first process (the hub); the rest are coming up
            assert wait_for(lambda: bool(children_of(robot.proc.pid)) or robot.proc.poll() is not None, 180.0)
            assert robot.proc.poll() is None, robot.stderr
        else:
            pids = robot.ready()["pids"]
            assert cpu_latency_target_us() == 0  # held for the session
        os.kill(robot.proc.pid if who == "launcher" else pids[who], sig)
        code = robot.wait(timeout_s=120)
        assert cpu_latency_target_us() == before
        # its processes end with it (after a launcher killed outright, by the death signal it armed in each)
        assert wait_gone(list(pids.values()), 30.0) == [], pids
        summary_path = out / "robot" / "summary.json"
        if who == "launcher" and sig == signal.SIGKILL:
            assert code == -signal.SIGKILL  # nothing of it may speak; the kernel dropped the request
            return
        if who == "launcher":
            assert code == {"SIGINT": 130, "SIGTERM": 143}[signame], robot.stderr
            summary = json.loads(summary_path.read_text())  # a session stopped while it starts up says so too
            assert summary["end"] == {"reason": "interrupted", "signal": signame}
            assert summary["exit_code"] == code
            # the console says what happened: the signal on stderr, how the session ended on stdout
            assert len(robot.stderr) == 1 and re.fullmatch(
                rf"ilcrig: interrupted \({signame}\); stopping [0-6] processes", robot.stderr[0]
            ), robot.stderr
            closing = robot.stdout[-1]
            if starting:
                assert closing.startswith(f"ilcrig robot: interrupted ({signame}) before the robot was ready: no period stepped")
            else:
                assert robot.stderr[0].endswith("stopping 6 processes")  # the hub, the plant, four drives
                assert re.match(r"ilcrig robot: \d+ periods stepped", closing), closing
        else:
            assert code == 3, robot.stderr  # one of its processes ended under it: a fault
            summary = json.loads(summary_path.read_text())
            assert summary["exit_code"] == 3 and summary["end"]["process"] == who
            assert [line for line in robot.stderr if line.startswith("ilcrig: fault:")], robot.stderr
    finally:
        robot.kill()
        shutil.rmtree(out, ignore_errors=True)
