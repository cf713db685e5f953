"""Where the lockstep processes waited (host/rig/wake_waits.py), on a hand-written scheduler trace:
each wake-up's wait for a CPU, who held that CPU meanwhile, long run stretches, preemptions; only
wake-ups inside the trials and of the rig's roles count."""

from __future__ import annotations

import pytest

from host.rig.wake_waits import parse_waits, summarise_waits


def _line(comm: str, tid: int, tgid: int, cpu: int, t: float, event: str, rest: str) -> str:
    return f"{comm:>16}-{tid:<7} ({tgid:>7}) [{cpu:03d}] d..2.  {t:.6f}: {event}: {rest}"


def _switch(cpu: int, t: float, prev: tuple[str, int, int], state: str, nxt: tuple[str, int]) -> str:
    comm, tid, tgid = prev
    return _line(
        comm,
        tid,
        tgid,
        cpu,
        t,
        "sched_switch",
        f"prev_comm={comm} prev_pid={tid} prev_prio=120 prev_state={state} "
        f"==> next_comm={nxt[0]} next_pid={nxt[1]} next_prio=120",
    )


def _wakeup(cpu: int, t: float, waker: tuple[str, int, int], woken: tuple[str, int], target: int) -> str:
    comm, tid, tgid = waker
    return _line(comm, tid, tgid, cpu, t, "sched_wakeup", f"comm={woken[0]} pid={woken[1]} prio=120 target_cpu={target:03d}")


PLANT = ("python", 100, 100)
HUB = ("python", 200, 200)
HOST_THREAD = ("python", 301, 300)
OTHER = ("make", 900, 900)
IDLE = ("swapper/0", 0, 0)

TRACE = [
    # cpu 0: the plant runs, then "make"; cpu 1: the host's thread, then idle
    _switch(0, 10.000000, IDLE, "R", ("python", 100)),
    _switch(1, 10.000000, IDLE, "R", ("python", 301)),
    # the plant wakes the hub (on cpu 1, held by the host's thread for 0.5 ms), then sleeps
    _wakeup(0, 10.000100, PLANT, ("python", 200), 1),
    _switch(0, 10.000150, PLANT, "S", ("make", 900)),
    _switch(1, 10.000600, HOST_THREAD, "R", ("python", 200)),  # the host preempted by the hub
    # the hub wakes the plant on cpu 0 where make runs: 3 ms of make, then the plant
    _wakeup(1, 10.001000, HUB, ("python", 100), 0),
    _switch(1, 10.001050, HUB, "S", ("swapper/1", 0)),
    _switch(0, 10.004000, OTHER, "R", ("python", 100)),  # make preempted: the plant at last
    # the plant runs 3 ms without a break (a long stretch), sleeps
    _switch(0, 10.007000, PLANT, "S", ("swapper/0", 0)),
    # outside the trial: a wake-up of the plant that must not count
    _wakeup(1, 20.000000, HUB, ("python", 100), 0),
    _switch(0, 20.005000, IDLE, "R", ("python", 100)),
]


def test_each_wakeup_its_wait_and_who_held_the_cpu() -> None:
    trace = parse_waits(TRACE, [(9.9, 10.01)])
    waits = {(w.tid, round(w.woken_s, 6)): w for w in trace.waits}
    assert set(waits) == {(200, 10.0001), (100, 10.001)}
    hub = waits[(200, 10.0001)]
    assert hub.wait_s == pytest.approx(0.0005) and hub.cpu == 1
    assert dict(hub.held_by) == pytest.approx({301: 0.0005})
    plant = waits[(100, 10.001)]
    assert plant.wait_s == pytest.approx(0.003)
    assert dict(plant.held_by) == pytest.approx({900: 0.003})
    assert trace.tgid[301] == 300
    assert [(tid, round(b - a, 6)) for tid, a, b in trace.long_runs] == [(900, 0.00385), (100, 0.003)]

    s = summarise_waits(trace, {100: "plant", 200: "hub", 300: "host"}, threshold_s=200e-6)
    assert s["waits"]["plant"]["wakeups"] == 1 and s["waits"]["plant"]["max_s"] == pytest.approx(0.003)
    assert s["waits"]["hub"]["over_threshold"] == 1
    assert s["held_while_waiting_s"] == pytest.approx({"make": 0.003, "host": 0.0005})
    assert list(s["held_while_waiting_s"]) == ["make", "host"]  # the most first
    assert s["long_runs_s"] == {"plant": [pytest.approx(0.003)]}  # make is no role
    # who took the CPU from a lockstep process still runnable: nobody here (the host and make are no lockstep)
    assert s["lockstep_preempted_by"] == {}
    # a process that is no lockstep role may be named (a launcher, a benchmark's master): it holds, never waits
    named = summarise_waits(trace, {100: "plant", 200: "hub", 300: "host"}, threshold_s=200e-6, names={900: "master"})
    assert named["held_while_waiting_s"] == pytest.approx({"master": 0.003, "host": 0.0005})
    assert set(named["waits"]) == set(s["waits"])


def test_a_lockstep_process_preempted_is_counted_by_who_took_the_cpu() -> None:
    lines = [
        _switch(0, 1.0, IDLE, "R", ("python", 100)),
        _switch(0, 1.0005, PLANT, "R+", ("python", 301)),
        _switch(0, 1.0010, HOST_THREAD, "S", ("python", 100)),
    ]
    s = summarise_waits(parse_waits(lines, [(0.0, 2.0)]), {100: "plant", 300: "host"})
    assert s["lockstep_preempted_by"] == {"host": 1}
