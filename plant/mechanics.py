"""The robot's mechanics around the plant: holding brakes, mechanical limits and the home pose.

This module owns what a real axis has besides its dynamics (docs/robot.md "Limits"):

* **holding brakes** — a joint whose drive gives no torque (its power stage off) is held by its
  brake: it does not move, the other joints move with it fixed (:meth:`plant.simulator.Plant.step`
  with ``locked``);
* **mechanical limits** (:class:`MechanicalLimits`) — an end stop per joint at the ends of the
  joint range (−20°..80°, the planner's range ``host.planning.feasibility.JointLimits``), the end
  of the screw's travel between the sub-platforms (gap z_u − z_l, i.e. the tool angle θ), and the
  mechanism itself (forward kinematics fails: a rod at full stretch, a singularity).  Driving into
  one is a :class:`LimitHit`: the robot stops there — a joint at its end stop is clamped to the
  stop, at the screw or mechanism limit the robot stays at the last pose inside — with every
  velocity 0, never a non-finite state;
* the **home pose** (:data:`HOME_POSE`): the workspace centre, where the robot stands at rest when
  it is switched on.

:class:`Mechanics` steps a :class:`plant.simulator.Plant` one control period with these rules;
:func:`warm_up_robot` compiles every kernel such a period may use before the robot's node boots.
Imports numpy and the plant's model modules only.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from plant.kinematics import inverse_kinematics
from plant.simulator import Plant, PlantError

logger = logging.getLogger(__name__)

__all__ = ["HOME_POSE", "LimitHit", "MechanicalLimits", "Mechanics", "warm_up_robot"]

#: the home pose X = (x, y, z, θ) [m, rad]: the workspace centre (docs/robot-model.md §3.5)
HOME_POSE: tuple[float, float, float, float] = (0.0, 0.0, -0.65, 0.0)

_ZERO4 = np.zeros(4, dtype=np.float64)


@dataclass(frozen=True)
class MechanicalLimits:
    """Where the mechanism stops (SI units).

    :ivar q_min_rad: every joint's lower end stop, rad (arm up).
    :ivar q_max_rad: every joint's upper end stop, rad (arm down).
    :ivar gap_min_m: shortest gap z_u − z_l the screw allows, m (θ = −180° with the default lead).
    :ivar gap_max_m: longest gap, m (θ = +180°).
    """

    q_min_rad: float = math.radians(-20.0)
    q_max_rad: float = math.radians(80.0)
    gap_min_m: float = 0.030
    gap_max_m: float = 0.070

    def __post_init__(self) -> None:
        if not self.q_min_rad < self.q_max_rad:
            raise ValueError(f"q_min_rad {self.q_min_rad} must be below q_max_rad {self.q_max_rad}")
        if not 0.0 < self.gap_min_m < self.gap_max_m:
            raise ValueError(f"need 0 < gap_min_m < gap_max_m, got {self.gap_min_m}, {self.gap_max_m}")


@dataclass(frozen=True)
class LimitHit:
    """The robot ran into a mechanical limit in one period.

    :ivar kind: ``"end_stop"``, ``"screw_stop"`` or ``"mechanism"``.
    :ivar joint: the joint 1..4 at its end stop (0 for the screw and the mechanism).
    :ivar message: what happened, with the values.
    """

    kind: str
    joint: int
    message: str


class Mechanics:
    """One plant with brakes and mechanical limits (see the module docstring).

    :param plant: the plant to step (its Ts and sub-steps).
    :param limits: the mechanical limits.
    """

    def __init__(self, plant: Plant, limits: MechanicalLimits | None = None) -> None:
        self.plant = plant
        self.limits = limits if limits is not None else MechanicalLimits()
        self._lo = self.limits.q_min_rad
        self._hi = self.limits.q_max_rad

    def home(self, pose: tuple[float, float, float, float] = HOME_POSE) -> None:
        """The robot at rest at task pose ``pose`` (x, y, z [m], θ [rad]); time 0.

        :raises plant.kinematics.OutOfReachError: the pose cannot be reached.
        """
        self.plant.reset(inverse_kinematics(np.asarray(pose, dtype=np.float64)), _ZERO4)

    def step(self, torque_units: np.ndarray, held: np.ndarray | None) -> LimitHit | None:
        """Integrate one control period: the joints ``held`` (bool (4,); None: none) by their brakes, the others
        with ``torque_units`` (int64 (4,), µN·m) held.  Returns the limit the robot ran into in this
        period (it then stands at the limit at rest), or None.

        :raises PlantError: the plant fails at the pose it stood at (never expected: that pose was valid).
        """
        plant = self.plant
        q_before = plant.q_list()  # Python floats: no array made every period (set_state takes them)
        try:
            plant.step(torque_units, None, held)
        except PlantError as err:
            plant.set_state(q_before)
            return LimitHit("mechanism", 0, f"the mechanism cannot follow: {err}")
        angles = plant.q_list()
        if min(angles) < self._lo or max(angles) > self._hi:
            q = np.array(angles)
            low, high = q < self._lo, q > self._hi
            j = int(np.flatnonzero(low | high)[0])
            stop = self._lo if low[j] else self._hi
            message = (
                f"joint {j + 1} reached its {'lower' if low[j] else 'upper'} end stop at {math.degrees(stop):.1f} deg "
                f"({math.degrees(float(plant.qd[j])):.1f} deg/s)"
            )
            try:
                plant.set_state(np.clip(q, self._lo, self._hi))
            except PlantError:
                plant.set_state(q_before)
            if not self._gap_ok():
                plant.set_state(q_before)
            return LimitHit("end_stop", j + 1, message)
        if not self._gap_ok():
            gap = self.gap_m()
            plant.set_state(q_before)
            return LimitHit(
                "screw_stop",
                0,
                f"the screw reached the end of its travel: gap {1000 * gap:.1f} mm outside "
                f"[{1000 * self.limits.gap_min_m:.0f}, {1000 * self.limits.gap_max_m:.0f}] mm",
            )
        return None

    def hold(self) -> None:
        """Every velocity to 0 where the robot stands (the brakes close on a moving robot)."""
        self.plant.set_state(self.plant.q)

    def gap_m(self) -> float:
        """The screw's gap z_u − z_l at the last evaluation, m."""
        y = self.plant.Y.tolist()  # Python floats: no numpy scalar arithmetic every period
        return y[2] - y[3]

    def _gap_ok(self) -> bool:
        gap = self.gap_m()
        return self.limits.gap_min_m <= gap <= self.limits.gap_max_m


def warm_up_robot(scratch: Plant, limits: MechanicalLimits) -> float:
    """Compile (or load from numba's cache) every kernel a robot period may use, on ``scratch`` (a
    plant of the robot's Ts and sub-steps, thrown away afterwards): a period with no joint held,
    with some held (the locked-joint dynamics, first used when the first drive is enabled), with
    all held, the forward kinematics of 0x2452.  Without it the first period with one drive
    enabled paid the compilation — seconds on a loaded machine, while the master's SYNCs piled up
    (a stall of the SYNC-stepped robot).  Returns the seconds it took."""
    t0 = time.perf_counter()
    mech = Mechanics(scratch, limits)
    mech.home()
    zero = np.zeros(4, dtype=np.int64)
    for held in ([False] * 4, [True, False, False, False], [True] * 4):
        mech.step(zero, np.array(held))
    scratch.encoder_counts()
    scratch.task_pose()
    seconds = time.perf_counter() - t0
    logger.info("robot kernels ready in %.2f s", seconds)
    return seconds
