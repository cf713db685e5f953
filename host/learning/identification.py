"""Estimating the robot's dynamic parameters from measured trials (the model correction of the
``no-ilc-id`` law).

This module owns :class:`DynamicsEstimate`: a least-squares fit of the robot's base parameters to
the joint angles and the total torques the drives recorded in a trial, and the corrected inverse
dynamics, mass matrices and friction slopes it gives along the reference.

Model (the structure of ``plant.dynamics`` and ``docs/robot-model.md`` §4–5; its parameters are
what is estimated — the nominal model's values are only the prior)::

    τ = Σ_i θ_i · τ_i(q, q̇, q̈)  +  Σ_j [F_c,j tanh(q̇_j / v_s) + F_v,j q̇_j] e_j

with the rigid-body dynamics linear in five base parameters θ = (m_u, m_l, I_b, k_g, I_ee): the
lumped upper and lower sub-platform masses (kg), the joint-side arm inertia (kg·m²), the arm
gravity coefficient m_a·l_c + ρ·m_fa·l_a (kg·m) and the tool spin inertia (kg·m²); τ_i is the
nominal inverse dynamics of a mass model with θ_i = 1 and every other parameter 0.  Friction:
Coulomb F_c (N·m) smoothed over v_s = 0.01 rad/s and viscous F_v (N·m·s/rad) per joint.
13 parameters in all.

Data of one trial (N samples at Ts): q = q_d − e from the encoder (the error smoothed by a 50 Hz
zero-phase low-pass), q̇ and q̈ by central differences, and the torque ½(τ[n−1] + τ[n]) — the mean
of the two held torques a central second difference integrates — at n = 1..N−2.  A weak ridge
toward the nominal parameters (relative weight :data:`PRIOR_WEIGHT`) keeps parameters the trial
does not excite at their nominal values.  If the estimate is not usable (non-finite, or a
non-positive arm inertia) the nominal parameters are kept and a warning is logged.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import numpy.typing as npt

from host.learning.signals import ZeroPhaseFilter
from plant.dynamics import inverse_dynamics, mass_matrix
from plant.params import Geometry, MassModel

logger = logging.getLogger(__name__)

__all__ = ["DynamicsEstimate", "COULOMB_SMOOTHING_RAD_S", "PRIOR_WEIGHT", "SMOOTHING_HZ", "PARAMETER_NAMES"]

Array = npt.NDArray[np.float64]

#: smoothing velocity of the Coulomb regressor tanh(q̇/v_s), rad/s (docs/robot-model.md §5.1)
COULOMB_SMOOTHING_RAD_S = 0.01
#: ridge weight toward the nominal parameters, relative to each regressor column's norm²
PRIOR_WEIGHT = 1e-4
#: cut-off of the zero-phase low-pass applied to the measured error before differentiating, Hz
SMOOTHING_HZ = 50.0
#: the estimated parameters, in order (units in the names)
PARAMETER_NAMES: tuple[str, ...] = (
    "m_up_kg",
    "m_low_kg",
    "i_b_kgm2",
    "k_g_kgm",
    "i_ee_kgm2",
    "fc1_nm",
    "fc2_nm",
    "fc3_nm",
    "fc4_nm",
    "fv1_nms",
    "fv2_nms",
    "fv3_nms",
    "fv4_nms",
)
_N_RIGID = 5


def _zero_mass(model: MassModel) -> MassModel:
    return dataclasses.replace(model, m_up=0.0, m_low=0.0, m_a=0.0, I_a=0.0, l_c=0.0, m_fa=0.0, J_m=0.0, payload=0.0, I_ee=0.0)


def _basis_models(model: MassModel) -> list[MassModel]:
    """Mass models with one base parameter = 1 and all others 0 (same ρ, n, g as ``model``)."""
    z = _zero_mass(model)
    return [
        dataclasses.replace(z, m_up=1.0),
        dataclasses.replace(z, m_low=1.0),
        dataclasses.replace(z, I_a=1.0),
        dataclasses.replace(z, m_a=1.0, l_c=1.0),
        dataclasses.replace(z, I_ee=1.0),
    ]


def _rigid_theta(model: MassModel, geometry: Geometry) -> Array:
    """The base parameters of a mass model."""
    return np.array(
        [
            model.m_up_eff,
            model.m_low_eff,
            model.joint_inertia(geometry.l_a),
            model.arm_gravity_coefficient(geometry.l_a) / model.g,
            model.I_ee,
        ]
    )


class DynamicsEstimate:
    """Least-squares estimate of the 13 dynamic parameters (module docstring).

    :param nominal: the host's nominal mass model (prior and structure)
    :param geometry: the robot geometry (known)
    :param ts_s: control period, s
    """

    def __init__(self, nominal: MassModel, geometry: Geometry, ts_s: float) -> None:
        self.nominal, self.geometry, self.ts_s = nominal, geometry, float(ts_s)
        self._basis = _basis_models(nominal)
        self.theta_nominal = np.concatenate([_rigid_theta(nominal, geometry), np.zeros(8)])
        self.theta = self.theta_nominal.copy()
        n_p = len(PARAMETER_NAMES)
        self._ata = np.zeros((n_p, n_p))
        self._atb = np.zeros(n_p)
        self.trials = 0
        self.residual_rms_nm = float("nan")

    # -- regressor -------------------------------------------------------------------------------

    def regressor(self, q: Array, qd: Array, qdd: Array) -> Array:
        """Y (N, 4, 13): τ = Y θ at the states (q rad, q̇ rad/s, q̈ rad/s²), each (N, 4)."""
        n = q.shape[0]
        y = np.zeros((n, 4, len(PARAMETER_NAMES)))
        for i, m in enumerate(self._basis):
            y[:, :, i] = inverse_dynamics(q, qd, qdd, m, self.geometry)
        for j in range(4):
            y[:, j, _N_RIGID + j] = np.tanh(qd[:, j] / COULOMB_SMOOTHING_RAD_S)
            y[:, j, _N_RIGID + 4 + j] = qd[:, j]
        return y

    def add_trial(self, q_ref_rad: Array, e_rad: Array, tau_nm: Array) -> None:
        """Add one trial: the reference q_d (N, 4) rad, the measured error e = q_d − q (N, 4) rad and
        the total torques (N, 4) N·m.  The error is smoothed (zero-phase, :data:`SMOOTHING_HZ`) before
        q = q_d − e is differentiated: the encoder's quantisation would otherwise dominate q̈ in slow
        motions (one count over Ts² is 0.6 rad/s² at 1 kHz)."""
        tau = np.asarray(tau_nm, dtype=float)
        e = np.asarray(e_rad, dtype=float)
        if e.shape[0] < 3:
            return
        ts = self.ts_s
        if e.shape[0] > 3 * 3:
            e = ZeroPhaseFilter(min(SMOOTHING_HZ, 0.2 / ts), 2, ts)(e)
        q = np.asarray(q_ref_rad, dtype=float) - e
        qc = q[1:-1]
        qd = (q[2:] - q[:-2]) / (2.0 * ts)
        qdd = (q[2:] - 2.0 * q[1:-1] + q[:-2]) / ts**2
        t_mean = 0.5 * (tau[:-2] + tau[1:-1])
        y = self.regressor(qc, qd, qdd).reshape(-1, len(PARAMETER_NAMES))
        b = t_mean.reshape(-1)
        self._ata += y.T @ y
        self._atb += y.T @ b
        self.trials += 1
        self._solve()
        self.residual_rms_nm = float(np.sqrt(np.mean((y @ self.theta - b) ** 2)))
        logger.info(
            "dynamics estimate after %d trial(s): %s; torque residual %.3g N·m RMS",
            self.trials,
            ", ".join(f"{k} {v:.4g}" for k, v in zip(PARAMETER_NAMES, self.theta)),
            self.residual_rms_nm,
        )

    def _solve(self) -> None:
        diag = np.diag(self._ata).copy()
        scale = np.sqrt(np.where(diag > 0, diag, 1.0))
        a = self._ata / np.outer(scale, scale)
        b = self._atb / scale
        lam = PRIOR_WEIGHT
        prior = self.theta_nominal * scale
        z = np.linalg.solve(a + lam * np.eye(len(b)), b + lam * prior)
        theta = z / scale
        if not np.all(np.isfinite(theta)) or theta[2] <= 0:
            logger.warning("dynamics estimate rejected (non-finite or non-positive inertia): nominal kept")
            return
        self.theta = theta

    # -- the corrected model along a trajectory ---------------------------------------------------

    def inverse_dynamics(self, q: Array, qd: Array, qdd: Array) -> Array:
        """τ (N, 4) N·m the estimated model needs along (q, q̇, q̈)."""
        return np.einsum("nji,i->nj", self.regressor(q, qd, qdd), self.theta)

    def mass_matrices(self, q: Array) -> Array:
        """M(q) (N, 4, 4) kg·m² of the estimated model."""
        m = np.zeros((q.shape[0], 4, 4))
        for i, basis in enumerate(self._basis):
            m += self.theta[i] * mass_matrix(q, basis, self.geometry)
        return m

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in zip(PARAMETER_NAMES, self.theta)}
