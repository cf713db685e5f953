"""One ILC experiment: plan, check, then trial after trial on a bench, learning in between.

The host side is the same for every mode: it talks to the four drives only through
:class:`host.nodes.drive_client.DriveClient` (object-dictionary reads and writes) and asks a
:class:`Bench` to run a trial.  ``ilcrig sim`` uses the in-process bench of
:mod:`host.sim.inprocess`; ``ilcrig run`` a bench whose drives and plant are other processes on CAN.

Feed-forward transport (``cfg.ff_transport``): ``table`` downloads the learned feed-forward by SDO
before every trial (the drives play it back in their manufacturer mode −1); ``pdo`` puts the drives
in cyclic synchronous position (CSP) and hands the bench the per-tick set-points (target position,
counts, and torque offset, ‰ of the rated torque) that it streams by SYNC + RPDO; the bench returns
the TPDO actuals (position counts, torque ‰), from which the learning takes q and τ.  The recorder
is uploaded in both modes (the trace digest, the recording) and must agree with the TPDOs.

Trials: :class:`TrialRunner` runs one trial per step — a learning trial, or one of the auxiliary
rollouts a law asks for after a learning trial (:mod:`host.learning.protocol`: counted as trials
everywhere, marked ``"role": "auxiliary"`` in the summary) — and runs the law after a learning
trial (or after the last auxiliary trial of its step); :func:`run_experiment` steps it to the end.

The run folder gets ``summary.json`` (:mod:`host.experiment.summary`), written before the first
trial and rewritten atomically after every trial so a fault or Ctrl-C never corrupts the results
of earlier trials.

One fault path: whatever ends a run early — a :class:`TrialFault` of the bench, a node that
stopped answering, a failing write of the outputs (a full disk), Ctrl-C / SIGTERM — ends it the
same way: the bench is closed (every live drive brought to a torque-free safe state, reported by
the bench's optional ``safe_state()`` into ``summary["safe_state"]``), the fault goes into
``summary["faults"]`` as a :class:`host.experiment.faults.FaultRecord` (an interrupt into
``summary["interrupted"]``), and the summary is written with every completed trial (the run
folder's space reserve given back first, so the final outputs fit on a full disk).  The same path
covers the whole run, not only the trials: a fault before the first trial (bring-up,
configuration), between two trials, after the last one or while the bench closes (its optional
``closing_fault()``) is placed with its :class:`host.experiment.faults.Position`, and a completed
run whose bench reports a fault while closing ends with it too (``completed`` stays true: every
trial was run and kept).

A trial counts as completed — kept — once its data is in the summary (in memory); its outputs
(recording, arrays, the summary file) are written right after, with the signals SIGINT / SIGTERM
held back meanwhile, so an interrupt never falls between a trial's recording and its summary
entry.  A trial whose outputs could not be written (a full disk) is written again after the
reserve is given back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from bus import units
from bus.cyclic import PDO_MODE, nm_to_permille_array, permille_to_nm_array
from bus.errors import IlcrigError, SdoAbort
from bus.objects import ModeOfOperation
from host.experiment.faults import (
    FaultKind,
    FaultRecord,
    Position,
    attach_injection,
    node_name,
    position_of,
    read_injections,
)
from host.experiment.outputs import OutputError, RunFolder
from host.experiment.plan import Plan, reference_tables
from host.experiment.summary import SCHEMA, jsonable, write_summary
from host.learning.gains import Gains
from host.learning.metrics import TraceDigest, TrialMetrics, trial_metrics
from host.learning.protocol import AUXILIARY, LEARNING, TrialData
from host.nodes.drive_client import DriveClient
from host.nodes.sdo_access import SdoTransportError
from host.planning.trajectory import JointReference

logger = logging.getLogger(__name__)

__all__ = [
    "Bench",
    "CyclicActuals",
    "CyclicSetpoints",
    "TrialRecorder",
    "TrialFault",
    "Interrupted",
    "interrupt_on_signals",
    "run_experiment",
    "ExperimentResult",
    "TrialOutcome",
    "TrialRunner",
    "new_summary",
    "place",
    "record_output_fault",
]


class TrialFault(IlcrigError):
    """A trial could not complete (drive fault, plant error, lost node); torque was removed.

    :ivar record: what the bench knows about it (kind, node, tick, who detected it), if anything
    """

    def __init__(self, message: str, record: FaultRecord | None = None) -> None:
        super().__init__(message)
        self.record = record


class Interrupted(KeyboardInterrupt):
    """SIGINT / SIGTERM during a run (raised by the signal handler of the process)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


class _Shield:
    """While :attr:`active` (the end of a run: safe state, summary), the signal handler of
    :func:`interrupt_on_signals` records a signal in :attr:`pending` instead of raising; while
    :attr:`defer_depth` > 0 (a trial's outputs being written) it keeps it in :attr:`deferred`,
    raised when the block ends (:func:`_deferred_interrupts`)."""

    active: bool = False
    pending: int | None = None
    defer_depth: int = 0
    deferred: int | None = None


_SHIELD = _Shield()


@contextlib.contextmanager
def _deferred_interrupts() -> Iterator[None]:
    """Hold SIGINT / SIGTERM back while inside (the handler of :func:`interrupt_on_signals` keeps
    the signal); at the end raise :class:`Interrupted` for it — unless an exception is already on
    its way, then the run's end marks the signal (:meth:`TrialRunner.finish`)."""
    _SHIELD.defer_depth += 1
    failed = False
    try:
        yield
    except BaseException:
        failed = True
        raise
    finally:
        _SHIELD.defer_depth -= 1
        if _SHIELD.defer_depth == 0 and _SHIELD.deferred is not None and not failed:
            signum, _SHIELD.deferred = _SHIELD.deferred, None
            raise Interrupted(signum)


@contextlib.contextmanager
def interrupt_on_signals(signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """While inside: SIGINT / SIGTERM raise :class:`Interrupted` in the main thread (the run then
    ends through its fault path: safe state, summary with an ``interrupted`` marker); a second
    signal during that shutdown is ignored so the summary gets written. Restores the handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum: int, _frame: object) -> None:
        if fired or _SHIELD.active:
            if _SHIELD.active and _SHIELD.pending is None:
                _SHIELD.pending = signum  # the run is ending already: marked, not raised
            logger.warning("signal %d while stopping: the run ends as soon as its outputs are written", signum)
            return
        fired.append(signum)
        if _SHIELD.defer_depth > 0:
            _SHIELD.deferred = signum  # a trial's outputs are being written: raised when they are
            return
        raise Interrupted(signum)

    old = {s: signal.signal(s, handler) for s in signals}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class TrialRecorder(Protocol):
    """Receives every completed trial (e.g. :class:`host.analysis.recording.RunRecorder`)."""

    def log_trial(
        self, k: int, ref: JointReference, traces: Sequence[Any], u: np.ndarray, error_rad: np.ndarray, metrics: TrialMetrics
    ) -> None:
        """``traces``: the DriveTrace of each drive; ``u`` (N, 4) the feed-forward of trial k, N·m;
        ``error_rad`` (N, 4) = q_d − q."""

    def close(self) -> None:
        """Finish the recording (called once, also after a fault).

        Optional, used when present: ``committed() -> dict | None`` (what is durably in the
        recording: its ``bytes`` and ``trials``, kept in ``summary["recording"]`` with every
        summary write, so a survivor can cut the file back to the summary's trials)."""


@dataclass(frozen=True)
class CyclicSetpoints:
    """What the host streams each tick in the pdo transport (RPDO1 of every drive).

    :ivar target_counts: (N, 4) int32, 0x607A target position, counts
    :ivar torque_offset_permille: (N, 4) int16, 0x60B2 torque offset, ‰ of 0x6076
    """

    target_counts: np.ndarray
    torque_offset_permille: np.ndarray


@dataclass(frozen=True)
class CyclicActuals:
    """What the drives' TPDOs reported each tick (TPDO1 of every drive).

    :ivar position_counts: (N, 4) 0x6064 position actual, counts
    :ivar torque_permille: (N, 4) 0x6077 torque actual, ‰ of 0x6076
    """

    position_counts: np.ndarray
    torque_permille: np.ndarray


class Bench(Protocol):
    """What the host needs from a set of drives plus a plant, whatever connects them."""

    @property
    def drives(self) -> Sequence[DriveClient]:
        """The drives in joint order (read-only here: an implementation may keep a list)."""

    def start(self) -> None:
        """Bring the nodes to operational (NMT) so they can be configured and enabled."""

    def run_trial(
        self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray, cyclic: CyclicSetpoints | None = None
    ) -> CyclicActuals | None:
        """Reset the plant to (q0, qd0) and run ``n_ticks`` lockstep ticks with the armed drives;
        with ``cyclic`` stream its set-points by SYNC + RPDO each tick and return the TPDO actuals.
        Raises :class:`TrialFault` if the trial did not complete."""

    def info(self) -> dict[str, Any]:
        """Mode-specific facts for the summary (transport, frame counts, bus load...)."""

    def recover(self, trial: int) -> list[int]:
        """Indices of drives that rebooted and must be configured again before ``trial`` (the
        rig detects a heartbeat loss followed by a boot-up; in-process nothing reboots: [])."""

    def close(self) -> None:
        """Remove torque and release every resource (processes, buses).

        Optional, used when present: ``safe_state() -> list[dict]`` (after close: per drive the
        evidence of its torque-free state), ``describe_fault(exc, trial) -> FaultRecord | None``
        (what the bench knows about the fault ``exc``), ``progress() -> int | None`` (the tick of
        the trial in progress), ``closing_fault() -> FaultRecord | None`` (after close: a fault the
        bench saw after the trial loop's last step — while the run ended or while it closed)."""


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


def new_summary(plan: Plan, mode: str, digest: TraceDigest) -> dict[str, Any]:
    """The summary before the first trial (``completed`` false, no iterations)."""
    return {
        "schema": SCHEMA,
        "mode": mode,
        "config": plan.cfg.as_dict() | {"n_ticks": plan.n_ticks, "trial_s": float(plan.ref.t[-1])},
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
    } | ({"bus_fit": plan.bus_fit} if plan.bus_fit is not None else {})


@dataclass(frozen=True)
class TrialOutcome:
    """One completed trial as the loop measured it (what :meth:`TrialRunner.step` returns).

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


class _Trials:
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
            _check_tpdos_against_recorder(k, actuals, traces, [d.rated_torque_mnm() for d in bench.drives])
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
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                u = make()
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
        s["iterations"].append(m.as_dict() | ({"role": role} if role != LEARNING else {}))
        s["ticks"] = len(s["iterations"]) * self.plan.n_ticks
        s["wall_s"] = self.wall_s
        s["ticks_per_s"] = s["ticks"] / self.wall_s if self.wall_s > 0 else 0.0
        s["trace_sha256"] = self.digest.hexdigest()

    def trial_data(self, k: int, role: str, u: np.ndarray, e: np.ndarray, tau: np.ndarray) -> TrialData:
        """The trial as the law receives it (the recorded feedback torque from the traces)."""
        fb = np.stack([tr.tau_fb_nm for tr in self.last_traces], axis=1)
        return TrialData(k, u.copy(), e, tau, fb, self.plan.cfg.ts_s, role)


class TrialRunner:
    """The trial loop, one trial per :meth:`step` (``run_experiment`` and the API's stepping).

    :meth:`start` writes the summary before the first trial, starts the bench and configures the
    drives; every :meth:`step` runs the next trial — a learning trial, or an auxiliary rollout the
    law asked for (:mod:`host.learning.protocol`) — records it (summary, recording), and after a
    learning trial (or the last auxiliary trial of its step) runs the law for the next learning
    trial's feed-forward; :meth:`finish` closes the bench and writes the final summary.  A fault or
    an interrupt during :meth:`start` or :meth:`step` ends the run through the one fault path (module
    docstring) and :meth:`step` returns None from then on, as it does after the last planned trial.
    Between steps :meth:`set_gains` changes the gains (in-process stepping of the API).

    Parameters as :func:`run_experiment`.
    """

    def __init__(
        self,
        plan: Plan,
        bench: Bench,
        out_dir: str | Path | None,
        *,
        mode: str,
        on_trial: Callable[[TrialMetrics, str], None] | None = None,
        keep_traces: bool = False,
        recorder: TrialRecorder | None = None,
        folder: RunFolder | None = None,
    ) -> None:
        self.out = Path(out_dir) if out_dir is not None else None
        self.bench, self.on_trial, self.recorder, self.folder = bench, on_trial, recorder, folder
        self.result = ExperimentResult(summary={})
        self.trials = _Trials(plan, bench, self.result, keep_traces, recorder)
        self.result.summary.update(new_summary(plan, mode, self.trials.digest))
        self.k = 0
        self.started = False
        self.finished = False

    @property
    def plan(self) -> Plan:
        return self.trials.plan

    @property
    def done(self) -> bool:
        """No trial left to run (all planned trials ran, or the run ended by a fault or interrupt)."""
        return self.finished or self.k >= self.plan.cfg.iterations

    def start(self) -> None:
        """Summary before the first trial, bench started, drives configured (idempotent)."""
        if self.started:
            return
        self.started = True
        self._guarded(self._start)

    def _start(self) -> None:
        if self.out is not None:
            self._note_recording()
            write_summary(self.out, self.result.summary, folder=self.folder, trial=-1)
        self.bench.start()
        for j in range(len(self.bench.drives)):
            self.trials.setup_drive(j)

    def step(self) -> TrialOutcome | None:
        """Run the next trial; None when the run is over (then it is finished: bench closed)."""
        if not self.started:
            self.start()
        if self.done:
            self.finish()
            return None
        outcome = self._guarded(self._step)
        if outcome is None or self.k >= self.plan.cfg.iterations:
            if outcome is not None:
                self.result.summary["completed"] = True
            self.finish()
        return outcome

    def _step(self) -> TrialOutcome:
        t, plan, law = self.trials, self.plan, self.plan.law
        k, n_planned = self.k, plan.cfg.iterations
        aux_step = t.step_trial
        if aux_step is not None:
            role = AUXILIARY
            u = t.checked_table(lambda: law.auxiliary_input(aux_step, tuple(t.step_aux)), k)
        else:
            role, u = LEARNING, t.u
        m, e, tau = t.run_trial(k, u)
        with _deferred_interrupts():  # kept from here: summary entry, recording and summary file together
            t.pending = (k, m, e)
            t.record(m, role)
            self.k = k + 1
            self.result.roles.append(role)
            if self.on_trial is not None:
                self.on_trial(m, role)
            t.log_recording(k, m, e)
            if self.out is not None:
                self._note_recording()
                write_summary(self.out, self.result.summary, folder=self.folder, trial=k)
        data = t.trial_data(k, role, u, e, tau)
        outcome = TrialOutcome(k, role, m, u, e, tau, list(t.last_traces), plan.gains)
        if k + 1 >= n_planned:
            return outcome
        if role == AUXILIARY:
            assert aux_step is not None
            t.step_aux.append(data)
            if len(t.step_aux) == law.auxiliary_trials:
                full = dataclasses.replace(aux_step, auxiliary=tuple(t.step_aux))
                t.step_trial, t.step_aux = None, []
                t.u = t.checked_table(lambda: law.learn(full), k + 1)
        elif law.auxiliary_trials and n_planned - (k + 1) >= law.auxiliary_trials + 1:
            t.step_trial, t.step_aux = data, []
        else:
            t.u = t.checked_table(lambda: law.learn(data), k + 1)
        return outcome

    def set_gains(self, plan: Plan) -> None:
        """Continue with ``plan`` (the same experiment with other gains and the law built again for
        them, :func:`host.experiment.plan.plan_with_gains`): the drives get its feedback gains
        before the next trial; the next learning trial keeps the current feed-forward.

        :raises RuntimeError: during an auxiliary step (the law's rollouts belong together).
        """
        if self.trials.step_trial is not None:
            raise RuntimeError("the gains cannot change between a learning trial and its auxiliary trials")
        self.trials.plan = plan
        self.result.summary.setdefault("gain_changes", []).append({"before_trial": self.k, "gains": plan.gains.as_dict()})
        if self.started and not self.finished:
            for j, drive in enumerate(self.bench.drives):
                drive.configure(
                    kp_nm_per_rad=float(plan.gains.kp[j]),
                    kd_nms_per_rad=float(plan.gains.kd[j]),
                    torque_limit_nm=plan.torque_limit_nm,
                )

    def _note_recording(self) -> None:
        """``summary["recording"]``: what the recording holds durably now (if it says)."""
        committed = getattr(self.recorder, "committed", None)
        state = committed() if committed is not None else None
        if state is not None:
            self.result.summary["recording"] = state

    def _guarded(self, fn: Callable[[], Any]) -> Any:
        """``fn()``; a fault or an interrupt ends the run through the fault path (None)."""
        result, summary, bench = self.result, self.result.summary, self.bench
        try:
            return fn()
        except IlcrigError as exc:
            # a fault, a drive that stopped answering between trials (SDO timeout/abort while
            # downloading a table or uploading the recorder), a failing write: torque is removed by
            # closing the bench, the trials so far are kept
            done = len(summary["iterations"])
            record = _fault_record(bench, exc, done, self.out, self.plan.cfg.iterations, self.trials.in_trial)
            result.fault_record = record
            result.fault = record.message
            summary["faults"].append(record.as_dict())
            if record.position == Position.AFTER_LAST_TRIAL:
                summary["completed"] = True  # every trial was run and kept; the fault came after
            logger.info("fault (%s, trial %s): %s", record.position, record.trial, exc)  # the run's closing line says it
        except KeyboardInterrupt as exc:  # Ctrl-C, or Interrupted from the SIGTERM/SIGINT handler
            signum = getattr(exc, "signum", signal.SIGINT)
            result.interrupted = int(signum)
            summary["interrupted"] = self._where_now(signal.Signals(signum).name)
            if summary["interrupted"]["position"] == Position.AFTER_LAST_TRIAL:
                summary["completed"] = True  # every trial was run and kept
            logger.info("interrupted by %s (%s)", signal.Signals(signum).name, summary["interrupted"]["position"])
        self.finish()
        return None

    def _where_now(self, signal_name: str) -> dict[str, Any]:
        """The summary's ``interrupted`` marker: signal, position, trial and tick now."""
        done = len(self.result.summary["iterations"])
        position, trial = position_of(done, self.plan.cfg.iterations, self.trials.in_trial)
        progress = getattr(self.bench, "progress", None)
        tick = progress() if progress is not None and position == Position.IN_TRIAL else None
        return {"signal": signal_name, "position": str(position), "trial": trial, "tick": tick}

    def finish(self) -> ExperimentResult:
        """Close the bench (safe state), finish the recording, write the final summary (idempotent)."""
        if self.finished:
            return self.result
        self.finished = True
        _SHIELD.active, _SHIELD.pending = True, _SHIELD.deferred
        _SHIELD.deferred = None
        try:
            _finish(self.bench, self.result.summary, self.recorder, self.out, self.folder, self.result, self.trials)
        finally:
            _SHIELD.active = False
            if _SHIELD.pending is not None and self.result.interrupted is None and not self.result.summary.get("completed"):
                self.result.interrupted = _SHIELD.pending
        return self.result


def _fault_record(
    bench: Bench, exc: IlcrigError, kept: int, out_dir: Path | None = None, planned: int | None = None, in_trial: bool = False
) -> FaultRecord:
    """The :class:`FaultRecord` of ``exc`` (the bench's own description when it has one), placed
    in the run: ``kept`` trials in the summary of ``planned``, a trial running or not."""
    record = exc.record if isinstance(exc, TrialFault) else None
    describe = getattr(bench, "describe_fault", None)
    if record is None and describe is not None:
        record = describe(exc, kept)
    if record is None:
        sdo = isinstance(exc, SdoAbort | SdoTransportError) or "Sdo" in type(exc).__name__
        message = str(exc) if isinstance(exc, TrialFault | OutputError) or sdo else f"{type(exc).__name__}: {exc}"
        node_id = getattr(exc, "node_id", None)
        waited = getattr(exc, "elapsed_s", None) if not getattr(exc, "cancelled", False) else None
        if isinstance(exc, OutputError):
            kind = str(exc.kind)
        elif sdo:
            kind = FaultKind.SDO_ERROR
        else:
            kind = FaultKind.TRIAL_FAULT
        record = FaultRecord(
            kind=kind,
            message=message,
            node=node_name(node_id) if isinstance(node_id, int) else "host",
            node_id=node_id if isinstance(node_id, int) else None,
            t_detected_mono=time.monotonic(),
            t_detected_wall=time.time(),
            latency_ms=1000.0 * waited if isinstance(waited, float) else 0.0,
            latency_basis="the SDO request (no answer)" if isinstance(waited, float) else "same process",
        )
    if record.injected is None and out_dir is not None:
        attach_injection(record, read_injections(out_dir))
    place(record, bench, kept, planned if planned is not None else kept + 1, in_trial)
    return record


def place(record: FaultRecord, bench: Any, kept: int, planned: int, in_trial: bool) -> FaultRecord:
    """Put ``record`` where the run was: its position and trial from the trials kept (of
    ``planned``) and whether a trial ran; in a trial its tick (the record's, else the bench's
    ``progress()``, else 0: no tick of it was seen yet), outside one none. Returns ``record``."""
    position, trial = position_of(kept, planned, in_trial)
    record.position = str(position)
    record.trial = trial
    if position == Position.IN_TRIAL:
        if record.tick is None:
            progress = getattr(bench, "progress", None)
            record.tick = progress() if progress is not None else None
        if record.tick is None:
            record.tick = 0  # the trial had begun, its first tick was not seen yet
    else:
        record.tick = None
    return record


def _check_tpdos_against_recorder(k: int, actuals: CyclicActuals, traces: Sequence[Any], rated_mnm: Sequence[int]) -> None:
    """The TPDO of tick n must carry the recorder's sample n (position, torque in ‰, rounded as
    the drive's 0x6077 rounds: half up): anything else is a fault of the data path."""
    for j, tr in enumerate(traces):
        r = int(rated_mnm[j])
        expected_permille = np.clip((2 * tr.torque_units.astype(np.int64) + r) // (2 * r), -(1 << 15), (1 << 15) - 1)
        if not np.array_equal(actuals.position_counts[:, j], tr.position_counts) or not np.array_equal(
            actuals.torque_permille[:, j], expected_permille
        ):
            raise TrialFault(f"trial {k}: drive {j + 1}'s TPDOs differ from its recorder")


def run_experiment(
    plan: Plan,
    bench: Bench,
    out_dir: str | Path | None,
    *,
    mode: str,
    on_trial: Callable[[TrialMetrics, str], None] | None = None,
    keep_traces: bool = False,
    recorder: TrialRecorder | None = None,
    folder: RunFolder | None = None,
) -> ExperimentResult:
    """Run ``plan.cfg.iterations`` trials on ``bench``; write ``summary.json`` before the first
    and after each.

    A fault (:class:`TrialFault`, a node that stopped answering, a failing write of the outputs)
    or an interrupt ends the run (module docstring): torque is removed by closing the bench, the
    completed trials are kept, the fault is in ``summary["faults"]`` / ``result.fault_record``, an
    interrupt in ``summary["interrupted"]`` / ``result.interrupted``.

    :param folder: the run folder's space reserve (given back on a full disk before the final write)
    :param on_trial: called after each trial with its metrics and its role (``learning`` / ``auxiliary``)
    """
    runner = TrialRunner(
        plan, bench, out_dir, mode=mode, on_trial=on_trial, keep_traces=keep_traces, recorder=recorder, folder=folder
    )
    while runner.step() is not None:
        pass
    return runner.finish()


def _finish(
    bench: Bench,
    summary: dict[str, Any],
    recorder: TrialRecorder | None,
    out: Path | None,
    folder: RunFolder | None,
    result: ExperimentResult,
    trials: _Trials,
) -> None:
    """The end of every run: bench info, close (safe state), recording, the final summary."""
    try:
        summary["bench"] = jsonable(bench.info())
    except Exception:  # noqa: BLE001 - the summary must still be written
        logger.warning("bench info unavailable", exc_info=True)
    try:
        bench.close()
    finally:
        safe_state = getattr(bench, "safe_state", None)
        if safe_state is not None:
            summary["safe_state"] = jsonable(safe_state())
        _closing_fault(bench, summary, result, trials)
        if folder is not None:
            folder.release()  # the final outputs go into the reserve's room
        if recorder is not None:
            trials.record_pending()
            recorder.close()
            committed = getattr(recorder, "committed", None)
            state = committed() if committed is not None else None
            if state is not None:
                summary["recording"] = state
        _final_write(out, summary, folder, result)


def _closing_fault(bench: Bench, summary: dict[str, Any], result: ExperimentResult, trials: _Trials) -> None:
    """A fault the bench saw after the trial loop's last step (``closing_fault()``), when the run
    has no fault or interrupt yet: recorded and placed (after the last trial, for a run that
    completed)."""
    closing = getattr(bench, "closing_fault", None)
    record = closing() if closing is not None else None
    if record is None or result.fault_record is not None or result.interrupted is not None:
        return
    place(record, bench, len(summary["iterations"]), trials.plan.cfg.iterations, trials.in_trial)
    result.fault_record = record
    result.fault = record.message
    summary["faults"].append(record.as_dict())
    logger.info("fault while the run ended (%s): %s", record.position, record.message)


def _final_write(out: Path | None, summary: dict[str, Any], folder: RunFolder | None, result: ExperimentResult) -> None:
    """The last summary write, after giving back the run folder's space reserve (room for it on
    a full disk). A failure here is logged and recorded in the result (the previous summary stays
    valid)."""
    if folder is not None:
        folder.release()
    if out is None:
        return
    try:
        write_summary(out, summary, folder=folder)
    except OutputError as exc:
        logger.error("the final summary could not be written (the last one written stays): %s", exc)
        record_output_fault(result, exc)


def record_output_fault(result: ExperimentResult, exc: OutputError) -> FaultRecord | None:
    """A failing write of the run's final outputs (the final summary, ``report.md``) as the run's
    fault, when it has none yet (placed after what was kept: after the last trial for a completed
    run); returns the record (None: the run had a fault or an interrupt already)."""
    summary = result.summary
    if result.fault_record is not None or result.interrupted is not None:
        return None
    planned = int(summary.get("config", {}).get("iterations", len(summary["iterations"])))
    record = FaultRecord(
        kind=exc.kind,
        message=str(exc),
        node="host",
        detected_by="host",
        t_detected_mono=time.monotonic(),
        t_detected_wall=time.time(),
        latency_ms=0.0,
        latency_basis="failed write",
    )
    place(record, None, len(summary["iterations"]), planned, False)
    result.fault_record = record
    result.fault = record.message
    summary["faults"].append(record.as_dict())
    return record
