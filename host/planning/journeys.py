"""The time grid of a trial and the journeys of a path.

This module owns the number of samples of a trial (:func:`trial_samples`), the axis windows of one
journey (:class:`AxisWindows`) and the journeys of a path (:class:`Journey`).

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

May import: ``numpy``, :mod:`host.planning.paths`, :mod:`host.planning.planning_errors`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from host.planning.paths import PathSpec
from host.planning.planning_errors import TrajectoryError

__all__ = ["AxisWindows", "Journey", "LATERAL_AXES", "axis_windows", "path_journeys", "samples_per_journey", "trial_samples"]


#: Tolerance on "cycle is a whole number of samples" (relative to one sample).
_SAMPLE_TOL = 1e-6


def trial_samples(cycle_s: float, ts_s: float, journeys: int = 2) -> int:
    """N = round(journeys·cycle_s/ts_s) + 1 (end point included)."""
    return samples_per_journey(cycle_s, ts_s) * journeys + 1


def samples_per_journey(cycle_s: float, ts_s: float) -> int:
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
class AxisWindows:
    """Axis windows of one journey, in samples (local index 0..m)."""

    m: int
    n_z: int  # z up over [0, n_z], z down over [m - n_z, m]
    n_h: int  # lateral over [n_h, m - n_h]

    @property
    def n_lat(self) -> int:
        return self.m - 2 * self.n_h


def axis_windows(m: int, fz: float, fh: float) -> AxisWindows:
    n_z = int(math.floor(fz * m + 0.5))
    n_h = int(math.floor(fh * m + 0.5))
    w = AxisWindows(m, n_z, n_h)
    if n_z < 1 or w.n_lat < 1 or 2 * n_z > m:
        raise TrajectoryError(f"cycle of {m} samples is too short to place the axis windows (f_z {fz}, f_h {fh})")
    return w


@dataclass(frozen=True)
class Journey:
    start: np.ndarray  # (4,) x, y, z, θ
    end: np.ndarray
    top_z: float

    @property
    def delta_lat(self) -> np.ndarray:
        """(3,) lateral displacement (Δx, Δy, Δθ)."""
        return self.end[[0, 1, 3]] - self.start[[0, 1, 3]]


def path_journeys(path: PathSpec, journeys: int) -> list[Journey]:
    pick = np.array([*path.pick_xyz, 0.0])
    place = np.array([*path.place_xyz, path.rotation_rad])
    out = []
    for k in range(journeys):
        a, b = (pick, place) if k % 2 == 0 else (place, pick)
        out.append(Journey(a, b, path.top_z_m))
    return out


LATERAL_AXES = (0, 1, 3)
