"""Benchmark: cost of the learning laws against the trial length N.

For N = 251, 501, 1001, 2001, 5001, 10001, 20001 ticks per trial (path 1, ``ruckig``, single
journeys of 0.25 … 10 s at Ts = 1 ms; N = 251 is the 0.25 s cycle at Ts = 2 ms) and every law,
prints

* **prep** — the learning's preparation: the closed-loop model along the reference, the law, and
  its convergence check for 10 planned trials (spectral radius, 2-norm, the simulated prediction and
  the long-run verdict on the nominal plant and on the plant with twice the inertia);
* **update** — one ``law.update`` (for ``no-ilc-id`` its first one, which estimates the model);
* **CPU** — the CPU time of prep + update (all threads of the process: what a busy machine does not
  inflate, unlike the wall-clock times);
* **peak MB** — the peak resident memory of the process doing both (``VmHWM``, reset before), and
  its increase over the idle process;
* **floor** — one forward sweep of the closed-loop model (e = G u), measured in the same run; prep
  and update are also given in floors, which does not depend on how busy the machine is;
* the fitted growth exponent b of time ∝ N^b (least squares over all N).

Each measurement runs in a forked child after a warm-up (numba kernels loaded).  Goals on 2 cores:
prep + update ≤ 1 s at N = 501, ≤ 10 s and ≤ 500 MB at N = 20,001, exponent ≤ 1.3.

    python benchmarks/learning_cost.py [--laws pd-ilc,no-ilc] [--sizes 501,20001]
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import time
from typing import Any

import numpy as np

#: (N, single-journey time s, Ts s)
SIZES: tuple[tuple[int, float, float], ...] = (
    (251, 0.25, 0.002),
    (501, 0.25, 0.001),
    (1001, 0.5, 0.001),
    (2001, 1.0, 0.001),
    (5001, 2.5, 0.001),
    (10001, 5.0, 0.001),
    (20001, 10.0, 0.001),
)


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
    except OSError:
        pass


def _setup(n: int, cycle_s: float, ts_s: float) -> dict[str, Any]:
    from host.learning.gains import GainSpec, resolve_gains
    from host.planning.joint_reference import joint_reference
    from host.planning.paths import resolve_path
    from host.planning.task_plan import plan_task
    from plant.dynamics import inverse_dynamics, mass_matrix
    from plant.params import nominal_mass_model

    ref = joint_reference(plan_task(resolve_path("1"), cycle_s, "ruckig", ts_s))
    assert ref.q.shape[0] == n, (ref.q.shape, n)
    model = nominal_mass_model()
    inertia = mass_matrix(ref.q, model)
    gains = resolve_gains(GainSpec(), np.mean(np.diagonal(inertia, axis1=1, axis2=2), axis=0), ts_s)
    tau = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, model), dtype=float)
    return {"ref": ref, "inertia": inertia, "gains": gains, "tau": tau, "ts_s": ts_s, "mass_model": model}


def _measure(law_name: str, setup: dict[str, Any]) -> dict[str, float]:
    from host.learning.check import PROBE_TORQUE_FRACTION
    from host.learning.laws.base import LawContext
    from host.learning.laws.checked import build_law as make_law
    from host.learning.model import ClosedLoopModel
    from host.learning.protocol import TrialData
    from plant.params import Geometry

    g, ts = setup["gains"], setup["ts_s"]
    idle_kb = _status_kb("VmRSS")
    _reset_peak()
    c0 = time.process_time()
    t0 = time.perf_counter()
    model = ClosedLoopModel(setup["inertia"], g.kp, g.kd, ts)
    ctx = LawContext(
        gains=g,
        ts_s=ts,
        model=model,
        reference=setup["ref"],
        u0_nm=setup["tau"],
        mass_model=setup["mass_model"],
        geometry=Geometry(),
    )
    law = make_law(law_name, ctx)
    law.check(model, PROBE_TORQUE_FRACTION * setup["tau"], 10)
    t1 = time.perf_counter()
    c1 = time.process_time()
    e = model.g(PROBE_TORQUE_FRACTION * setup["tau"])
    u = setup["tau"]
    tau = u + model.k(e)
    c2 = time.process_time()
    t2 = time.perf_counter()
    law.update(TrialData(0, u, e, tau, tau - u, ts))
    t3 = time.perf_counter()
    c3 = time.process_time()
    floor = math.inf
    for _ in range(3):
        s = time.perf_counter()
        model.g(u)
        floor = min(floor, time.perf_counter() - s)
    peak_kb = _status_kb("VmHWM")
    return {
        "prep": t1 - t0,
        "update": t3 - t2,
        "cpu": (c1 - c0) + (c3 - c2),
        "floor": floor,
        "peak_mb": peak_kb / 1024,
        "delta_mb": (peak_kb - idle_kb) / 1024,
    }


def _child(law: str, size: tuple[int, float, float], queue: Any) -> None:
    try:
        queue.put(_measure(law, _setup(*size)))
    except Exception as exc:  # report, do not hang the parent
        queue.put({"error": f"{type(exc).__name__}: {exc}"})


def main() -> None:
    from host.learning.names import LAWS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--laws", default=",".join(LAWS))
    ap.add_argument("--sizes", default=",".join(str(s[0]) for s in SIZES))
    args = ap.parse_args()
    laws = [x for x in args.laws.split(",") if x]
    wanted = {int(x) for x in args.sizes.split(",") if x}
    sizes = [s for s in SIZES if s[0] in wanted]

    # warm-up in the parent: imports, numba kernels (cached), one small run of every law
    warm = _setup(*SIZES[1])
    for law in laws:
        _measure(law, warm)
    ctx = mp.get_context("fork")
    print(
        f"ilcrig learning benchmark: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; "
        "times in s (and in floors = one forward sweep e = G u at that N), memory = peak RSS of the process"
    )
    header = (
        f"{'law':10s} {'N':>6s} {'prep s':>8s} {'update s':>9s} {'CPU s':>7s} {'floor ms':>9s} "
        f"{'prep/fl':>8s} {'upd/fl':>7s} {'peak MB':>8s} {'+MB':>6s}"
    )
    print(header)
    results: dict[str, list[tuple[int, dict[str, float]]]] = {}
    for law in laws:
        for size in sizes:
            q = ctx.Queue()
            p = ctx.Process(target=_child, args=(law, size, q))
            p.start()
            r = q.get()
            p.join()
            if "error" in r:
                print(f"{law:10s} {size[0]:6d}  failed: {r['error']}")
                continue
            results.setdefault(law, []).append((size[0], r))
            print(
                f"{law:10s} {size[0]:6d} {r['prep']:8.3f} {r['update']:9.4f} {r['cpu']:7.3f} {1e3 * r['floor']:9.3f} "
                f"{r['prep'] / r['floor']:8.0f} {r['update'] / r['floor']:7.1f} {r['peak_mb']:8.0f} "
                f"{r['delta_mb']:6.0f}",
                flush=True,
            )
    print("\ngrowth exponent b (time ∝ N^b, least squares over the sizes) and the goals:")
    print(
        f"{'law':10s} {'b prep':>7s} {'b update':>9s} {'b prep+upd':>10s}  {'N=501 prep+upd s':>17s}  "
        f"{'N=20001 prep+upd s':>18s}  {'N=20001 peak MB':>15s}"
    )
    for law, rows in results.items():
        n = np.log([r[0] for r in rows])

        def slope(key: str, rows: list[tuple[int, dict[str, float]]] = rows, n: np.ndarray = n) -> float:
            y = np.log([max(sum(r[1][k] for k in key.split("+")), 1e-9) for r in rows])
            return float(np.polyfit(n, y, 1)[0]) if len(rows) > 1 else float("nan")

        by_n = dict(rows)
        at501 = by_n[501]["prep"] + by_n[501]["update"] if 501 in by_n else float("nan")
        at20k = by_n[20001]["prep"] + by_n[20001]["update"] if 20001 in by_n else float("nan")
        peak = by_n[20001]["peak_mb"] if 20001 in by_n else float("nan")
        print(
            f"{law:10s} {slope('prep'):7.2f} {slope('update'):9.2f} {slope('prep+update'):10.2f}  "
            f"{at501:17.3f}  {at20k:18.2f}  {peak:15.0f}"
        )


if __name__ == "__main__":
    main()
