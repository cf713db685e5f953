"""The plan of an experiment: everything decided before anything moves.

This module owns :func:`prepare`: plan the task trajectory, map it to joint references,
check feasibility, resolve the gains, build the closed-loop model along the reference, the
learning law and its convergence check, and compute the initial feed-forward.  Anything
infeasible raises a ``ValueError`` subclass (:class:`PlanError` for the checks made here) with a
one-line message naming the option, before a process starts or a drive is configured.  The cheap
checks come first (:func:`check_config_limits`), so a bad input is refused in well under a second: the trial
length against the drives' table capacity, the memory of the run against the memory available,
the learning lead against N; then path, trajectory and feasibility, then the feedback gains against
the drive's fixed-point range (:mod:`bus.fixedpoint`), and only then the closed-loop model and the
convergence check (whose non-finite results, e.g. of absurd learning gains, count as "diverges").

The memory check: :func:`run_memory_bytes` is a model of the peak resident memory of a run fitted
to measurements (``benchmarks/run_memory.py``; linear in the trial length N, per law, plus a part
per trial and sample, times a margin); :func:`available_memory_bytes` is MemAvailable, or less under
a cgroup memory limit, or ``$ILCRIG_AVAILABLE_MEMORY`` (:data:`MEMORY_ENV`) when set.

The process that runs the law rehearses its first update on a copy (:func:`rehearse_first_update`)
before the first trial: ``ilcrig run``'s host process, so that what the update imports or compiles
on first use is paid before the nodes watch its heartbeat; a sim session (``ilcrig sim``, the API),
so that no interrupt lands inside that import.
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
from bus.errors import InputError
from bus.objects import TABLE_CAPACITY
from host.experiment.config import ExperimentConfig
from host.experiment.summary import jsonable
from host.learning.check import BOUNDED_BLOCK, PROBE_TORQUE_FRACTION, ConvergenceReport
from host.learning.gains import Gains, GainSpec, resolve_gains
from host.learning.laws.base import LawContext
from host.learning.laws.checked import CheckedLaw, build_law
from host.learning.model import ClosedLoopModel
from host.learning.names import LAWS
from host.learning.registry import law_class
from host.planning.feasibility import check_feasibility
from host.planning.joint_reference import JointReference, joint_reference
from host.planning.journeys import trial_samples
from host.planning.paths import resolve_path
from host.planning.task_plan import plan_task
from plant.dynamics import inverse_dynamics, mass_matrix
from plant.params import Geometry, default_true_plant, nominal_mass_model

logger = logging.getLogger(__name__)

__all__ = [
    "MEMORY_ENV",
    "PLUGIN_SAMPLE_BYTES",
    "Plan",
    "PlanError",
    "available_memory_bytes",
    "prepare",
    "check_config_limits",
    "plan_with_gains",
    "reference_tables",
    "rehearse_first_update",
    "run_memory_bytes",
]

#: environment variable: the memory the preflight may count on, bytes (suffix K, M, G or T for
#: KiB … TiB), instead of what the machine reports (:func:`available_memory_bytes`)
MEMORY_ENV: str = "ILCRIG_AVAILABLE_MEMORY"

# The memory model below is fitted to the peak resident memory of whole runs, measured by
# ``benchmarks/run_memory.py`` (N = 1001 … 59999, 2 … 100 trials, every law of different cost);
# each coefficient is rounded up, and the sum is multiplied by MEMORY_MARGIN.

#: the fixed part of the peak memory of ``ilcrig sim`` (one process: the interpreter with numpy,
#: scipy, numba and its compiled kernels, rerun and matplotlib; the drives' tables of fixed capacity), bytes.
#: It holds a first run's compilation of the numba kernels (an empty cache, as after installation:
#: 140 MB above a run that loads them, at N = 20,001)
RUN_BASE_BYTES: int = 510 * 1000**2
#: the part per sample of a trial, by law, bytes: the reference, the closed-loop model along it, the
#: law's operators (norm-optimal: the Riccati gains; no-ilc-id: the identification's regressor),
#: the convergence check's vectors (a Krylov basis of 41 vectors of 4N when the map is not causal)
#: and one trial's traces
SAMPLE_BYTES: dict[str, int] = {
    "pd-ilc": 2250,
    "pd-ol": 2250,
    "p-ol": 2250,
    "d-ilc": 2250,
    "pd-ilc-q": 2250,
    "q-ilc": 2250,
    "no-ilc": 3050,
    "no-ilc-id": 3100,
}
#: the part per sample and trial, bytes: every trial's error and feed-forward ((N, 4) float64 each)
#: stay for the summary, the report and the recording (measured 75 B: 100 against 2 trials at N = 20,001)
TRIAL_SAMPLE_BYTES: int = 80
#: ``ilcrig run``: the rig's other processes (launcher, hub, plant, four drives) together, their
#: fixed part (summed resident memory, shared library pages counted in each process), bytes
RIG_EXTRA_BYTES: int = 1150 * 1000**2
#: ``ilcrig run``: the rig's other processes, their part per sample of a trial, bytes
RIG_SAMPLE_BYTES: int = 1000
#: the estimate is the fitted model × this factor
MEMORY_MARGIN: float = 1.25
#: the part per sample for a law from outside the package (a plug-in may say its own with a class
#: attribute ``memory_bytes_per_sample``): the largest of the built-in laws
PLUGIN_SAMPLE_BYTES: int = max(SAMPLE_BYTES.values())
if set(SAMPLE_BYTES) != set(LAWS):  # pragma: no cover - a programming error, caught by every test
    raise ImportError(f"SAMPLE_BYTES {sorted(SAMPLE_BYTES)} differs from host.learning.names.LAWS {sorted(LAWS)}")


class PlanError(InputError):
    """The experiment cannot be prepared (one line naming the option and the allowed range)."""


def _law_sample_bytes(law: str) -> int:
    """The per-sample memory of ``law``: measured for the built-in laws, the class attribute
    ``memory_bytes_per_sample`` of a law from outside if it has one, else :data:`PLUGIN_SAMPLE_BYTES`."""
    if law in SAMPLE_BYTES:
        return SAMPLE_BYTES[law]
    try:
        declared = getattr(law_class(law), "memory_bytes_per_sample", None)
    except ValueError:  # an unknown name is refused where the law is built, with its own message
        declared = None
    return int(declared) if isinstance(declared, int | float) and declared > 0 else PLUGIN_SAMPLE_BYTES


def run_memory_bytes(n_ticks: int, iterations: int, law: str, *, rig: bool = False) -> int:
    """Estimated peak memory of a run of ``iterations`` trials of ``n_ticks`` samples with the law
    ``law``, margin included, bytes: of ``ilcrig sim`` (its one process), or with ``rig`` of all
    processes of ``ilcrig run``."""
    fitted = RUN_BASE_BYTES + n_ticks * (_law_sample_bytes(law) + iterations * TRIAL_SAMPLE_BYTES)
    if rig:
        fitted += RIG_EXTRA_BYTES + n_ticks * RIG_SAMPLE_BYTES
    return int(MEMORY_MARGIN * fitted)


def _max_samples(have_bytes: int, iterations: int, law: str, rig: bool) -> int:
    """The largest N whose :func:`run_memory_bytes` fits in ``have_bytes`` (0 if none)."""
    fixed = RUN_BASE_BYTES + (RIG_EXTRA_BYTES if rig else 0)
    per_sample = _law_sample_bytes(law) + iterations * TRIAL_SAMPLE_BYTES + (RIG_SAMPLE_BYTES if rig else 0)
    return max(int((have_bytes / MEMORY_MARGIN - fixed) // per_sample), 0)


_SUFFIX = {"": 1, "K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}


def _memory_from_env(text: str) -> int:
    """``$ILCRIG_AVAILABLE_MEMORY``: bytes, or with a suffix K, M, G, T (KiB … TiB; "2G", "512MiB")."""
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    unit = t[-1:] if t[-1:] in ("K", "M", "G", "T") else ""
    try:
        value = float(t[: len(t) - len(unit)])
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise PlanError(f"{MEMORY_ENV}={text!r}: must be a size in bytes, optionally with K, M, G or T (e.g. 2G)")
    return int(value * _SUFFIX[unit])


def _cgroup_room_bytes() -> int | None:
    """The room left under this process's cgroup memory limit (v2 memory.max, v1
    memory.limit_in_bytes), bytes; None without a limit."""
    try:
        with open("/proc/self/cgroup", encoding="ascii") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            files = (f"/sys/fs/cgroup{path}/memory.max", f"/sys/fs/cgroup{path}/memory.current")
        elif "memory" in controllers.split(","):
            files = (f"/sys/fs/cgroup/memory{path}/memory.limit_in_bytes", f"/sys/fs/cgroup/memory{path}/memory.usage_in_bytes")
        else:
            continue
        try:
            with open(files[0], encoding="ascii") as fh:
                limit = fh.read().strip()
            with open(files[1], encoding="ascii") as fh:
                usage = int(fh.read().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 2**60:  # v1 writes "no limit" as a number near 2**63
            return max(int(limit) - usage, 0)
    return None


def _available_memory() -> tuple[int | None, str]:
    """(bytes a run may count on or None, where the number comes from)."""
    env = os.environ.get(MEMORY_ENV)
    if env:
        return _memory_from_env(env), MEMORY_ENV
    have: int | None = None
    source = "MemAvailable"
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    have = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    if have is None:
        try:
            have, source = int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")), "physical memory"
        except (ValueError, OSError, AttributeError):
            pass
    room = _cgroup_room_bytes()
    if room is not None and (have is None or room < have):
        have, source = room, "cgroup memory limit"
    return have, source


def available_memory_bytes() -> int | None:
    """The memory a run may count on, bytes: ``$ILCRIG_AVAILABLE_MEMORY`` if set, else the smaller
    of MemAvailable (/proc/meminfo; else the physical memory) and the room under the cgroup's
    memory limit; None if unknown.

    :raises PlanError: ``$ILCRIG_AVAILABLE_MEMORY`` is not a size.
    """
    return _available_memory()[0]


def _size(n_bytes: float) -> str:
    """Bytes as MiB below 1 GiB, else GiB."""
    return f"{n_bytes / 1024**2:.0f} MiB" if n_bytes < 1024**3 else f"{n_bytes / 1024**3:.1f} GiB"


def _check_memory(cfg: ExperimentConfig, n: int, rig: bool) -> None:
    """Refuse a run whose estimated peak memory (:func:`run_memory_bytes`) exceeds what is available."""
    need = run_memory_bytes(n, cfg.iterations, cfg.law, rig=rig)
    have, source = _available_memory()
    if have is None or need <= have:
        return
    what = "the rig's processes need" if rig else "the run needs"
    journey = (min(_max_samples(have, cfg.iterations, cfg.law, rig), TABLE_CAPACITY) - 1) // 2
    if journey > 0:
        advice = f"use a cycle of at most about {journey * cfg.ts_s:.2f} s or fewer trials"
    else:
        fixed = MEMORY_MARGIN * (RUN_BASE_BYTES + (RIG_EXTRA_BYTES if rig else 0))
        advice = f"not even the fixed part of about {_size(fixed)} fits"
    raise PlanError(
        f"--cycle {cfg.cycle_s:g}, --iterations {cfg.iterations}: {cfg.iterations} trials of N = {n} samples with law "
        f"{cfg.law}: {what} about {_size(need)} of memory, this machine has {_size(have)} available ({source}); {advice}"
    )


def check_config_limits(cfg: ExperimentConfig, *, rig: bool = False) -> int:
    """The cheap checks that need no planning: the trial length N against the drives' table
    capacity, the run's memory against the machine's (with ``rig``: of all processes of
    ``ilcrig run``), the learning lead against N. Returns N.

    :raises PlanError: one line naming the option.
    """
    n = trial_samples(cfg.cycle_s, cfg.ts_s)
    if n > TABLE_CAPACITY:
        max_cycle = (TABLE_CAPACITY - 1) // 2 * cfg.ts_s
        raise PlanError(
            f"--cycle {cfg.cycle_s:g}: a trial of N = {n} samples exceeds the drives' table capacity "
            f"of {TABLE_CAPACITY} samples (0x2103:2); use a cycle of at most {max_cycle:g} s"
        )
    _check_memory(cfg, n, rig)
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
    law: CheckedLaw
    check: ConvergenceReport
    u0: np.ndarray  # (N, 4) initial feed-forward, N·m
    feasibility: dict[str, Any]
    torque_limit_nm: float
    bus_fit: dict[str, Any] | None = None  # pdo transport: the cyclic exchange against the fieldbus

    @property
    def n_ticks(self) -> int:
        return int(self.ref.q.shape[0])


def prepare(cfg: ExperimentConfig, *, rig: bool = False) -> Plan:
    """Plan the task, map it to joints, check feasibility and convergence (raise ValueError
    subclasses with one-line messages on anything infeasible); ``rig``: the memory check counts all
    processes of ``ilcrig run`` (:func:`check_config_limits`). The law's first update is not
    rehearsed here: that is the step of the process that runs the law (:func:`rehearse_first_update`)."""
    check_config_limits(cfg, rig=rig)
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


def rehearse_first_update(law: CheckedLaw, u0_nm: np.ndarray) -> None:
    """The law's first update rehearsed on a copy in the process that runs the law, before its first
    trial (:meth:`host.learning.laws.checked.CheckedLaw.rehearse_first_update`): what the update
    imports or compiles on first use is paid there — in the rig's host process before its nodes
    watch its heartbeat, in a sim session before the trials (where an interrupt may end the run,
    never inside an import). A launcher that rehearsed it would only pay it once more."""
    law.rehearse_first_update(u0_nm)


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
