"""The plan of an experiment: everything decided before anything moves.

This module owns :func:`prepare`: plan the task trajectory, map it to joint references,
check feasibility, resolve the gains, build the learning law and run its convergence check,
and compute the initial feed-forward.  Anything infeasible raises a ``ValueError`` subclass
with a one-line message, before a process starts or a drive is configured.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from bus import units
from bus.cyclic import cyclic_bus_fit
from host.experiment.config import ExperimentConfig
from host.experiment.summary import jsonable
from host.learning.ilc import ConvergenceReport, Gains, LearningLaw, LiftedModel, make_law, resolve_gains
from host.planning.paths import resolve_path
from host.planning.trajectory import JointReference, check_feasibility, joint_reference, plan_task
from plant.dynamics import inverse_dynamics, mass_matrix
from plant.params import default_true_plant, nominal_mass_model

logger = logging.getLogger(__name__)

__all__ = ["Plan", "prepare", "reference_tables"]


@dataclass
class Plan:
    """Everything decided before anything moves."""

    cfg: ExperimentConfig
    ref: JointReference
    gains: Gains
    law: LearningLaw
    check: ConvergenceReport
    u0: np.ndarray  # (N, 4) initial feed-forward, N·m
    feasibility: dict[str, Any]
    torque_limit_nm: float
    bus_fit: dict[str, Any] | None = None  # pdo transport: the cyclic exchange against the fieldbus

    @property
    def n_ticks(self) -> int:
        return int(self.ref.q.shape[0])


def prepare(cfg: ExperimentConfig) -> Plan:
    """Plan the task, map it to joints, check feasibility and convergence (raise ValueError
    subclasses with one-line messages on anything infeasible)."""
    path = resolve_path(cfg.path)
    task = plan_task(path, cfg.cycle_s, cfg.profile, cfg.ts_s)
    ref = joint_reference(task)
    model = nominal_mass_model()
    true_cfg = default_true_plant()
    feas = check_feasibility(ref, model)
    inertia_seq = np.array([mass_matrix(q, model) for q in ref.q])
    mean_inertia = np.mean(np.diagonal(inertia_seq, axis1=1, axis2=2), axis=0)
    gains = resolve_gains(cfg.gains, mean_inertia, cfg.ts_s)
    lifted = LiftedModel(inertia_seq, gains.kp, gains.kd, cfg.ts_s)
    law = make_law(cfg.law, gains, cfg.ts_s, model=lifted)
    check = law.check(lifted, None, cfg.iterations)
    if not check.ok:
        logger.warning("convergence check failed for law %s: spectral radius %.3f, predicted error ratio "
                       "after %d trials %.3g: expect divergence", cfg.law, check.rho_max, check.iterations,
                       check.predicted_ratio)
    if cfg.ff0 == "model":
        u0 = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, model), dtype=float)
    else:
        u0 = np.zeros_like(ref.q)
    bus_fit = None
    if cfg.ff_transport == "pdo":
        fit = cyclic_bus_fit(cfg.ts_s, cfg.fieldbus_bitrate)
        bus_fit = fit.as_dict() | {"message": fit.message(), "forced": bool(cfg.force_bus_fit and not fit.fits)}
    return Plan(cfg=cfg, ref=ref, gains=gains, law=law, check=check, u0=u0,
                feasibility=jsonable(feas), torque_limit_nm=float(true_cfg.joint_torque_limit_nm), bus_fit=bus_fit)


def reference_tables(ref: JointReference) -> tuple[np.ndarray, np.ndarray]:
    """Reference positions (counts) and velocities (counts/s) as the drives get them.

    The velocity table is the backward difference of the integer position table, the same
    estimator the drive applies to the encoder, so that zero position error means zero
    velocity error."""
    counts = np.rint(ref.q / units.RAD_PER_COUNT).astype(np.int64)
    vel = np.zeros_like(counts)
    vel[1:] = np.rint((counts[1:] - counts[:-1]) / ref.t[1]).astype(np.int64) if len(ref.t) > 1 else 0
    return counts, vel
