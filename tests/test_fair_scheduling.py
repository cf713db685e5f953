"""Real time without privileges (host/rig/fair_scheduling.py, bus/lockstep_process.py): where SCHED_FIFO
is not in force the lockstep processes get a short scheduler slice (as the kernel then reports it),
a lower nice only within RLIMIT_NICE, the host SCHED_BATCH (not when it produces the SYNC), the
plant sleeps instead of spinning, the roles freeze their heap; each mechanism can be left out, and
the record and the console line say what was in force."""

from __future__ import annotations

import ctypes
import gc
import io
import json
import logging
import os
import platform
import struct
import subprocess
import sys
from pathlib import Path

import can
import pytest
from clock_util import ManualClock
from test_plant_node import PlantBox, fake_disturbance, request_paced_trial

from bus.lockstep_process import (
    WITHOUT_ENV,
    in_realtime_class,
    mechanisms_left_out,
    spin_in_this_class,
    watch_collections,
)
from bus.plant_objects import TrialTiming
from host.rig import fair_scheduling, realtime, role_commands
from host.rig.fair_scheduling import LOCKSTEP_SLICE_NS, apply_fair_scheduling, host_policy, lowest_nice_permitted
from host.rig.launcher import RigLauncher
from host.rig.options import RobotOptions, RunOptions
from host.rig.processes import Child, spawn, terminate
from host.rig.realtime import schedule_lockstep, scheduling_mechanisms, scheduling_text, timing_line, timing_summary
from host.rig.robot_launcher import RobotLauncher
from plant.plant_node import PlantNode

REPO = Path(__file__).resolve().parent.parent


def _sched_runtime_ns(tid: int) -> int | None:
    """The scheduler slice the kernel reports for ``tid`` (``sched_getattr``), None where unknown."""
    number = {"x86_64": 315, "aarch64": 275}.get(platform.machine())
    if number is None or not sys.platform.startswith("linux"):
        return None
    buf = ctypes.create_string_buffer(56)
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(ctypes.c_long(number), ctypes.c_int(tid), buf, ctypes.c_uint(56), ctypes.c_uint(0)) != 0:
        return None
    return int(struct.unpack("IIQiIQQQII", buf.raw)[5])


def test_the_left_out_mechanisms_are_read_from_the_environment() -> None:
    assert mechanisms_left_out({}) == frozenset()
    assert mechanisms_left_out({WITHOUT_ENV: " slice, gc ,,host"}) == {"slice", "gc", "host"}


def test_without_fifo_the_lockstep_threads_get_a_short_slice(sleeper: subprocess.Popen[bytes]) -> None:
    got = schedule_lockstep({"plant": sleeper.pid}, 0, frozenset())
    assert (got["policy"], got["reason"], got["roles"]) == ("normal", "--rt-priority 0", ["plant"])
    tids = [int(t) for t in os.listdir(f"/proc/{sleeper.pid}/task")]
    if "slice_us" in got["fair"]:  # Linux >= 6.12: the kernel reports the slice of every thread
        assert got["fair"]["slice_us"] == LOCKSTEP_SLICE_NS / 1000
        assert {_sched_runtime_ns(t) for t in tids} == {LOCKSTEP_SLICE_NS}
        assert "scheduler slice 100 µs" in scheduling_mechanisms(got)
        assert "lockstep processes (plant) with a 100 µs scheduler slice" in scheduling_text(got)
    else:
        assert got["fair"]["slice"].startswith("not available")
    assert all(os.sched_getscheduler(t) == os.SCHED_OTHER for t in tids)


def test_a_mechanism_left_out_is_not_applied_and_the_record_says_so(
    sleeper: subprocess.Popen[bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[int, int, int | None]] = []
    monkeypatch.setattr(fair_scheduling, "set_fair_slice", lambda tid, ns, nice=None: calls.append((tid, ns, nice)))
    got = apply_fair_scheduling({"plant": sleeper.pid}, frozenset({"slice", "nice"}))
    assert calls == []
    assert got == {"slice": f"left out ({WITHOUT_ENV})", "nice": f"left out ({WITHOUT_ENV})"}


def test_nice_is_lowered_only_as_far_as_rlimit_nice_permits(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(fair_scheduling.resource, "getrlimit", lambda what: (0, 0))
    assert lowest_nice_permitted() == 20  # the usual limit: nothing below the current value
    monkeypatch.setattr(fair_scheduling.resource, "getrlimit", lambda what: (25, 25))
    assert lowest_nice_permitted() == -5

    calls: list[tuple[int, int, int | None]] = []
    groups: list[tuple[int, int]] = []
    monkeypatch.setattr(fair_scheduling, "set_fair_slice", lambda tid, ns, nice=None: calls.append((tid, ns, nice)))
    monkeypatch.setattr(fair_scheduling, "set_autogroup_nice", lambda pid, nice: groups.append((pid, nice)))
    monkeypatch.setattr(fair_scheduling, "threads", lambda pid: [pid, pid + 1])
    monkeypatch.setattr(fair_scheduling, "autogroups_enabled", lambda: True)
    got = apply_fair_scheduling({"hub": 100, "plant": 200})
    assert got == {"slice_us": LOCKSTEP_SLICE_NS / 1000, "nice": -5}
    assert calls == [(t, LOCKSTEP_SLICE_NS, -5) for t in (100, 101, 200, 201)]
    assert groups == [(100, -5), (200, -5)]
    assert "nice -5" in scheduling_mechanisms({"policy": "normal", "fair": got})

    monkeypatch.setattr(fair_scheduling.resource, "getrlimit", lambda what: (0, 0))
    calls.clear()
    got = apply_fair_scheduling({"plant": 200})
    assert got["nice"] == "0 (RLIMIT_NICE 0 permits no lower value)"
    assert calls == [(t, LOCKSTEP_SLICE_NS, None) for t in (200, 201)]


def test_the_host_is_batch_unless_it_produces_the_sync_and_spawn_starts_it_so(tmp_path: Path) -> None:
    assert host_policy(False) == {"policy": "SCHED_BATCH"}
    assert host_policy(True) == {"policy": "normal", "reason": "its SYNC producer is part of every tick"}
    assert host_policy(False, frozenset({"host"})) == {"policy": "normal", "reason": f"left out ({WITHOUT_ENV})"}
    code = "import os, threading; t = threading.Thread(target=lambda: print(os.sched_getscheduler(0))); t.start(); t.join()"
    child = spawn("host", [sys.executable, "-c", code], tmp_path / "host.log", batch=True)
    try:
        assert child.proc.wait(timeout=60) == 0
    finally:
        terminate([child], 1.0, lambda: False)
    assert (tmp_path / "host.log").read_text().strip() == str(os.SCHED_BATCH)  # the thread it started too


def _refuse_fifo(monkeypatch: pytest.MonkeyPatch) -> None:
    """SCHED_FIFO not permitted (an ordinary user without CAP_SYS_NICE or RLIMIT_RTPRIO), whoever runs the test."""
    real = os.sched_setscheduler

    def refuse(tid: int, policy: int, param: os.sched_param) -> None:
        if policy == os.SCHED_FIFO:
            raise PermissionError(1, "Operation not permitted")
        real(tid, policy, param)

    monkeypatch.setattr(realtime.os, "sched_setscheduler", refuse)


@pytest.mark.parametrize("command", ["run", "robot"])
def test_both_launchers_take_the_fair_scheduling_fallback_without_sched_fifo(
    command: str, sleeper: subprocess.Popen[bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The launch core schedules ``ilcrig run --realtime`` and ``ilcrig robot --realtime`` alike:
    no SCHED_FIFO, then the lockstep processes in fair scheduling and no busy loops; the host's
    policy only where there is a host."""
    _refuse_fifo(monkeypatch)
    launcher = RigLauncher(RunOptions(realtime=True)) if command == "run" else RobotLauncher(RobotOptions(realtime=True))
    launcher.children.append(Child("plant", sleeper, ["sleeper"]))
    try:
        got = launcher.schedule_realtime(host_in_tick=False if command == "run" else None)
    finally:
        if launcher._cpu_latency is not None:  # the PM QoS request, where root: not past the test
            launcher._cpu_latency.release()
    assert got["policy"] == "normal" and got["reason"].startswith("SCHED_FIFO 10 not permitted")
    assert got["roles"] == ["plant"]
    assert "slice_us" in got["fair"] or got["fair"]["slice"].startswith("not available")
    assert got["idle_poll"] == {"loops": 0, "reason": "not beside normal scheduling"}
    assert got["cpu_latency"] in ({"latency_us": 0}, {"reason": "not permitted (root's)"})  # beside normal scheduling too
    assert ("host" in got) is (command == "run")
    assert all(os.sched_getscheduler(int(t)) == os.SCHED_OTHER for t in os.listdir(f"/proc/{sleeper.pid}/task"))


def test_ilcrig_robot_realtime_without_sched_fifo_permission_takes_the_fair_scheduling_fallback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ilcrig robot --realtime`` (the robot launcher on a private hub, its roles sleeping stand-ins
    whose boot is not waited for): where SCHED_FIFO is refused the robot's summary records the
    fair-scheduling fallback, as ``ilcrig run --realtime``'s does."""
    _refuse_fifo(monkeypatch)
    stand_in = [sys.executable, "-c", "import time; time.sleep(60)"]
    monkeypatch.setattr(role_commands, "ROLE_COMMAND", {"plant": stand_in, "drive": stand_in})
    monkeypatch.setattr(RobotLauncher, "_wait_booted", lambda self: None)
    monkeypatch.setattr(RobotLauncher, "_watch", lambda self: 0)
    out = tmp_path / "robot"
    said = io.StringIO()
    launcher = RobotLauncher(RobotOptions(bus="hub", out=str(out), realtime=True), stdout=said, stderr=io.StringIO())
    assert launcher.run() == 0
    assert all(c.proc.returncode is not None for c in launcher.children)
    summary = json.loads((out / "summary.json").read_text())
    scheduling = summary["scheduling"]
    assert scheduling["policy"] == "normal" and "not permitted" in scheduling["reason"]
    assert scheduling["roles"] == ["hub", "plant", "drive1", "drive2", "drive3", "drive4"]
    assert "fair" in scheduling and "host" not in scheduling
    assert scheduling["idle_poll"] == {"loops": 0, "reason": "not beside normal scheduling"}
    assert scheduling["mechanisms"] == scheduling_mechanisms(scheduling)
    # the ready lines say it too, as ilcrig run --realtime's timing line does
    assert f"  scheduling: {scheduling_text(scheduling)}\n" in said.getvalue()
    assert "scheduling: normal scheduling (SCHED_FIFO 10 not permitted" in said.getvalue()


def test_the_console_line_names_every_mechanism_in_force() -> None:
    record = {
        "policy": "normal",
        "reason": "SCHED_FIFO 10 not permitted (Operation not permitted; needs CAP_SYS_NICE or RLIMIT_RTPRIO >= 10)",
        "roles": ["hub", "plant"],
        "fair": {"slice_us": 100.0, "nice": "0 (RLIMIT_NICE 0 permits no lower value)"},
        "host": {"policy": "SCHED_BATCH"},
        "idle_poll": {"loops": 0, "reason": "not beside normal scheduling"},
        "in_roles": {"heap_frozen": True, "timer_slack_ns": 1000, "plant_spins": False},
    }
    line = timing_line(timing_summary([TrialTiming(True, 501, 501_000, 0, 50, 200, 400)], 1e-3, True, record))
    assert line.endswith(
        "; normal scheduling (SCHED_FIFO 10 not permitted (Operation not permitted; needs CAP_SYS_NICE or RLIMIT_RTPRIO"
        " >= 10)): lockstep processes (hub, plant) with a 100 µs scheduler slice, nice 0 (RLIMIT_NICE 0 permits no lower"
        " value), host in SCHED_BATCH, idle CPUs may halt (not beside normal scheduling), heap frozen, timer slack 1 µs,"
        " plant sleeps until each tick is due"
    )
    assert scheduling_mechanisms(record) == [
        "scheduler slice 100 µs",
        "host in SCHED_BATCH",
        "heap frozen (gc)",
        "timer slack 1 µs",
        "plant sleeps until each tick is due",
    ]
    fifo = {"policy": "SCHED_FIFO", "priority": 10, "roles": ["plant"], "idle_poll": {"loops": 2}}
    fifo["in_roles"] = {"heap_frozen": True, "timer_slack_ns": 1000, "plant_spins": True}
    assert scheduling_mechanisms(fifo) == ["SCHED_FIFO 10", "2 SCHED_IDLE busy loops", "heap frozen (gc)", "timer slack 1 µs"]


def test_the_plant_sleeps_until_a_paced_tick_when_it_may_not_spin() -> None:
    """spin_when False: the select loop's deadline is the due time itself, and a wake-up before it
    sends nothing and reads the clock no more than once."""
    clock = ManualClock(100.0)
    fb = can.Bus(interface="virtual", channel="fair-fb")
    io = can.Bus(interface="virtual", channel="fair-io")
    drives = can.Bus(interface="virtual", channel="fair-io")
    bench = PlantNode(
        fb, io, plant_factory=PlantBox(), disturbance_fn=fake_disturbance, clock=clock, spin_s=200e-6, spin_when=lambda: False
    )
    try:
        request_paced_trial(bench, 2)
        bench.step(0.0)
        assert bench.next_deadline() == pytest.approx(100.001)  # not 100.001 - 200 µs
        while drives.recv(timeout=0) is not None:
            pass
        clock.now = 100.0009  # inside what would be the spin window: nothing goes out
        bench.step(0.0)
        assert drives.recv(timeout=0) is None
        clock.now = 100.001
        bench.step(0.0)
        msg = drives.recv(timeout=0)
        assert msg is not None and msg.arbitration_id != 0
    finally:
        for bus in (fb, io, drives):
            bus.shutdown()


def test_a_process_spins_only_in_a_real_time_class(monkeypatch: pytest.MonkeyPatch) -> None:
    assert in_realtime_class() is (os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR))
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: os.SCHED_OTHER)
    monkeypatch.delenv(WITHOUT_ENV, raising=False)
    assert not spin_in_this_class()
    monkeypatch.setenv(WITHOUT_ENV, "sleep-wait")
    assert spin_in_this_class()
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: os.SCHED_FIFO)
    monkeypatch.delenv(WITHOUT_ENV)
    assert spin_in_this_class()


@pytest.mark.parametrize(("without", "frozen"), [("", True), ("gc", False)])
def test_a_role_freezes_its_heap_unless_left_out(without: str, frozen: bool) -> None:
    code = "import gc; from bus.lockstep_process import freeze_heap; print(freeze_heap('drive 1'), gc.get_freeze_count() > 0)"
    env = dict(os.environ, **{WITHOUT_ENV: without})
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env, cwd=REPO)
    assert out.stdout.split() == [str(frozen), str(frozen)]


@pytest.mark.parametrize("linalg_first", [False, True])
def test_numba_loads_without_its_blas_probe_and_scipy_linalg_still_imports(linalg_first: bool) -> None:
    """A role's first kernel load inside :func:`numba_without_blas` does not import scipy.linalg;
    afterwards scipy.linalg imports as usual. With scipy.linalg imported before, the block changes
    nothing."""
    code = f"""
import sys, logging
logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
logging.getLogger("bus.lockstep_process").setLevel(logging.DEBUG)
if {linalg_first}:
    import scipy.linalg
from bus.lockstep_process import numba_without_blas
from firmware_model import control_law as cl
with numba_without_blas("drive 3"):
    cl.warm_up()
print("linalg", "scipy.linalg" in sys.modules)
import numba.np.arraymath
print("blas", numba.np.arraymath._HAVE_BLAS)
import scipy.linalg
print("solve", float(scipy.linalg.solve([[2.0]], [4.0])[0]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    lines = out.stdout.splitlines()
    if linalg_first:
        assert lines[0] == "drive 3: numba's BLAS probe left as it was (it had run, or scipy.linalg was imported)"
        assert lines[1:] == ["linalg True", "blas True", "solve 2.0"]
    else:
        assert lines[0] == "drive 3: numba's kernels loaded without its BLAS probe (scipy.linalg not imported)"
        assert lines[1:] == ["linalg False", "blas False", "solve 2.0"]


def test_a_drive_process_loads_its_kernel_without_scipy_linalg() -> None:
    """The drive role's entry (:func:`firmware_model.drive_node.run_node`, virtual buses, stopped at
    once) warms its kernel up without numba's BLAS probe: scipy.linalg, 0.3 s of CPU per drive and
    run, is never imported, and the drive serves and stops as before."""
    code = """
import sys, threading
from firmware_model.drive_node import run_node
stop = threading.Event()
stop.set()
cfg = {"interface": "virtual", "receive_own_messages": False}
print(run_node(2, dict(cfg, channel="fb-blas"), dict(cfg, channel="io-blas"), stop), "scipy.linalg" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO, timeout=120)
    assert out.stdout.split() == ["None", "False"]


def test_a_long_garbage_collection_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    callback = watch_collections("drive 2", longer_than_s=0.0)
    try:
        with caplog.at_level(logging.INFO, logger="bus.lockstep_process"):
            gc.collect(2)
    finally:
        gc.callbacks.remove(callback)
    assert any(r.getMessage().startswith("drive 2: garbage collection of generation 2 took ") for r in caplog.records)
