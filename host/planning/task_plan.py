"""The pick→place→pick trial plan in the task frame: :func:`plan_task` → :class:`TaskTrajectory`
(t, X, Ẋ, Ẍ with X = (x, y, z, θ) in m, m, m, rad), with the profiles ``poly4567``, ``poly5``
(:mod:`host.planning.motion_laws`) and ``ruckig`` (:mod:`host.planning.ruckig_adapter`) on the axis
windows of :mod:`host.planning.journeys`, checked straight and inside the path's bounding box.

The planning modules: :mod:`host.planning.motion_laws`, :mod:`host.planning.journeys`,
:mod:`host.planning.ruckig_adapter`, this one, :mod:`host.planning.joint_reference` (IK) and
:mod:`host.planning.feasibility`; their errors are :mod:`host.planning.planning_errors`.

May import: ``numpy``, the modules of :mod:`host.planning` named above.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from host.planning.journeys import LATERAL_AXES, AxisWindows, Journey, axis_windows, path_journeys, samples_per_journey
from host.planning.motion_laws import POLY_LAWS, LawResult
from host.planning.paths import PathSpec
from host.planning.planning_errors import InfeasibleTaskError, TrajectoryError
from host.planning.ruckig_adapter import CartesianLimits, journey_ruckig, ruckig_min_durations, ruckig_needed_cycle, windows_fit

logger = logging.getLogger(__name__)

__all__ = ["PROFILES", "RUCKIG_STRETCH", "Profile", "TaskTrajectory", "plan_task"]


Profile = Literal["poly4567", "poly5", "ruckig"]

#: Motion profiles accepted by :func:`plan_task`.
PROFILES: tuple[str, ...] = ("ruckig", "poly4567", "poly5")

#: How the ``ruckig`` profile fills a window longer than its time-optimal move (see plan_task).
RUCKIG_STRETCH: tuple[str, ...] = ("scale", "hold")

#: Straightness / bounding-box tolerances (m or rad).
_STRAIGHT_TOL = 1e-9
_BOX_TOL = 1e-9


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


def _journey_poly(j: Journey, w: AxisWindows, ts: float, law: Callable[[Any], LawResult]) -> tuple[np.ndarray, ...]:
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
    for axis in LATERAL_AXES:
        add(axis, w.n_h, w.m - w.n_h, j.end[axis] - j.start[axis])
    return X, Xd, Xdd


def _check_straight(X: np.ndarray, j: Journey, label: str) -> None:
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
    m = samples_per_journey(cycle_s, ts_s)
    w = axis_windows(m, fz, fh)
    legs = path_journeys(path, journeys)

    if profile == "ruckig":
        durations = [ruckig_min_durations(j, lim, ts_s) for j in legs]
        if not all(windows_fit(w, d, ts_s) for d in durations):
            need = ruckig_needed_cycle(m, fz, fh, durations, ts_s)
            raise InfeasibleTaskError(
                f"cycle {cycle_s:g} s is too short for {path.name} with profile ruckig: needs ≥ {need:.3f} s"
            )
        parts = [journey_ruckig(j, w, ts_s, lim, ruckig_stretch) for j in legs]
    else:
        law = POLY_LAWS[profile]
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
