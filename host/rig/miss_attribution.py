"""Whose were the deadline misses of a real-time run: the hypervisor's, or the rig's (or another's).

This module owns the reading of a Linux scheduler trace (ftrace text, ``trace_clock`` = ``mono``,
events ``sched:sched_switch`` and ``sched:sched_stat_runtime``) beside the plant's list of missed
ticks (0x2441, ``summary.json``: ``bench.timing.per_trial[k].missed_ticks`` and ``t0_monotonic_s``),
and the verdict per miss. ``benchmarks/rt_attribution.py`` records the trace around
``ilcrig run --realtime`` and prints what this module finds.

The measure is the CPU time the hypervisor took from a CPU *while a task held it*: with
``CONFIG_PARAVIRT_TIME_ACCOUNTING`` (KVM guests) the kernel leaves steal time out of a task's run
time, so for every stretch a task held a CPU (one ``sched_switch`` to the next) the wall time
minus the run time the kernel accounted to it in that stretch is CPU time the machine did not
have. ``/proc/stat`` counts the same steal in 10 ms units over the whole machine; here it is per
CPU and per tick, in µs.

Per missed tick n (due at t0 + n·Ts, done ``overrun`` after t0 + (n + 1)·Ts) the window is
[t0 + n·Ts, done]; its hidden steal is, per CPU, the steal of the stretches (of any task but the
idle task: a stolen CPU also delays the wake-up of a lockstep process sent to it) prorated to their
overlap with the window, and the largest over the CPUs (the tick's critical path runs on either).
Verdicts:

* ``steal``: the hypervisor's: the steal in the window is at least the overrun, so without it
  the tick would have kept its deadline;
* ``knock-on``: the tick started late because the tick before it missed (a chain): the cause is
  that of the chain's first miss;
* ``other``: the tick overran by more than the steal in it: the rig's own time, or a stall of the
  machine the trace does not show as steal (it shows only what the kernel accounts).
"""

from __future__ import annotations

import bisect
import logging
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["RunStretch", "MissVerdict", "parse_sched_trace", "attribute_misses", "summarise_verdicts"]

_SWITCH = re.compile(
    r"\[(\d+)\]\s+\S+\s+(\d+\.\d+):\s+sched_switch:\s.*?prev_pid=(\d+)\s.*?"
    r"next_pid=(\d+)\s+next_prio=(\d+)"
)
_RUNTIME = re.compile(r"\[(\d+)\]\s+\S+\s+(\d+\.\d+):\s+sched_stat_runtime:\s.*?pid=(\d+)\s+runtime=(\d+)")


@dataclass(frozen=True)
class RunStretch:
    """A task holding a CPU from one ``sched_switch`` to the next.

    :ivar cpu: the CPU
    :ivar start_s, end_s: the two switches, s (trace clock: ``CLOCK_MONOTONIC``)
    :ivar pid: the task
    :ivar prio: its kernel priority (below 100: real time; 120: normal)
    :ivar accounted_s: the run time the kernel accounted to it in the stretch, s
    """

    cpu: int
    start_s: float
    end_s: float
    pid: int
    prio: int
    accounted_s: float

    @property
    def hidden_steal_s(self) -> float:
        """Wall time of the stretch the task was not given: the hypervisor's, s (≥ 0)."""
        return max(0.0, (self.end_s - self.start_s) - self.accounted_s)


def parse_sched_trace(lines: Iterable[str]) -> list[RunStretch]:
    """The run stretches of a trace (ftrace text lines); the run time of a stretch is the sum of the
    task's ``sched_stat_runtime`` records after its start up to and including its end switch."""
    current: dict[int, tuple[float, int, int]] = {}
    runtime: dict[int, list[tuple[float, int]]] = {}
    bounds: list[tuple[int, float, float, int, int]] = []
    for line in lines:
        if "sched_stat_runtime" in line:
            m = _RUNTIME.search(line)
            if m:
                runtime.setdefault(int(m.group(3)), []).append((float(m.group(2)), int(m.group(4))))
            continue
        m = _SWITCH.search(line)
        if not m:
            continue
        cpu, t = int(m.group(1)), float(m.group(2))
        if cpu in current:
            start, pid, prio = current[cpu]
            bounds.append((cpu, start, t, pid, prio))
        current[cpu] = (t, int(m.group(4)), int(m.group(5)))
    times = {pid: [t for t, _ in recs] for pid, recs in runtime.items()}
    sums: dict[int, list[int]] = {}
    for pid, recs in runtime.items():
        acc, total = [], 0
        for _, ns in recs:
            total += ns
            acc.append(total)
        sums[pid] = acc
    out = []
    for cpu, start, end, pid, prio in bounds:
        ts = times.get(pid)
        accounted_ns = 0
        if ts:
            # records in (start, end]; the record of the switch itself carries the same time stamp as it
            lo, hi = bisect.bisect_right(ts, start), bisect.bisect_right(ts, end)
            if hi > lo:
                accounted_ns = sums[pid][hi - 1] - (sums[pid][lo - 1] if lo else 0)
        out.append(RunStretch(cpu, start, end, pid, prio, accounted_ns * 1e-9))
    out.sort(key=lambda r: (r.start_s, r.cpu))
    return out


@dataclass(frozen=True)
class MissVerdict:
    """One missed tick and whose it was (module docstring).

    :ivar trial: the trial's index in the run
    :ivar tick: the tick's index in the trial
    :ivar started_late_s, overrun_s: as the plant measured them, s
    :ivar steal_s: the hypervisor's CPU time in the tick's window (largest over the CPUs), s
    :ivar verdict: ``steal``, ``knock-on`` or ``other``
    """

    trial: int
    tick: int
    started_late_s: float
    overrun_s: float
    steal_s: float
    verdict: str


def _window_steal(stretches: Sequence[RunStretch], starts: Sequence[float], a: float, b: float, max_span_s: float) -> float:
    """Largest per-CPU hidden steal of the stretches overlapping [a, b], prorated (any task but the
    idle task, which is accounted no run time)."""
    per_cpu: dict[int, float] = {}
    i = bisect.bisect_left(starts, a - max_span_s)
    while i < len(stretches) and stretches[i].start_s < b:
        r = stretches[i]
        i += 1
        span = r.end_s - r.start_s
        if r.pid == 0 or r.end_s <= a or span <= 0:
            continue
        overlap = min(r.end_s, b) - max(r.start_s, a)
        if overlap > 0:
            per_cpu[r.cpu] = per_cpu.get(r.cpu, 0.0) + r.hidden_steal_s * overlap / span
    return max(per_cpu.values(), default=0.0)


def attribute_misses(stretches: Sequence[RunStretch], per_trial: Sequence[Mapping[str, Any]], ts_s: float) -> list[MissVerdict]:
    """The verdict on every listed missed tick of ``per_trial`` (the summary's
    ``bench.timing.per_trial``; trials without ``missed_ticks`` had none) against the trace."""
    starts = [r.start_s for r in stretches]
    max_span = max((r.end_s - r.start_s for r in stretches), default=0.0)
    out: list[MissVerdict] = []
    for k, row in enumerate(per_trial):
        missed = row.get("missed_ticks") or []
        t0 = row.get("t0_monotonic_s")
        if t0 is None:
            continue
        previous = -2
        for m in missed:
            n, late, over = int(m["tick"]), float(m["started_late_s"]), float(m["overrun_s"])
            due = t0 + n * ts_s
            done = due + ts_s + over
            steal = _window_steal(stretches, starts, due, done, max_span)
            if n == previous + 1 and late > 0:
                verdict = "knock-on"
            elif steal >= over:
                verdict = "steal"
            else:
                verdict = "other"
            out.append(MissVerdict(k, n, late, over, steal, verdict))
            previous = n
    return out


def summarise_verdicts(verdicts: Sequence[MissVerdict]) -> dict[str, Any]:
    """Counts per verdict, and the chains: a chain's first miss decides its knock-ons."""
    counts = {"steal": 0, "knock-on": 0, "other": 0}
    chains = {"steal": 0, "other": 0}
    by_cause = {"steal": 0, "other": 0}
    cause = "other"
    for v in verdicts:
        counts[v.verdict] += 1
        if v.verdict != "knock-on":
            cause = v.verdict
            chains[cause] += 1
        by_cause[cause] += 1
    return {"misses": len(verdicts), "verdicts": counts, "chains": chains, "misses_by_cause": by_cause}
