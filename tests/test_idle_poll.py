"""The idle-poll loops of a real-time run (host/rig/idle_poll.py): one SCHED_IDLE busy loop per CPU,
gone when stopped and gone when the process that started them dies, even by SIGKILL (the death
signal armed before exec by bus/processes.py); what the run's scheduling line says of them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable

import pytest
from cli_util import pid_alive

from bus.processes import spawn_process
from host.rig.fair_scheduling import autogroups_enabled
from host.rig.idle_poll import _LOOP, AUTOGROUP_NICE, IdlePollers, idle_poll_available
from host.rig.realtime import scheduling_text

pytestmark = pytest.mark.skipif(not idle_poll_available(), reason="no SCHED_IDLE on this system")


def _wait_for(what: str, cond: Callable[[], bool], timeout_s: float = 20.0) -> None:
    """Wait until ``cond()`` holds (an event, checked every few ms), failing after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.005)


def _dying(pid: int) -> bool:
    """The process is gone (or a zombie), or the kernel has killed it: SIGKILL is pending and it
    will run no code of its own again (it finishes exiting when it next gets a CPU, which a
    SCHED_IDLE task beside CPU-bound processes may not for seconds)."""
    if not pid_alive(pid):
        return True
    try:
        with open(f"/proc/{pid}/status") as f:
            fields = dict(line.split(":\t", 1) for line in f.read().splitlines() if ":\t" in line)
    except OSError:
        return True
    pending = int(fields.get("SigPnd", "0"), 16) | int(fields.get("ShdPnd", "0"), 16)
    return bool(pending & 1 << (signal.SIGKILL - 1))


def _policy(pid: int) -> int | None:
    try:
        return os.sched_getscheduler(pid)
    except ProcessLookupError:
        return None


def test_one_sched_idle_loop_per_cpu_until_stopped() -> None:
    pollers = IdlePollers(2)
    pids = pollers.pids
    try:
        assert len(pids) == 2 and len(set(pids)) == 2
        _wait_for("both loops in SCHED_IDLE", lambda: all(_policy(p) == os.SCHED_IDLE for p in pids))
        # each bound to its own CPU (round the CPUs this process may use)
        cpus = sorted(os.sched_getaffinity(0))
        assert pollers.cpus == [cpus[0], cpus[1 % len(cpus)]]
        _wait_for("each loop on its CPU", lambda: [os.sched_getaffinity(p) for p in pids] == [{c} for c in pollers.cpus])
        # their own session: a terminal's Ctrl-C (our process group) does not reach them
        assert all(os.getsid(p) == p for p in pids)
    finally:
        pollers.stop()
    assert pollers.pids == [] and all(map(_dying, pids))
    pollers.stop()  # again: nothing to do


def _autogroup_nice(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/autogroup") as f:
            return int(f.read().split()[-1])  # "/autogroup-123 nice 19"
    except (OSError, ValueError, IndexError):
        return None


@pytest.mark.skipif(not autogroups_enabled(), reason="no scheduler autogroups on this system")
def test_each_loop_lowers_its_sessions_autogroup_to_nice_19() -> None:
    """Each loop is a session, and so an autogroup: at nice 0 the group would claim a full share
    against each of the lockstep processes' groups, whatever SCHED_IDLE says inside it."""
    pollers = IdlePollers(2)
    pids = pollers.pids
    try:
        _wait_for("both autogroups at nice 19", lambda: all(_autogroup_nice(p) == AUTOGROUP_NICE for p in pids))
    finally:
        pollers.stop()
    left_alone = IdlePollers(1, autogroup_nice=None)
    try:
        pid = left_alone.pids[0]
        _wait_for("the loop in SCHED_IDLE", lambda: _policy(pid) == os.SCHED_IDLE)
        assert _autogroup_nice(pid) == 0
    finally:
        left_alone.stop()


def test_the_loops_die_with_the_process_that_started_them() -> None:
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); from host.rig.idle_poll import IdlePollers; "
        "p = IdlePollers(2); print(' '.join(map(str, p.pids)), flush=True); import time; time.sleep(600)"
    )
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    parent = subprocess.Popen([sys.executable, "-c", code, repo], stdout=subprocess.PIPE, text=True)
    pids: list[int] = []
    try:
        assert parent.stdout is not None
        pids = [int(x) for x in parent.stdout.readline().split()]
        assert len(pids) == 2
        _wait_for("both loops in SCHED_IDLE", lambda: all(_policy(p) == os.SCHED_IDLE for p in pids))
        parent.send_signal(signal.SIGKILL)  # no chance to stop them itself
        parent.wait()
        _wait_for("the kernel to kill the loops with their parent", lambda: all(map(_dying, pids)))
    finally:
        parent.kill()
        parent.wait()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


@pytest.mark.parametrize("death_signal", [signal.SIGKILL, signal.SIGTERM, None])
def test_the_death_signal_is_armed_before_the_child_runs_a_line_of_its_own(death_signal: int | None) -> None:
    """The cause of a loop outliving its killed parent on a busy machine: the loop armed
    PR_SET_PDEATHSIG itself, after entering SCHED_IDLE, where it may wait long for a CPU. Now
    bus.processes.spawn_process arms it between fork and exec: the child's first line sees it."""
    code = "import ctypes; v = ctypes.c_int(); ctypes.CDLL(None).prctl(2, ctypes.byref(v), 0, 0, 0); print(v.value)"
    proc = spawn_process([sys.executable, "-S", "-c", code], stdout=subprocess.PIPE, death_signal=death_signal)
    out, _ = proc.communicate(timeout=60)
    assert int(out) == (0 if death_signal is None else int(death_signal))
    assert "prctl" not in _LOOP  # the loop does not arm it late itself


def test_the_scheduling_line_says_whether_the_cpus_were_kept_awake() -> None:
    fifo = {"policy": "SCHED_FIFO", "priority": 10, "roles": ["hub", "plant"]}
    assert scheduling_text(fifo | {"idle_poll": {"loops": 2}}) == (
        "lockstep processes (hub, plant) in SCHED_FIFO 10, CPUs kept awake by 2 SCHED_IDLE busy loops"
    )
    assert scheduling_text(fifo | {"idle_poll": {"loops": 0, "reason": "--no-idle-poll"}}) == (
        "lockstep processes (hub, plant) in SCHED_FIFO 10, idle CPUs may halt (--no-idle-poll)"
    )
    assert scheduling_text(fifo) == "lockstep processes (hub, plant) in SCHED_FIFO 10"
