"""Kinematics of the 4-limb Schönflies robot with a screw-pair platform (docs/robot-model.md §3).

This module owns the public kinematic API (all lengths in m, angles in rad):

* task X = (x, y, z, θ) ↔ sub-platform Y = (x, y, z_u, z_l) coordinates and the screw pair,
* closed-form elbow-out inverse kinematics per limb (§3.3), vectorised over (..., 4),
* forward kinematics by Newton with warm start (§3.4),
* the velocity Jacobian J = A⁻¹B with Ẏ = J q̇, J_up / J_low (§3.5),
* the analytic J̇q̇ (§3.6), joint velocities / accelerations from sub-platform or task rates.

The numerics live in :mod:`plant._kernels` (numba); these functions are thin wrappers.
Every function takes an optional :class:`~plant.params.Geometry` (default: the proposed one).
"""

from __future__ import annotations

import functools
import logging
import math

import numpy as np

from plant import _kernels as K
from plant.params import Geometry

logger = logging.getLogger(__name__)

#: default FK start: the workspace centre (x, y, z_u, z_l) = (0, 0, -0.60, -0.65) m
DEFAULT_Y_GUESS: tuple[float, float, float, float] = (0.0, 0.0, -0.60, -0.65)


class KinematicsError(ValueError):
    """A kinematic query has no (regular) answer."""


class OutOfReachError(KinematicsError):
    """IK: a limb cannot reach the requested point."""


class ForwardKinematicsError(KinematicsError):
    """FK: Newton did not converge (no assembly near the start guess, or a singularity)."""


class SingularConfigurationError(KinematicsError):
    """A serial (b_i = 0) or parallel (det A = 0) singularity was hit."""


@functools.lru_cache(maxsize=16)
def _geo_params(geometry: Geometry) -> np.ndarray:
    return K.pack_params(geometry)


def _params(geometry: Geometry | None) -> np.ndarray:
    return _geo_params(geometry if geometry is not None else Geometry())


def _as_batch(a: np.ndarray | list[float] | tuple[float, ...], name: str) -> tuple[np.ndarray, tuple[int, ...]]:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[-1:] != (4,):
        raise ValueError(f"{name} must have shape (..., 4), got {arr.shape}")
    lead = arr.shape[:-1]
    return np.ascontiguousarray(arr.reshape(-1, 4)), lead


# ---- coordinates and the screw pair --------------------------------------------------------


def subplatform_from_task(X: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """Y = (x, y, z_u, z_l) from X = (x, y, z, θ): z_l = z + e, z_u = z_l + d0 + h θ/(2π)."""
    g = geometry if geometry is not None else Geometry()
    X = np.asarray(X, dtype=np.float64)
    Y = np.empty_like(X)
    Y[..., 0] = X[..., 0]
    Y[..., 1] = X[..., 1]
    Y[..., 3] = X[..., 2] + g.e
    Y[..., 2] = Y[..., 3] + g.d0 + g.h * X[..., 3] / (2.0 * math.pi)
    return Y


def task_from_subplatform(Y: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """X = (x, y, z, θ) from Y = (x, y, z_u, z_l): θ = 2π (z_u − z_l − d0)/h (§3.2)."""
    g = geometry if geometry is not None else Geometry()
    Y = np.asarray(Y, dtype=np.float64)
    X = np.empty_like(Y)
    X[..., 0] = Y[..., 0]
    X[..., 1] = Y[..., 1]
    X[..., 2] = Y[..., 3] - g.e
    X[..., 3] = 2.0 * math.pi * (Y[..., 2] - Y[..., 3] - g.d0) / g.h
    return X


def subplatform_rates_from_task(Xd: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """Ẏ (or Ÿ) from Ẋ (or Ẍ): the map is linear, ż_u = ż + h θ̇/(2π), ż_l = ż."""
    g = geometry if geometry is not None else Geometry()
    Xd = np.asarray(Xd, dtype=np.float64)
    Yd = np.empty_like(Xd)
    Yd[..., 0] = Xd[..., 0]
    Yd[..., 1] = Xd[..., 1]
    Yd[..., 3] = Xd[..., 2]
    Yd[..., 2] = Xd[..., 2] + g.h * Xd[..., 3] / (2.0 * math.pi)
    return Yd


def task_rates_from_subplatform(Yd: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """Ẋ from Ẏ: θ̇ = 2π (ż_u − ż_l)/h."""
    g = geometry if geometry is not None else Geometry()
    Yd = np.asarray(Yd, dtype=np.float64)
    Xd = np.empty_like(Yd)
    Xd[..., 0] = Yd[..., 0]
    Xd[..., 1] = Yd[..., 1]
    Xd[..., 2] = Yd[..., 3]
    Xd[..., 3] = 2.0 * math.pi * (Yd[..., 2] - Yd[..., 3]) / g.h
    return Xd


# ---- position kinematics ---------------------------------------------------------------------


def inverse_kinematics(X: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """Joint angles q (..., 4) [rad] for task poses X (..., 4) = (x, y, z, θ) [m, rad].

    Closed-form elbow-out branch per limb (docs/robot-model.md §3.3).

    :raises OutOfReachError: if a limb cannot reach a point (message names limb and point).
    """
    xs, lead = _as_batch(X, "X")
    qs = np.empty_like(xs)
    r = K.ik_batch(xs, _params(geometry), qs)
    if r >= 0:
        n, limb = divmod(r, 4)
        x = xs[n]
        where = f" (sample {n})" if xs.shape[0] > 1 else ""
        raise OutOfReachError(
            f"limb {limb + 1} cannot reach X = ({x[0]:.6g} m, {x[1]:.6g} m, {x[2]:.6g} m, {x[3]:.6g} rad){where}"
        )
    return qs.reshape(lead + (4,))


def forward_kinematics(q: np.ndarray, Y_guess: np.ndarray | None = None, geometry: Geometry | None = None) -> np.ndarray:
    """Sub-platform coordinates Y (..., 4) = (x, y, z_u, z_l) [m] for joint angles q (..., 4).

    Newton on the four rod constraints (docs/robot-model.md §3.4), started from ``Y_guess`` (default
    :data:`DEFAULT_Y_GUESS`); along a batch each sample is warm-started from the previous one.

    :raises ForwardKinematicsError: if Newton does not converge.
    """
    qs, lead = _as_batch(q, "q")
    y0 = np.array(DEFAULT_Y_GUESS if Y_guess is None else Y_guess, dtype=np.float64).reshape(-1)[:4].copy()
    ys = np.empty_like(qs)
    r = K.fk_batch(qs, y0, _params(geometry), ys)
    if r >= 0:
        raise ForwardKinematicsError(f"forward kinematics did not converge for q = {qs[r].tolist()} rad")
    return ys.reshape(lead + (4,))


# ---- velocity level ---------------------------------------------------------------------------


def jacobian(q: np.ndarray, Y: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """J = A⁻¹B (..., 4, 4) [m/rad] with Ẏ = J q̇, at a consistent (q, Y) pair."""
    qs, lead = _as_batch(q, "q")
    ys, _ = _as_batch(Y, "Y")
    if ys.shape != qs.shape:
        raise ValueError(f"q and Y shapes differ: {qs.shape} vs {ys.shape}")
    js = np.empty((qs.shape[0], 4, 4))
    r = K.jacobian_batch(qs, ys, _params(geometry), js)
    if r >= 0:
        raise SingularConfigurationError(f"parallel singularity (A singular) at q = {qs[r].tolist()} rad")
    return js.reshape(lead + (4, 4))


def jacobian_up_low(q: np.ndarray, Y: np.ndarray, geometry: Geometry | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(J_up, J_low), each (..., 3, 4): rows (ẋ, ẏ, ż_u) and (ẋ, ẏ, ż_l) of J."""
    J = jacobian(q, Y, geometry)
    return J[..., [0, 1, 2], :], J[..., [0, 1, 3], :]


def jdot_qdot(
    q: np.ndarray, qd: np.ndarray, Y: np.ndarray, Yd: np.ndarray | None = None, geometry: Geometry | None = None
) -> np.ndarray:
    """J̇q̇ (..., 4) [m/s²] = A⁻¹w (docs/robot-model.md §3.6), so that Ÿ = J q̈ + J̇q̇.

    ``Yd`` is accepted for interface symmetry; the kernel recomputes Ẏ = J q̇ for consistency.
    """
    qs, lead = _as_batch(q, "q")
    qds, _ = _as_batch(qd, "qd")
    ys, _ = _as_batch(Y, "Y")
    out = np.empty_like(qs)
    r = K.jdot_qdot_batch(qs, qds, ys, _params(geometry), out)
    if r >= 0:
        raise SingularConfigurationError(f"parallel singularity (A singular) at q = {qs[r].tolist()} rad")
    return out.reshape(lead + (4,))


def _joint_rates(
    q: np.ndarray, Y: np.ndarray, Yd: np.ndarray, Ydd: np.ndarray | None, geometry: Geometry | None
) -> tuple[np.ndarray, np.ndarray | None, tuple[int, ...]]:
    qs, lead = _as_batch(q, "q")
    ys, _ = _as_batch(Y, "Y")
    yds, _ = _as_batch(Yd, "Yd")
    want = Ydd is not None
    ydds = _as_batch(Ydd, "Ydd")[0] if Ydd is not None else yds
    qds = np.empty_like(qs)
    qdds = np.empty_like(qs)
    r = K.joint_rates_batch(qs, ys, yds, ydds, _params(geometry), qds, qdds, want)
    if r >= 0:
        n, limb = divmod(r, 4)
        raise SingularConfigurationError(f"serial singularity of limb {limb + 1} (b = 0) at q = {qs[n].tolist()} rad")
    return qds, (qdds if want else None), lead


def joint_velocity(q: np.ndarray, Y: np.ndarray, Yd: np.ndarray, geometry: Geometry | None = None) -> np.ndarray:
    """q̇ = B⁻¹ A Ẏ (..., 4) [rad/s] for sub-platform velocity Ẏ [m/s]."""
    qds, _, lead = _joint_rates(q, Y, Yd, None, geometry)
    return qds.reshape(lead + (4,))


def joint_acceleration(
    q: np.ndarray, qd: np.ndarray | None, Y: np.ndarray, Yd: np.ndarray, Ydd: np.ndarray, geometry: Geometry | None = None
) -> np.ndarray:
    """q̈ = B⁻¹(A Ÿ − w) (..., 4) [rad/s²] (docs/robot-model.md §3.6).

    ``qd`` is accepted for interface symmetry; q̇ is recomputed from Ẏ (consistent by
    construction).
    """
    _, qdds, lead = _joint_rates(q, Y, Yd, Ydd, geometry)
    assert qdds is not None
    return qdds.reshape(lead + (4,))


def joint_states_from_task(
    X: np.ndarray, Xd: np.ndarray, Xdd: np.ndarray, geometry: Geometry | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, q̇, q̈), each (..., 4), from a task trajectory (X, Ẋ, Ẍ) (..., 4).

    IK at every sample plus the exact velocity / acceleration maps (no numerical
    differentiation).  Raises :class:`OutOfReachError` / :class:`SingularConfigurationError`.
    """
    q = inverse_kinematics(X, geometry)
    Y = subplatform_from_task(X, geometry)
    Yd = subplatform_rates_from_task(Xd, geometry)
    Ydd = subplatform_rates_from_task(Xdd, geometry)
    qds, qdds, lead = _joint_rates(q, Y, Yd, Ydd, geometry)
    assert qdds is not None
    return q, qds.reshape(lead + (4,)), qdds.reshape(lead + (4,))


def task_velocity(q: np.ndarray, qd: np.ndarray, Y: np.ndarray | None = None, geometry: Geometry | None = None) -> np.ndarray:
    """Task rates Ẋ (..., 4) = (ẋ, ẏ, ż, θ̇) from joint rates (FK if Y is not given)."""
    if Y is None:
        Y = forward_kinematics(q, geometry=geometry)
    J = jacobian(q, Y, geometry)
    Yd = np.einsum("...ij,...j->...i", J, np.asarray(qd, dtype=np.float64))
    return task_rates_from_subplatform(Yd, geometry)
