"""The plan of an experiment: everything decided before anything moves.

This module owns :func:`prepare`: plan the task trajectory, map it to joint references,
check feasibility, resolve the gains, build the closed-loop model along the reference, the
learning law and its convergence check, and compute the initial feed-forward.  Anything
infeasible raises a ``ValueError`` subclass with a one-line message, before a process starts or a
drive is configured.
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
from host.learning.check import BOUNDED_BLOCK, PROBE_TORQUE_FRACTION, ConvergenceReport
from host.learning.gains import Gains, resolve_gains
from host.learning.laws import LawContext, LearningLaw, make_law
from host.learning.model import ClosedLoopModel
from host.planning.paths import resolve_path
from host.planning.trajectory import JointReference, check_feasibility, joint_reference, plan_task
from plant.dynamics import inverse_dynamics, mass_matrix
from plant.params import Geometry, default_true_plant, nominal_mass_model

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
    closed_loop = ClosedLoopModel(inertia_seq, gains.kp, gains.kd, cfg.ts_s)
    tau_nominal = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, model), dtype=float)
    u0 = tau_nominal if cfg.ff0 == "model" else np.zeros_like(ref.q)
    ctx = LawContext(gains=gains, ts_s=cfg.ts_s, model=closed_loop, reference=ref, u0_nm=u0, mass_model=model,
                     geometry=Geometry())
    law = make_law(cfg.law, ctx)
    # the prediction starts from the error a PROBE_TORQUE_FRACTION error of the nominal torque causes
    check = law.check(closed_loop, PROBE_TORQUE_FRACTION * tau_nominal, cfg.iterations)
    if not check.ok:
        logger.warning("convergence check failed for law %s: spectral radius %.3f, predicted error ratio "
                       "after %d trials %.3g: expect divergence", cfg.law, check.rho_max, check.iterations,
                       check.predicted_ratio)
    bus_fit = None
    if cfg.ff_transport == "pdo":
        fit = cyclic_bus_fit(cfg.ts_s, cfg.fieldbus_bitrate)
        bus_fit = fit.as_dict() | {"message": fit.message(), "forced": bool(cfg.force_bus_fit and not fit.fits)}
    if not check.long_bounded:
        logger.warning("law %s is predicted to grow again within %d trials (last %d trials %.3g x the best)",
                       cfg.law, check.long_horizon, BOUNDED_BLOCK, check.predicted_long_growth)
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
