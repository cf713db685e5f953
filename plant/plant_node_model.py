"""What the plant node simulates in a trial: the plant and the trial's disturbance torques.

Owns :class:`TrialModel`: the plant built by a factory and kept while the control period and the
sub-steps stay the same, and the disturbance of the trial in progress.  The plant node's trial
protocol (:mod:`plant.plant_node_trial`) begins a trial with :meth:`TrialModel.begin` and steps
it once per tick with :meth:`TrialModel.step`; anything either raises is a fault of the trial
(the plant is a plug-in).

* ``plant_factory(ts_s, substeps) -> plant`` — an object with ``reset(q0_rad, qd0_rad_s)``,
  ``encoder_counts() -> int (4,)`` [counts] and ``step(torque_units int64 (4,) [µN·m],
  disturbance_nm float64 (4,) [N·m])`` that raises on failure (``plant.simulator.Plant``); with
  plant-uncertainty factors other than 1 (0x2400:6..9) it is called as
  ``plant_factory(ts_s, substeps, scales)``, ``scales`` = (inertia, mass, friction, payload) — a
  factory without that argument serves the robot as built only (a trial with factors then faults);
* ``disturbance_fn(kind, seed, trial, n_ticks, ts_s) -> (n_ticks, 4)`` [N·m], ``kind`` a
  disturbance label (``plant.disturbance.disturbance_torque``).

Imports numpy and the standard library only.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import numpy as np
import numpy.typing as npt

logger = logging.getLogger(__name__)

N_JOINTS = 4
#: the plant-uncertainty factors of the robot as built (inertia, mass, friction, payload)
AS_BUILT: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)


class PlantLike(Protocol):
    """The plant as the plant node uses it (``plant.simulator.Plant``)."""

    def reset(self, q0: np.ndarray, qd0: np.ndarray) -> None: ...

    def encoder_counts(self) -> np.ndarray: ...

    def step(self, torque_units: np.ndarray, disturbance_nm: np.ndarray) -> None: ...


#: ``(ts_s, substeps) -> plant``
PlantFactory = Callable[[float, int], PlantLike]
#: ``(kind, seed, trial, n_ticks, ts_s) -> (n_ticks, 4)`` [N·m]
DisturbanceFn = Callable[[str, int, int, int, float], npt.ArrayLike]


class TrialModel:
    """The plant and the disturbance of the plant node's trials (see the module docstring).

    :param node_id: CANopen node id (log messages).
    :param plant_factory: builds the plant for (Ts [s], sub-steps).
    :param disturbance_fn: the disturbance torques of a trial.
    """

    def __init__(self, node_id: int, plant_factory: PlantFactory, disturbance_fn: DisturbanceFn) -> None:
        self.node_id = node_id
        self.plant_factory = plant_factory
        self.disturbance_fn = disturbance_fn
        self._plant: PlantLike | None = None
        self._plant_key: tuple[float, int, tuple[float, ...]] | None = None
        self._dist: np.ndarray = np.zeros((0, N_JOINTS))

    def plant(self, ts_s: float, substeps: int, scales: tuple[float, ...] = AS_BUILT) -> PlantLike:
        """The plant for (``ts_s`` [s], ``substeps``, the plant-uncertainty ``scales``), built on
        first use and when they change."""
        key = (ts_s, substeps, tuple(scales))
        if self._plant is None or self._plant_key != key:
            self._plant = None
            if tuple(scales) == AS_BUILT:
                self._plant = self.plant_factory(ts_s, substeps)
            else:
                self._plant = self.plant_factory(ts_s, substeps, tuple(scales))  # type: ignore[call-arg]
            self._plant_key = key
            logger.info("node %d: plant built (Ts = %g s, %d sub-steps)", self.node_id, ts_s, substeps)
        return self._plant

    def warm_up(self, ts_s: float, substeps: int, kind: str) -> None:
        """Build the plant and compute one short disturbance of ``kind`` now, so that a trial never
        pays for the first call (compilation, scipy.signal's import); a failure is logged (it shows
        up again, as a fault, at the first trial)."""
        try:
            self.plant(ts_s, substeps)
        except Exception:
            logger.exception("node %d: building the plant failed", self.node_id)
        try:
            self.disturbance_fn(kind, 0, 0, 2, ts_s)
        except Exception:
            logger.exception("node %d: computing a disturbance failed", self.node_id)

    def begin(
        self,
        ts_s: float,
        substeps: int,
        kind: str,
        seed: int,
        trial: int,
        n_ticks: int,
        q0: np.ndarray,
        qd0: np.ndarray,
        scales: tuple[float, ...] = AS_BUILT,
    ) -> np.ndarray:
        """A new trial: compute its disturbance and reset the plant (with the plant-uncertainty
        ``scales``) to (``q0`` [rad], ``qd0`` [rad/s]); returns the encoder counts of tick 0 [counts].

        :raises Exception: whatever the plant or the disturbance raises; ValueError for a
            disturbance of the wrong shape.
        """
        plant = self.plant(ts_s, substeps, scales)
        dist = np.ascontiguousarray(self.disturbance_fn(kind, seed, trial, n_ticks, ts_s), dtype=np.float64)
        if dist.shape != (n_ticks, N_JOINTS):
            raise ValueError(f"disturbance has shape {dist.shape}, expected ({n_ticks}, {N_JOINTS})")
        plant.reset(q0, qd0)
        counts = plant.encoder_counts()
        self._dist = dist
        return counts

    def step(self, n: int, torque_units: np.ndarray, last: bool) -> np.ndarray | None:
        """Integrate tick ``n`` with ``torque_units`` (4,) [µN·m] held and the trial's disturbance;
        the encoder counts of tick n + 1, None after the ``last`` tick.

        :raises Exception: whatever the plant raises.
        """
        plant = self._plant
        assert plant is not None
        plant.step(torque_units, self._dist[n])
        return None if last else plant.encoder_counts()
