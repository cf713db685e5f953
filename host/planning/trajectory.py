"""Task trajectories and joint references: motion laws, the pick→place→pick trial plan, the
joint reference by inverse kinematics, and the feasibility check against joint limits.

Owns
----
* the motion laws :func:`poly4567` and :func:`poly5` (docs/robot-model.md §6.3: analytic s, s', s'', s'''
  on normalised time τ ∈ [0, 1]) and the jerk-limited ``ruckig`` profile;
* :func:`plan_task` → :class:`TaskTrajectory` (t, X, Ẋ, Ẍ with X = (x, y, z, θ) in m, m, m, rad);
* :func:`joint_reference` → :class:`JointReference` (t, q, q̇, q̈ in rad, rad/s, rad/s²);
* :func:`check_feasibility` → :class:`FeasibilityReport`, with :class:`JointLimits`.

Time grid
---------
One trial is ``journeys`` single journeys of ``cycle_s`` each (default 2: pick→place, then the
mirrored place→pick with the opposite tool turn).  It is sampled at t_n = n·ts_s, n = 0..N−1,
N = round(journeys·cycle_s/ts_s) + 1, end point included; ``cycle_s`` must be a whole number of
samples, so the trial lasts exactly (N−1)·ts_s.

Corner blending (docs/robot-model.md §6.2, option 1, for every profile)
-------------------------------------------------------------
Inside one journey of M = cycle_s/ts_s samples each axis moves over its own window, rounded to
whole samples (symmetric, so the journey is mirror-symmetric in time):

* z up over samples [0, n_z], z down over [M − n_z, M], n_z = round(f_z·M);
* x, y, θ together over [n_h, M − n_h], n_h = round(f_h·M).

The polynomial laws put one law on each window (all analytic).  ``ruckig`` follows docs/robot-model.md
§6.3 construction (b) — z up, lateral, z down planned separately and summed on one clock — with
every window given exactly its length (``minimum_duration`` + ``DurationDiscretization.Discrete``,
so durations are whole samples).  If a time-optimal move does not fit its window the cycle is
infeasible (:class:`InfeasibleTaskError`, naming the shortest feasible cycle).  A window longer
than the time-optimal move is filled, by default (``ruckig_stretch="scale"``), by the
time-optimal profile slowed down uniformly (limits × k, k², k³ with k = d_opt/window), so loads
fall with 1/T² as with the polynomial laws; ``"hold"`` lets Ruckig stretch the profile at the
full limits (it keeps the peak acceleration and lowers the cruise speed: path 1 at 0.25 s then
peaks at 194 m/s² and 162 N·m instead of 55 m/s² and 45 N·m).

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

Errors
------
All subclass :class:`bus.errors.InputError` (a ``ValueError``; the CLI maps it to exit code 2):
:class:`TrajectoryError` (bad arguments, internal planning failure) and
:class:`InfeasibleTaskError` (the task cannot be done within the limits).  Reach failures are the
plant's ``OutOfReachError``, re-raised with the sample time and the point.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from bus.errors import InputError
from host.planning.paths import PathSpec

logger = logging.getLogger(__name__)

__all__ = [
    "PROFILES",
    "RUCKIG_STRETCH",
    "Profile",
    "TrajectoryError",
    "InfeasibleTaskError",
    "poly4567",
    "poly5",
    "CartesianLimits",
    "TaskTrajectory",
    "plan_task",
    "trial_samples",
    "JointReference",
    "joint_reference",
    "JointLimits",
    "FeasibilityReport",
    "check_feasibility",
]

Profile = Literal["poly4567", "poly5", "ruckig"]
#: Motion profiles accepted by :func:`plan_task`.
PROFILES: tuple[str, ...] = ("ruckig", "poly4567", "poly5")
#: How the ``ruckig`` profile fills a window longer than its time-optimal move (see plan_task).
RUCKIG_STRETCH: tuple[str, ...] = ("scale", "hold")

#: Tolerance on "cycle is a whole number of samples" (relative to one sample).
_SAMPLE_TOL = 1e-6
#: Straightness / bounding-box tolerances (m or rad).
_STRAIGHT_TOL = 1e-9
_BOX_TOL = 1e-9
#: Lateral displacements (m or rad) at or below this are no move for the Ruckig path parameter.
_LAT_NEGLIGIBLE = 1e-9


class TrajectoryError(InputError):
    """Bad planning arguments or an internal planning failure (one-line message)."""


class InfeasibleTaskError(InputError):
    """The task cannot be executed within the kinematic, joint or torque limits."""


# ----------------------------------------------------------------------------- motion laws

LawResult = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _law(tau: Any, coeffs: tuple[float, ...], first_power: int) -> LawResult:
    """Evaluate s(τ) = Σ c_k τ^(first_power+k) and its first three derivatives on τ.

    Outside [0, 1] the law is held: s = 0 before, s = 1 after, all derivatives 0.
    """
    tau = np.asarray(tau, dtype=float)
    # both laws are point-symmetric about (1/2, 1/2): evaluate on the nearer end to avoid the
    # cancellation of the coefficients near τ = 1 (s(1) is then exactly 1, s monotonic)
    upper = tau > 0.5
    x = np.clip(np.where(upper, 1.0 - tau, tau), 0.0, 1.0)
    s = np.zeros_like(x)
    s1 = np.zeros_like(x)
    s2 = np.zeros_like(x)
    s3 = np.zeros_like(x)
    for k, c in enumerate(coeffs):
        p = first_power + k
        s = s + c * x**p
        s1 = s1 + c * p * x ** (p - 1)
        s2 = s2 + c * p * (p - 1) * x ** (p - 2)
        s3 = s3 + c * p * (p - 1) * (p - 2) * x ** (p - 3)
    s = np.where(upper, 1.0 - s, s)
    s2 = np.where(upper, -s2, s2)
    inside = (tau >= 0.0) & (tau <= 1.0)
    s1 = np.where(inside, s1, 0.0)
    s2 = np.where(inside, s2, 0.0)
    s3 = np.where(inside, s3, 0.0)
    return s, s1, s2, s3


def poly4567(tau: Any) -> LawResult:
    """4-5-6-7 law s = 35τ⁴ − 84τ⁵ + 70τ⁶ − 20τ⁷ (zero velocity, acceleration and jerk at both ends).

    :param tau: normalised time t/T (scalar or array); held outside [0, 1].
    :returns: (s, s', s'', s''') derivatives with respect to τ.  Max s' = 2.1875 (τ = 0.5),
        max |s''| = 7.513 (τ = 0.2764, 0.7236), max |s'''| = 52.5 (τ = 0.5).
    """
    return _law(tau, (35.0, -84.0, 70.0, -20.0), 4)


def poly5(tau: Any) -> LawResult:
    """5th-order law s = 10τ³ − 15τ⁴ + 6τ⁵ (zero velocity and acceleration at both ends; jerk 60 there).

    :param tau: normalised time t/T (scalar or array); held outside [0, 1].
    :returns: (s, s', s'', s''').  Max s' = 1.875 (τ = 0.5), max |s''| = 5.774 (τ = 0.2113, 0.7887).
    """
    return _law(tau, (10.0, -15.0, 6.0), 3)


_POLY_LAWS: dict[str, Callable[[Any], LawResult]] = {"poly4567": poly4567, "poly5": poly5}


# ----------------------------------------------------------------------------- limits, records


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


@dataclass(frozen=True, eq=False)
class TaskTrajectory:
    """A sampled task-space trial.

    :ivar t: (N,) sample times t_n = n·ts_s, s.
    :ivar X: (N, 4) pose (x, y, z, θ) in m, m, m, rad.
    :ivar Xd: (N, 4) velocity in m/s, rad/s.
    :ivar Xdd: (N, 4) acceleration in m/s², rad/s².
    """

    t: np.ndarray
    X: np.ndarray
    Xd: np.ndarray
    Xdd: np.ndarray
    path: PathSpec
    profile: str
    cycle_s: float
    ts_s: float
    journeys: int = 2
    fz: float = 0.4
    fh: float = 0.15

    @property
    def n_samples(self) -> int:
        """Number of samples N (end point included)."""
        return int(self.t.shape[0])

    @property
    def duration_s(self) -> float:
        """Trial duration (N − 1)·ts_s, s."""
        return (self.n_samples - 1) * self.ts_s

    def describe(self) -> str:
        """One line for logs and reports."""
        return (
            f"{self.path.name}, profile {self.profile}, cycle {self.cycle_s:g} s x {self.journeys}, "
            f"Ts {self.ts_s:g} s, N = {self.n_samples}"
        )


def trial_samples(cycle_s: float, ts_s: float, journeys: int = 2) -> int:
    """N = round(journeys·cycle_s/ts_s) + 1 (end point included)."""
    return _samples_per_journey(cycle_s, ts_s) * journeys + 1


def _samples_per_journey(cycle_s: float, ts_s: float) -> int:
    if not (isinstance(ts_s, (int, float)) and math.isfinite(ts_s) and ts_s > 0):
        raise TrajectoryError(f"sample period must be > 0 s, got {ts_s!r}")
    if not (isinstance(cycle_s, (int, float)) and math.isfinite(cycle_s) and cycle_s > 0):
        raise TrajectoryError(f"cycle time must be > 0 s, got {cycle_s!r}")
    ratio = cycle_s / ts_s
    m = int(round(ratio))
    if m < 1 or abs(ratio - m) > _SAMPLE_TOL:
        raise TrajectoryError(f"cycle {cycle_s:g} s is not a whole number of samples of {ts_s:g} s")
    return m


@dataclass(frozen=True)
class _Windows:
    """Axis windows of one journey, in samples (local index 0..m)."""

    m: int
    n_z: int  # z up over [0, n_z], z down over [m - n_z, m]
    n_h: int  # lateral over [n_h, m - n_h]

    @property
    def n_lat(self) -> int:
        return self.m - 2 * self.n_h


def _windows(m: int, fz: float, fh: float) -> _Windows:
    n_z = int(math.floor(fz * m + 0.5))
    n_h = int(math.floor(fh * m + 0.5))
    w = _Windows(m, n_z, n_h)
    if n_z < 1 or w.n_lat < 1 or 2 * n_z > m:
        raise TrajectoryError(f"cycle of {m} samples is too short to place the axis windows (f_z {fz}, f_h {fh})")
    return w


# ----------------------------------------------------------------------------- journeys


@dataclass(frozen=True)
class _Journey:
    start: np.ndarray  # (4,) x, y, z, θ
    end: np.ndarray
    top_z: float

    @property
    def delta_lat(self) -> np.ndarray:
        """(3,) lateral displacement (Δx, Δy, Δθ)."""
        return self.end[[0, 1, 3]] - self.start[[0, 1, 3]]


def _journeys(path: PathSpec, journeys: int) -> list[_Journey]:
    pick = np.array([*path.pick_xyz, 0.0])
    place = np.array([*path.place_xyz, path.rotation_rad])
    out = []
    for k in range(journeys):
        a, b = (pick, place) if k % 2 == 0 else (place, pick)
        out.append(_Journey(a, b, path.top_z_m))
    return out


_LAT = (0, 1, 3)


def _journey_poly(j: _Journey, w: _Windows, ts: float, law: Callable[[Any], LawResult]) -> tuple[np.ndarray, ...]:
    """(m+1, 4) X, Xd, Xdd of one journey with a polynomial law on every window."""
    n = np.arange(w.m + 1, dtype=float)
    X = np.tile(j.start, (w.m + 1, 1))
    Xd = np.zeros_like(X)
    Xdd = np.zeros_like(X)

    def add(axis: int, n0: int, n1: int, delta: float) -> None:
        dur = (n1 - n0) * ts
        s, s1, s2, _ = law((n - n0) / (n1 - n0))
        X[:, axis] += delta * s
        Xd[:, axis] += delta * s1 / dur
        Xdd[:, axis] += delta * s2 / dur**2

    add(2, 0, w.n_z, j.top_z - j.start[2])
    add(2, w.m - w.n_z, w.m, j.end[2] - j.top_z)
    for axis in _LAT:
        add(axis, w.n_h, w.m - w.n_h, j.end[axis] - j.start[axis])
    return X, Xd, Xdd


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


def _ruckig_min_durations(j: _Journey, lim: CartesianLimits, ts: float) -> tuple[float, float, float]:
    """Time-optimal durations (s) of z up, lateral, z down of one journey."""
    vz, az, jz = lim.v_xyz_m_s, lim.a_xyz_m_s2, lim.j_xyz_m_s3
    d_up = _ruckig_plan(j.start[2], j.top_z, vz, az, jz, ts, None).duration
    d_dn = _ruckig_plan(j.top_z, j.end[2], vz, az, jz, ts, None).duration
    delta = j.delta_lat
    d_lat = 0.0
    if _has_lateral(delta):
        d_lat = _ruckig_plan(0.0, 1.0, *_lateral_limits(delta, lim), ts, None).duration
    return d_up, d_lat, d_dn


def _fits(w: _Windows, d: tuple[float, float, float], ts: float) -> bool:
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


def _journey_ruckig(j: _Journey, w: _Windows, ts: float, lim: CartesianLimits, stretch: str) -> tuple[np.ndarray, ...]:
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


# ----------------------------------------------------------------------------- checks


def _check_straight(X: np.ndarray, j: _Journey, label: str) -> None:
    """The lateral part (x, y, θ) of a journey must stay on the segment start→end."""
    s0 = j.start[[0, 1, 3]]
    delta = j.delta_lat
    P = X[:, [0, 1, 3]] - s0
    norm2 = float(delta @ delta)
    if norm2 == 0.0:
        dev = np.abs(P).max(initial=0.0)
    else:
        lam = P @ delta / norm2
        dev = float(np.abs(P - np.outer(lam, delta)).max(initial=0.0))
    if dev > _STRAIGHT_TOL:
        raise TrajectoryError(f"{label}: lateral move is not straight (deviation {dev:.3g})")


def _check_box(X: np.ndarray, path: PathSpec, label: str) -> None:
    """The trial must stay in the bounding box of its gate (no overshoot of the planned path)."""
    pick = np.array([*path.pick_xyz, 0.0])
    place = np.array([*path.place_xyz, path.rotation_rad])
    lo = np.minimum(pick, place)
    hi = np.maximum(pick, place)
    hi[2] = path.top_z_m
    for axis, name in enumerate(("x", "y", "z", "theta")):
        below = lo[axis] - X[:, axis].min()
        above = X[:, axis].max() - hi[axis]
        if below > _BOX_TOL or above > _BOX_TOL:
            raise InfeasibleTaskError(f"{label}: {name} leaves the path's bounding box by {max(below, above):.3g}")


# ----------------------------------------------------------------------------- plan_task


def plan_task(
    path: PathSpec,
    cycle_s: float,
    profile: str,
    ts_s: float,
    *,
    fz: float = 0.4,
    fh: float = 0.15,
    journeys: int = 2,
    limits: CartesianLimits | None = None,
    ruckig_stretch: str = "scale",
) -> TaskTrajectory:
    """Plan one trial (pick→place→pick by default) and sample it at t_n = n·ts_s.

    :param path: the gate path.
    :param cycle_s: duration of one single journey, s (a whole number of samples).
    :param profile: ``"poly4567"``, ``"poly5"`` or ``"ruckig"``.
    :param ts_s: sample period, s.
    :param fz: z-up window is [0, f_z·T], z-down [(1 − f_z)·T, T]; 0 < f_z ≤ 0.5.
    :param fh: lateral window is [f_h·T, (1 − f_h)·T]; 0 ≤ f_h < 0.5.
    :param journeys: number of single journeys (≥ 1); odd ones go back with −rotation.
    :param limits: Cartesian limits for ``ruckig`` (default :class:`CartesianLimits`).
    :param ruckig_stretch: how ``ruckig`` uses a window longer than the time-optimal move:
        ``"scale"`` (default) slows the time-optimal profile down uniformly (limits × k, k², k³);
        ``"hold"`` lets Ruckig stretch it at the full limits (peak acceleration stays at the
        limit whatever the cycle time — about 3× the torque of ``"scale"`` at 0.25 s).
    :raises TrajectoryError: bad arguments.
    :raises InfeasibleTaskError: ``ruckig`` cannot make a window within the limits.
    """
    if profile not in PROFILES:
        raise TrajectoryError(f"unknown motion profile {profile!r} (known: {', '.join(PROFILES)})")
    if ruckig_stretch not in RUCKIG_STRETCH:
        raise TrajectoryError(f"unknown ruckig_stretch {ruckig_stretch!r} (known: {', '.join(RUCKIG_STRETCH)})")
    if not (isinstance(journeys, int) and journeys >= 1):
        raise TrajectoryError(f"journeys must be an integer >= 1, got {journeys!r}")
    if not (0.0 < fz <= 0.5):
        raise TrajectoryError(f"f_z must be in (0, 0.5], got {fz!r}")
    if not (0.0 <= fh < 0.5):
        raise TrajectoryError(f"f_h must be in [0, 0.5), got {fh!r}")
    lim = limits if limits is not None else CartesianLimits()
    m = _samples_per_journey(cycle_s, ts_s)
    w = _windows(m, fz, fh)
    legs = _journeys(path, journeys)

    if profile == "ruckig":
        durations = [_ruckig_min_durations(j, lim, ts_s) for j in legs]
        if not all(_fits(w, d, ts_s) for d in durations):
            need = _ruckig_needed_cycle(m, fz, fh, durations, ts_s)
            raise InfeasibleTaskError(
                f"cycle {cycle_s:g} s is too short for {path.name} with profile ruckig: needs ≥ {need:.3f} s"
            )
        parts = [_journey_ruckig(j, w, ts_s, lim, ruckig_stretch) for j in legs]
    else:
        law = _POLY_LAWS[profile]
        parts = [_journey_poly(j, w, ts_s, law) for j in legs]

    label = f"{path.name} ({profile}, {cycle_s:g} s)"
    for j, (Xj, _, _) in zip(legs, parts):
        _check_straight(Xj, j, label)
    X = np.concatenate([parts[0][0]] + [p[0][1:] for p in parts[1:]])
    Xd = np.concatenate([parts[0][1]] + [p[1][1:] for p in parts[1:]])
    Xdd = np.concatenate([parts[0][2]] + [p[2][1:] for p in parts[1:]])
    _check_box(X, path, label)
    n = m * journeys + 1
    t = np.arange(n) * ts_s
    task = TaskTrajectory(t, X, Xd, Xdd, path, profile, float(cycle_s), float(ts_s), journeys, fz, fh)
    logger.debug(
        "planned %s: peak |v| %s, peak |a| %s",
        task.describe(),
        np.round(np.abs(Xd).max(axis=0), 3),
        np.round(np.abs(Xdd).max(axis=0), 1),
    )
    return task


def _ruckig_needed_cycle(m: int, fz: float, fh: float, durations: list[tuple[float, float, float]], ts: float) -> float:
    """Smallest cycle (whole samples) whose windows fit every time-optimal Ruckig duration, s."""
    d_z = max(max(d[0], d[2]) for d in durations)
    d_lat = max(d[1] for d in durations)
    guess = max(d_z / fz, d_lat / max(1.0 - 2.0 * fh, 1e-9))
    m_try = max(1, int(math.floor(guess / ts)) - 3)
    while True:
        try:
            w = _windows(m_try, fz, fh)
        except TrajectoryError:
            w = None
        if w is not None and all(_fits(w, d, ts) for d in durations):
            return m_try * ts
        m_try += 1


# ----------------------------------------------------------------------------- joint side


@dataclass(frozen=True, eq=False)
class JointReference:
    """Joint reference of a trial, sampled like its task trajectory.

    :ivar t: (N,) s.  :ivar q: (N, 4) rad.  :ivar qd: (N, 4) rad/s.  :ivar qdd: (N, 4) rad/s².
    """

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    task: TaskTrajectory | None = field(default=None, repr=False)

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])


def joint_reference(task: TaskTrajectory, geometry: Any | None = None) -> JointReference:
    """Joint reference by inverse kinematics at every sample and the exact Jacobian relations.

    q = IK(X); q̇ = B⁻¹AẎ and q̈ = B⁻¹(AŸ − w) with Ẏ, Ÿ the (linear) sub-platform images of
    Ẋ, Ẍ (docs/robot-model.md §3.5–3.6, ``plant.kinematics``) — no numerical differentiation.

    :param geometry: ``plant.params.Geometry`` (default: the plant's default geometry).
    :raises OutOfReachError: (from plant) a sample is out of reach; the one-line message names
        the first such sample's time and point.
    """
    from plant import kinematics as kin

    X = task.X
    try:
        q = kin.inverse_kinematics(X, geometry)
    except kin.OutOfReachError as exc:
        n = _first_unreachable(X, geometry)
        x = X[n]
        raise kin.OutOfReachError(
            f"{task.path.name} ({task.profile}, {task.cycle_s:g} s): point out of reach at "
            f"t = {task.t[n]:.3f} s, X = ({x[0]:.4f} m, {x[1]:.4f} m, {x[2]:.4f} m, "
            f"{math.degrees(x[3]):.1f} deg) [{exc}]"
        ) from exc
    Y = kin.subplatform_from_task(X, geometry)
    Yd = kin.subplatform_rates_from_task(task.Xd, geometry)
    Ydd = kin.subplatform_rates_from_task(task.Xdd, geometry)
    qd = kin.joint_velocity(q, Y, Yd, geometry)
    qdd = kin.joint_acceleration(q, qd, Y, Yd, Ydd, geometry)
    return JointReference(task.t.copy(), q, qd, qdd, task)


def _first_unreachable(X: np.ndarray, geometry: Any | None) -> int:
    from plant import kinematics as kin

    for n in range(X.shape[0]):
        try:
            kin.inverse_kinematics(X[n], geometry)
        except kin.OutOfReachError:
            return n
    return 0


# ----------------------------------------------------------------------------- feasibility


@dataclass(frozen=True)
class JointLimits:
    """Joint-side limits checked before anything moves.

    Defaults: speed and torque from the plant's drive train (``plant.params.TruePlantConfig``:
    5000 rpm / n = 52.4 rad/s, n·η·τ_peak = 264.6 N·m), 90 % torque margin, joint range
    −20°..80° [P] (q = 0 arm horizontal, 90° straight down; the built-in paths use 4°..60°).

    :param qd_max_rad_s: max |q̇| per joint, rad/s.
    :param tau_max_nm: drive torque limit (joint side), N·m.
    :param tau_margin: fraction of ``tau_max_nm`` the nominal inverse dynamics may use.
    :param q_min_rad: lowest joint angle, rad.
    :param q_max_rad: highest joint angle, rad.
    """

    qd_max_rad_s: float = field(default_factory=lambda: _plant_limits()[0])
    tau_max_nm: float = field(default_factory=lambda: _plant_limits()[1])
    tau_margin: float = 0.9
    q_min_rad: float = math.radians(-20.0)
    q_max_rad: float = math.radians(80.0)

    def __post_init__(self) -> None:
        if not (self.qd_max_rad_s > 0 and self.tau_max_nm > 0 and 0 < self.tau_margin <= 1):
            raise TrajectoryError("JointLimits: speed and torque limits must be > 0, margin in (0, 1]")
        if not self.q_min_rad < self.q_max_rad:
            raise TrajectoryError("JointLimits: q_min_rad must be below q_max_rad")


def _plant_limits() -> tuple[float, float]:
    """(joint speed limit rad/s, joint torque limit N·m) of the plant's drive train."""
    from plant.params import TruePlantConfig

    cfg = TruePlantConfig()
    return cfg.joint_speed_limit_rad_s, cfg.joint_torque_limit_nm


@dataclass(frozen=True)
class FeasibilityReport:
    """Peaks of a joint reference: torque (N·m), speed (rad/s), angle range (rad), per joint."""

    peak_tau_nm: tuple[float, ...]
    rms_tau_nm: tuple[float, ...]
    peak_qd_rad_s: tuple[float, ...]
    q_min_rad: tuple[float, ...]
    q_max_rad: tuple[float, ...]
    tau_limit_nm: float
    qd_limit_rad_s: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (for summary.json)."""
        return {
            "peak_tau_nm": list(self.peak_tau_nm),
            "rms_tau_nm": list(self.rms_tau_nm),
            "peak_qd_rad_s": list(self.peak_qd_rad_s),
            "q_min_deg": [math.degrees(v) for v in self.q_min_rad],
            "q_max_deg": [math.degrees(v) for v in self.q_max_rad],
            "tau_limit_nm": self.tau_limit_nm,
            "qd_limit_rad_s": self.qd_limit_rad_s,
        }

    def format(self) -> str:
        """A few lines for the CLI."""
        f = lambda xs, k=1.0, d=1: " ".join(f"{k * x:7.{d}f}" for x in xs)  # noqa: E731
        return "\n".join(
            [
                f"peak |tau| N·m  {f(self.peak_tau_nm)}   (limit {self.tau_limit_nm:.1f})",
                f"rms tau N·m     {f(self.rms_tau_nm)}",
                f"peak |qd| rad/s {f(self.peak_qd_rad_s, d=2)}   (limit {self.qd_limit_rad_s:.1f})",
                "q min..max deg  "
                + " ".join(f"{math.degrees(a):.1f}..{math.degrees(b):.1f}" for a, b in zip(self.q_min_rad, self.q_max_rad)),
            ]
        )


def check_feasibility(ref: JointReference, model: Any, limits: JointLimits | None = None) -> FeasibilityReport:
    """Check a joint reference against joint range, speed and torque limits.

    Order: joint range, joint speed, torque.  The torque is the nominal inverse dynamics
    τ = M q̈ + C q̇ + G at every sample (``plant.dynamics.inverse_dynamics`` with ``model``),
    compared with ``tau_margin · tau_max_nm``.  (Reach was checked by :func:`joint_reference`.)

    :param ref: joint reference.
    :param model: ``plant.params.MassModel`` (normally ``nominal_mass_model()``).
    :param limits: joint limits (default :class:`JointLimits`, from the plant's drive train).
    :returns: peaks per joint, for the CLI and summary.json.
    :raises InfeasibleTaskError: one-line message naming the joint, the value, the limit and t.
    """
    from plant.dynamics import inverse_dynamics

    lim = limits if limits is not None else JointLimits()
    where = ""
    if ref.task is not None:
        where = f"{ref.task.path.name} ({ref.task.profile}, {ref.task.cycle_s:g} s): "

    q_lo = ref.q.min(axis=0)
    q_hi = ref.q.max(axis=0)
    for j in range(4):
        if q_lo[j] < lim.q_min_rad:
            n = int(np.argmin(ref.q[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} angle {math.degrees(q_lo[j]):.1f} deg is below the range limit "
                f"{math.degrees(lim.q_min_rad):.1f} deg at t = {ref.t[n]:.3f} s"
            )
        if q_hi[j] > lim.q_max_rad:
            n = int(np.argmax(ref.q[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} angle {math.degrees(q_hi[j]):.1f} deg is above the range limit "
                f"{math.degrees(lim.q_max_rad):.1f} deg at t = {ref.t[n]:.3f} s"
            )

    qd_abs = np.abs(ref.qd)
    qd_peak = qd_abs.max(axis=0)
    for j in range(4):
        if qd_peak[j] > lim.qd_max_rad_s:
            n = int(np.argmax(qd_abs[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} speed {qd_peak[j]:.2f} rad/s exceeds the limit "
                f"{lim.qd_max_rad_s:.2f} rad/s at t = {ref.t[n]:.3f} s"
            )

    tau = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, model))
    tau_abs = np.abs(tau)
    tau_peak = tau_abs.max(axis=0)
    tau_allowed = lim.tau_margin * lim.tau_max_nm
    for j in range(4):
        if tau_peak[j] > tau_allowed:
            n = int(np.argmax(tau_abs[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} peak torque {tau_peak[j]:.1f} N·m exceeds the limit "
                f"{tau_allowed:.1f} N·m ({lim.tau_margin:g} × {lim.tau_max_nm:.1f} N·m) "
                f"at t = {ref.t[n]:.3f} s"
            )

    report = FeasibilityReport(
        peak_tau_nm=tuple(float(v) for v in tau_peak),
        rms_tau_nm=tuple(float(v) for v in np.sqrt(np.mean(tau**2, axis=0))),
        peak_qd_rad_s=tuple(float(v) for v in qd_peak),
        q_min_rad=tuple(float(v) for v in q_lo),
        q_max_rad=tuple(float(v) for v in q_hi),
        tau_limit_nm=float(tau_allowed),
        qd_limit_rad_s=float(lim.qd_max_rad_s),
    )
    logger.debug("feasibility %s", report.as_dict())
    return report
