"""Benchmark: the cost of the constrained norm-optimal law's QP per trial (``cno-ilc``).

For N = 501 and N = 5,001 samples per trial (path 1, ``ruckig``, 0.25 s and 2.5 s single journeys at
Ts = 1 ms) prints

* **setup** — building the sparse QP (states and inputs of every sample) and OSQP's set-up with
  its factorisation (once per model);
* **solve** — one trial's QP (cost and bounds updated, warm start), with OSQP's iterations and status;
* **floor** — one unconstrained norm-optimal update (the Riccati sweeps of ``no-ilc``), measured in
  the same run, and the ratios setup/floor and solve/floor (which do not depend on how busy the
  machine is);
* **nnz** — non-zeros of the constraint matrix (O(N)), and the peak resident memory (VmHWM).

The error fed to the QP is the first trial's error of the default experiment's kind (a 10 %
inverse-dynamics model error through the nominal closed loop); the limit is the drives' 264.6 N·m.

    python benchmarks/constrained_cost.py [--sizes 501,5001]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _vmhwm_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def measure(n: int) -> dict[str, float]:
    from host.learning.gains import GainSpec, resolve_gains
    from host.learning.laws.constrained import ConstrainedStep
    from host.learning.model import ClosedLoopModel
    from host.learning.norm_optimal import NormOptimalStep
    from host.planning.joint_reference import joint_reference
    from host.planning.paths import resolve_path
    from host.planning.task_plan import plan_task
    from plant.dynamics import inverse_dynamics, mass_matrix
    from plant.params import nominal_mass_model

    cycle_s = (n - 1) / 2 * 0.001
    ref = joint_reference(plan_task(resolve_path("1"), cycle_s, "ruckig", 0.001))
    mm = nominal_mass_model()
    inertia = mass_matrix(ref.q, mm)
    gains = resolve_gains(GainSpec(), np.mean(np.diagonal(inertia, axis1=1, axis2=2), axis=0), 0.001)
    model = ClosedLoopModel(inertia, gains.kp, gains.kd, 0.001)
    tau = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, mm), dtype=float)
    e = model.g(0.1 * tau)
    step = NormOptimalStep(model, 1e-5)
    step(e)  # warm-up (numba)
    t0 = time.perf_counter()
    reps = 5
    for _ in range(reps):
        step(e)
    floor = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    qp = ConstrainedStep(model, step.r, 264.6 * 0.98, None)
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    qp(tau, e, tau)
    solve = time.perf_counter() - t0
    return {
        "n": n,
        "setup_s": setup,
        "solve_s": solve,
        "iterations": qp.last_iterations,
        "status": qp.last_status,  # type: ignore[dict-item]
        "floor_s": floor,
        "nnz": qp.nnz,
        "peak_mb": _vmhwm_mb(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="501,5001")
    sizes = [int(s) for s in ap.parse_args().sizes.split(",")]
    print(
        f"{'N':>6}  {'setup s':>8}  {'solve s':>8}  {'iter':>5}  status   {'floor s':>9}  {'setup/floor':>11}  "
        f"{'solve/floor':>11}  {'nnz':>8}  {'peak MB':>7}"
    )
    for n in sizes:
        m = measure(n)
        print(
            f"{m['n']:>6}  {m['setup_s']:8.3f}  {m['solve_s']:8.3f}  {m['iterations']:>5}  {m['status']:<8} "
            f"{m['floor_s']:9.5f}  {m['setup_s'] / m['floor_s']:11.0f}  {m['solve_s'] / m['floor_s']:11.0f}  "
            f"{m['nnz']:>8}  {m['peak_mb']:7.0f}"
        )


if __name__ == "__main__":
    main()
