"""Rigid-body dynamics of the robot: the paper's model eq. (1)–(4) with docs/robot-model.md §4 lumping.

This module owns the public dynamics API, joint side, SI units (N·m, rad, s)::

    τ = M(q) q̈ + C(q, q̇) q̇ + G(q)        (+ τ_f(q̇) for the true plant)

    Mbar  = diag(m_u + m_l, m_u + m_l, m_u, m_l) + (2π/h)² I_ee (e₃ − e₄)(e₃ − e₄)ᵀ   (Y-space)
    M     = Jᵀ Mbar J + I_b                 (= J_lowᵀ M_p,low J_low + J_upᵀ M_p,up J_up + I_b
                                              when I_ee = 0, the paper's eq. (2))
    C q̇  = Jᵀ Mbar (J̇q̇)                  (eq. (3); exact for point-mass platforms)
    G     = ∂V/∂q = Jᵀ (0, 0, m_u g, m_l g) − (m_a l_c + ρ m_fa l_a) g cos q    (eq. (4))
    V     = g (m_u z_u + m_l z_l) − Σ_i (m_a l_c + ρ m_fa l_a) g sin q_i

with m_u, m_l the lumped sub-platform masses (incl. 2(1−ρ) m_fa, payload on the lower one),
I_b = I_a + ρ m_fa l_a² + n² J_m.  The tool spin term I_ee (true plant only; 0 nominally) adds
½ I_ee θ̇² = ½ (2π/h)² I_ee (ż_u − ż_l)² to the kinetic energy, so it enters Mbar and, through
the same Jᵀ Mbar J̇q̇, the velocity-product term: energy stays consistent.

Sign convention: q positive with the elbow down, so holding an arm against gravity needs a
negative torque (≈ −2.9 N·m on limbs 1/3 and −3.2 N·m on limbs 2/4 at the path centre).

All functions accept a single state (4,) or a batch (N, 4); FK is solved inside (warm-started
sample to sample along a batch).  Friction is not part of these nominal functions; see
:func:`friction_torque` for the true plant's.
"""

from __future__ import annotations

import functools
import logging

import numpy as np

from plant import _kernels as K
from plant.kinematics import DEFAULT_Y_GUESS, ForwardKinematicsError, SingularConfigurationError
from plant.params import Geometry, MassModel, TruePlantConfig

logger = logging.getLogger(__name__)


class DynamicsError(ValueError):
    """The dynamic model cannot be evaluated at the given state."""


@functools.lru_cache(maxsize=32)
def _model_params(model: MassModel, geometry: Geometry) -> np.ndarray:
    return K.pack_params(geometry, model)


@functools.lru_cache(maxsize=32)
def _config_params(config: TruePlantConfig) -> np.ndarray:
    return K.pack_params(config.geometry, config=config)


def _params(model: MassModel, geometry: Geometry | None) -> np.ndarray:
    return _model_params(model, geometry if geometry is not None else Geometry())


def _batch(a: np.ndarray, name: str) -> tuple[np.ndarray, tuple[int, ...]]:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[-1:] != (4,):
        raise ValueError(f"{name} must have shape (..., 4), got {arr.shape}")
    return np.ascontiguousarray(arr.reshape(-1, 4)), arr.shape[:-1]


def _raise_status(code: int, qs: np.ndarray) -> None:
    n, st = divmod(code, 16)
    text = K.STATUS_TEXT.get(st, f"status {st}")
    if st == K.ST_FK_FAIL:
        raise ForwardKinematicsError(f"{text} at q = {qs[n].tolist()} rad")
    if st in (K.ST_SINGULAR_A, K.ST_SERIAL_SINGULAR):
        raise SingularConfigurationError(f"{text} at q = {qs[n].tolist()} rad")
    raise DynamicsError(f"{text} at q = {qs[n].tolist()} rad")


def dynamic_terms(
    q: np.ndarray, qd: np.ndarray | None, model: MassModel, geometry: Geometry | None = None, Y_guess: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(M (…,4,4) [kg·m²], C q̇ (…,4) [N·m], G (…,4) [N·m], Y (…,4) [m]) in one pass."""
    qs, lead = _batch(q, "q")
    qds = np.zeros_like(qs) if qd is None else _batch(qd, "qd")[0]
    if qds.shape != qs.shape:
        raise ValueError(f"q and qd shapes differ: {qs.shape} vs {qds.shape}")
    y0 = np.array(DEFAULT_Y_GUESS if Y_guess is None else Y_guess, dtype=np.float64)
    n = qs.shape[0]
    ys = np.empty((n, 4))
    ms = np.empty((n, 4, 4))
    cs = np.empty((n, 4))
    gs = np.empty((n, 4))
    r = K.dynamics_batch(qs, qds, y0, _params(model, geometry), ys, ms, cs, gs)
    if r >= 0:
        _raise_status(r, qs)
    return (ms.reshape(lead + (4, 4)), cs.reshape(lead + (4,)), gs.reshape(lead + (4,)), ys.reshape(lead + (4,)))


def mass_matrix(q: np.ndarray, model: MassModel, geometry: Geometry | None = None) -> np.ndarray:
    """Joint-space mass matrix M(q) (…, 4, 4) [kg·m²], eq. (2) (+ tool spin if I_ee > 0)."""
    return dynamic_terms(q, None, model, geometry)[0]


def coriolis_vector(q: np.ndarray, qd: np.ndarray, model: MassModel, geometry: Geometry | None = None) -> np.ndarray:
    """Velocity-product torque C(q, q̇) q̇ (…, 4) [N·m], eq. (3) via J̇q̇."""
    return dynamic_terms(q, qd, model, geometry)[1]


def gravity_vector(q: np.ndarray, model: MassModel, geometry: Geometry | None = None) -> np.ndarray:
    """Gravity torque G(q) (…, 4) [N·m], eq. (4) (= static holding torque)."""
    return dynamic_terms(q, None, model, geometry)[2]


def inverse_dynamics(
    q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, model: MassModel, geometry: Geometry | None = None
) -> np.ndarray:
    """τ = M q̈ + C q̇ + G (…, 4) [N·m] (rigid body, no friction); vectorised over (N, 4)."""
    M, C, G, _ = dynamic_terms(q, qd, model, geometry)
    qdd = np.asarray(qdd, dtype=np.float64)
    return np.einsum("...ij,...j->...i", M, qdd) + C + G


def forward_dynamics(
    q: np.ndarray, qd: np.ndarray, tau: np.ndarray, model: MassModel, geometry: Geometry | None = None
) -> np.ndarray:
    """q̈ = M⁻¹(τ − C q̇ − G) (…, 4) [rad/s²] for joint torques τ [N·m] (no friction)."""
    return _forward(q, qd, tau, _params(model, geometry))


def true_forward_dynamics(q: np.ndarray, qd: np.ndarray, tau: np.ndarray, config: TruePlantConfig) -> np.ndarray:
    """q̈ of the true plant (its mass model + friction) for applied joint torques τ [N·m]
    (no clamping: τ is taken as applied)."""
    return _forward(q, qd, tau, _config_params(config))


def _forward(q: np.ndarray, qd: np.ndarray, tau: np.ndarray, p: np.ndarray) -> np.ndarray:
    qs, lead = _batch(q, "q")
    qds, _ = _batch(qd, "qd")
    taus, _ = _batch(tau, "tau")
    out = np.empty_like(qs)
    r = K.forward_dynamics_batch(qs, qds, taus, np.array(DEFAULT_Y_GUESS), p, out)
    if r >= 0:
        _raise_status(r, qs)
    return out.reshape(lead + (4,))


def friction_torque(qd: np.ndarray, config: TruePlantConfig) -> np.ndarray:
    """True-plant joint friction τ_f(q̇) (…, 4) [N·m]:
    F_c·(1 + (r_s − 1) e^{−(q̇/v_s)²})·tanh(q̇/v_smooth) + F_v q̇."""
    qds, lead = _batch(qd, "qd")
    out = np.empty_like(qds)
    K.friction_batch(qds, _config_params(config), out)
    return out.reshape(lead + (4,))


def true_inverse_dynamics(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, config: TruePlantConfig) -> np.ndarray:
    """τ the true plant needs (its mass model, tool spin, friction; no clamp) (…, 4) [N·m]."""
    return inverse_dynamics(q, qd, qdd, config.mass, config.geometry) + friction_torque(qd, config)


def potential_energy(
    q: np.ndarray, model: MassModel, geometry: Geometry | None = None, Y: np.ndarray | None = None
) -> np.ndarray:
    """V(q) (…) [J] = g (m_u z_u + m_l z_l) − Σ (m_a l_c + ρ m_fa l_a) g sin q_i."""
    g = geometry if geometry is not None else Geometry()
    if Y is None:
        from plant.kinematics import forward_kinematics

        Y = forward_kinematics(q, geometry=g)
    q = np.asarray(q, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    kb = model.arm_gravity_coefficient(g.l_a)
    return model.g * (model.m_up_eff * Y[..., 2] + model.m_low_eff * Y[..., 3]) - kb * np.sin(q).sum(axis=-1)


def energy(q: np.ndarray, qd: np.ndarray, model: MassModel, geometry: Geometry | None = None) -> np.ndarray:
    """Total mechanical energy ½ q̇ᵀ M q̇ + V (…) [J] (kinetic incl. tool spin + potential)."""
    M, _, _, Y = dynamic_terms(q, qd, model, geometry)
    qd = np.asarray(qd, dtype=np.float64)
    kin = 0.5 * np.einsum("...i,...ij,...j->...", qd, M, qd)
    return kin + potential_energy(q, model, geometry, Y)
