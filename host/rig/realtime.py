"""Wall-clock timing of the rig's trials as the plant measured them: real-time statistics.

This module owns how the per-trial timing of the plant node (0x2440,
:class:`bus.plant_objects.TrialTiming`) becomes the run's figures in ``summary.json``
(:func:`timing_summary`) and on the console (:func:`timing_line`): in real-time mode
(``ilcrig run --realtime``) the deadline misses, the tick lateness p50 / p99 / max and the
achieved rate, and whether the run kept up; in lockstep mode the emulator throughput (ticks per
second of wall time inside the trials). With them, in both modes, the CPU time the hypervisor of a
virtual machine took from it while the trials ran (``steal`` in ``/proc/stat``: :func:`steal_during`),
so that a run can tell the machine's stalls from the rig's. It also schedules the lockstep
processes of a real-time run (:func:`schedule_lockstep`): in ``SCHED_FIFO`` where permitted
(:func:`raise_lockstep_priority`), otherwise in normal scheduling with what an unprivileged process
may use (:mod:`host.rig.fair_scheduling`), and says which mechanisms were in force
(:func:`scheduling_mechanisms`, :func:`scheduling_text`). Wall-clock figures are diagnostics: they
depend on the machine and never on or in the model.
"""

from __future__ import annotations

import logging
import os
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bus.lockstep_process import mechanisms_left_out
from bus.plant_objects import DeadlineMisses, TrialTiming
from host.rig.fair_scheduling import apply_fair_scheduling, threads

logger = logging.getLogger(__name__)

__all__ = [
    "timing_summary",
    "timing_line",
    "raise_lockstep_priority",
    "schedule_lockstep",
    "scheduling_mechanisms",
    "scheduling_text",
    "DEFAULT_RT_PRIORITY",
    "HostBoundary",
    "MachineSteal",
    "cpu_steal_s",
    "steal_during",
    "steal_text",
]

#: the SCHED_FIFO priority of the lockstep processes in a real-time run (``--rt-priority``)
DEFAULT_RT_PRIORITY: int = 10


#: where Linux counts the CPU time its hypervisor took from the machine (``steal``, all CPUs)
PROC_STAT = Path("/proc/stat")


def cpu_steal_s(stat_path: Path = PROC_STAT) -> float | None:
    """The CPU time [s] the hypervisor has taken from this (virtual) machine since it booted, all
    CPUs summed: the 8th figure of ``/proc/stat``'s ``cpu`` line (``steal``, in ``USER_HZ`` ticks).
    None where there is no such figure (not Linux, or a kernel without steal accounting)."""
    try:
        with open(stat_path, "rb") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != b"cpu":
        return None
    return int(fields[8]) / os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class MachineSteal:
    """CPU time the hypervisor took from this machine while one trial ran, as the host saw it."""

    #: CPU time taken, s, all CPUs summed (``USER_HZ`` resolution: 10 ms on most kernels)
    steal_s: float
    #: wall time of the window, s: from the host's trial start to its completion (a little longer than the trial)
    window_s: float
    #: CPUs of the machine
    cpus: int


@dataclass(frozen=True)
class HostBoundary:
    """One trial by the host's clock (``time.perf_counter``), s: the set-up (the start command),
    the ticks (start command done until the plant reported the trial done) and the end (the
    plant's timing read, the channels' end-of-trial markers awaited, the watchdog's round)."""

    setup_s: float
    ticks_s: float
    end_s: float

    @property
    def total_s(self) -> float:
        return self.setup_s + self.ticks_s + self.end_s


def host_timing(boundaries: Sequence[HostBoundary], ticks: int, plant_rate: float) -> dict[str, Any]:
    """The summary's ``timing.host``: the trials by the host's clock, their set-up, ticks and end
    summed and per trial, and the host's ticks per second against the plant's."""
    total = sum(b.total_s for b in boundaries)
    rate = ticks / total if total > 0 else 0.0
    return {
        "basis": "the host's clock around each trial: set-up (start command), ticks (until the plant "
        "reported done), end (the plant's timing read, the channels' end-of-trial markers)",
        "seconds": total,
        "setup_s": sum(b.setup_s for b in boundaries),
        "ticks_s": sum(b.ticks_s for b in boundaries),
        "end_s": sum(b.end_s for b in boundaries),
        "ticks_per_s": rate,
        "of_plant_rate": rate / plant_rate if plant_rate > 0 else 0.0,
        "per_trial": [{"setup_s": b.setup_s, "ticks_s": b.ticks_s, "end_s": b.end_s} for b in boundaries],
    }


def steal_during(
    body: Callable[[], None], clock: Callable[[], float] = time.monotonic, steal: Callable[[], float | None] = cpu_steal_s
) -> MachineSteal | None:
    """Run ``body()`` and return the CPU time the hypervisor took from the machine meanwhile (None
    where the system does not count it)."""
    s0, t0 = steal(), clock()
    body()
    s1, t1 = steal(), clock()
    if s0 is None or s1 is None:
        return None
    return MachineSteal(max(0.0, s1 - s0), t1 - t0, os.cpu_count() or 1)


def raise_lockstep_priority(pids: Mapping[str, int], priority: int) -> dict[str, Any]:
    """Put every thread of the processes ``pids`` (role name -> pid) in ``SCHED_FIFO`` at ``priority``
    (1..99; 0: leave them in normal scheduling). Threads they start later inherit it.

    :return: what the run got, for the summary: ``{"policy": "SCHED_FIFO", "priority": p, "roles": [...]}``,
        or ``{"policy": "normal", "reason": ...}`` (nothing changed: not asked for, or not permitted)
    """
    if priority == 0:
        return {"policy": "normal", "reason": "--rt-priority 0"}
    if not hasattr(os, "sched_setscheduler"):
        return {"policy": "normal", "reason": "this system has no SCHED_FIFO"}
    done: list[int] = []
    try:
        for pid in pids.values():
            for tid in threads(pid):
                try:
                    os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
                except ProcessLookupError:
                    continue  # a thread that ended meanwhile
                done.append(tid)
    except PermissionError as err:
        for tid in done:  # all or nothing: undo what was set
            try:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            except OSError as undo:
                logger.warning("cannot put thread %d back to normal scheduling: %s", tid, undo)
        return {
            "policy": "normal",
            "reason": f"SCHED_FIFO {priority} not permitted ({err.strerror}; needs CAP_SYS_NICE or RLIMIT_RTPRIO >= {priority})",
        }
    logger.info("lockstep processes %s in SCHED_FIFO %d (%d threads)", ", ".join(pids), priority, len(done))
    return {"policy": "SCHED_FIFO", "priority": priority, "roles": list(pids)}


def schedule_lockstep(pids: Mapping[str, int], priority: int, without: frozenset[str] | None = None) -> dict[str, Any]:
    """The lockstep processes ``pids`` (role name -> pid) of a real-time run in ``SCHED_FIFO`` at
    ``priority`` where permitted (:func:`raise_lockstep_priority`), else in normal scheduling made
    as prompt as an unprivileged process may (:func:`host.rig.fair_scheduling.apply_fair_scheduling`).

    :param without: mechanisms to leave out (default: ``ILCRIG_RT_WITHOUT``)
    :return: the scheduling record: :func:`raise_lockstep_priority`'s, with ``"roles"`` and, in
        normal scheduling, ``"fair"`` (what the lockstep processes got instead)
    """
    got = raise_lockstep_priority(pids, priority)
    if got["policy"] != "SCHED_FIFO":
        left_out = mechanisms_left_out() if without is None else without
        got |= {"roles": list(pids), "fair": apply_fair_scheduling(pids, left_out)}
    return got


def scheduling_mechanisms(scheduling: Mapping[str, Any]) -> list[str]:
    """The mechanisms in force in a scheduling record, in words (the record's ``mechanisms``)."""
    out: list[str] = []
    if scheduling.get("policy") == "SCHED_FIFO":
        out.append(f"SCHED_FIFO {scheduling['priority']}")
    fair = scheduling.get("fair") or {}
    if "slice_us" in fair:
        out.append(f"scheduler slice {fair['slice_us']:g} µs")
    if isinstance(fair.get("nice"), int) and fair["nice"] < 0:
        out.append(f"nice {fair['nice']}")
    if (scheduling.get("host") or {}).get("policy") == "SCHED_BATCH":
        out.append("host in SCHED_BATCH")
    idle = scheduling.get("idle_poll") or {}
    if idle.get("loops"):
        out.append(f"{idle['loops']} SCHED_IDLE busy loops")
    latency = scheduling.get("cpu_latency") or {}
    if "latency_us" in latency:
        out.append(f"idle CPUs polling (PM QoS {latency['latency_us']} µs)")
    roles = scheduling.get("in_roles") or {}
    if roles.get("heap_frozen"):
        out.append("heap frozen (gc)")
    if roles.get("timer_slack_ns"):
        out.append(f"timer slack {roles['timer_slack_ns'] / 1000:g} µs")
    if roles.get("plant_spins") is False:
        out.append("plant sleeps until each tick is due")
    return out


def scheduling_text(scheduling: Mapping[str, Any]) -> str:
    """How the lockstep processes were scheduled, in words (for the console line)."""
    if scheduling.get("policy") == "SCHED_FIFO":
        text = f"lockstep processes ({', '.join(scheduling['roles'])}) in SCHED_FIFO {scheduling['priority']}"
    else:
        text = f"normal scheduling ({scheduling.get('reason', 'not asked for')})"
        fair = scheduling.get("fair")
        if fair is not None:
            got = [f"a {fair['slice_us']:g} µs scheduler slice" if "slice_us" in fair else f"no short slice: {fair.get('slice')}"]
            got.append(f"nice {fair.get('nice')}")
            text += f": lockstep processes ({', '.join(scheduling.get('roles', []))}) with {', '.join(got)}"
    host = scheduling.get("host")
    if host is not None:
        batch = host.get("policy") == "SCHED_BATCH"
        text += ", host in SCHED_BATCH" if batch else f", host in normal scheduling ({host.get('reason')})"
    idle = scheduling.get("idle_poll")
    latency = scheduling.get("cpu_latency")
    polling = latency is not None and "latency_us" in latency
    if idle is not None:
        loops = idle.get("loops", 0)
        why = idle.get("reason", "no idle-poll loops")
        if loops:
            text += f", CPUs kept awake by {loops} SCHED_IDLE busy loops"
        else:
            text += f", no SCHED_IDLE busy loops ({why})" if polling else f", idle CPUs may halt ({why})"
    if latency is not None:
        text += (
            f", idle CPUs polling (PM QoS CPU latency {latency['latency_us']} µs)"
            if polling
            else f", no PM QoS CPU latency request ({latency.get('reason')})"
        )
    roles = scheduling.get("in_roles")
    if roles is not None:
        done = ["heap frozen" if roles.get("heap_frozen") else "heap not frozen"]
        if roles.get("timer_slack_ns"):
            done.append(f"timer slack {roles['timer_slack_ns'] / 1000:g} µs")
        if "plant_spins" in roles:
            done.append("plant spins the end of each wait" if roles["plant_spins"] else "plant sleeps until each tick is due")
        text += f", {', '.join(done)}"
    return text


def timing_summary(
    timings: Sequence[TrialTiming],
    ts_s: float,
    realtime: bool,
    scheduling: Mapping[str, Any] | None = None,
    steal: Sequence[MachineSteal | None] | None = None,
    missed: Sequence[DeadlineMisses | None] | None = None,
    host: Sequence[HostBoundary] | None = None,
) -> dict[str, Any]:
    """The run's timing figures from the trials' :class:`TrialTiming` (see the module docstring);
    ``scheduling``: what :func:`raise_lockstep_priority` gave the run (real time only); ``steal``:
    per trial, the CPU time the hypervisor took meanwhile (:func:`steal_during`; the summary's
    ``machine_steal`` when every trial has it); ``missed``: per trial, the plant's list of the ticks
    that missed their deadline (0x2441, read only after a trial with misses; real time only), as
    ``per_trial[k].missed_ticks`` with ``t0_monotonic_s``, the machine's ``CLOCK_MONOTONIC`` when tick 0
    was due; ``host``: per trial, its boundary by the host's clock (:func:`host_timing`, the
    summary's ``host`` when every trial has it).

    Over several trials: lateness p50 is the median of the trials' medians, p99 the worst trial's
    p99, max the worst tick; the achieved rate is all ticks over the sum of the trials' durations.
    """
    ticks = sum(t.ticks for t in timings)
    duration_s = sum(t.duration_us for t in timings) * 1e-6
    rate = ticks / duration_s if duration_s > 0 else 0.0
    out: dict[str, Any] = {
        "mode": "realtime" if realtime else "lockstep",
        "basis": "wall clock of the plant (the clock master), from the start of a trial to its last tick; "
        "diagnostics: depends on the machine, never on the model",
        "control_period_s": ts_s,
        "trials": len(timings),
        "ticks": ticks,
        "duration_s": duration_s,
        "achieved_ticks_per_s": rate,
        "real_time_factor": rate * ts_s,
        "per_trial": [
            {
                "ticks": t.ticks,
                "duration_s": t.duration_us * 1e-6,
                "ticks_per_s": t.ticks_per_s,
                "deadline_misses": t.deadline_misses,
                "lateness_p50_s": t.lateness_p50_us * 1e-6,
                "lateness_p99_s": t.lateness_p99_us * 1e-6,
                "lateness_max_s": t.lateness_max_us * 1e-6,
            }
            for t in timings
        ],
    }
    if realtime and missed is not None:
        for row, m in zip(out["per_trial"], missed, strict=False):
            if m is not None:
                row["t0_monotonic_s"] = m.t0_ns * 1e-9
                row["missed_ticks"] = [
                    {"tick": x.tick, "started_late_s": x.started_late_us * 1e-6, "overrun_s": x.overrun_us * 1e-6}
                    for x in m.misses
                ]
    if steal and len(steal) == len(timings) and all(x is not None for x in steal):
        taken = [x for x in steal if x is not None]
        steal_s = sum(x.steal_s for x in taken)
        cpu_s = sum(x.window_s * x.cpus for x in taken)
        out["machine_steal"] = {
            "seconds": steal_s,
            "percent_of_cpu_time": 100.0 * steal_s / cpu_s if cpu_s > 0 else 0.0,
            "cpus": taken[0].cpus,
            "per_trial_s": [x.steal_s for x in taken],
            "basis": "/proc/stat steal: CPU time the hypervisor gave to others while a trial ran (from the host's "
            "trial start to its completion), all CPUs summed; no process of the machine could run then",
        }
    if host and len(host) == len(timings):
        out["host"] = host_timing(host, ticks, rate)
    if realtime:
        misses = sum(t.deadline_misses for t in timings)
        late_max_s = max((t.lateness_max_us for t in timings), default=0) * 1e-6
        out |= {
            "deadline_misses": misses,
            "deadline_miss_percent": 100.0 * misses / ticks if ticks else 0.0,
            "lateness_p50_s": statistics.median(t.lateness_p50_us for t in timings) * 1e-6 if timings else 0.0,
            "lateness_p99_s": max((t.lateness_p99_us for t in timings), default=0) * 1e-6,
            "lateness_max_s": late_max_s,
            "kept_up": bool(timings) and misses == 0 and late_max_s < ts_s,
            "scheduling": dict(scheduling) if scheduling else {"policy": "normal", "reason": "not asked for"},
        }
    return out


def steal_text(timing: Mapping[str, Any]) -> str:
    """``"; the hypervisor took …"`` when the machine lost CPU time during the trials, else ``""``."""
    steal = timing.get("machine_steal")
    if steal is None or steal["seconds"] <= 0:
        return ""
    return (
        f"; the hypervisor took {steal['seconds'] * 1e3:,.0f} ms of CPU time from this machine during the trials "
        f"({steal['percent_of_cpu_time']:.1f} % of its {steal['cpus']} CPUs: steal time)"
    )


def timing_line(timing: dict[str, Any]) -> str:
    """One console line of :func:`timing_summary`'s figures."""
    rate = timing["achieved_ticks_per_s"]
    ts_ms = timing["control_period_s"] * 1e3
    steal = steal_text(timing)
    if timing["mode"] != "realtime":
        return (
            f"emulator throughput (lockstep, wall clock): {rate:,.0f} ticks/s inside the trials "
            f"({timing['real_time_factor']:.2f}x real time at Ts = {ts_ms:g} ms){steal}"
        )
    late = (
        f"tick lateness p50 {timing['lateness_p50_s'] * 1e3:.3f} ms, p99 {timing['lateness_p99_s'] * 1e3:.3f} ms, "
        f"max {timing['lateness_max_s'] * 1e3:.3f} ms"
    )
    sched = f"; {scheduling_text(timing['scheduling'])}" if "scheduling" in timing else ""
    if timing["kept_up"]:
        return (
            f"real time: kept up, {timing['ticks']} ticks paced at Ts = {ts_ms:g} ms, 0 deadline misses, {late} "
            f"(no tick later than one period); achieved {rate:,.1f} ticks/s{sched}{steal}"
        )
    return (
        f"real time: could NOT keep up at Ts = {ts_ms:g} ms: {timing['deadline_misses']} of {timing['ticks']} ticks "
        f"missed their deadline ({timing['deadline_miss_percent']:.1f} %), {late}; the rig held "
        f"{rate:,.1f} ticks/s ({timing['real_time_factor']:.2f}x real time){sched}{steal}"
    )
