"""The machine's own real-time floor: how late a lone periodic loop wakes, for ``ilcrig run --realtime``.

One process does nothing but wait for t0 + n·Ts, n = 0..N−1, the way the plant waits for a paced
tick in the scheduling it gets (``plant/plant_node_trial.py``, ``host/rig/fair_scheduling.py``):
in ``SCHED_FIFO`` at ``--rt-priority`` (where permitted) it sleeps until 250 µs before the due
time and waits the rest on the clock; in normal scheduling (``--rt-priority 0``, or SCHED_FIFO not
permitted) it takes the lockstep processes' 100 µs scheduler slice and sleeps until the due time.
Both with the plant's 1 µs timer slack. It prints the lateness of the wake-ups (p50, p99, p99.9,
max) and how many came later than one period. Then it spins on the clock for ``--spin-s``
seconds and counts the gaps between two consecutive clock readings longer than half a period:
the moments the process did not run at all, although it never waited, and the CPU time the
hypervisor took from the machine meanwhile (``/proc/stat`` steal). No rig can keep a deadline
the machine itself misses: a virtual machine whose CPU is taken away by its host shows it here,
with nothing else running.

In ``SCHED_FIFO`` the spinning runs in slices of half a second with half a second of sleep between
them: a real-time task that never sleeps is stopped by the kernel's real-time throttling
(``/proc/sys/kernel/sched_rt_runtime_us`` of every ``sched_rt_period_us``: 50 ms of every second by
default), and those 50 ms pauses are the kernel's rule, not the machine's floor.

``--json`` prints one JSON object instead of the lines (``benchmarks/rt_compare.py`` reads it).

    python benchmarks/timer_latency.py [--periods 10000] [--period-ms 1] [--rt-priority 10] [--spin-s 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bus.timer_slack import fine_timer_slack  # noqa: E402
from host.rig.fair_scheduling import LOCKSTEP_SLICE_NS, set_fair_slice  # noqa: E402
from host.rig.realtime import cpu_steal_s  # noqa: E402

SPIN_S = 250e-6  # plant.plant_node.PlantNode.REALTIME_SPIN_S
#: spinning in SCHED_FIFO: slices of this length, each followed by as long a sleep (under the
#: kernel's real-time throttling, 950 ms of every 1 s by default), s
SPIN_SLICE_S = 0.5


def wake_lateness(periods: int, period_s: float, spin_s: float) -> list[float]:
    """The lateness [s] of ``periods`` wake-ups at t0 + n·period: sleep until ``spin_s`` before each
    due time (until it, with 0), then wait the rest on the clock; sorted."""
    late = [0.0] * periods
    t0 = time.monotonic() + 0.01
    for i in range(periods):
        due = t0 + i * period_s
        while True:
            now = time.monotonic()
            if now >= due:
                break
            if spin_s == 0.0:
                time.sleep(due - now)
            elif due - now > spin_s + 50e-6:
                time.sleep(due - now - spin_s)
        late[i] = now - due
    late.sort()
    return late


def spin_gaps(spin_s: float, period_s: float, sliced: bool) -> list[float]:
    """Spin on the clock for ``spin_s`` s (in :data:`SPIN_SLICE_S` slices with as long a sleep between
    them when ``sliced``): the gaps [s] longer than half a period between two clock readings."""
    gaps: list[float] = []
    left = spin_s
    while left > 0:
        last = time.monotonic()
        end = last + (min(left, SPIN_SLICE_S) if sliced else left)
        while last < end:
            now = time.monotonic()
            if now - last > period_s / 2:
                gaps.append(now - last)
            last = now
        left -= SPIN_SLICE_S if sliced else left
        if sliced and left > 0:
            time.sleep(SPIN_SLICE_S)
    return gaps


def take_scheduling(rt_priority: int) -> tuple[str, bool]:
    """This process scheduled as a lockstep process of ``ilcrig run --realtime --rt-priority P`` would
    be: ``(in words, in SCHED_FIFO)``."""
    if rt_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
            return f"SCHED_FIFO {rt_priority}", True
        except PermissionError as err:
            why = f"SCHED_FIFO not permitted: {err.strerror}"
    else:
        why = "--rt-priority 0"
    try:
        set_fair_slice(0, LOCKSTEP_SLICE_NS)
        got = f"{LOCKSTEP_SLICE_NS / 1000:g} µs slice"
    except OSError as err:
        got = f"no short slice: {err.strerror}"
    return f"normal scheduling ({why}; {got})", False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=int, default=10_000)
    ap.add_argument("--period-ms", type=float, default=1.0)
    ap.add_argument("--rt-priority", type=int, default=10, help="SCHED_FIFO priority, 0 = normal scheduling")
    ap.add_argument("--spin-s", type=float, default=3.0, help="length of the spinning test, s (0: skip it)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()
    fine_timer_slack()
    policy, fifo = take_scheduling(args.rt_priority)
    ts = args.period_ms / 1e3
    n = args.periods
    load = os.getloadavg()[0]
    late = wake_lateness(n, ts, SPIN_S if fifo else 0.0)

    def q(p: float) -> float:
        return late[min(n - 1, int(p * n))]

    over = sum(1 for x in late if x > ts)
    out: dict[str, Any] = {
        "scheduling": policy,
        "fifo": fifo,
        "periods": n,
        "period_s": ts,
        "load_average_1min": load,
        "lateness_p50_s": q(0.5),
        "lateness_p99_s": q(0.99),
        "lateness_p999_s": q(0.999),
        "lateness_max_s": late[-1],
        "later_than_one_period": over,
    }
    if not args.json:
        print(
            f"timer latency, {n} periods of {args.period_ms:g} ms, {policy}, load average {load:.1f}: "
            f"wake-up lateness p50 {q(0.5) * 1e3:.3f} ms, p99 {q(0.99) * 1e3:.3f} ms, p99.9 {q(0.999) * 1e3:.3f} ms, "
            f"max {late[-1] * 1e3:.3f} ms; {over} wake-ups ({100 * over / n:.1f} %) later than one period"
        )
    if args.spin_s > 0:
        steal0 = cpu_steal_s()
        gaps = spin_gaps(args.spin_s, ts, sliced=fifo)
        steal1 = cpu_steal_s()
        steal_s = steal1 - steal0 if steal0 is not None and steal1 is not None else None
        out |= {"spin_s": args.spin_s, "gaps_s": sum(gaps), "longest_gap_s": max(gaps, default=0.0), "steal_s": steal_s}
        if not args.json:
            stolen = (
                f"; the hypervisor took {steal_s * 1e3:.0f} ms of CPU time from the machine meanwhile (steal, all CPUs)"
                if steal_s is not None
                else ""
            )
            how = f"in {SPIN_SLICE_S:g} s slices, for the real-time throttling" if fifo else "at once"
            long = sum(1 for g in gaps if g > ts)
            print(
                f"spinning {args.spin_s:g} s without waiting ({how}): {len(gaps)} gaps > {args.period_ms / 2:g} ms between "
                f"two clock readings, {long} > {args.period_ms:g} ms, longest {max(gaps, default=0.0) * 1e3:.3f} ms, "
                f"{sum(gaps) * 1e3:.1f} ms in all (the process did not run){stolen}"
            )
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
