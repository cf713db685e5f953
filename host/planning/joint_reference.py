"""The joint reference of a trial: inverse kinematics at every sample of a task trajectory and the
exact Jacobian relations for q̇, q̈ (:func:`joint_reference` → :class:`JointReference`, t, q, q̇, q̈
in s, rad, rad/s, rad/s²).

May import: ``numpy``, ``plant`` (kinematics, inside the function), :mod:`host.planning.task_plan`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.planning.task_plan import TaskTrajectory

__all__ = ["JointReference", "first_unreachable", "joint_reference"]


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
        n = first_unreachable(X, geometry)
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


def first_unreachable(X: np.ndarray, geometry: Any | None) -> int:
    from plant import kinematics as kin

    for n in range(X.shape[0]):
        try:
            kin.inverse_kinematics(X[n], geometry)
        except kin.OutOfReachError:
            return n
    return 0
