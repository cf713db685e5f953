"""A short joint move for bench-node tests and benchmarks: a smooth 1−cos move from a reachable pose
and the drive set-up that follows it (Ts = 1 ms)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bus import units

TS_S = 0.001


def short_reference(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` samples of the move: q, qd (rad, rad/s), ff (N·m, nominal inverse dynamics), q0 (rad)."""
    from plant.dynamics import inverse_dynamics
    from plant.kinematics import inverse_kinematics
    from plant.params import nominal_mass_model

    q0 = inverse_kinematics(np.array([0.02, -0.01, -0.65, 0.1]))
    t = np.arange(n) * TS_S
    T = (n - 1) * TS_S
    amp = np.array([0.03, -0.02, 0.025, -0.015])
    s = (1 - np.cos(np.pi * t / T))[:, None] / 2
    sd = (np.pi / T * np.sin(np.pi * t / T))[:, None] / 2
    sdd = ((np.pi / T) ** 2 * np.cos(np.pi * t / T))[:, None] / 2
    q = q0 + amp * s
    qd = amp * sd
    ff = inverse_dynamics(q, qd, amp * sdd, nominal_mass_model())
    return q, qd, np.asarray(ff), q0


def configure_drives(drives: list[Any], q: np.ndarray, qd: np.ndarray) -> None:
    """Gains, limits and the reference (q [rad], qd [rad/s]) on every drive, then enable."""
    counts = np.rint(q / units.RAD_PER_COUNT).astype(np.int64)
    for j, d in enumerate(drives):
        d.configure(kp_nm_per_rad=2400.0, kd_nms_per_rad=48.0, torque_limit_nm=200.0, following_error_rad=math.radians(10.0))
        d.set_mode(-1)  # table playback (the drive boots in profile position)
        d.load_reference(counts[:, j] * units.RAD_PER_COUNT, qd[:, j])
        d.enable()
