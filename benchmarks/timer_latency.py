"""The machine's own real-time floor: how late a lone periodic loop wakes, for ``ilcrig run --realtime``.

One process does nothing but wait for t0 + n·Ts, n = 0..N−1, the way the plant waits for a paced
tick (``plant/node.py``: sleep until ``spin_s`` before the due time, then wait the rest on the
clock), in ``SCHED_FIFO`` at ``--rt-priority`` like the rig's lockstep processes when that is
permitted. It prints the lateness of the wake-ups (p50, p99, p99.9, max) and how many came later
than one period. Then it spins on the clock for ``--spin-s`` seconds and counts the gaps between
two consecutive clock readings longer than half a period: the moments the process did not run at
all, although it never waited. No rig can keep a deadline the machine itself misses: a virtual
machine whose CPU is taken away by its host shows it here, with nothing else running.

    python benchmarks/timer_latency.py [--periods 10000] [--period-ms 1] [--rt-priority 10] [--spin-s 3]
"""

from __future__ import annotations

import argparse
import os
import time

SPIN_S = 250e-6  # plant.node.BenchNode.REALTIME_SPIN_S


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
    print(f"timer latency, {n} periods of {args.period_ms:g} ms, {policy}, load average {os.getloadavg()[0]:.1f}: "
          f"wake-up lateness p50 {q(0.5):.3f} ms, p99 {q(0.99):.3f} ms, p99.9 {q(0.999):.3f} ms, max {late[-1] * 1e3:.3f} ms; "
          f"{over} wake-ups ({100 * over / n:.1f} %) later than one period")
    if args.spin_s > 0:
        gaps: list[float] = []
        last = time.monotonic()
        end = last + args.spin_s
        while last < end:
            now = time.monotonic()
            if now - last > ts / 2:
                gaps.append(now - last)
            last = now
        long = sum(1 for g in gaps if g > ts)
        print(f"spinning {args.spin_s:g} s without waiting: {len(gaps)} gaps > {args.period_ms / 2:g} ms between two clock "
              f"readings, {long} > {args.period_ms:g} ms, longest {max(gaps, default=0.0) * 1e3:.3f} ms, "
              f"{sum(gaps) * 1e3:.1f} ms in all (the process did not run)")


if __name__ == "__main__":
    main()
