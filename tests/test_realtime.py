"""Real-time mode: the plant's pacing and its statistics on an injected clock (never the wall
clock): ticks start at t0 + n·Ts, not before; late ticks and deadline misses are counted exactly;
the host's figures and console line say plainly whether the run kept up."""

from __future__ import annotations

import itertools
import os
import struct
import subprocess

import can
import pytest
from clock_util import ManualClock
from hypothesis import given, settings
from hypothesis import strategies as st
from test_plant_node import PlantBox, fake_disturbance, request_paced_trial

from bus import io_frames
from bus.plant_objects import (
    DEADLINE_MISSES_KEPT,
    DeadlineMiss,
    DeadlineMisses,
    PlantObj,
    PlantStatus,
    TrialTiming,
    pack_deadline_misses,
    pack_trial_timing,
    unpack_deadline_misses,
    unpack_trial_timing,
)
from host.rig import realtime
from host.rig.realtime import (
    MachineSteal,
    cpu_steal_s,
    raise_lockstep_priority,
    scheduling_text,
    steal_during,
    timing_line,
    timing_summary,
)
from plant.pacing import MISSES_KEPT, TickPacer
from plant.plant_node import PlantNode

_counter = itertools.count()


def test_pacer_statistics_from_scripted_times() -> None:
    p = TickPacer(ts_s=0.001, n_ticks=4, paced=True, t0_s=10.0)
    assert [p.due_s(n) for n in range(3)] == pytest.approx([10.0, 10.001, 10.002])
    # tick 0 on time, done in 0.5 ms; tick 1 starts 0.2 ms late, done after tick 2's start (miss);
    # tick 2 starts 0.4 ms late and is done in time; tick 3 starts 1.5 ms late (more than a period)
    # and is done after tick 4's start (a second miss)
    for n, start, done in ((0, 10.0, 10.0005), (1, 10.0012, 10.0021), (2, 10.0024, 10.0029), (3, 10.0045, 10.0049)):
        p.started(n, start)
        p.completed(n, done)
    r = p.result()
    assert (r.paced, r.ticks, r.deadline_misses) == (True, 4, 2)
    assert r.duration_s == pytest.approx(0.0049)
    assert r.lateness_max_s == pytest.approx(0.0015)
    assert r.lateness_p50_s == pytest.approx(0.0003)  # median of 0, 0.2, 0.4, 1.5 ms


def test_unpaced_trial_has_duration_but_no_lateness() -> None:
    p = TickPacer(ts_s=0.001, n_ticks=2, paced=False, t0_s=0.0)
    p.started(0, 0.0)
    p.completed(0, 0.01)  # ten periods late: not a miss when nothing is paced
    p.started(1, 0.01)
    p.completed(1, 0.02)
    r = p.result()
    assert (r.ticks, r.deadline_misses, r.lateness_max_s) == (2, 0, 0.0)
    assert r.duration_s == pytest.approx(0.02)


def _start_paced_trial(bench: PlantNode, n_ticks: int, clock: ManualClock) -> float:
    """Boot ``bench``, configure pacing and a trial of ``n_ticks`` as the host would and start it
    at ``clock.now``: TRIAL_START goes out at once, tick 0 one period later (Ts = 1 ms), when the
    clock is moved there and the bench stepped. Returns t0, when tick 0 was due."""
    request_paced_trial(bench, n_ticks)
    bench.step(0.0)
    t0 = clock.now + 0.001
    assert bench.next_deadline() == pytest.approx(t0 - bench.spin_s)
    clock.now = t0
    bench.step(0.0)
    return t0


def test_paced_bench_holds_each_tick_until_its_time() -> None:
    """The bench stepped by the test on a manual clock (virtual buses deliver on send): TRIAL_START
    goes out when the trial starts and tick 0 one period later, so that the drives take the start
    command in a period of its own; tick n's encoder frames go out at t0 + n·Ts, not a microsecond
    before; a tick answered late starts the next one late and is a deadline miss; 0x2440 reports it
    and 0x2441 names the tick, with t0 on the node clock."""
    k = next(_counter)
    clock = ManualClock(100.0)
    fb = can.Bus(interface="virtual", channel=f"rt-fb-{k}")
    io = can.Bus(interface="virtual", channel=f"rt-io-{k}")
    drives = can.Bus(interface="virtual", channel=f"rt-io-{k}")
    bench = PlantNode(fb, io, plant_factory=PlantBox(), disturbance_fn=fake_disturbance, clock=clock)

    def io_frames_seen() -> list[str]:
        got = []
        while (msg := drives.recv(timeout=0)) is not None:
            frame = io_frames.decode_io(msg)
            got.append(f"enc{frame.tick}" if isinstance(frame, io_frames.EncoderFrame) else type(frame).__name__)
        return got

    def encoder_ticks() -> list[int]:
        return [int(f[3:]) for f in io_frames_seen() if f.startswith("enc")]

    def answer(wire: int, at: float) -> None:
        clock.now = at
        for j in range(4):
            drives.send(io_frames.encode_torque(j, wire, 0, io_frames.TorqueStatus.ENABLED))
        bench.step(0.0)

    try:
        request_paced_trial(bench, 4)
        bench.step(0.0)  # at 100.0: the start command only; tick 0 is due at t0 = 100.001
        assert io_frames_seen() == ["ControlFrame"]
        assert bench.next_deadline() == pytest.approx(100.001)
        clock.now = 100.000999
        bench.step(0.0)
        assert encoder_ticks() == []
        clock.now = 100.001
        bench.step(0.0)
        assert encoder_ticks() == [0] * 4
        answer(0, 100.0013)  # tick 0 done after 0.3 ms: tick 1 is held until 100.002
        assert encoder_ticks() == []
        assert bench.next_deadline() == pytest.approx(100.002)
        clock.now = 100.001999
        bench.step(0.0)
        assert encoder_ticks() == []
        clock.now = bench.next_deadline()  # 100.002 in floating point: t0 + Ts
        bench.step(0.0)
        assert encoder_ticks() == [1] * 4
        answer(1, 100.0035)  # done after tick 2's start (100.003): a miss, tick 2 starts 0.5 ms late
        assert encoder_ticks() == [2] * 4
        answer(2, 100.0036)
        assert bench.next_deadline() == pytest.approx(100.004)
        clock.now = bench.next_deadline()
        bench.step(0.0)
        assert encoder_ticks() == [3] * 4
        answer(3, 100.0041)
        assert bench.status == PlantStatus.DONE
        t = unpack_trial_timing(bench.read_object(PlantObj.TRIAL_TIMING, 0))
        assert (t.paced, t.ticks, t.deadline_misses, t.lateness_max_us) == (True, 4, 1, 500)
        assert t.duration_us == 3100
        m = unpack_deadline_misses(bench.read_object(PlantObj.DEADLINE_MISSES, 0))
        assert m == DeadlineMisses(100_001_000_000, (DeadlineMiss(tick=1, started_late_us=0, overrun_us=500),))
    finally:
        for bus in (fb, io, drives):
            bus.shutdown()


def test_trial_timing_round_trips_through_its_bytes() -> None:
    t = TrialTiming(True, 501, 500_123, 2, 40, 300, 1200)
    assert unpack_trial_timing(pack_trial_timing(t)) == t
    assert t.ticks_per_s == pytest.approx(501 / 0.500123)


def test_pacer_keeps_the_first_missed_ticks_with_their_times() -> None:
    p = TickPacer(ts_s=0.001, n_ticks=MISSES_KEPT + 10, paced=True, t0_s=5.0)
    for n in range(MISSES_KEPT + 10):  # every tick starts 0.1 ms late and ends 0.2 ms after its deadline
        p.started(n, p.due_s(n) + 100e-6)
        p.completed(n, p.due_s(n + 1) + 200e-6)
    r = p.result()
    assert MISSES_KEPT == DEADLINE_MISSES_KEPT  # the pacer keeps what 0x2441 can list
    assert r.deadline_misses == MISSES_KEPT + 10  # the count goes on ...
    assert len(r.missed) == MISSES_KEPT  # ... the list stops: bounded memory over any trial
    assert r.t0_s == 5.0
    assert [m.tick for m in r.missed] == list(range(MISSES_KEPT))
    assert all(m.started_late_s == pytest.approx(100e-6) and m.overrun_s == pytest.approx(200e-6) for m in r.missed)


_MISS = st.builds(DeadlineMiss, st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1))


@settings(max_examples=200, deadline=None)
@given(t0_ns=st.integers(0, 2**64 - 1), misses=st.lists(_MISS, max_size=DEADLINE_MISSES_KEPT))
def test_deadline_misses_round_trip_through_their_bytes(t0_ns: int, misses: list[DeadlineMiss]) -> None:
    m = DeadlineMisses(t0_ns, tuple(misses))
    data = pack_deadline_misses(m)
    assert len(data) == 10 + 12 * len(misses)
    assert unpack_deadline_misses(data) == m


def test_deadline_misses_bytes_are_exact_and_bad_lengths_are_refused() -> None:
    data = pack_deadline_misses(DeadlineMisses(0x0102030405060708, (DeadlineMiss(7, 300, 2**33),)))
    assert data == bytes.fromhex("08070605040302010100070000002c010000ffffffff")  # overrun clamped to u32
    with pytest.raises(ValueError, match="at least 10 bytes"):
        unpack_deadline_misses(b"\x00" * 9)
    with pytest.raises(ValueError, match="1 entries must be 22 bytes, got 21"):
        unpack_deadline_misses(data[:-1])
    with pytest.raises(ValueError, match="at most 64"):
        unpack_deadline_misses(struct.pack("<QH", 0, 65) + b"\x00" * 12 * 65)
    many = DeadlineMisses(1, tuple(DeadlineMiss(n, 0, 1) for n in range(100)))
    assert len(unpack_deadline_misses(pack_deadline_misses(many)).misses) == DEADLINE_MISSES_KEPT


def test_summary_lists_the_missed_ticks_of_the_trials_that_had_some() -> None:
    timings = [TrialTiming(True, 501, 501_000, 0, 30, 60, 200), TrialTiming(True, 501, 501_500, 2, 30, 900, 1500)]
    missed = [None, DeadlineMisses(12_500_000_000, (DeadlineMiss(40, 50, 700), DeadlineMiss(41, 1500, 300)))]
    out = timing_summary(timings, 0.001, True, missed=missed)
    assert "missed_ticks" not in out["per_trial"][0]
    row = out["per_trial"][1]
    assert row["t0_monotonic_s"] == pytest.approx(12.5)
    assert row["missed_ticks"] == [
        {"tick": 40, "started_late_s": pytest.approx(50e-6), "overrun_s": pytest.approx(700e-6)},
        {"tick": 41, "started_late_s": pytest.approx(1500e-6), "overrun_s": pytest.approx(300e-6)},
    ]
    assert "missed_ticks" not in timing_summary(timings, 0.001, False, missed=missed)["per_trial"][1]


def test_host_figures_say_whether_the_run_kept_up() -> None:
    good = [TrialTiming(True, 501, 501_000, 0, 50, 200, 400), TrialTiming(True, 501, 501_000, 0, 60, 300, 900)]
    s = timing_summary(good, 1e-3, realtime=True)
    assert s["kept_up"] and s["deadline_misses"] == 0
    assert s["lateness_max_s"] == pytest.approx(900e-6) and s["lateness_p99_s"] == pytest.approx(300e-6)
    assert s["lateness_p50_s"] == pytest.approx(55e-6)
    assert s["achieved_ticks_per_s"] == pytest.approx(1000.0)
    assert timing_line(s).startswith("real time: kept up")
    bad = good + [TrialTiming(True, 501, 801_600, 300, 20_000, 290_000, 300_000)]
    s = timing_summary(bad, 1e-3, realtime=True)
    assert not s["kept_up"] and s["deadline_misses"] == 300
    line = timing_line(s)
    assert "could NOT keep up" in line and "held" in line and f"{s['achieved_ticks_per_s']:,.1f} ticks/s" in line
    lock = timing_summary([TrialTiming(False, 501, 250_500, 0, 0, 0, 0)], 1e-3, realtime=False)
    assert "deadline_misses" not in lock and timing_line(lock).startswith("emulator throughput")
    assert lock["achieved_ticks_per_s"] == pytest.approx(2000.0)


def test_steal_time_is_read_from_proc_stat(tmp_path) -> None:
    hz = os.sysconf("SC_CLK_TCK")
    stat = tmp_path / "stat"
    stat.write_text(f"cpu  4705 150 1120 16250 520 0 7 {3 * hz} 0 0\ncpu0 2000 70 500 8000 300 0 5 {hz} 0 0\n")
    assert cpu_steal_s(stat) == pytest.approx(3.0)  # the all-CPU line, USER_HZ ticks -> s
    stat.write_text("cpu  4705 150 1120 16250\n")  # a kernel without steal accounting
    assert cpu_steal_s(stat) is None
    assert cpu_steal_s(tmp_path / "missing") is None
    if os.path.exists("/proc/stat"):
        assert cpu_steal_s() is not None and cpu_steal_s() >= 0.0


def test_steal_during_a_trial_and_what_the_run_says_of_it() -> None:
    clock = iter([100.0, 100.6])
    steals = iter([12.34, 12.38])
    calls: list[str] = []
    got = steal_during(lambda: calls.append("trial"), clock=lambda: next(clock), steal=lambda: next(steals))
    assert calls == ["trial"] and got is not None
    assert (got.steal_s, got.window_s, got.cpus) == (pytest.approx(0.04), pytest.approx(0.6), os.cpu_count())
    assert steal_during(lambda: None, steal=lambda: None) is None  # not counted on this system

    timings = [TrialTiming(True, 501, 501_000, 0, 50, 200, 400), TrialTiming(True, 501, 520_000, 30, 60, 9_000, 14_000)]
    steal = [MachineSteal(0.0, 0.6, 2), MachineSteal(0.04, 0.6, 2)]
    s = timing_summary(timings, 1e-3, True, None, steal)
    assert s["machine_steal"]["seconds"] == pytest.approx(0.04)
    assert s["machine_steal"]["percent_of_cpu_time"] == pytest.approx(100 * 0.04 / 2.4)
    assert s["machine_steal"]["per_trial_s"] == [0.0, pytest.approx(0.04)]
    line = timing_line(s)
    assert "could NOT keep up" in line
    assert line.endswith(
        "; the hypervisor took 40 ms of CPU time from this machine during the trials (1.7 % of its 2 CPUs: steal time)"
    )
    lock = timing_summary(timings[:1], 1e-3, False, None, [MachineSteal(0.01, 0.6, 2)])
    assert timing_line(lock).endswith(
        "x real time at Ts = 1 ms); the hypervisor took 10 ms of CPU time from this "
        "machine during the trials (0.8 % of its 2 CPUs: steal time)"
    )
    # nothing taken: no clause; a trial without the figure: no figure for the run
    assert "hypervisor" not in timing_line(timing_summary(timings[:1], 1e-3, True, None, steal[:1]))
    assert "machine_steal" not in timing_summary(timings, 1e-3, True, None, [steal[0], None])


class SteppingClock(ManualClock):
    """A clock that moves ``step_s`` every time it is read (a loop on it ends)."""

    def __init__(self, now: float, step_s: float) -> None:
        super().__init__(now)
        self.step_s = step_s
        self.reads = 0

    def __call__(self) -> float:
        self.reads += 1
        self.now += self.step_s
        return self.now


def test_a_paced_tick_is_waited_for_on_the_clock_for_the_last_spin_s() -> None:
    """With spin_s, the loop wakes spin_s before a held tick is due and the bench waits the rest on
    the clock: the frames go out at the first clock reading at or after the due time, not before
    and not at the next wake-up of the select loop."""
    k = next(_counter)
    clock = SteppingClock(100.0, 0.0)
    fb = can.Bus(interface="virtual", channel=f"rt-fb-{k}")
    io = can.Bus(interface="virtual", channel=f"rt-io-{k}")
    drives = can.Bus(interface="virtual", channel=f"rt-io-{k}")
    bench = PlantNode(fb, io, plant_factory=PlantBox(), disturbance_fn=fake_disturbance, clock=clock, spin_s=200e-6)
    try:
        assert _start_paced_trial(bench, 3, clock) == pytest.approx(100.001)  # tick 0 at t0 = 100.001
        while drives.recv(timeout=0) is not None:
            pass
        clock.now = 100.0013
        for j in range(4):
            drives.send(io_frames.encode_torque(j, 0, 0, io_frames.TorqueStatus.ENABLED))
        bench.step(0.0)  # tick 1 held until 100.002: the loop is to wake at 100.0018
        assert bench.next_deadline() == pytest.approx(100.002 - 200e-6)
        assert drives.recv(timeout=0) is None
        clock.now, clock.step_s = 100.00185, 10e-6  # woken inside the window: waits on the clock
        reads = clock.reads
        bench.step(0.0)
        msg = drives.recv(timeout=0)
        assert msg is not None and isinstance(io_frames.decode_io(msg), io_frames.EncoderFrame)
        assert clock.reads - reads >= 10  # (100.002 − 100.00185) / 10 µs readings, at least
        t = bench.lockstep.pacer
        assert t is not None and 0 <= t._lateness_s[1] < 30e-6  # started within a few clock steps of the due time
    finally:
        for bus in (fb, io, drives):
            bus.shutdown()
    with pytest.raises(ValueError, match="spin_s"):
        PlantNode(fb, io, plant_factory=PlantBox(), disturbance_fn=fake_disturbance, spin_s=0.5)


def test_real_time_scheduling_is_fifo_where_permitted_and_said_where_not(
    sleeper: subprocess.Popen[bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    got = raise_lockstep_priority({"plant": sleeper.pid}, 7)
    if got["policy"] == "SCHED_FIFO":  # root, CAP_SYS_NICE or an RLIMIT_RTPRIO
        assert got == {"policy": "SCHED_FIFO", "priority": 7, "roles": ["plant"]}
        for tid in os.listdir(f"/proc/{sleeper.pid}/task"):
            assert os.sched_getscheduler(int(tid)) == os.SCHED_FIFO
            assert os.sched_getparam(int(tid)).sched_priority == 7
        assert scheduling_text(got) == "lockstep processes (plant) in SCHED_FIFO 7"
    else:
        assert "not permitted" in got["reason"] and "CAP_SYS_NICE" in got["reason"]
    assert raise_lockstep_priority({"plant": sleeper.pid}, 0) == {"policy": "normal", "reason": "--rt-priority 0"}

    calls: list[tuple[int, int]] = []

    def refuse_the_third(tid: int, policy: int, param: os.sched_param) -> None:
        calls.append((tid, policy))
        if len(calls) == 3:
            raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(realtime.os, "sched_setscheduler", refuse_the_third)
    monkeypatch.setattr(realtime, "threads", lambda pid: [pid, pid + 1])
    got = raise_lockstep_priority({"hub": 100, "plant": 200}, 10)
    assert got["policy"] == "normal" and got["reason"].startswith("SCHED_FIFO 10 not permitted (Operation not permitted")
    # all or nothing: the two threads already raised are put back
    assert calls == [
        (100, os.SCHED_FIFO),
        (101, os.SCHED_FIFO),
        (200, os.SCHED_FIFO),
        (100, os.SCHED_OTHER),
        (101, os.SCHED_OTHER),
    ]
    line = timing_line(timing_summary([TrialTiming(True, 501, 501_000, 0, 50, 200, 400)], 1e-3, True, got))
    assert line.endswith(
        "; normal scheduling (SCHED_FIFO 10 not permitted (Operation not permitted; needs CAP_SYS_NICE or RLIMIT_RTPRIO >= 10))"
    )
