"""The plan of an experiment: everything decided before anything moves.

This module owns :func:`prepare`: plan the task trajectory, map it to joint references,
check feasibility, resolve the gains, build the closed-loop model along the reference, the
learning law and its convergence check, and compute the initial feed-forward.  Anything
infeasible raises a ``ValueError`` subclass (:class:`PlanError` for the checks made here) with a
one-line message naming the option, before a process starts or a drive is configured.  The cheap
checks come first, so a bad input is refused in well under a second: the trial length against the
drives' table capacity and the memory the preparation needs (:func:`prepare_memory_bytes`, an
estimate easy to change), the learning lead against N, then path, trajectory and feasibility, then
the feedback gains against the drive's fixed-point range (:mod:`bus.fixedpoint`), and only then
the closed-loop model and the convergence check (whose non-finite results, e.g. of absurd learning
gains, count as "diverges").
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from bus import fixedpoint as fp
from bus import units
from bus.cyclic import cyclic_bus_fit
from bus.objects import TABLE_CAPACITY
from host.experiment.config import ExperimentConfig
from host.experiment.summary import jsonable
from host.learning.check import BOUNDED_BLOCK, PROBE_TORQUE_FRACTION, ConvergenceReport
from host.learning.gains import Gains, GainSpec, resolve_gains
from host.learning.laws import LawContext, LearningLaw
from host.learning.model import ClosedLoopModel
from host.learning.plugin import build_law
from host.planning.paths import resolve_path
from host.planning.trajectory import JointReference, check_feasibility, joint_reference, plan_task, trial_samples
from plant.dynamics import inverse_dynamics, mass_matrix
from plant.params import Geometry, default_true_plant, nominal_mass_model

logger = logging.getLogger(__name__)

__all__ = ["Plan", "PlanError", "prepare", "preflight", "prepare_memory_bytes", "reference_tables", "plan_with_gains"]

#: the preparation holds about this many dense (4N × 4N) float64 matrices at its peak (the lifted
#: model G, the iteration map and their temporaries; measured: 0.35 GB more at N = 1001 than at
#: N = 501).  Issue 11 makes the preparation O(N); then change :func:`prepare_memory_bytes`.
PREPARE_DENSE_MATRICES: float = 4.0
#: fixed part of the preparation's memory, bytes
PREPARE_BASE_BYTES: int = 300 * 1024**2


class PlanError(ValueError):
    """The experiment cannot be prepared (one line naming the option and the allowed range)."""


def prepare_memory_bytes(n_ticks: int, joints: int = 4) -> int:
    """Estimated peak memory of :func:`prepare` for trials of ``n_ticks`` samples, bytes."""
    return int(PREPARE_BASE_BYTES + PREPARE_DENSE_MATRICES * 8 * (joints * n_ticks) ** 2)


def available_memory_bytes() -> int | None:
    """MemAvailable of /proc/meminfo (else physical memory), bytes; None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def _gib(n: float) -> str:
    return f"{n / 1024**3:.1f} GiB"


def preflight(cfg: ExperimentConfig) -> int:
    """The cheap checks that need no planning: the trial length N against the drives' table
    capacity and the machine's memory, the learning lead against N. Returns N.

    :raises PlanError: one line naming the option.
    """
    n = trial_samples(cfg.cycle_s, cfg.ts_s)
    if n > TABLE_CAPACITY:
        max_cycle = (TABLE_CAPACITY - 1) // 2 * cfg.ts_s
        raise PlanError(
            f"--cycle {cfg.cycle_s:g}: a trial of N = {n} samples exceeds the drives' table capacity "
            f"of {TABLE_CAPACITY} samples (0x2103:2); use a cycle of at most {max_cycle:g} s"
        )
    need = prepare_memory_bytes(n)
    have = available_memory_bytes()
    if have is not None and need > have:
        # the largest N whose estimate fits, as a cycle time
        n_fit = int(math.sqrt(max(have - PREPARE_BASE_BYTES, 0) / (PREPARE_DENSE_MATRICES * 8)) / 4)
        max_cycle = max((n_fit - 1) // 2, 0) * cfg.ts_s
        raise PlanError(
            f"--cycle {cfg.cycle_s:g}: preparing a trial of N = {n} samples needs about {_gib(need)} of "
            f"memory (the convergence check's lifted model), this machine has {_gib(have)} available; "
            f"use a cycle of at most about {max_cycle:.2f} s"
        )
    if cfg.gains.lead >= n:
        raise PlanError(f"--lead {cfg.gains.lead}: the learning lead must be less than N = {n} samples per trial (0..{n - 1})")
    g = cfg.gains
    if g.lp is not None or g.ld is not None:
        # absolute learning gains fix the feedback gains without the inertia along the path: checked
        # here, before the planning (normalised ones are checked once the inertia is known)
        kp = np.full(4, (g.alpha - 1.0) * g.lp if g.lp is not None else 0.0)
        kd = np.full(4, (g.beta - 1.0) * g.ld if g.ld is not None else 0.0)
        with np.errstate(over="ignore", invalid="ignore"):
            _check_gain_values(kp, kd)
    return n


def _check_gain_range(gains: Gains) -> None:
    """The feedback gains must be representable in the drive's Q16 formats (bus.fixedpoint)."""
    _check_gain_values(gains.kp, gains.kd)


def _check_gain_values(kp_nm_per_rad: Any, kd_nms_per_rad: Any) -> None:
    """Per-joint Kp [N·m/rad] and Kd [N·m·s/rad] against the drive's fixed-point range."""
    for what, values, top, option in (
        ("Kp", kp_nm_per_rad, fp.KP_MAX_NM_PER_RAD, "--alpha/--lp/--lp-norm"),
        ("Kd", kd_nms_per_rad, fp.KD_MAX_NMS_PER_RAD, "--beta/--ld/--ld-norm"),
    ):
        unit = "N·m/rad" if what == "Kp" else "N·m·s/rad"
        for j, v in enumerate(np.asarray(values, dtype=float)):
            if not math.isfinite(v) or not 0.0 <= v <= top:
                raise PlanError(
                    f"{option}: the feedback gain {what} of joint {j + 1} = {v:.6g} {unit} is outside the "
                    f"drive's fixed-point range 0..{top:.6g} {unit} (bus/fixedpoint.py)"
                )


def _finite_check(check: ConvergenceReport) -> ConvergenceReport:
    """Non-finite numbers of the convergence check (overflowing predictions) → inf, not ok."""
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(check):
        v = getattr(check, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            changes[f.name] = math.inf
    if not changes:
        return check
    logger.warning("convergence check: non-finite %s (the linearised model diverges)", ", ".join(sorted(changes)))
    return dataclasses.replace(check, ok=False, **changes)


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
    preflight(cfg)
    path = resolve_path(cfg.path)
    task = plan_task(path, cfg.cycle_s, cfg.profile, cfg.ts_s)
    ref = joint_reference(task)
    model = nominal_mass_model()
    true_cfg = default_true_plant()
    feas = check_feasibility(ref, model)
    inertia_seq = np.array([mass_matrix(q, model) for q in ref.q])
    mean_inertia = np.mean(np.diagonal(inertia_seq, axis1=1, axis2=2), axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        gains = resolve_gains(cfg.gains, mean_inertia, cfg.ts_s)
    _check_gain_range(gains)
    closed_loop = ClosedLoopModel(inertia_seq, gains.kp, gains.kd, cfg.ts_s)
    tau_nominal = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, model), dtype=float)
    u0 = tau_nominal if cfg.ff0 == "model" else np.zeros_like(ref.q)
    ctx = LawContext(
        gains=gains,
        ts_s=cfg.ts_s,
        model=closed_loop,
        reference=ref,
        u0_nm=u0,
        mass_model=model,
        geometry=Geometry(),
        torque_limit_nm=float(true_cfg.joint_torque_limit_nm),
        options=dict(cfg.law_options),
    )
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        law = build_law(cfg.law, ctx)
        # the prediction starts from the error a PROBE_TORQUE_FRACTION error of the nominal torque causes
        check = law.check(closed_loop, PROBE_TORQUE_FRACTION * tau_nominal, cfg.iterations)
        check = _finite_check(check) if check.checked else check
    if check.checked and not check.ok:
        logger.warning(
            "convergence check failed for law %s: spectral radius %.3f, predicted error ratio "
            "after %d trials %.3g: expect divergence",
            cfg.law,
            check.rho_max,
            check.iterations,
            check.predicted_ratio,
        )
    bus_fit = None
    if cfg.ff_transport == "pdo":
        fit = cyclic_bus_fit(cfg.ts_s, cfg.fieldbus_bitrate)
        bus_fit = fit.as_dict() | {"message": fit.message(), "forced": bool(cfg.force_bus_fit and not fit.fits)}
    if check.checked and not check.long_bounded:
        logger.warning(
            "law %s is predicted to grow again within %d trials (last %d trials %.3g x the best)",
            cfg.law,
            check.long_horizon,
            BOUNDED_BLOCK,
            check.predicted_long_growth,
        )
    return Plan(
        cfg=cfg,
        ref=ref,
        gains=gains,
        law=law,
        check=check,
        u0=u0,
        feasibility=jsonable(feas),
        torque_limit_nm=float(true_cfg.joint_torque_limit_nm),
        bus_fit=bus_fit,
    )


def reference_tables(ref: JointReference) -> tuple[np.ndarray, np.ndarray]:
    """Reference positions (counts) and velocities (counts/s) as the drives get them.

    The velocity table is the backward difference of the integer position table, the same
    estimator the drive applies to the encoder, so that zero position error means zero
    velocity error."""
    counts = np.rint(ref.q / units.RAD_PER_COUNT).astype(np.int64)
    vel = np.zeros_like(counts)
    vel[1:] = np.rint((counts[1:] - counts[:-1]) / ref.t[1]).astype(np.int64) if len(ref.t) > 1 else 0
    return counts, vel


def plan_with_gains(plan: Plan, spec: GainSpec) -> Plan:
    """The same experiment with the gains ``spec`` (between trials: the API's stepping): the gains
    resolved on the plan's inertia, checked against the drive's range, the closed-loop model and the
    law built again for them, and their convergence check.

    :raises PlanError: a feedback gain outside the drive's fixed-point range (one line).
    """
    cfg = dataclasses.replace(plan.cfg, gains=spec)
    with np.errstate(over="ignore", invalid="ignore"):
        gains = resolve_gains(spec, plan.gains.inertia, cfg.ts_s)
    _check_gain_range(gains)
    ctx = dataclasses.replace(plan.law.ctx, gains=gains, model=plan.law.ctx.model.with_gains(gains.kp, gains.kd))
    ref = plan.ref
    tau_nominal = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, nominal_mass_model()), dtype=float)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        law = build_law(cfg.law, ctx)
        check = law.check(ctx.model, PROBE_TORQUE_FRACTION * tau_nominal, cfg.iterations)
        check = _finite_check(check) if check.checked else check
    return dataclasses.replace(plan, cfg=cfg, gains=gains, law=law, check=check)
