"""The jerk-limited ``ruckig`` profile: the Ruckig library planning one window of a journey, with
:class:`CartesianLimits`.

Why the lateral Ruckig move is a 1-DOF plan of the path parameter
-----------------------------------------------------------------
Ruckig 0.19 only phase-synchronises when a DOF is *limiting*; when ``minimum_duration`` sets the
duration there is no limiting DOF and it silently falls back to time synchronisation (see
``calculator_target.hpp``: the Phase branch needs ``limiting_dof``).  Measured on path 1 with a
0.175 s window: the x/θ move deviates from the straight line by 1 % of the stroke.  The lateral
move is therefore planned as what phase synchronisation means — one profile λ(t) ∈ [0, 1] scaled
onto every axis, (x, y, θ) = S + Δ·λ(t) — with limits v_λ = min_i v_i/|Δ_i| (same for a, j),
which keeps every per-axis limit and is straight by construction.  The straightness is still
checked after sampling (:class:`TrajectoryError` if it ever fails).

Cartesian limits (:class:`CartesianLimits`, used by ``ruckig`` only)
--------------------------------------------------------------------
Per-axis box limits at the scale of the 4-5-6-7 law at 0.15 s on the 305 mm gate (docs/robot-model.md §6.5:
≈ 210 m/s², 6.4 m/s, 1.4·10⁴ m/s³ on x; 33 rad/s, 1.1·10³ rad/s², 7·10⁴ rad/s³ on θ), in line with
the fastest Delta/Par4-class robots (docs/robot-model.md S6: 5.5 m/s, 165 m/s², 13 g):
x/y/z: 6 m/s, 200 m/s², 2·10⁴ m/s³; θ: 40 rad/s, 1500 rad/s², 1·10⁵ rad/s³.  With these every
built-in path is feasible with ``ruckig`` at 0.15 s (path 1 needs ≥ 0.132 s).

May import: ``numpy``, ``ruckig`` (inside functions: importing this module does not load it),
:mod:`host.planning.journeys`, :mod:`host.planning.planning_errors`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.planning.journeys import AxisWindows, Journey, axis_windows
from host.planning.planning_errors import TrajectoryError

logger = logging.getLogger(__name__)

__all__ = ["CartesianLimits", "journey_ruckig", "ruckig_min_durations", "ruckig_needed_cycle", "windows_fit"]


#: Lateral displacements (m or rad) at or below this are no move for the Ruckig path parameter.
_LAT_NEGLIGIBLE = 1e-9


@dataclass(frozen=True)
class CartesianLimits:
    """Per-axis kinematic limits for the jerk-limited (``ruckig``) profile.

    Velocity m/s (rad/s), acceleration m/s² (rad/s²), jerk m/s³ (rad/s³); the same limits
    apply to x, y and z.  See the module docstring for how the defaults were chosen.
    """

    v_xyz_m_s: float = 6.0
    a_xyz_m_s2: float = 200.0
    j_xyz_m_s3: float = 2.0e4
    v_theta_rad_s: float = 40.0
    a_theta_rad_s2: float = 1500.0
    j_theta_rad_s3: float = 1.0e5

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise TrajectoryError(f"CartesianLimits.{name} must be a finite number > 0, got {value!r}")

    @property
    def velocity(self) -> np.ndarray:
        """(4,) velocity limits for (x, y, z, θ)."""
        return np.array([self.v_xyz_m_s] * 3 + [self.v_theta_rad_s])

    @property
    def acceleration(self) -> np.ndarray:
        """(4,) acceleration limits for (x, y, z, θ)."""
        return np.array([self.a_xyz_m_s2] * 3 + [self.a_theta_rad_s2])

    @property
    def jerk(self) -> np.ndarray:
        """(4,) jerk limits for (x, y, z, θ)."""
        return np.array([self.j_xyz_m_s3] * 3 + [self.j_theta_rad_s3])


def _ruckig_plan(p0: float, p1: float, v: float, a: float, jerk: float, ts: float, n_window: int | None) -> Any:
    """1-DOF rest-to-rest Ruckig plan; time-optimal if ``n_window`` is None, else exactly n_window samples.

    Ruckig 0.19 can fail in step 1 on the exact boundary between profile types (e.g. a 40 mm
    move from −0.625 m with a = 200 m/s², j = 2·10⁴ m/s³, where the acceleration just touches its
    limit).  Such a failure is retried with the acceleration and jerk limits lowered by a few
    parts in 10⁹ (deterministic, still within the limits).
    """
    from ruckig import DurationDiscretization, InputParameter, Result, Ruckig, RuckigError, Trajectory

    last = ""
    for shrink in (0.0, 1e-9, 1e-7, 1e-5):
        otg = Ruckig(1, ts)
        inp = InputParameter(1)
        inp.current_position = [float(p0)]
        inp.target_position = [float(p1)]
        inp.max_velocity = [v]
        inp.max_acceleration = [a * (1.0 - shrink)]
        inp.max_jerk = [jerk * (1.0 - 2.0 * shrink)]
        if n_window is not None:
            # slightly below the whole-sample window so that Discrete rounding cannot add a sample
            inp.minimum_duration = (n_window - 1e-6) * ts
            inp.duration_discretization = DurationDiscretization.Discrete
        traj = Trajectory(1)
        try:
            res = otg.calculate(inp, traj)
        except RuckigError as exc:
            last = str(exc).strip().splitlines()[0] if str(exc).strip() else "RuckigError"
            logger.debug("ruckig failed for %g -> %g (shrink %g): %s", p0, p1, shrink, last)
            continue
        if res == Result.Working:
            return traj
        last = str(res)
    raise TrajectoryError(f"ruckig failed for a move {float(p0):g} -> {float(p1):g}: {last}")


def _ruckig_window(
    p0: float, p1: float, v: float, a: float, jerk: float, ts: float, n_window: int, stretch: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sampled (p, v, a) of a 1-DOF rest-to-rest move lasting exactly ``n_window`` samples.

    ``stretch="scale"``: the limits are scaled by k = d_opt/window (v·k, a·k², j·k³) so that the
    time-optimal profile itself fills the window — the time-optimal profile slowed down
    uniformly.  ``stretch="hold"``: Ruckig stretches the profile at the full limits (it keeps
    the peak acceleration and lowers the cruise speed).  Either way ``minimum_duration`` +
    ``Discrete`` pin the duration to the window.
    """
    if stretch == "scale":
        d_opt = _ruckig_plan(p0, p1, v, a, jerk, ts, None).duration
        # a hair above the exact ratio, so that the scaled optimum is just inside the window and
        # minimum_duration (not a rounding of the optimum) sets the duration
        k = min(1.0, d_opt / (n_window * ts) * (1.0 + 1e-9))
        v, a, jerk = v * k, a * k**2, jerk * k**3
    return _sample_ruckig(_ruckig_plan(p0, p1, v, a, jerk, ts, n_window), n_window, ts)


def _lateral_limits(delta: np.ndarray, lim: CartesianLimits) -> tuple[float, float, float]:
    """Limits of the path parameter λ ∈ [0, 1] that keep every lateral axis inside its box limits."""
    axes = [(i, abs(d)) for i, d in zip((0, 1, 3), delta) if abs(d) > _LAT_NEGLIGIBLE]
    v = min(lim.velocity[i] / d for i, d in axes)
    a = min(lim.acceleration[i] / d for i, d in axes)
    jk = min(lim.jerk[i] / d for i, d in axes)
    return v, a, jk


def _has_lateral(delta: np.ndarray) -> bool:
    return bool(np.any(np.abs(delta) > _LAT_NEGLIGIBLE))


def ruckig_min_durations(j: Journey, lim: CartesianLimits, ts: float) -> tuple[float, float, float]:
    """Time-optimal durations (s) of z up, lateral, z down of one journey."""
    vz, az, jz = lim.v_xyz_m_s, lim.a_xyz_m_s2, lim.j_xyz_m_s3
    d_up = _ruckig_plan(j.start[2], j.top_z, vz, az, jz, ts, None).duration
    d_dn = _ruckig_plan(j.top_z, j.end[2], vz, az, jz, ts, None).duration
    delta = j.delta_lat
    d_lat = 0.0
    if _has_lateral(delta):
        d_lat = _ruckig_plan(0.0, 1.0, *_lateral_limits(delta, lim), ts, None).duration
    return d_up, d_lat, d_dn


def windows_fit(w: AxisWindows, d: tuple[float, float, float], ts: float) -> bool:
    eps = 1e-9
    return d[0] <= w.n_z * ts + eps and d[2] <= w.n_z * ts + eps and d[1] <= w.n_lat * ts + eps


def _sample_ruckig(traj: Any, n_window: int, ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if abs(traj.duration - n_window * ts) > 1e-9:
        raise TrajectoryError(f"ruckig returned a {traj.duration:.9f} s profile for a {n_window * ts:.9f} s window")
    p = np.empty(n_window + 1)
    v = np.empty(n_window + 1)
    a = np.empty(n_window + 1)
    for k in range(n_window + 1):
        pk, vk, ak = traj.at_time(min(k * ts, traj.duration))
        p[k], v[k], a[k] = pk[0], vk[0], ak[0]
    # the window ends exactly at rest: remove the last-sample rounding of at_time
    v[-1] = 0.0
    a[-1] = 0.0
    v[0] = 0.0
    a[0] = 0.0
    return p, v, a


def journey_ruckig(j: Journey, w: AxisWindows, ts: float, lim: CartesianLimits, stretch: str) -> tuple[np.ndarray, ...]:
    """(m+1, 4) X, Xd, Xdd of one journey, docs/robot-model.md §6.3 construction (b) on fixed windows."""
    vz, az, jz = lim.v_xyz_m_s, lim.a_xyz_m_s2, lim.j_xyz_m_s3
    X = np.tile(j.start, (w.m + 1, 1))
    Xd = np.zeros_like(X)
    Xdd = np.zeros_like(X)

    def place(axis_cols: list[int], scale: np.ndarray, base: np.ndarray, n0: int, n1: int, pva: tuple) -> None:
        p, v, a = pva
        for col, sc, b0 in zip(axis_cols, scale, base):
            X[n0 : n1 + 1, col] = b0 + sc * p
            X[n1 + 1 :, col] = b0 + sc * p[-1]
            Xd[n0 : n1 + 1, col] += sc * v
            Xdd[n0 : n1 + 1, col] += sc * a

    up = _ruckig_window(j.start[2], j.top_z, vz, az, jz, ts, w.n_z, stretch)
    dn = _ruckig_window(j.top_z, j.end[2], vz, az, jz, ts, w.n_z, stretch)
    # z = up(t) + (down(t) - top): write up, then add the descent on top of it
    place([2], np.array([1.0]), np.array([0.0]), 0, w.n_z, up)
    n0 = w.m - w.n_z
    X[n0:, 2] += dn[0] - j.top_z
    Xd[n0:, 2] += dn[1]
    Xdd[n0:, 2] += dn[2]
    delta = j.delta_lat
    if _has_lateral(delta):
        lam = _ruckig_window(0.0, 1.0, *_lateral_limits(delta, lim), ts, w.n_lat, stretch)
        place([0, 1, 3], delta, j.start[[0, 1, 3]], w.n_h, w.m - w.n_h, lam)
    # pin the journey end exactly on the target (no accumulated rounding)
    X[-1] = j.end
    return X, Xd, Xdd


def ruckig_needed_cycle(m: int, fz: float, fh: float, durations: list[tuple[float, float, float]], ts: float) -> float:
    """Smallest cycle (whole samples) whose windows fit every time-optimal Ruckig duration, s."""
    d_z = max(max(d[0], d[2]) for d in durations)
    d_lat = max(d[1] for d in durations)
    guess = max(d_z / fz, d_lat / max(1.0 - 2.0 * fh, 1e-9))
    m_try = max(1, int(math.floor(guess / ts)) - 3)
    while True:
        try:
            w = axis_windows(m_try, fz, fh)
        except TrajectoryError:
            w = None
        if w is not None and all(windows_fit(w, d, ts) for d in durations):
            return m_try * ts
        m_try += 1
