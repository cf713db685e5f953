"""The trial loop's state and what it produces: :class:`LoopState` (the plan, the bench, the
feed-forward; one trial set up, run, measured and put in the summary), :class:`ExperimentResult`,
:class:`TrialOutcome` and the summary before the first trial (:func:`new_summary`).

The loop that steps it is :class:`host.experiment.trial_loop.TrialLoop`.

May import: ``bus``, ``numpy``, :mod:`host.experiment` (bench, faults, law_watch, plan, summary, tpdo_check),
:mod:`host.learning`, :mod:`host.nodes`, :mod:`host.planning`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from bus import units
from bus.cyclic import PDO_MODE, nm_to_permille_array, permille_to_nm_array
from bus.errors import IlcrigError
from bus.objects import ModeOfOperation
from bus.process_identity import process_identity
from host.experiment.bench import Bench, CyclicSetpoints, TrialFault, TrialRecorder
from host.experiment.faults import FaultKind, FaultRecord
from host.experiment.law_watch import LawWatch
from host.experiment.plan import Plan, reference_tables
from host.experiment.summary import SCHEMA
from host.experiment.tpdo_check import check_tpdos_against_recorder
from host.learning.gains import Gains
from host.learning.metrics import TraceDigest, TrialMetrics, trial_metrics
from host.learning.protocol import LEARNING, TrialData

logger = logging.getLogger(__name__)

__all__ = ["EndReason", "ExperimentResult", "TrialOutcome", "LoopState", "end_reason", "new_summary"]


class EndReason(StrEnum):
    """How a run ended: ``summary["end_reason"]`` (docs/api.md, docs/faults.md)."""

    COMPLETED = "completed"  # every planned trial ran and was kept
    FAULT = "fault"  # a fault ended it (summary["faults"])
    INTERRUPTED = "interrupted"  # SIGINT / SIGTERM / SIGHUP / Ctrl-C (summary["interrupted"])
    LAW_ERROR = "law_error"  # the learning law failed or diverged (a fault of the law, in summary["faults"])
    USER_EXCEPTION = "user_exception"  # an exception of the caller's code in the API (summary["user_exception"])
    STOPPED = "stopped"  # the caller ended it early (the API: a break, close())
    LAUNCHER_LOST = "launcher_lost"  # ilcrig run's launcher died first (SIGKILL, SIGQUIT): its janitor said so
    #: never written: what a reader says of a summary still without an end whose writer is gone
    #: (host.experiment.outputs.end_reason_of: killed with nobody left to say so)
    WRITER_LOST = "writer_lost"


@dataclass
class ExperimentResult:
    """What :func:`run_experiment` returns: the summary and, per trial, metrics and signals."""

    summary: dict[str, Any]
    metrics: list[TrialMetrics] = field(default_factory=list)
    errors: list[np.ndarray] = field(default_factory=list)  # (N, 4) rad per trial
    traces: list[list[Any]] = field(default_factory=list)  # per trial: DriveTrace per drive
    feedforward: list[np.ndarray] = field(default_factory=list)  # (N, 4) N·m per trial
    fault: str | None = None
    fault_record: FaultRecord | None = None
    interrupted: int | None = None  # the signal number
    roles: list[str] = field(default_factory=list)  # per trial: "learning" or "auxiliary"
    end_reason: EndReason | None = None  # set where it is decided (law error, user exception), else derived


def end_reason(result: ExperimentResult) -> EndReason:
    """How the run of ``result`` ended: an exception of the caller's code first, then an interrupt,
    a fault of the law, another fault, all trials done, else stopped early by the caller."""
    if result.end_reason == EndReason.USER_EXCEPTION:
        return EndReason.USER_EXCEPTION
    if result.interrupted is not None:
        return EndReason.INTERRUPTED
    if result.end_reason is not None:
        return result.end_reason
    if result.fault_record is not None or result.fault:
        return EndReason.FAULT
    return EndReason.COMPLETED if result.summary.get("completed") else EndReason.STOPPED


def new_summary(plan: Plan, mode: str, digest: TraceDigest) -> dict[str, Any]:
    """The summary before the first trial (``completed`` false, no iterations)."""
    return {
        "schema": SCHEMA,
        "mode": mode,
        "config": plan.cfg.as_dict() | {"n_ticks": plan.n_ticks, "trial_s": float(plan.ref.t[-1])},
        "law_source": plan.law.source,
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
        "end_reason": None,
        "writer": process_identity(),  # who ends this summary: a reader can tell a run killed unseen
    } | ({"bus_fit": plan.bus_fit} if plan.bus_fit is not None else {})


@dataclass(frozen=True)
class TrialOutcome:
    """One completed trial as the loop measured it (what :meth:`TrialLoop.step` returns).

    :ivar k: the trial's index (every rollout counts)
    :ivar role: ``learning`` or ``auxiliary`` (:mod:`host.learning.protocol`)
    :ivar metrics: its metrics
    :ivar feedforward_nm: (N, J) the feed-forward played, N·m
    :ivar error_rad: (N, J) e = q_d − q, rad
    :ivar torque_nm: (N, J) the total torque the learning uses (recorder, or TPDO in the pdo transport), N·m
    :ivar traces: the DriveTrace of each drive (the recorders' integer traces)
    :ivar gains: the gains the trial ran with
    """

    k: int
    role: str
    metrics: TrialMetrics
    feedforward_nm: np.ndarray
    error_rad: np.ndarray
    torque_nm: np.ndarray
    traces: list[Any]
    gains: Gains


class LoopState:
    """The trial loop's state: the plan, the bench, the feed-forward and what was measured."""

    def __init__(
        self, plan: Plan, bench: Bench, result: ExperimentResult, keep_traces: bool, recorder: TrialRecorder | None
    ) -> None:
        self.plan, self.bench, self.result = plan, bench, result
        self.keep_traces, self.recorder = keep_traces, recorder
        self.digest = TraceDigest()
        ref_counts, ref_vel = reference_tables(plan.ref)
        self.q_ref_rad = ref_counts * units.RAD_PER_COUNT
        self.qd_ref_rad_s = ref_vel * units.RAD_PER_COUNT
        self.u = plan.u0.copy()  # (N, 4) feed-forward of the next learning trial, N·m
        self.wall_s = 0.0
        self.last_traces: list[Any] = []
        self.last_u = self.u
        self.pending: tuple[int, TrialMetrics, np.ndarray] | None = None  # in the summary, not yet recorded
        self.pdo = plan.cfg.ff_transport == "pdo"
        self.ref_counts = ref_counts.astype(np.int32)
        #: the learning trial whose auxiliary trials are running, and those done so far
        self.step_trial: TrialData | None = None
        self.step_aux: list[TrialData] = []
        #: a trial runs: from its first tick until its data is in the summary
        self.in_trial = False
        #: the law's calls watched (the rig, :mod:`host.experiment.law_watch`), else None (in process)
        self.law_watch: LawWatch | None = None

    def setup_drive(self, j: int) -> None:
        """Gains, limits, reference tables, then enable (CiA 402 Operation enabled)."""
        plan, drive = self.plan, self.bench.drives[j]
        drive.configure(
            kp_nm_per_rad=float(plan.gains.kp[j]),
            kd_nms_per_rad=float(plan.gains.kd[j]),
            torque_limit_nm=plan.torque_limit_nm,
            following_error_rad=float(np.radians(plan.cfg.following_error_deg)),
        )
        if self.pdo:  # the reference is streamed as 0x607A; the drive needs only the trial length
            drive.set_trial_length(plan.n_ticks)
            drive.set_mode(PDO_MODE)
        else:  # the manufacturer's table playback (the drive boots in another mode)
            drive.set_mode(ModeOfOperation.TABLE_PLAYBACK)
            drive.load_reference(self.q_ref_rad[:, j], self.qd_ref_rad_s[:, j])
        drive.enable()

    def run_trial(self, k: int, u: np.ndarray) -> tuple[TrialMetrics, np.ndarray, np.ndarray]:
        """Trial ``k`` with the feed-forward ``u`` (N, 4) N·m: set up rebooted drives, download u,
        run, upload the traces, measure.  Returns the metrics, the error q_d − q (N, 4) rad and the
        total torque (N, 4) N·m."""
        plan, bench, ref = self.plan, self.bench, self.plan.ref
        for j in bench.recover(k):
            # a drive that rebooted since the last trial (heartbeat loss + boot-up) is set up
            # again from scratch; it then gets this trial's feed-forward like the others
            logger.warning("drive %d rebooted: configured again before trial %d", j + 1, k)
            self.setup_drive(j)
        cyclic = None
        for j, drive in enumerate(bench.drives):
            if not self.pdo:
                drive.load_feedforward(u[:, j])
            drive.arm_trial()
        if self.pdo:
            cyclic = CyclicSetpoints(self.ref_counts, nm_to_permille_array(u))
        t0 = time.perf_counter()
        self.in_trial = True
        actuals = bench.run_trial(k, plan.n_ticks, ref.q[0].copy(), ref.qd[0].copy(), cyclic=cyclic)
        self.wall_s += time.perf_counter() - t0
        traces = [drive.read_trace() for drive in bench.drives]
        self.digest.add_trial([(tr.position_counts, tr.velocity_counts_s, tr.torque_units, tr.torque_fb_units) for tr in traces])
        if self.pdo:
            if actuals is None:
                raise TrialFault(f"trial {k}: the bench returned no TPDO actuals")
            check_tpdos_against_recorder(k, actuals, traces, [d.rated_torque_mnm() for d in bench.drives])
            q_meas = actuals.position_counts * units.RAD_PER_COUNT
            tau = np.stack(
                [
                    permille_to_nm_array(actuals.torque_permille[:, j], bench.drives[j].rated_torque_mnm())
                    for j in range(len(traces))
                ],
                axis=1,
            )
        else:
            q_meas = np.stack([tr.q_rad for tr in traces], axis=1)
            tau = np.stack([tr.tau_nm for tr in traces], axis=1)
        e = ref.q - q_meas
        m = trial_metrics(k, e, tau)
        res = self.result
        res.metrics.append(m)
        res.errors.append(e)
        res.feedforward.append(u.copy())
        if self.keep_traces:
            res.traces.append(traces)
        self.last_traces = traces
        self.last_u = u
        return m, e, tau

    def record_pending(self) -> None:
        """After a fault between a trial's summary entry and its recording (a full disk): the
        recording gets the trial too (a failure is logged, never raised)."""
        if self.pending is None or self.recorder is None:
            return
        k, m, e = self.pending
        self.pending = None
        try:
            self.log_recording(k, m, e)
        except IlcrigError as exc:
            logger.info("trial %d not recorded: %s", k, exc)

    def checked_table(self, make: Callable[[], np.ndarray], next_trial: int) -> np.ndarray:
        """A feed-forward table from the learning law (``make``); one that is not finite or beyond
        the drive's int32 µN·m table is a fault (the law diverged), never a table."""
        limit = units.INT32_MAX * units.TORQUE_LSB_NM

        def quiet() -> np.ndarray:
            with np.errstate(over="ignore", invalid="ignore"):
                return make()

        try:
            # on the rig the law's code runs watched: a time limit, its hold of the interpreter
            u = quiet() if self.law_watch is None else self.law_watch.call(quiet, next_trial - 1)
            ok = bool(np.all(np.isfinite(u))) and float(np.max(np.abs(u), initial=0.0)) <= limit
        except FloatingPointError:
            ok, u = False, self.u
        if not ok:
            msg = (
                f"the learning law {self.plan.law.name} diverged: the feed-forward for trial {next_trial} is not "
                f"finite or beyond the drive's ±{limit:.0f} N·m table range"
            )
            raise TrialFault(
                msg,
                FaultRecord(
                    kind=FaultKind.LEARNING_DIVERGED,
                    message=msg,
                    trial=next_trial,
                    tick=0,
                    detected_by="host",
                    latency_ms=0.0,
                    latency_basis="same process",
                ),
            )
        return u

    def log_recording(self, k: int, m: TrialMetrics, e: np.ndarray) -> None:
        """Trial ``k`` into the recording (after it is in the summary: a failing recording
        write never loses a completed trial)."""
        if self.recorder is not None:
            self.recorder.log_trial(k, self.plan.ref, self.last_traces, self.last_u, e, m)
        self.pending = None

    def record(self, m: TrialMetrics, role: str = LEARNING) -> None:
        """Add trial ``m`` to the summary (an auxiliary trial with ``"role": "auxiliary"``): it is
        kept from now on."""
        self.in_trial = False
        s = self.result.summary
        peak_ff = np.max(np.abs(self.last_u), axis=0) if self.last_u.size else np.zeros(self.last_u.shape[-1])
        entry = m.as_dict() | {"peak_feedforward_nm": [float(v) for v in peak_ff]}
        s["iterations"].append(entry | ({"role": role} if role != LEARNING else {}))
        s["ticks"] = len(s["iterations"]) * self.plan.n_ticks
        s["wall_s"] = self.wall_s
        s["ticks_per_s"] = s["ticks"] / self.wall_s if self.wall_s > 0 else 0.0
        s["trace_sha256"] = self.digest.hexdigest()

    def trial_data(self, k: int, role: str, u: np.ndarray, e: np.ndarray, tau: np.ndarray) -> TrialData:
        """The trial as the law receives it (the recorded feedback torque from the traces)."""
        fb = np.stack([tr.tau_fb_nm for tr in self.last_traces], axis=1)
        return TrialData(k, u.copy(), e, tau, fb, self.plan.cfg.ts_s, role)
