"""Keeping the CPUs awake during a real-time run: one busy loop per CPU in ``SCHED_IDLE``.

This module owns :class:`IdlePollers`, which ``ilcrig run --realtime`` starts for the length of
the run (``--no-idle-poll`` leaves them out).

Why
    A paced tick is a chain of wake-ups: the plant sends the encoder frames, the hub wakes and
    forwards them, four drives wake and answer, the hub wakes again, then the plant. Between
    ticks every process sleeps, and a CPU with nothing to run halts. Waking a halted CPU costs
    time, and in a virtual machine a lot of it: the halt leaves the guest, and the hypervisor
    must schedule the virtual CPU again before the woken process can run. A process in
    ``SCHED_IDLE`` runs only when nothing else wants the CPU, and any woken process takes the
    CPU from it at once, so with one busy loop per CPU no CPU halts and every wake-up of the
    chain finds its CPU running. Linux's ``idle=poll`` boot option does the same for a whole
    machine; this does it for one run, without privileges (any process may enter
    ``SCHED_IDLE``).

Cost
    Every CPU is busy for the whole run (power, heat, and on a shared machine the CPU time
    shows as used). The loops take CPU time only that nobody else wants: a process in normal
    scheduling gets ~99.7 % of a CPU beside one (``SCHED_IDLE`` weight 3 against 1,024).

Only beside SCHED_FIFO
    The launcher starts them only when the lockstep processes are in ``SCHED_FIFO``, which
    preempts anything in normal scheduling at once. Beside lockstep processes in normal
    scheduling they make the ticks far later, not earlier (docs/timing.md §1): the fair
    scheduler weighs a woken task against the loop's scheduling group, not against the loop.

Autogroups
    With ``CONFIG_SCHED_AUTOGROUP`` every session is a scheduling group, weighed against the
    other groups by the group's nice value, whatever the policy of the tasks inside: a loop in
    a session of its own at the group's default nice 0 claims as large a share of a CPU as the
    host's group does. Each loop therefore sets its group's nice to :data:`AUTOGROUP_NICE`
    (``/proc/self/autogroup``; raising it needs no privilege).

Lifetime
    The loops are started by :func:`bus.processes.spawn_process`: processes in their own session
    (a terminal's Ctrl-C does not reach them), killed by :meth:`IdlePollers.stop`, and killed by
    the kernel when the process that started them dies (``PR_SET_PDEATHSIG``, armed before
    ``exec``: a loop already in ``SCHED_IDLE`` may get no CPU for a long time on a busy machine, so
    the signal must not wait for the loop's own code); each also checks its parent every few
    milliseconds, so none outlives the launcher, even one killed with SIGKILL. A killed loop still
    needs the CPU to finish exiting, which beside CPU-bound processes may take seconds (measured
    0.02–0.35 s, at times several seconds, beside four to five): :meth:`IdlePollers.stop` waits
    :data:`STOP_WAIT_S` for them, then leaves them to a reaper thread.

What the loops change is measured by ``benchmarks/rt_compare.py`` (docs/benchmarks.md).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time

from bus.processes import spawn_process

logger = logging.getLogger(__name__)

__all__ = ["AUTOGROUP_NICE", "IdlePollers", "idle_poll_available"]

#: the busy loop, run with ``python -S -c`` (nothing imported but os, sys, time and ctypes): its session's
#: autogroup at nice ``argv[2]`` (empty: left alone; retried while the kernel's 100 ms rate limit refuses it)
#: first, while the process is still in normal scheduling (in SCHED_IDLE on a busy machine it would wait
#: seconds for the CPU to do it), then SCHED_IDLE, bound to CPU ``argv[3]``, and a check of the parent
#: every ~10 ms (the death signal is armed before exec, by :func:`bus.processes.spawn_process`)
_LOOP = """
import os, sys, time
parent = int(sys.argv[1])
if sys.argv[2]:
    for _ in range(20):
        try:
            fd = os.open("/proc/self/autogroup", os.O_WRONLY)
            try:
                os.write(fd, sys.argv[2].encode())
            finally:
                os.close(fd)
            break
        except BlockingIOError:
            time.sleep(0.11)
        except OSError:
            break
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
try:
    os.sched_setaffinity(0, {int(sys.argv[3])})
except (OSError, AttributeError):
    pass
while os.getppid() == parent:
    for _ in range(20000):
        pass
"""

#: the nice value of each loop's autogroup (module docstring, "Autogroups")
AUTOGROUP_NICE: int = 19
#: how long :meth:`IdlePollers.stop` waits for its killed loops to be gone before it leaves them to
#: a reaper thread, s
STOP_WAIT_S: float = 2.0


def _reap(procs: list[subprocess.Popen[bytes]]) -> None:
    """Wait for killed loops to finish exiting (a daemon thread: the process may end first; then
    init reaps them)."""
    for p in procs:
        p.wait()


def idle_poll_available() -> bool:
    """Whether this system has ``SCHED_IDLE`` (Linux)."""
    return hasattr(os, "SCHED_IDLE") and hasattr(os, "sched_setscheduler")


class IdlePollers:
    """One ``SCHED_IDLE`` busy loop per CPU (see the module docstring), started at once.

    Each loop is bound to its CPU: left to the load balancer, two loops may share one CPU while
    the other halts (the balancer weighs ``SCHED_IDLE`` tasks too lightly to move them apart).

    :param n_cpus: how many loops (default: one on each CPU this process may run on; loop k is
        bound to the k-th of those CPUs, taken round)
    :param autogroup_nice: the nice value of each loop's autogroup (None: the kernel's 0)
    """

    def __init__(self, n_cpus: int | None = None, autogroup_nice: int | None = AUTOGROUP_NICE) -> None:
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(os.cpu_count() or 1))
        if n_cpus is None:
            n_cpus = len(cpus)
        #: the CPU each loop is bound to
        self.cpus = [cpus[k % len(cpus)] for k in range(n_cpus)]
        self.procs: list[subprocess.Popen[bytes]] = []
        nice = "" if autogroup_nice is None else str(autogroup_nice)
        try:
            for cpu in self.cpus:
                argv = [sys.executable, "-S", "-c", _LOOP, str(os.getpid()), nice, str(cpu)]
                self.procs.append(spawn_process(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        except OSError:
            self.stop()
            raise
        logger.info("%d idle-poll loops (SCHED_IDLE): pids %s", n_cpus, " ".join(str(p.pid) for p in self.procs))

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self.procs]

    def stop(self) -> None:
        """Kill and reap every loop (idempotent). A killed loop still needs CPU time to finish
        exiting, which a busy machine may not give a task in ``SCHED_IDLE`` for seconds: the loops
        not gone after :data:`STOP_WAIT_S` are reaped by a background thread instead -- they run no
        code of their own again (their SIGKILL is pending), and the run's shutdown does not wait."""
        procs, self.procs = self.procs, []
        for p in procs:
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGKILL)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + STOP_WAIT_S
        exiting = []
        for p in procs:
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                exiting.append(p)
        if exiting:
            logger.info(
                "%d idle-poll loop(s) killed and still exiting (no CPU for them yet): reaped in the background", len(exiting)
            )
            threading.Thread(target=_reap, args=(exiting,), name="idle-poll reaper", daemon=True).start()
