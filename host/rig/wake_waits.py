"""Where the lockstep processes of a real-time run wait: for a CPU after each wake-up, and who held it.

This module owns the reading of a Linux scheduler trace (ftrace text with the ``record-tgid``
option, ``trace_clock`` = ``mono``, events ``sched:sched_wakeup`` and ``sched:sched_switch``) of an
``ilcrig run --realtime``: :func:`parse_waits` finds, for every wake-up of a task inside the trials,
when it ran next and which tasks held that CPU in between; :func:`summarise_waits` puts it per role
of the rig (a thread group id -> role map: ``hub``, ``plant``, ``drive1``…, ``host``, ``idle-poll``)
and per holder. ``benchmarks/rt_attribution.py --waits`` records the trace and prints the result.

A tick is a chain of wake-ups (plant → hub → four drives → hub → plant): a late tick is one whose
chain waited somewhere. For each woken task the wait is wake-up → its next ``sched_switch`` onto a
CPU; the holders are the tasks that ran on that CPU meanwhile (``idle`` is the CPU's idle task: the
CPU was free, and the wait was the wake-up itself — an idle CPU leaving a halt, or the IPI). Waits
longer than ``threshold_s`` are summed per holder, so a cause that delays many wake-ups a little
and one that delays a few by much show alike, in CPU time. Also kept: the stretches a lockstep
task ran without a break for longer than ``long_run_s`` (a garbage collection or the model
holding a CPU that long shows there).
"""

from __future__ import annotations

import re
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Wait", "WaitTrace", "parse_waits", "summarise_waits"]

#: the task of an event line with ``record-tgid``: ``comm-tid (tgid) [cpu] flags time:``
_HEAD = re.compile(r"^\s*(.+?)-(\d+)\s+\(\s*(\d+|-+)\)\s+\[(\d+)\]\s+\S+\s+(\d+\.\d+):\s+(\w+):\s(.*)$")
_SWITCH = re.compile(r"prev_comm=(.*?) prev_pid=(\d+) prev_prio=(\d+) prev_state=(\S+) ==> next_comm=(.*?) next_pid=(\d+)")
_WAKEUP = re.compile(r"comm=(.*?) pid=(\d+) prio=(\d+)(?: success=\d+)? target_cpu=(\d+)")


@dataclass(frozen=True)
class Wait:
    """One wake-up of a task and its wait for a CPU.

    :ivar tid: the woken task; :ivar woken_s, ran_s: the wake-up and its next switch onto a CPU, s
    :ivar cpu: where it ran; :ivar held_by: (tid, s) of the tasks that ran on that CPU meanwhile
    """

    tid: int
    woken_s: float
    ran_s: float
    cpu: int
    held_by: tuple[tuple[int, float], ...]

    @property
    def wait_s(self) -> float:
        return self.ran_s - self.woken_s


@dataclass
class WaitTrace:
    """What :func:`parse_waits` found in a trace."""

    waits: list[Wait] = field(default_factory=list)
    #: (tid, start, end) of the stretches the tasks ran without a break longer than ``long_run_s``
    long_runs: list[tuple[int, float, float]] = field(default_factory=list)
    #: thread id -> thread group id (process), from the events' task column
    tgid: dict[int, int] = field(default_factory=dict)
    #: thread id -> command name
    comm: dict[int, str] = field(default_factory=dict)
    #: (tid, preempting tid, time) of every switch away from a task still runnable (``R``)
    preempted: list[tuple[int, int, float]] = field(default_factory=list)


def _inside(t: float, windows: Sequence[tuple[float, float]]) -> bool:
    return any(a <= t <= b for a, b in windows)


def parse_waits(lines: Iterable[str], windows: Sequence[tuple[float, float]], long_run_s: float = 2e-3) -> WaitTrace:
    """Every wake-up inside ``windows`` ([start, end] s on the trace clock) with its wait, and the
    long run stretches (module docstring)."""
    out = WaitTrace()
    running: dict[int, tuple[int, float]] = {}  # cpu -> (tid, since)
    history: dict[int, list[tuple[int, float, float]]] = {}  # cpu -> stretches (tid, start, end)
    pending: dict[int, float] = {}  # tid -> woken at
    for line in lines:
        m = _HEAD.match(line)
        if not m:
            continue
        tid, tgid, cpu, t, event, rest = int(m.group(2)), m.group(3), int(m.group(4)), float(m.group(5)), m.group(6), m.group(7)
        if tgid.isdigit():
            out.tgid.setdefault(tid, int(tgid))
        if event == "sched_wakeup":
            w = _WAKEUP.search(rest)
            if w and _inside(t, windows):
                woken = int(w.group(2))
                out.comm.setdefault(woken, w.group(1))
                pending.setdefault(woken, t)
        elif event == "sched_switch":
            s = _SWITCH.search(rest)
            if not s:
                continue
            prev, nxt = int(s.group(2)), int(s.group(6))
            out.comm.setdefault(prev, s.group(1))
            out.comm.setdefault(nxt, s.group(5))
            if cpu in running:
                was, since = running[cpu]
                history.setdefault(cpu, []).append((was, since, t))
                if was and t - since > long_run_s and _inside(t, windows):
                    out.long_runs.append((was, since, t))
            if s.group(4).startswith("R") and prev and _inside(t, windows):
                out.preempted.append((prev, nxt, t))
            running[cpu] = (nxt, t)
            woken_at = pending.pop(nxt, None)
            if woken_at is not None:
                out.waits.append(Wait(nxt, woken_at, t, cpu, _held(history.get(cpu, []), woken_at, t)))
    return out


def _held(stretches: list[tuple[int, float, float]], a: float, b: float) -> tuple[tuple[int, float], ...]:
    """Who ran in [a, b] among the last stretches of one CPU (newest last)."""
    held: dict[int, float] = {}
    for tid, start, end in reversed(stretches):
        if end <= a:
            break
        overlap = min(end, b) - max(start, a)
        if overlap > 0:
            held[tid] = held.get(tid, 0.0) + overlap
    return tuple(held.items())


def summarise_waits(
    trace: WaitTrace, roles: Mapping[int, str], threshold_s: float = 200e-6, names: Mapping[int, str] | None = None
) -> dict[str, Any]:
    """Per role (``roles``: thread group id -> role; only their tasks' wake-ups count, not the
    ``idle-poll`` loops'): wake-ups, the wait p50 / p99 / max [s] and how many waited longer than
    ``threshold_s``; per holder (a role, ``idle``, a process named in ``names`` — thread group id ->
    name, e.g. the launcher, a benchmark's master —, or another process's command name), the CPU time
    it held while a lockstep task (not the host's) waited longer than ``threshold_s``; the lockstep
    roles' and the host's long run stretches; who preempted a lockstep task."""

    def role_of(tid: int) -> str | None:
        return roles.get(trace.tgid.get(tid, tid))

    def holder(tid: int) -> str:
        if tid == 0:
            return "idle"
        named = names.get(trace.tgid.get(tid, tid)) if names else None
        return role_of(tid) or named or trace.comm.get(tid, "?")

    per_role: dict[str, list[float]] = {}
    held: dict[str, float] = {}
    for w in trace.waits:
        role = role_of(w.tid)
        if role is None or role == "idle-poll":
            continue
        per_role.setdefault(role, []).append(w.wait_s)
        if w.wait_s > threshold_s and role != "host":
            for tid, s in w.held_by:
                held[holder(tid)] = held.get(holder(tid), 0.0) + s
    waits = {}
    for role, values in sorted(per_role.items()):
        values.sort()
        n = len(values)
        waits[role] = {
            "wakeups": n,
            "p50_s": statistics.median(values),
            "p99_s": values[min(n - 1, int(0.99 * n))],
            "max_s": values[-1],
            "over_threshold": sum(1 for v in values if v > threshold_s),
        }
    long_runs: dict[str, list[float]] = {}
    for tid, start, end in trace.long_runs:
        role = role_of(tid)
        if role is not None and role != "idle-poll":
            long_runs.setdefault(role, []).append(end - start)
    preempted_by: dict[str, int] = {}
    for tid, by, _ in trace.preempted:
        if role_of(tid) not in (None, "host", "idle-poll"):
            preempted_by[holder(by)] = preempted_by.get(holder(by), 0) + 1
    return {
        "threshold_s": threshold_s,
        "waits": waits,
        "held_while_waiting_s": dict(sorted(held.items(), key=lambda kv: -kv[1])),
        "long_runs_s": {r: sorted(v, reverse=True) for r, v in sorted(long_runs.items())},
        "lockstep_preempted_by": dict(sorted(preempted_by.items(), key=lambda kv: -kv[1])),
    }
