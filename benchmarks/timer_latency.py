"""The machine's own real-time floor: how late a lone periodic loop wakes, for ``ilcrig run --realtime``.

One process does nothing but wait for t0 + n·Ts, n = 0..N−1, the way the plant waits for a paced
tick (``plant/plant_node_trial.py``: sleep until ``spin_s`` before the due time, then wait the rest on the
clock), in ``SCHED_FIFO`` at ``--rt-priority`` like the rig's lockstep processes when that is
permitted. It prints the lateness of the wake-ups (p50, p99, p99.9, max) and how many came later
than one period. Then it spins on the clock for ``--spin-s`` seconds and counts the gaps between
two consecutive clock readings longer than half a period: the moments the process did not run at
all, although it never waited, and the CPU time the hypervisor took from the machine meanwhile
(``/proc/stat`` steal). No rig can keep a deadline the machine itself misses: a virtual machine
whose CPU is taken away by its host shows it here, with nothing else running.

In ``SCHED_FIFO`` the spinning runs in slices of half a second with half a second of sleep between
them: a real-time task that never sleeps is stopped by the kernel's real-time throttling
(``/proc/sys/kernel/sched_rt_runtime_us`` of every ``sched_rt_period_us``: 50 ms of every second by
default), and those 50 ms pauses are the kernel's rule, not the machine's floor.

    python benchmarks/timer_latency.py [--periods 10000] [--period-ms 1] [--rt-priority 10] [--spin-s 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.rig.realtime import cpu_steal_s  # noqa: E402

SPIN_S = 250e-6  # plant.plant_node.PlantNode.REALTIME_SPIN_S
#: spinning in SCHED_FIFO: slices of this length, each followed by as long a sleep (under the
#: kernel's real-time throttling, 950 ms of every 1 s by default), s
SPIN_SLICE_S = 0.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=int, default=10_000)
    ap.add_argument("--period-ms", type=float, default=1.0)
    ap.add_argument("--rt-priority", type=int, default=10, help="SCHED_FIFO priority, 0 = normal scheduling")
    ap.add_argument("--spin-s", type=float, default=3.0, help="length of the spinning test, s (0: skip it)")
    args = ap.parse_args()
    policy = "normal scheduling"
    if args.rt_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
            policy = f"SCHED_FIFO {args.rt_priority}"
        except PermissionError as err:
            policy = f"normal scheduling (SCHED_FIFO not permitted: {err.strerror})"
    ts = args.period_ms / 1e3
    n = args.periods
    late = [0.0] * n
    t0 = time.monotonic() + 0.01
    for i in range(n):
        due = t0 + i * ts
        while True:
            now = time.monotonic()
            if now >= due:
                break
            if due - now > SPIN_S + 50e-6:
                time.sleep(due - now - SPIN_S)
        late[i] = now - due
    late.sort()

    def q(p: float) -> float:
        return late[min(n - 1, int(p * n))] * 1e3

    over = sum(1 for x in late if x > ts)
    print(
        f"timer latency, {n} periods of {args.period_ms:g} ms, {policy}, load average {os.getloadavg()[0]:.1f}: "
        f"wake-up lateness p50 {q(0.5):.3f} ms, p99 {q(0.99):.3f} ms, p99.9 {q(0.999):.3f} ms, max {late[-1] * 1e3:.3f} ms; "
        f"{over} wake-ups ({100 * over / n:.1f} %) later than one period"
    )
    if args.spin_s > 0:
        sliced = policy.startswith("SCHED_FIFO")
        gaps: list[float] = []
        steal0 = cpu_steal_s()
        left = args.spin_s
        while left > 0:
            last = time.monotonic()
            end = last + (min(left, SPIN_SLICE_S) if sliced else left)
            while last < end:
                now = time.monotonic()
                if now - last > ts / 2:
                    gaps.append(now - last)
                last = now
            left -= SPIN_SLICE_S if sliced else left
            if sliced and left > 0:
                time.sleep(SPIN_SLICE_S)
        steal1 = cpu_steal_s()
        stolen = (
            f"; the hypervisor took {(steal1 - steal0) * 1e3:.0f} ms of CPU time from the machine meanwhile (steal, all CPUs)"
            if steal0 is not None and steal1 is not None
            else ""
        )
        how = f"in {SPIN_SLICE_S:g} s slices, for the real-time throttling" if sliced else "at once"
        long = sum(1 for g in gaps if g > ts)
        print(
            f"spinning {args.spin_s:g} s without waiting ({how}): {len(gaps)} gaps > {args.period_ms / 2:g} ms between "
            f"two clock readings, {long} > {args.period_ms:g} ms, longest {max(gaps, default=0.0) * 1e3:.3f} ms, "
            f"{sum(gaps) * 1e3:.1f} ms in all (the process did not run){stolen}"
        )


if __name__ == "__main__":
    main()
