"""Plant micro-benchmark and drivetrain feasibility check (``python -m host.cli.selfcheck`` runs it).

This module owns two quick measurements the lead asked for, printed (logging at INFO):

* kernel load/compile time of the first ``Plant`` step and µs per :meth:`Plant.step`
  (CPU time, best and median of repeated batches), with 4 RK4 sub-steps per 1 ms;
* peak / RMS joint torque of the nominal inverse dynamics along the gate path of docs/robot-model.md §6.1–6.2
  (25 × 305 × 25 mm, +90° tool turn, 4-5-6-7 law, overlap blend f_z = 0.4, f_h = 0.15) for
  single-journey times 0.50 / 0.25 / 0.15 s, to compare with the joint torque limit.

The gate path here is a self-contained copy of docs/robot-model.md §6.2 (default blend) for this check
only; the host's trajectory module is the reference for real runs.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from plant import dynamics, kinematics
from plant.params import default_true_plant, nominal_mass_model, robot_md_mass_model
from plant.simulator import Plant

logger = logging.getLogger(__name__)

RAD_PER_COUNT = 2.0 * math.pi / (10 * 2**20)  # = bus.units.RAD_PER_COUNT (plant must not import bus)
TORQUE_LSB_NM = 1e-6


def _law4567(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.clip(tau, 0.0, 1.0)
    s = 35 * t**4 - 84 * t**5 + 70 * t**6 - 20 * t**7
    sd = 140 * t**3 * (1 - t) ** 3
    sdd = 420 * t**2 * (1 - t) ** 2 * (1 - 2 * t)
    return s, sd, sdd


def _axis(t: np.ndarray, t0: float, t1: float, length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = t1 - t0
    s, sd, sdd = _law4567((t - t0) / w)
    inside = (t >= t0) & (t <= t1)
    return length * s, np.where(inside, length * sd / w, 0.0), np.where(inside, length * sdd / w**2, 0.0)


def gate_path(
    T: float, ts_s: float = 1e-3, fz: float = 0.4, fh: float = 0.15, dtheta: float = math.pi / 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, X, Ẋ, Ẍ) of one single journey of the docs/robot-model.md §6.1–6.2 gate path (pick at x = −0.1525 m)."""
    t = np.arange(0.0, T + 0.5 * ts_s, ts_s)
    X = np.zeros((t.size, 4))
    Xd = np.zeros_like(X)
    Xdd = np.zeros_like(X)
    x, xd, xdd = _axis(t, fh * T, (1 - fh) * T, 0.305)
    th, thd, thdd = _axis(t, fh * T, (1 - fh) * T, dtheta)
    zu, zud, zudd = _axis(t, 0.0, fz * T, 0.025)
    zd, zdd1, zddd = _axis(t, (1 - fz) * T, T, -0.025)
    X[:, 0], Xd[:, 0], Xdd[:, 0] = -0.1525 + x, xd, xdd
    X[:, 2], Xd[:, 2], Xdd[:, 2] = -0.65 + zu + zd, zud + zdd1, zudd + zddd
    X[:, 3], Xd[:, 3], Xdd[:, 3] = th, thd, thdd
    return t, X, Xd, Xdd


def bench_step(batches: int = 30, steps: int = 1000) -> dict[str, float]:
    """First-step time (kernel compile or cache load) and µs per Plant.step (CPU time)."""
    cfg = default_true_plant()
    t0 = time.perf_counter()
    p = Plant(cfg, 1e-3, 4, RAD_PER_COUNT, TORQUE_LSB_NM)
    t, X, Xd, Xdd = gate_path(0.15)
    q, qd, qdd = kinematics.joint_states_from_task(X, Xd, Xdd)
    tau = dynamics.true_inverse_dynamics(q, qd, qdd, cfg)
    units = np.rint(tau / TORQUE_LSB_NM).astype(np.int64)
    p.reset(q[0], qd[0])
    p.step(units[0])
    first = time.perf_counter() - t0
    per = []
    for _ in range(batches):
        p.reset(q[0], qd[0])
        c0 = time.process_time()
        for n in range(steps):
            p.step(units[min(n, len(units) - 1)])
        per.append((time.process_time() - c0) / steps * 1e6)
    return {"first_step_s": first, "step_us_best": min(per), "step_us_median": float(np.median(per))}


def peak_torques() -> list[tuple[float, str, np.ndarray, np.ndarray]]:
    """(T, model name, peak |τ| (4,), RMS τ (4,)) along the gate path for T = 0.5/0.25/0.15 s."""
    models = {"docs/robot-model.md 1 kW (J_m=1.9e-4)": robot_md_mass_model(), "nominal 3 kW (J_m=7.16e-4)": nominal_mass_model()}
    out = []
    for T in (0.50, 0.25, 0.15):
        _, X, Xd, Xdd = gate_path(T, ts_s=1e-4)
        q, qd, qdd = kinematics.joint_states_from_task(X, Xd, Xdd)
        for name, m in models.items():
            tau = dynamics.inverse_dynamics(q, qd, qdd, m)
            out.append((T, name, np.abs(tau).max(0), np.sqrt((tau**2).mean(0))))
        tau = dynamics.true_inverse_dynamics(q, qd, qdd, default_true_plant())
        out.append((T, "true plant incl. friction", np.abs(tau).max(0), np.sqrt((tau**2).mean(0))))
    return out


def report() -> None:
    """Both measurements, logged at INFO (what ``python -m host.cli.selfcheck`` shows)."""
    r = bench_step()
    logger.info("first Plant step (compile or cache load): %.2f s", r["first_step_s"])
    logger.info("Plant.step: best %.2f us, median %.2f us (CPU time, 4 RK4 sub-steps)", r["step_us_best"], r["step_us_median"])
    logger.info("joint torque limit %.1f N·m", default_true_plant().joint_torque_limit_nm)
    for T, name, pk, rms in peak_torques():
        logger.info(
            "T=%.2f s  %-28s peak |τ| = %s N·m  RMS = %s N·m",
            T,
            name,
            np.array2string(pk, precision=1),
            np.array2string(rms, precision=1),
        )
