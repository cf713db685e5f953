"""A silence the machine caused is no loss (bus/run_queue.py): a heartbeat consumer whose carriers
(the hub; for the launcher also the silent node's own process) waited in a run queue for a CPU
long enough to explain the silence judges the producer from then on, and the launcher keeps the
silence as an incident of the summary; a carrier that did not wait (a producer stopped, dead or
spinning, a hub stopped with SIGSTOP) leaves the silence a loss.  The kernel's wait is real:
two busy processes on one CPU wait for each other, a stopped one does not; a hub member finds
its hub's pid.  Fast tier."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import can
import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from bus.cia301.nmt import HeartbeatConsumer, NodeHeartbeatConsumer, heartbeat_cob_id
from bus.run_queue import RECHECK_S, RunQueueLedger, SchedStat, carrier_pid, sched_stat
from bus.transports.config import FIELDBUS, hub_transport, virtual_transport
from bus.transports.hub.process import start_hub
from host.rig.liveness import LivenessWatch, judge_silences, process_stopped

CONSUMER_S = 0.5
HUB_PID = 4242


class Stats:
    """The kernel's statistics by pid, set by the test: waits that ended (s), and whether a thread
    is runnable now with its run time (a carrier waiting now: runnable, run time unchanged)."""

    def __init__(self) -> None:
        self.wait: dict[int, float] = {}
        self.slices: dict[int, int] = {}
        self.runnable: dict[int, bool] = {}
        self.run: dict[int, float] = {}
        self.t = 0.0

    def __call__(self, pid: int) -> SchedStat | None:
        if pid not in self.wait:
            return None
        return SchedStat(self.run.get(pid, 0.0), self.wait[pid], self.slices.get(pid, 0), self.runnable.get(pid, False))

    def clock(self) -> float:
        return self.t


def ledger(stats: Stats, *pids: int) -> RunQueueLedger:
    return RunQueueLedger(lambda _nid: pids or (HUB_PID,), stat_of=stats, clock=stats.clock)


def test_a_wait_going_on_is_waited_for_and_counted_from_the_first_look() -> None:
    """The kernel adds a wait to schedstat once it ends: a hub runnable now is looked at again."""
    stats = Stats()
    stats.wait[HUB_PID] = 2.0
    consumer = NodeHeartbeatConsumer(ledger(stats))
    consumer.configure({127: CONSUMER_S})
    consumer.on_heartbeat(127, 0.0)
    stats.runnable[HUB_PID] = True  # waiting for a CPU now (or on one)
    stats.t = 0.5
    assert consumer.expired(0.5) == []
    assert consumer.next_deadline() == pytest.approx(0.5 + RECHECK_S)  # looked at again soon
    stats.t = 0.6  # still runnable, neither ran nor was put on a CPU: waiting 100 ms so far
    assert consumer.expired(0.6) == []
    assert consumer.next_deadline() == pytest.approx(0.6 + RECHECK_S)
    stats.t = 0.7  # 200 ms: a quarter of the consumer time and more
    assert consumer.expired(0.7) == []
    assert consumer.next_deadline() == pytest.approx(0.7 + CONSUMER_S)  # excused: judged from now
    stats.runnable[HUB_PID] = False
    assert consumer.expired(0.7 + CONSUMER_S) == [127]


def test_a_carrier_busy_on_a_cpu_is_not_waited_for_past_half_a_consumer_time() -> None:
    stats = Stats()
    stats.wait[HUB_PID] = 0.0
    stats.runnable[HUB_PID] = True
    consumer = NodeHeartbeatConsumer(ledger(stats))
    consumer.configure({127: CONSUMER_S})
    consumer.on_heartbeat(127, 0.0)
    lost: list[int] = []
    t = CONSUMER_S
    while not lost:
        stats.t = t
        stats.run[HUB_PID] = t  # it runs: its run time grows at every look
        lost = consumer.expired(t)
        t += RECHECK_S
        assert t < 2.0
    assert lost == [127] and t - RECHECK_S == pytest.approx(CONSUMER_S + CONSUMER_S / 2, abs=1.5 * RECHECK_S)


def test_a_nodes_consumer_excuses_a_silence_its_hubs_wait_explains_and_no_other() -> None:
    stats = Stats()
    stats.wait[HUB_PID] = 1.0
    consumer = NodeHeartbeatConsumer(ledger(stats))
    consumer.configure({127: CONSUMER_S})
    consumer.on_heartbeat(127, 10.0)
    stats.wait[HUB_PID] = 1.0 + 0.40  # the hub waited 400 ms for a CPU: silent 510 ms - 400 ms <= 500 ms
    assert consumer.expired(10.51) == []
    assert consumer.next_deadline() == pytest.approx(10.51 + CONSUMER_S)  # judged from then on
    # from then on nothing waited: the producer is lost one consumer time later
    assert consumer.expired(10.51 + CONSUMER_S) == [127]


def test_a_wait_shorter_than_the_silence_needs_excuses_nothing() -> None:
    stats = Stats()
    stats.wait[HUB_PID] = 0.0
    consumer = NodeHeartbeatConsumer(ledger(stats))
    consumer.configure({127: CONSUMER_S})
    consumer.on_heartbeat(127, 0.0)
    stats.wait[HUB_PID] = 0.1  # 100 ms of waiting: less than a quarter of the consumer time
    assert consumer.expired(0.6) == [127]
    consumer.on_heartbeat(127, 1.0)
    stats.wait[HUB_PID] = 0.4  # 300 ms more: a real wait, but 1.6 s - 300 ms is longer than the consumer time
    assert consumer.expired(2.6) == [127]


def test_a_busy_hubs_many_short_waits_excuse_no_producer_that_stopped() -> None:
    """A loaded machine: the hub relays other traffic in a time slice every 5 ms and waits 1.5 ms
    before each (30 % of the time, 150 ms of each 500 ms consumer time, enough if summed); the
    producer's heartbeat has stopped.  No single wait explains the silence: lost at once, every
    time."""
    stats = Stats()
    stats.wait[HUB_PID], stats.slices[HUB_PID] = 0.0, 0
    consumer = NodeHeartbeatConsumer(ledger(stats))
    consumer.configure({127: CONSUMER_S})
    for start in (0.0, 2.0, 4.0):
        consumer.on_heartbeat(127, start)
        stats.t = start + CONSUMER_S
        stats.wait[HUB_PID] += 0.3 * CONSUMER_S
        stats.slices[HUB_PID] += round(CONSUMER_S / 0.005)
        assert consumer.expired(stats.t) == [127]


def test_a_long_wait_among_a_few_slices_still_excuses() -> None:
    """The hub waited 400 ms, then ran three slices before the judge looked: the longest wait is at
    least 400 / 3 ms, a quarter of the consumer time and more, and silent 510 ms - 133 ms <= 500 ms."""
    stats = Stats()
    stats.wait[HUB_PID], stats.slices[HUB_PID] = 1.0, 10
    consumer = NodeHeartbeatConsumer(ledger(stats))
    consumer.configure({127: CONSUMER_S})
    consumer.on_heartbeat(127, 10.0)
    stats.wait[HUB_PID], stats.slices[HUB_PID] = 1.4, 13
    assert consumer.expired(10.51) == []
    assert consumer.next_deadline() == pytest.approx(10.51 + CONSUMER_S)


def test_without_a_ledger_or_a_known_wait_a_silence_is_a_loss() -> None:
    plain = NodeHeartbeatConsumer()
    plain.configure({127: CONSUMER_S})
    plain.on_heartbeat(127, 0.0)
    assert plain.expired(0.5) == [127]
    unknown = NodeHeartbeatConsumer(ledger(Stats()))  # the hub's statistics cannot be read (gone)
    unknown.configure({127: CONSUMER_S})
    unknown.on_heartbeat(127, 0.0)
    assert unknown.expired(0.5) == [127]


def test_the_hosts_consumer_excuses_a_silence_of_every_node_its_hubs_wait_explains() -> None:
    stats = Stats()
    stats.wait[HUB_PID] = 0.0
    consumer = HeartbeatConsumer({1: CONSUMER_S, 2: CONSUMER_S}, ledger=ledger(stats))
    consumer.on_heartbeat(1, b"\x05", 0.0)
    consumer.on_heartbeat(2, b"\x05", 0.1)
    stats.wait[HUB_PID] = 0.5
    assert consumer.report_at(0.7).overdue == []
    assert consumer.last_heard(1) == consumer.last_heard(2) == 0.7
    assert consumer.report_at(1.21).overdue == [1, 2]


def test_the_launcher_keeps_a_silence_its_nodes_wait_explains_as_an_incident_not_a_fault() -> None:
    stats = Stats()
    pids = {"hub": HUB_PID, "drive3": 77}
    watch = LivenessWatch(virtual_transport(prefix="run-queue-test"), pids=lambda: dict(pids))
    watch._ledger = RunQueueLedger(watch._carriers, stat_of=stats)  # the kernel's statistics, as set here
    stats.wait.update({HUB_PID: 0.0, 77: 0.0})
    t0 = time.monotonic()
    for nid in (1, 2, 3):
        watch._heard(can.Message(arbitration_id=heartbeat_cob_id(nid), data=b"\x05", is_extended_id=False), t0)
    for nid in (1, 2):  # the other drives are heard on
        watch._heard(can.Message(arbitration_id=heartbeat_cob_id(nid), data=b"\x05", is_extended_id=False), t0 + 0.5)
    stats.wait[77] = 0.53  # drive3 waited 530 ms in a run queue (the case measured: 531 ms)
    watch._judge(t0 + 0.74)
    assert [(s.node, s.how, s.carrier) for s in watch.silences] == [("drive3", "waited", "drive3")]
    faults, incidents = judge_silences(watch.silences, planned=2, t_safe_mono=t0 + 10, injections=[])
    assert faults == []
    assert incidents[0]["what"] == (
        "drive3 silent for 740 ms while drive3 waited 530 ms for a CPU (the machine had none to spare): "
        "judged from then on, not a fault"
    )
    # judged from then on: silent a consumer time more without a wait, it is lost
    for nid in (1, 2):
        watch._heard(can.Message(arbitration_id=heartbeat_cob_id(nid), data=b"\x05", is_extended_id=False), t0 + 1.2)
    watch._judge(t0 + 0.74 + CONSUMER_S + 0.01)
    faults, _ = judge_silences(watch.silences, planned=2, t_safe_mono=t0 + 10, injections=[])
    assert [(f.kind.value, f.node) for f in faults] == [("node_lost", "drive3")]


def _busy_pinned(cpu: int) -> subprocess.Popen[bytes]:
    code = f"import os; os.sched_setaffinity(0, {{{cpu}}}); print(flush=True)\nwhile True: pass"
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline()  # pinned
    return proc


def test_two_busy_processes_on_one_cpu_wait_for_it_and_a_stopped_one_does_not() -> None:
    cpu = sorted(os.sched_getaffinity(0))[0]
    a, b = _busy_pinned(cpu), _busy_pinned(cpu)
    try:
        start = sched_stat(a.pid)
        assert start is not None
        deadline = time.monotonic() + 60.0
        while True:  # until the kernel counts 100 ms of a's wait (it shares the CPU with b)
            now = sched_stat(a.pid)
            assert now is not None
            if now.wait_s - start.wait_s > 0.1:
                break
            assert time.monotonic() < deadline, "a busy process sharing its CPU never waited for it"
            time.sleep(0.02)
        os.kill(a.pid, signal.SIGSTOP)
        while not process_stopped(a.pid):  # it runs once more to stop (waiting for the CPU meanwhile)
            assert time.monotonic() < deadline + 60.0
            time.sleep(0.01)
        stopped = sched_stat(a.pid)
        assert stopped is not None
        b_from = sched_stat(b.pid)
        assert b_from is not None
        while (sched_stat(b.pid) or b_from).run_s - b_from.run_s < 0.2:
            assert time.monotonic() < deadline + 60.0
            time.sleep(0.02)  # until b ran 200 ms more, alone on the CPU
        after = sched_stat(a.pid)
        assert after is not None and after.wait_s == stopped.wait_s  # a stopped process waits for nothing
    finally:
        for p in (a, b):
            p.kill()
            p.wait()


def test_a_process_runnable_but_kept_off_the_cpu_is_seen_waiting_and_a_stopped_one_is_not() -> None:
    cpu = sorted(os.sched_getaffinity(0))[0]
    busy = _busy_pinned(cpu)
    code = (
        f"import os; os.sched_setaffinity(0, {{{cpu}}}); os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\n"
        "print(flush=True)\nwhile True: pass"
    )
    idle = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    try:
        assert idle.stdout is not None and idle.stdout.readline()
        deadline = time.monotonic() + 60.0
        before = sched_stat(idle.pid)
        while True:  # SCHED_IDLE beside a busy process on its CPU: runnable, rarely put on it
            time.sleep(0.05)
            after = sched_stat(idle.pid)
            assert before is not None and after is not None
            if after.runnable and (after.run_s, after.slices) == (before.run_s, before.slices):
                break  # runnable and not run for 50 ms: what a judge counts as waiting
            assert time.monotonic() < deadline, "a runnable process kept off its CPU was never seen waiting"
            before = after
        os.kill(idle.pid, signal.SIGSTOP)
        while not process_stopped(idle.pid):
            assert time.monotonic() < deadline + 60.0
            time.sleep(0.01)
        stopped = sched_stat(idle.pid)
        assert stopped is not None and not stopped.runnable  # stopped: waits for nothing
    finally:
        for p in (busy, idle):
            p.kill()
            p.wait()
    assert sched_stat(idle.pid) is None  # gone


def test_a_hub_member_knows_its_hubs_pid_a_virtual_bus_has_none() -> None:
    hub = start_hub(None)
    try:
        bus = hub_transport(str(hub.address)).open(FIELDBUS)
        try:
            assert carrier_pid(bus) == hub.pid
        finally:
            bus.shutdown()
    finally:
        hub.stop()
    virtual = virtual_transport(prefix="run-queue-pid").open(FIELDBUS)
    try:
        assert carrier_pid(virtual) is None
    finally:
        virtual.shutdown()


# ------------------------------------------------------------------ a machine at random


class MachineAtRandom(RuleBasedStateMachine):
    """A heartbeat producer behind a hub on a machine at random, judged by a node's consumer that
    runs on time (its service at every deadline it asks for).  The hub, by turns: runs with
    hundreds of short waits for a CPU (up to half the time waiting, runnable or not at a look, on
    a CPU or not), or is starved: runnable, its run time and slices standing still, the beats
    meanwhile held and handed over when it runs again (the kernel then adds the whole wait and one
    slice).  The producer beats every 200 ms until it stops.  After every step: a producer that
    beats is never lost, whatever the machine did; a producer that stopped is lost once, and by
    1.5 consumer times (the consumer time, then at most half of it for a hub runnable at the
    judgement) plus two looks after its last beat, or 2.5 consumer times after the end of the last
    wait long enough to excuse (a quarter of the consumer time) -- never excused for as long as the
    machine is merely busy."""

    STEP_S = 0.005
    BEAT_S = 0.2

    def __init__(self) -> None:
        super().__init__()
        self.stats = Stats()
        self.stats.wait[HUB_PID], self.stats.slices[HUB_PID] = 0.0, 0
        self.consumer = NodeHeartbeatConsumer(ledger(self.stats))
        self.consumer.configure({127: CONSUMER_S})
        self.now = 0.0
        self.alive = True
        self.held = False  # a beat came while the hub was starved: handed over when it runs
        self.next_beat = 0.0
        self.last_heard = 0.0
        self.long_wait_end = -1.0
        self.lost: list[float] = []
        self.consumer.on_heartbeat(127, 0.0)

    def _tick(self, starved: bool) -> None:
        self.now = round(self.now + self.STEP_S, 9)
        self.stats.t = self.now
        if self.alive and self.now >= self.next_beat - 1e-9:
            self.next_beat += self.BEAT_S
            if starved:
                self.held = True
            else:
                self._heard()
        self._judge()

    def _heard(self) -> None:
        self.consumer.on_heartbeat(127, self.now)
        self.last_heard = self.now

    def _judge(self) -> None:
        due = self.consumer.next_deadline()
        if due is not None and self.now >= due - 1e-9:
            self.lost += [self.now] * len(self.consumer.expired(self.now))

    @rule(
        ms=st.integers(5, 400),
        wait_fraction=st.floats(0.0, 0.5),
        slice_ms=st.sampled_from([1, 2, 5]),
        runnable=st.booleans(),
        on_cpu=st.booleans(),
    )
    def busy(self, ms: int, wait_fraction: float, slice_ms: int, runnable: bool, on_cpu: bool) -> None:
        stats = self.stats
        stats.runnable[HUB_PID] = runnable
        for _ in range(ms // 5):
            stats.wait[HUB_PID] += wait_fraction * self.STEP_S
            stats.slices[HUB_PID] += max(1, 5 // slice_ms)
            if on_cpu:
                stats.run[HUB_PID] = stats.run.get(HUB_PID, 0.0) + (1 - wait_fraction) * self.STEP_S
            self._tick(starved=False)

    @rule(ms=st.integers(5, 1500))
    def starved(self, ms: int) -> None:
        stats = self.stats
        stats.runnable[HUB_PID] = True
        for _ in range(ms // 5):
            self._tick(starved=True)
        stats.wait[HUB_PID] += ms // 5 * self.STEP_S
        stats.slices[HUB_PID] += 1
        stats.runnable[HUB_PID] = False
        if ms // 5 * self.STEP_S >= CONSUMER_S / 4:
            self.long_wait_end = self.now
        if self.held:
            self.held = False
            self._heard()  # the hub runs: the held beat reaches the node before it judges again
        self._judge()

    @rule()
    def stop(self) -> None:
        self.alive = False

    @invariant()
    def a_beating_producer_is_never_lost_and_a_stopped_one_is_lost_in_time(self) -> None:
        if self.alive:
            assert self.lost == []
            return
        assert len(self.lost) <= 1
        bound = max(self.last_heard + 1.5 * CONSUMER_S, self.long_wait_end + 2.5 * CONSUMER_S) + 2 * RECHECK_S + self.STEP_S
        if self.now > bound and not self.held:
            assert self.lost, f"stopped at {self.last_heard:.3f} s, not lost by {self.now:.3f} s"


TestMachineAtRandom = MachineAtRandom.TestCase
TestMachineAtRandom.settings = settings(max_examples=150, stateful_step_count=15, deadline=None)
