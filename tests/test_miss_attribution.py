"""Attributing real-time deadline misses from a kernel scheduler trace: a scripted ftrace text
(the format of ``/sys/kernel/tracing/trace``) and a scripted list of missed ticks give known
stretches, known hidden steal and known verdicts."""

from __future__ import annotations

import pytest

from host.rig.miss_attribution import attribute_misses, parse_sched_trace, summarise_verdicts


def _switch(cpu: int, t: float, prev: int, nxt: int, prio: int = 89) -> str:
    return (
        f"         python3-{prev:<5}   [{cpu:03d}] d..2. {t:.6f}: sched_switch: prev_comm=python3 prev_pid={prev} "
        f"prev_prio={prio} prev_state=S ==> next_comm=python3 next_pid={nxt} next_prio={prio}"
    )


def _runtime(cpu: int, t: float, pid: int, ns: int) -> str:
    return f"         python3-{pid:<5}   [{cpu:03d}] d.h1. {t:.6f}: sched_stat_runtime: comm=python3 pid={pid} runtime={ns} [ns]"


TRACE = [
    "# tracer: nop",
    "#",
    # trial 0 (t0 = 10.0): CPU 0 runs pid 101 for 1.5 ms of wall time but is accounted 0.3 ms
    # (1.2 ms taken by the hypervisor); CPU 1 runs pid 102 for 0.4 ms, all of it accounted
    _switch(0, 10.0, 0, 101),
    _switch(1, 10.0, 0, 102),
    _runtime(1, 10.0004, 102, 400_000),
    _switch(1, 10.0004, 102, 0),
    _runtime(0, 10.0010, 101, 200_000),  # a tick-interrupt record inside the stretch
    _runtime(0, 10.0015, 101, 100_000),
    _switch(0, 10.0015, 101, 0),
    # trial 1 (t0 = 20.0): pid 101 runs 1.2 ms and is accounted all of it (no steal); the idle
    # task's stretches in between are accounted nothing and must not count as steal
    _switch(0, 20.0, 0, 101),
    _runtime(0, 20.0012, 101, 1_200_000),
    _switch(0, 20.0012, 101, 0),
    _switch(1, 20.0013, 0, 102),
]

PER_TRIAL = [
    {
        "t0_monotonic_s": 10.0,
        "missed_ticks": [
            {"tick": 0, "started_late_s": 0.0, "overrun_s": 0.0008},  # done at 10.0018
            {"tick": 1, "started_late_s": 0.0008, "overrun_s": 0.0002},  # late because tick 0 was
        ],
    },
    {"t0_monotonic_s": 20.0, "missed_ticks": [{"tick": 0, "started_late_s": 0.0, "overrun_s": 0.0002}]},
    {"deadline_misses": 0},  # a trial without misses lists none
]


def test_stretches_and_their_hidden_steal_from_a_trace() -> None:
    stretches = parse_sched_trace(TRACE)
    busy = [(r.cpu, r.pid, round(r.end_s - r.start_s, 7), round(r.accounted_s, 7)) for r in stretches if r.pid]
    assert busy == [(0, 101, 0.0015, 0.0003), (1, 102, 0.0004, 0.0004), (0, 101, 0.0012, 0.0012)]
    assert [round(r.hidden_steal_s, 7) for r in stretches if r.pid] == [0.0012, 0.0, 0.0]
    assert all(r.prio == 89 for r in stretches if r.pid)


def test_each_miss_gets_its_verdict() -> None:
    verdicts = attribute_misses(parse_sched_trace(TRACE), PER_TRIAL, ts_s=0.001)
    got = [(v.trial, v.tick, v.verdict) for v in verdicts]
    assert got == [(0, 0, "steal"), (0, 1, "knock-on"), (1, 0, "other")]
    assert verdicts[0].steal_s == pytest.approx(0.0012)  # the whole stolen stretch lies in [10.0, 10.0018]
    assert verdicts[2].steal_s == pytest.approx(0.0, abs=1e-12)
    assert summarise_verdicts(verdicts) == {
        "misses": 3,
        "verdicts": {"steal": 1, "knock-on": 1, "other": 1},
        "chains": {"steal": 1, "other": 1},
        "misses_by_cause": {"steal": 2, "other": 1},
    }


def test_steal_is_prorated_to_the_part_of_a_stretch_inside_the_tick() -> None:
    # tick 1 of trial 0 (window [10.001, 10.0022]) overlaps a third of the stolen stretch
    row = {"t0_monotonic_s": 10.0, "missed_ticks": [{"tick": 1, "started_late_s": 0.0, "overrun_s": 0.0002}]}
    (v,) = attribute_misses(parse_sched_trace(TRACE), [row], ts_s=0.001)
    assert v.steal_s == pytest.approx(0.0012 * 0.5 / 1.5)
    assert v.verdict == "steal"
    row["missed_ticks"][0]["overrun_s"] = 0.0005  # more than the 0.4 ms of steal in it
    (v,) = attribute_misses(parse_sched_trace(TRACE), [row], ts_s=0.001)
    assert v.verdict == "other"
