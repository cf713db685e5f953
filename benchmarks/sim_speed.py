"""Benchmark: in-process lockstep speed of the default experiment (``ilcrig sim`` defaults).

Prints ticks/s of the whole experiment loop (plant + four fixed-point drives + host learning
between trials), the real-time factor at 1 kHz, and the cost of the pieces of one tick.
Target: >= 20,000 ticks/s on 2 cores.

    python benchmarks/sim_speed.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.experiment.trial_loop import run_experiment
    from host.sim.inprocess import InProcessBench

    cfg = build_config(None, {})
    t0 = time.perf_counter()
    plan = prepare(cfg)
    t_prepare = time.perf_counter() - t0

    rates = []
    walls = []
    for _ in range(args.repeat + 1):  # first run includes JIT warm-up / cache load
        bench = InProcessBench(cfg)
        t0 = time.perf_counter()
        res = run_experiment(plan, bench, None, mode="sim")
        walls.append(time.perf_counter() - t0)
        rates.append(res.summary["ticks_per_s"])
    ticks = res.summary["ticks"]
    steady = rates[1:]

    # pieces of one tick
    bench = InProcessBench(cfg)
    bench.start()
    plant, fw = bench.plant, bench.firmware[0]
    plant.reset(plan.ref.q[0], plan.ref.qd[0])
    tau = np.zeros(4, dtype=np.int64)
    dist = np.zeros(4)
    n = 20000
    t0 = time.perf_counter()
    for _ in range(n):
        plant.step(tau, dist)
    plant_us = (time.perf_counter() - t0) / n * 1e6
    c = int(plant.encoder_counts()[0])
    t0 = time.perf_counter()
    for i in range(n):
        fw.io_tick(i, c)
    drive_us = (time.perf_counter() - t0) / n * 1e6

    print("ilcrig in-process benchmark (default experiment: pd-ilc, path 1, 0.25 s, ruckig, 10 trials)")
    print(f"  prepare (plan, IK, feasibility, lifted model, convergence check): {t_prepare:.2f} s")
    print(f"  ticks per experiment: {ticks}")
    print(f"  first run (incl. JIT load): {rates[0]:,.0f} ticks/s")
    print(
        f"  steady: median {statistics.median(steady):,.0f} ticks/s "
        f"(min {min(steady):,.0f}, max {max(steady):,.0f}) over {len(steady)} runs"
    )
    print(
        f"  real-time factor at 1 kHz: {statistics.median(steady) / 1000:.1f}x ; target 20,000 ticks/s: "
        f"{statistics.median(steady) / 20000:.2f}x of target"
    )
    print(f"  experiment wall time incl. learning: median {statistics.median(walls[1:]):.3f} s")
    print(f"  Plant.step (4 RK4 sub-steps): {plant_us:.2f} us ; Drive.io_tick (idle, not enabled): {drive_us:.2f} us")


if __name__ == "__main__":
    main()
