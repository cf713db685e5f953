"""A process's time waiting for a CPU: whether a silence was the machine's, not the silent party's.

This module owns the reading of the kernel's scheduler statistics of a process
(:func:`sched_stat`: ``/proc/<pid>/task/*/schedstat``, run time ns, run-queue wait ns, time
slices, summed over its threads) and :class:`RunQueueLedger`, which every judge of a heartbeat
silence on this machine uses: the nodes' consumer of the host's heartbeat
(:class:`bus.cia301.nmt.NodeHeartbeatConsumer`, the hub that carries it) and the launcher's
(:class:`host.rig.liveness.LivenessWatch`, the silent node's process and the hub).

Why: on a machine with more runnable threads than CPUs the kernel can leave a runnable process
without a CPU for longer than a consumer time (500 ms).  Measured on this 2-core machine, two
rigs and four CPU hogs beside each other: the hub of one rig read nothing for 570 ms while every
node ran (every drive then reported the host lost), and a drive woken on one CPU waited 531 ms
in that CPU's run queue while about 500 other wake-ups ran there (ftrace ``sched_switch`` /
``sched_wakeup``; the launcher judged the drive lost).  Such a process did not stop: it waited
for the CPU, and the kernel counts that wait.  A stopped process (SIGSTOP, a fault injected by
``stall:``) or one that spins in its own code does not wait in a run queue: its silence stays a
fault.

The rule (:meth:`RunQueueLedger.excuse`) excuses a producer silent for ``silent_s`` for one wait
of one of its carriers (the processes its heartbeat passes through that this machine can ask),
and only for a wait of a quarter of the consumer time or more (a real one):

* a wait that ended since the producer was last heard, ``waited_s`` long, when ``silent_s -
  waited_s <= consumer_s``: without it the producer would have been silent no longer than its
  consumer time;
* a wait going on at the judgement: the beat may be held in it.

One wait, never a sum: a busy carrier on a loaded machine waits a few ms before each of its
hundreds of time slices, and those waits hold no frame for long -- summed, they would excuse a
producer whose heartbeat has really stopped at every judgement, for as long as the load lasts.
``schedstat`` holds sums only, so the longest wait that ended is bounded from below by the waits
that ended divided by the slices since (each ended wait is followed by a slice): only a wait that
long is sure.  The kernel adds a wait to ``schedstat`` only once it ends (the thread is put on a
CPU); a carrier that is runnable now and neither ran nor was put on a CPU since the judge last
looked is waiting now: the judge does not decide yet (:attr:`Excuse.pending`: it looks again
within :data:`RECHECK_S`) and counts that wait from its first such look, at most half a consumer
time (a carrier busy on a CPU all along is runnable too).  (A thread's ``se.exec_start`` in
``/proc/…/sched`` would date the wait, but the kernel zeroes it when it moves a waiting thread to
another CPU.)  The wait going on is counted from the judge's first look, which comes after the
producer was already a consumer time silent: that is why it is not held against the silence.  An
excused producer is judged from now: a producer lost meanwhile is lost one consumer time after
the machine lets its carriers run (at most two and a half consumer times after the end of the
last wait that excused it).

May import: the standard library, :mod:`bus.peer`.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from bus.peer import peer_pid

logger = logging.getLogger(__name__)

__all__ = ["RECHECK_S", "Excuse", "RunQueueLedger", "SchedStat", "carrier_ledger", "carrier_pid", "sched_stat"]

#: how soon a judge looks again at a carrier that is waiting for a CPU now, s
RECHECK_S = 0.02


@dataclass(frozen=True)
class SchedStat:
    """A process's scheduler statistics, all its threads: ``run_s`` on a CPU, ``wait_s`` runnable
    in a run queue without one (waits that ended), ``slices`` times put on a CPU, ``runnable``
    whether a thread is runnable now (state ``R``: on a CPU or waiting for one)."""

    run_s: float
    wait_s: float
    slices: int
    runnable: bool = False


def sched_stat(pid: int) -> SchedStat | None:
    """Process ``pid``'s :class:`SchedStat` (None: gone, or no ``schedstat`` in this kernel)."""
    run = wait = slices = 0
    runnable = seen = False
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", "rb") as fh:
                fields = fh.read().split()
            with open(f"/proc/{pid}/task/{tid}/stat", "rb") as fh:
                state = fh.read().rsplit(b")", 1)[-1].split()[:1]
            run += int(fields[0])
            wait += int(fields[1])
            slices += int(fields[2])
            runnable = runnable or state == [b"R"]
            seen = True
        except (OSError, IndexError, ValueError):
            continue  # a thread that ended meanwhile
    return SchedStat(run * 1e-9, wait * 1e-9, slices, runnable) if seen else None


@dataclass(frozen=True)
class Excuse:
    """A silence explained by a carrier's wait for a CPU: process ``pid`` waited ``waited_s`` in one wait; or,
    ``pending``, a carrier waiting now: no judgement yet, look again within :data:`RECHECK_S`."""

    pid: int
    waited_s: float
    pending: bool = False


class RunQueueLedger:
    """The run-queue wait of each producer's carriers, noted when it was last heard (module
    docstring).

    :param carriers: node id → the pids its heartbeat passes through (asked at every
        :meth:`heard` and :meth:`excuse`; a pid not noted at :meth:`heard` counts nothing)
    :param stat_of: pid → its :class:`SchedStat` (default :func:`sched_stat`)
    :param clock: the time of a look, s (default ``time.monotonic``)
    """

    def __init__(
        self,
        carriers: Callable[[int], Iterable[int]],
        stat_of: Callable[[int], SchedStat | None] = sched_stat,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._carriers = carriers
        self._stat_of = stat_of
        self._clock = clock
        #: node id → pid → (ended waits s, slices) when it was last heard
        self._marks: dict[int, dict[int, tuple[float, int]]] = {}
        #: node id → pid → (run s, slices) of a carrier seen waiting, and when it was first seen so
        self._waiting: dict[int, dict[int, tuple[tuple[float, int], float]]] = {}
        #: node id → when its judgement was first left pending
        self._pending_since: dict[int, float] = {}

    def heard(self, node_id: int) -> None:
        """Producer ``node_id`` was heard now."""
        marks = {}
        for pid in self._carriers(node_id):
            stat = self._stat_of(pid)
            if stat is not None:
                marks[pid] = (stat.wait_s, stat.slices)
        self._marks[node_id] = marks
        self._waiting.pop(node_id, None)
        self._pending_since.pop(node_id, None)

    def excuse(self, node_id: int, silent_s: float, consumer_s: float) -> Excuse | None:
        """The carrier wait that explains ``node_id``'s silence of ``silent_s`` against a consumer
        time ``consumer_s`` (module docstring), a pending one, or None: the silence is the producer's."""
        best: Excuse | None = None
        pending: Excuse | None = None
        carriers = set(self._carriers(node_id))
        seen = self._waiting.setdefault(node_id, {})
        now = self._clock()
        for pid, (wait_mark, slices_mark) in self._marks.get(node_id, {}).items():
            stat = self._stat_of(pid) if pid in carriers else None
            if stat is None:
                continue
            found: list[float] = []
            # the longest wait that ended is at least their mean (module docstring); it explains the
            # silence when, without it, the silence would have been no longer than the consumer time
            ended = (stat.wait_s - wait_mark) / max(1, stat.slices - slices_mark)
            if ended >= consumer_s / 4 and silent_s - ended <= consumer_s:
                found.append(ended)
            if not stat.runnable:
                seen.pop(pid, None)
            else:  # waiting now, or on a CPU
                key = (stat.run_s, stat.slices)
                if pid not in seen or seen[pid][0] != key:  # it ran since the last look
                    seen[pid] = (key, now)
                going_on = now - seen[pid][1]  # waiting since the first look with nothing run
                if going_on >= consumer_s / 4:
                    found.append(going_on)  # a wait at the judgement itself: the beat may be held in it
                pending = Excuse(pid, going_on, pending=True)
            for waited in found:
                if best is None or waited > best.waited_s:
                    best = Excuse(pid, waited)
        if best is not None:
            return best
        if pending is not None and now - self._pending_since.setdefault(node_id, now) <= consumer_s / 2:
            return pending  # a carrier busy on a CPU all along is not waited for longer than that
        return None

    def judge(self, node_id: int, silent_s: float, consumer_s: float) -> Excuse | None:
        """:meth:`excuse`; when there is one it is logged and ``node_id`` counts as heard now (the
        caller judges it from now); a pending one is returned as it is."""
        excuse = self.excuse(node_id, silent_s, consumer_s)
        if excuse is not None and not excuse.pending:
            logger.info(
                "node %d silent for %.0f ms while pid %d, which carries its heartbeat, waited %.0f ms for a CPU: judged from now",
                node_id,
                1e3 * silent_s,
                excuse.pid,
                1e3 * excuse.waited_s,
            )
            self.heard(node_id)
        return excuse


def carrier_pid(bus: object) -> int | None:
    """The process on this machine that carries every frame of ``bus``: the peer of its
    ``fileno()`` when that is a Unix socket (a hub member:
    :func:`bus.peer.peer_pid`); None for a kernel bus (SocketCAN), a network one
    (UDP, a hub over TCP) or one without a descriptor."""
    fileno = getattr(bus, "fileno", None)
    if fileno is None:
        return None
    try:
        with socket.fromfd(int(fileno()), socket.AF_UNIX, socket.SOCK_STREAM) as sock:  # a duplicate, closed here
            return peer_pid(sock)
    except (OSError, ValueError, TypeError, NotImplementedError):
        return None


def carrier_ledger(bus: object) -> RunQueueLedger | None:
    """A ledger of the process that carries every frame of ``bus`` (:func:`carrier_pid`: a hub on
    this machine), or None: no process of this machine to ask."""
    pid = carrier_pid(bus)
    if pid is None:
        return None
    carriers = (pid,)
    return RunQueueLedger(lambda _node_id: carriers)
