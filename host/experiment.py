"""One ILC experiment: plan, check, then trial after trial on a bench, learning in between.

The host side is the same for every mode: it talks to the four drives only through
:class:`host.drive_client.DriveClient` (object-dictionary reads and writes) and asks a
:class:`Bench` to run a trial.  ``ilcrig sim`` uses the in-process bench of
:mod:`host.compose`; ``ilcrig run`` a bench whose drives and plant are other processes on CAN.

The run folder gets ``summary.json`` (schema ``ilcrig.summary/1``), rewritten atomically after
every trial so a fault or Ctrl-C never corrupts the results of earlier trials.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from bus import units
from bus.errors import IlcrigError
from host.config import ExperimentConfig
from host.drive_client import DriveClient
from host.ilc import ConvergenceReport, Gains, LearningLaw, LiftedModel, make_law, resolve_gains
from host.metrics import TraceDigest, TrialMetrics, trial_metrics
from host.paths import resolve_path
from host.trajectory import JointReference, check_feasibility, joint_reference, plan_task
from plant.dynamics import inverse_dynamics, mass_matrix
from plant.params import default_true_plant, nominal_mass_model

logger = logging.getLogger(__name__)

__all__ = ["Bench", "TrialRecorder", "TrialFault", "Plan", "prepare", "run_experiment", "ExperimentResult", "SCHEMA"]

SCHEMA = "ilcrig.summary/1"


class TrialFault(IlcrigError):
    """A trial could not complete (drive fault, plant error, lost node); torque was removed."""


class TrialRecorder(Protocol):
    """Receives every completed trial (e.g. :class:`host.recording.RunRecorder`)."""

    def log_trial(self, k: int, ref: JointReference, traces: Sequence[Any], u: np.ndarray,
                  error_rad: np.ndarray, metrics: TrialMetrics) -> None:
        """``traces``: the DriveTrace of each drive; ``u`` (N, 4) the feed-forward of trial k, N·m;
        ``error_rad`` (N, 4) = q_d − q."""

    def close(self) -> None:
        """Finish the recording (called once, also after a fault)."""


class Bench(Protocol):
    """What the host needs from a set of drives plus a plant, whatever connects them."""

    drives: Sequence[DriveClient]

    def start(self) -> None:
        """Bring the nodes to operational (NMT) so they can be configured and enabled."""

    def run_trial(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray) -> None:
        """Reset the plant to (q0, qd0) and run ``n_ticks`` lockstep ticks with the armed drives.
        Raises :class:`TrialFault` if the trial did not complete."""

    def info(self) -> dict[str, Any]:
        """Mode-specific facts for the summary (transport, frame counts, bus load...)."""

    # optional: ``recover(trial) -> list[int]`` — indices of drives that rebooted and must be
    # configured again before ``trial`` (the rig implements it; in-process nothing reboots)

    def close(self) -> None:
        """Remove torque and release every resource (processes, buses)."""


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
    return Plan(cfg=cfg, ref=ref, gains=gains, law=law, check=check, u0=u0,
                feasibility=_jsonable(feas), torque_limit_nm=float(true_cfg.joint_torque_limit_nm))


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "as_dict"):
        return _jsonable(obj.as_dict())
    if dataclass_fields := getattr(obj, "__dataclass_fields__", None):
        return {k: _jsonable(getattr(obj, k)) for k in dataclass_fields}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


@dataclass
class ExperimentResult:
    summary: dict[str, Any]
    metrics: list[TrialMetrics] = field(default_factory=list)
    errors: list[np.ndarray] = field(default_factory=list)  # (N, 4) rad per trial
    traces: list[list[Any]] = field(default_factory=list)  # per trial: DriveTrace per drive
    feedforward: list[np.ndarray] = field(default_factory=list)  # (N, 4) N·m per trial
    fault: str | None = None


def reference_tables(ref: JointReference) -> tuple[np.ndarray, np.ndarray]:
    """Reference positions (counts) and velocities (counts/s) as the drives get them.

    The velocity table is the backward difference of the integer position table, the same
    estimator the drive applies to the encoder, so that zero position error means zero
    velocity error."""
    counts = np.rint(ref.q / units.RAD_PER_COUNT).astype(np.int64)
    vel = np.zeros_like(counts)
    vel[1:] = np.rint((counts[1:] - counts[:-1]) / ref.t[1]).astype(np.int64) if len(ref.t) > 1 else 0
    return counts, vel


def _write_summary(out_dir: Path, summary: dict[str, Any]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2, allow_nan=False))
    os.replace(tmp, out_dir / "summary.json")


def run_experiment(
    plan: Plan,
    bench: Bench,
    out_dir: str | Path | None,
    *,
    mode: str,
    on_trial: Callable[[TrialMetrics], None] | None = None,
    keep_traces: bool = False,
    recorder: TrialRecorder | None = None,
) -> ExperimentResult:
    """Run ``plan.cfg.iterations`` trials on ``bench``; write ``summary.json`` after each."""
    cfg, ref = plan.cfg, plan.ref
    n = plan.n_ticks
    out = Path(out_dir) if out_dir is not None else None
    digest = TraceDigest()
    summary: dict[str, Any] = {
        "schema": SCHEMA,
        "mode": mode,
        "config": cfg.as_dict() | {"n_ticks": n, "trial_s": float(ref.t[-1])},
        "iterations": [],
        "convergence_check": plan.check.as_dict(),
        "gains": plan.gains.as_dict(),
        "feasibility": plan.feasibility,
        "encoder_lsb_deg": units.DEG_PER_COUNT,
        "encoder_lsb_rad": units.RAD_PER_COUNT,
        "ticks": 0,
        "wall_s": 0.0,
        "ticks_per_s": 0.0,
        "trace_sha256": digest.hexdigest(),
        "faults": [],
        "completed": False,
    }
    result = ExperimentResult(summary=summary)
    ref_counts, ref_vel = reference_tables(ref)
    q_ref_rad = ref_counts * units.RAD_PER_COUNT
    u = plan.u0.copy()
    ticks = 0
    wall = 0.0
    try:
        bench.start()

        def setup_drive(j: int) -> None:
            drive = bench.drives[j]
            drive.configure(
                kp_nm_per_rad=float(plan.gains.kp[j]),
                kd_nms_per_rad=float(plan.gains.kd[j]),
                torque_limit_nm=plan.torque_limit_nm,
                following_error_rad=float(np.radians(cfg.following_error_deg)),
            )
            drive.load_reference(q_ref_rad[:, j], ref_vel[:, j] * units.RAD_PER_COUNT)
            drive.enable()

        for j in range(len(bench.drives)):
            setup_drive(j)
        recover = getattr(bench, "recover", None)
        for k in range(cfg.iterations):
            if recover is not None:
                # a drive that rebooted since the last trial (heartbeat loss + boot-up) is set up
                # again from scratch; it then gets this trial's feed-forward like the others
                for j in recover(k):
                    logger.warning("drive %d rebooted: configured again before trial %d", j + 1, k)
                    setup_drive(j)
            for j, drive in enumerate(bench.drives):
                drive.load_feedforward(u[:, j])
                drive.arm_trial()
            t0 = time.perf_counter()
            bench.run_trial(k, n, ref.q[0].copy(), ref.qd[0].copy())
            wall += time.perf_counter() - t0
            ticks += n
            traces = [drive.read_trace() for drive in bench.drives]
            digest.add_trial([(tr.position_counts, tr.velocity_counts_s, tr.torque_units, tr.torque_fb_units)
                              for tr in traces])
            q_meas = np.stack([tr.q_rad for tr in traces], axis=1)
            tau = np.stack([tr.tau_nm for tr in traces], axis=1)
            e = ref.q - q_meas
            m = trial_metrics(k, e, tau)
            result.metrics.append(m)
            result.errors.append(e)
            result.feedforward.append(u.copy())
            if keep_traces:
                result.traces.append(traces)
            if recorder is not None:
                recorder.log_trial(k, ref, traces, u, e, m)
            summary["iterations"].append(m.as_dict())
            summary["ticks"] = ticks
            summary["wall_s"] = wall
            summary["ticks_per_s"] = ticks / wall if wall > 0 else 0.0
            summary["trace_sha256"] = digest.hexdigest()
            if out is not None:
                _write_summary(out, summary)
            if on_trial is not None:
                on_trial(m)
            if k + 1 < cfg.iterations:
                u = plan.law.update(u, e, tau)
        summary["completed"] = True
    except (TrialFault, IlcrigError) as exc:
        # a fault, or a drive that stopped answering between trials (SDO timeout/abort while
        # downloading a table or uploading the recorder): torque is removed by closing the
        # bench, the trials so far are kept
        result.fault = str(exc) if isinstance(exc, TrialFault) else f"{type(exc).__name__}: {exc}"
        summary["faults"].append({"trial": len(summary["iterations"]), "message": str(exc)})
        logger.error("trial %d faulted: %s", len(summary["iterations"]), exc)
    finally:
        try:
            summary["bench"] = _jsonable(bench.info())
        finally:
            bench.close()
            if recorder is not None:
                recorder.close()
        if out is not None:
            _write_summary(out, summary)
    return result
