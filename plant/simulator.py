"""The emulated robot as a discrete-time process: state, encoder, torque input, RK4 integration.

This module owns :class:`Plant`.  One :meth:`Plant.step` integrates one control period Ts with
the commanded joint torques held (zero-order hold): ``τ = clamp(units · torque_lsb_nm,
±joint_torque_limit) + disturbance`` [N·m], RK4 with ``substeps`` equal sub-steps on the
true-plant dynamics (mass model of the config, tool spin, friction).  FK inside the dynamics
is warm-started from the previous evaluation (first-order predictor Y + J Δq, then Newton).
The encoder reading is the nearest integer count of q / rad_per_count.

Holding brakes: :meth:`Plant.step` takes the joints held this period (``locked``): their velocity
is set to 0 and they do not move; the free joints move with them fixed (``_kernels.plant_step_locked``).
:meth:`Plant.set_state` puts the robot at a state without restarting its time (an end stop).

Failures (FK does not converge, a singularity, a non-finite state) raise :class:`PlantError`
and leave the plant ``faulted`` until the next :meth:`Plant.reset` (or :meth:`Plant.set_state`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from plant import _kernels as K
from plant.kinematics import DEFAULT_Y_GUESS, forward_kinematics, inverse_kinematics, task_from_subplatform
from plant.params import TruePlantConfig, nominal_plant_config

logger = logging.getLogger(__name__)

_I64 = np.dtype(np.int64)
_F64 = np.dtype(np.float64)
_SHAPE4 = (4,)
_N_JOINTS = 4


class PlantError(RuntimeError):
    """The simulated robot failed (FK, singularity or non-finite state); reset required."""


class Plant:
    """Simulated robot, advanced one control period at a time.

    :param config: the robot to emulate (see :func:`plant.params.default_true_plant`)
    :param ts_s: control period, s
    :param substeps: RK4 sub-steps per control period
    :param rad_per_count: encoder LSB at the joint, rad
    :param torque_lsb_nm: torque command LSB, N·m
    """

    def __init__(self, config: TruePlantConfig, ts_s: float, substeps: int, rad_per_count: float, torque_lsb_nm: float) -> None:
        if not ts_s > 0.0:
            raise ValueError(f"ts_s must be > 0, got {ts_s!r}")
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        if not rad_per_count > 0.0 or not torque_lsb_nm > 0.0:
            raise ValueError("rad_per_count and torque_lsb_nm must be > 0")
        self.config = config
        self.ts_s = float(ts_s)
        self.substeps = int(substeps)
        self.rad_per_count = float(rad_per_count)
        self.torque_lsb_nm = float(torque_lsb_nm)
        self._p = K.pack_params(
            config.geometry,
            config=config,
            ts_s=self.ts_s,
            substeps=self.substeps,
            rad_per_count=self.rad_per_count,
            torque_lsb_nm=self.torque_lsb_nm,
        )
        self._ws = np.zeros((K.N_ROWS, 16), dtype=np.float64)
        self._q_view = self._ws[K.R_STATE, 0:4]  # the joint angles in the workspace (a view, made once)
        self._counts = np.zeros(4, dtype=np.int64)
        self._zero4 = np.zeros(4, dtype=np.float64)
        self._y_guess = np.array(DEFAULT_Y_GUESS, dtype=np.float64)
        self._n_steps = 0
        self._faulted = False
        self._fault_text = ""
        self._ready = False

    @classmethod
    def nominal(
        cls, ts_s: float, substeps: int, rad_per_count: float, torque_lsb_nm: float, torque_limit_enabled: bool = True
    ) -> Plant:
        """A plant on the nominal mass model without friction (for tests / model checks)."""
        return cls(nominal_plant_config(torque_limit_enabled), ts_s, substeps, rad_per_count, torque_lsb_nm)

    # ---- state ---------------------------------------------------------------------------

    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None) -> None:
        """Set q [rad], q̇ [rad/s], time 0; FK from a fixed start guess (reproducible)."""
        q0a = np.ascontiguousarray(q0, dtype=np.float64).reshape(4)
        qd0a = self._zero4 if qd0 is None else np.ascontiguousarray(qd0, dtype=np.float64).reshape(4)
        if not (np.all(np.isfinite(q0a)) and np.all(np.isfinite(qd0a))):
            raise ValueError("q0 and qd0 must be finite")
        st = K.plant_reset(self._ws, self._p, q0a, qd0a, self._y_guess, self._counts)
        self._n_steps = 0
        if st != K.ST_OK:
            self._fail(st)
        self._faulted = False
        self._fault_text = ""
        self._ready = True

    def set_state(self, q: np.ndarray | list[float], qd: np.ndarray | None = None) -> None:
        """Put the robot at q [rad] with q̇ [rad/s] (default at rest) without restarting its time: FK
        warm-started from the last sub-platform pose (the same assembly branch), e.g. a joint held
        at an end stop.

        :raises PlantError: FK fails at q (the plant is then faulted).
        """
        qa = np.ascontiguousarray(q, dtype=np.float64).reshape(4)
        qda = self._zero4 if qd is None else np.ascontiguousarray(qd, dtype=np.float64).reshape(4)
        if not (np.all(np.isfinite(qa)) and np.all(np.isfinite(qda))):
            raise ValueError("q and qd must be finite")
        guess = self._ws[K.R_FK, 0:4].copy() if self._ready else self._y_guess
        st = K.plant_reset(self._ws, self._p, qa, qda, guess, self._counts)
        if st != K.ST_OK:
            self._fail(st)
        self._faulted = False
        self._fault_text = ""
        self._ready = True

    def reset_to_pose(self, X0: np.ndarray) -> None:
        """Reset at rest at task pose X0 = (x, y, z, θ) [m, rad] (IK first)."""
        self.reset(inverse_kinematics(np.asarray(X0, dtype=np.float64), self.config.geometry), None)

    def _fail(self, status: int) -> None:
        self._faulted = True
        self._ready = False
        self._fault_text = K.STATUS_TEXT.get(status, f"status {status}")
        raise PlantError(
            f"plant fault at t = {self.time_s:.6f} s: {self._fault_text}; q = {self._ws[K.R_STATE, 0:4].tolist()} rad"
        )

    @property
    def q(self) -> np.ndarray:
        """Joint angles, rad (copy)."""
        return self._q_view.copy()

    def q_list(self) -> list[float]:
        """Joint angles, rad, as Python floats: one C call, no array made (a robot period's reads)."""
        return self._q_view.tolist()

    @property
    def qd(self) -> np.ndarray:
        """Joint velocities, rad/s (copy)."""
        return self._ws[K.R_STATE, 4:8].copy()

    @property
    def Y(self) -> np.ndarray:
        """Sub-platform coordinates (x, y, z_u, z_l) of the last FK evaluation, m (copy).

        After a step this is the FK of the last RK4 stage (within one sub-step of q); use
        :meth:`task_pose` for the pose at exactly q."""
        return self._ws[K.R_FK, 0:4].copy()

    def task_pose(self) -> np.ndarray:
        """Task pose X = (x, y, z, θ) [m, rad] at the current q (FK warm-started from :attr:`Y`)."""
        g = self.config.geometry
        return task_from_subplatform(forward_kinematics(self.q, self.Y, g), g)

    @property
    def time_s(self) -> float:
        """Simulated time since reset, s (= steps · Ts)."""
        return self._n_steps * self.ts_s

    @property
    def n_steps(self) -> int:
        """Number of control periods since reset."""
        return self._n_steps

    @property
    def faulted(self) -> bool:
        """True after a :class:`PlantError` until the next reset."""
        return self._faulted

    @property
    def fault_text(self) -> str:
        """Reason of the last fault ('' if none)."""
        return self._fault_text

    @property
    def applied_torque_nm(self) -> np.ndarray:
        """Joint torque applied in the last step after clamping (without disturbance), N·m."""
        return self._ws[K.R_V3, 12:16].copy()

    @property
    def saturated(self) -> np.ndarray:
        """Per joint: the last torque command was clamped (bool (4,))."""
        return self._ws[K.R_AUX, 0:4] != 0.0

    def encoder_counts(self) -> np.ndarray:
        """Encoder readings: nearest integer of q / rad_per_count, int64 (4,)."""
        return self._counts.copy()

    def encoder_counts_list(self) -> list[int]:
        """:meth:`encoder_counts` as Python ints: one C call, no array made (a robot period's encoder frames)."""
        return self._counts.tolist()

    # ---- integration ---------------------------------------------------------------------

    def step(self, torque_units: np.ndarray, disturbance_nm: np.ndarray | None = None, locked: np.ndarray | None = None) -> None:
        """Integrate one control period with the torque held.

        :param torque_units: int array (4,), commanded joint torque in torque LSBs
        :param disturbance_nm: float array (4,), external joint torque, N·m (None = 0)
        :param locked: bool array (4,): joints held by their brakes this period (velocity 0, no
            motion; the others move with these joints fixed); None: none.  With every joint held
            the state stays as it is.
        :raises PlantError: on a plant fault (then ``faulted`` is True)
        """
        if not self._ready:
            if self._faulted:
                raise PlantError(f"plant is faulted ({self._fault_text}); reset() first")
            raise PlantError("plant not reset; call reset(q0, qd0) first")
        tu = torque_units
        if type(tu) is not np.ndarray or tu.dtype is not _I64 or tu.shape != _SHAPE4:
            tu = np.ascontiguousarray(tu, dtype=np.int64)
            if tu.shape != _SHAPE4:
                raise ValueError(f"torque_units must have shape (4,), got {tu.shape}")
        d = self._zero4 if disturbance_nm is None else disturbance_nm
        if type(d) is not np.ndarray or d.dtype is not _F64 or d.shape != _SHAPE4:
            d = np.ascontiguousarray(d, dtype=np.float64)
            if d.shape != _SHAPE4:
                raise ValueError(f"disturbance_nm must have shape (4,), got {d.shape}")
        held = 0 if locked is None else int(np.count_nonzero(locked))  # one C call, not any() + all()
        if held == 0:
            st = K.plant_step(self._ws, self._p, tu, d, self._counts)
        elif held == _N_JOINTS:
            self._ws[K.R_STATE, 4:8] = 0.0
            self._ws[K.R_V3, 12:16] = 0.0
            self._ws[K.R_AUX, 0:4] = 0.0
            st = K.ST_OK
        else:
            st = K.plant_step_locked(self._ws, self._p, tu, d, self._counts, np.ascontiguousarray(locked, dtype=np.int64))
        if st != K.ST_OK:
            self._fail(st)
        self._n_steps += 1


def warm_up(config: TruePlantConfig | None = None) -> float:
    """Compile (or load from cache) the plant kernels; returns the seconds it took."""
    from plant.params import default_true_plant

    t0 = time.perf_counter()
    p = Plant(config or default_true_plant(), 1e-3, 4, 1e-6, 1e-6)
    p.reset_to_pose(np.array([0.0, 0.0, -0.65, 0.0]))
    p.step(np.zeros(4, dtype=np.int64), None)
    return time.perf_counter() - t0
