"""One ILC experiment: plan, check, then trial after trial on a bench, learning in between.

This module owns the trial loop (:class:`TrialLoop`, :func:`run_experiment`) and the end of every
run (bench closed, recording finished, final summary).  Its parts: the bench protocol
(:mod:`host.experiment.bench`), the loop's state (:mod:`host.experiment.loop_state`), the fault
records' placement (:mod:`host.experiment.fault_placement`), the signals
(:mod:`host.experiment.signal_shield`), the TPDO cross-check (:mod:`host.experiment.tpdo_check`).
May import: ``bus``, ``numpy``, :mod:`host.experiment`, :mod:`host.learning`, :mod:`host.nodes`,
:mod:`host.planning`.

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

Trials: :class:`TrialLoop` runs one trial per step — a learning trial, or one of the auxiliary
rollouts a law asks for after a learning trial (:mod:`host.learning.protocol`: counted as trials
everywhere, marked ``"role": "auxiliary"`` in the summary) — and runs the law after a learning
trial (or after the last auxiliary trial of its step); :func:`run_experiment` steps it to the end.
Running a trial and updating the law are two guarded parts of a step: the trial is kept (summary,
recording, arrays) before the law runs, and a law that fails — or an interrupt during its update —
ends the run after that trial, which the step still returns (so the API's results hold it too).  A
law's failure is a fault with its full traceback in ``<out>/logs/law-error.log`` (and at DEBUG: the
terminal with ``--debug``).  On the rig the law's code runs watched
(:mod:`host.experiment.law_watch`): up to a time limit, past which the run ends with a fault of the
law; a host-lost fault after an update during which the host's threads did not run names the
law.  ``summary["end_reason"]`` says how the run ended (:class:`host.experiment.loop_state.EndReason`);
:meth:`TrialLoop.end_by_user` ends a run for an exception of the caller's own code (the API's ``with`` block),
and for a signal that comes between the guarded parts of a step (:func:`run_experiment`).

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

import dataclasses
import logging
import signal
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bus.atomic import atomic_write
from bus.errors import IlcrigError
from host.experiment.bench import Bench, TrialRecorder
from host.experiment.fault_placement import fault_record_of, place, record_output_fault
from host.experiment.faults import FaultKind, Position, position_of
from host.experiment.law_watch import LawWatch
from host.experiment.loop_state import EndReason, ExperimentResult, LoopState, TrialOutcome, end_reason, new_summary
from host.experiment.outputs import OutputError, RunFolder
from host.experiment.plan import Plan
from host.experiment.signal_shield import SHIELD, deferred_interrupts, end_of_run, signum_of
from host.experiment.summary import jsonable, write_summary
from host.learning.laws.checked import LawError
from host.learning.metrics import TrialMetrics
from host.learning.protocol import AUXILIARY, LEARNING, TrialData

logger = logging.getLogger(__name__)

__all__ = ["LAW_ERROR_LOG", "TrialLoop", "run_experiment"]

#: the run's log of a failed law (its full traceback), in ``<out>/logs/``
LAW_ERROR_LOG = "law-error.log"


class TrialLoop:
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
        self.trials = LoopState(plan, bench, self.result, keep_traces, recorder)
        self.result.summary.update(new_summary(plan, mode, self.trials.digest))
        if mode == "rig":  # the law's code watched: a time limit, the host kept alive meanwhile
            self.trials.law_watch = LawWatch(plan.law.name, hold=getattr(bench, "hold_heartbeat", None))
        self.k = 0
        self.started = False
        self.finished = False
        #: the last kept trial as the law receives it, and the learning trial of its auxiliary step
        self._data: TrialData | None = None
        self._aux_step: TrialData | None = None

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
        outcome: TrialOutcome | None = self._guarded(self._run_next_trial)
        if outcome is None:
            return None  # the run ended before this trial was kept (finished by the fault path)
        if self.k >= self.plan.cfg.iterations:
            self.result.summary["completed"] = True
            self.finish()
            return outcome
        # the trial is kept in every view before the law runs: a law that fails (or an interrupt
        # during its update) ends the run after this trial, which is still returned
        self._guarded(lambda: self._learn(outcome))
        return outcome

    def _run_next_trial(self) -> TrialOutcome:
        """The next trial run, measured and kept (summary entry, recording, summary file)."""
        t, plan, law = self.trials, self.plan, self.plan.law
        k = self.k
        aux_step = t.step_trial
        if aux_step is not None:
            role = AUXILIARY
            u = t.checked_table(lambda: law.auxiliary_input(aux_step, tuple(t.step_aux)), k)
        else:
            role, u = LEARNING, t.u
        m, e, tau = t.run_trial(k, u)
        with deferred_interrupts():  # kept from here: summary entry, recording and summary file together
            t.pending = (k, m, e)
            t.record(m, role)
            self.k = k + 1
            self.result.roles.append(role)
            t.log_recording(k, m, e)
            if self.out is not None:
                self._note_recording()
                write_summary(self.out, self.result.summary, folder=self.folder, trial=k)
            if self.on_trial is not None:  # shown once durable: a printed trial is never lost
                self.on_trial(m, role)
        self._data = t.trial_data(k, role, u, e, tau)
        self._aux_step = aux_step
        return TrialOutcome(k, role, m, u, e, tau, list(t.last_traces), plan.gains)

    def _learn(self, outcome: TrialOutcome) -> None:
        """After the kept trial ``outcome``: the law's update for the next learning trial (or the
        start or end of an auxiliary step)."""
        t, law, n_planned = self.trials, self.plan.law, self.plan.cfg.iterations
        k, role, data, aux_step = outcome.k, outcome.role, self._data, self._aux_step
        assert data is not None
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
            record = fault_record_of(bench, exc, done, self.out, self.plan.cfg.iterations, self.trials.in_trial)
            watch = self.trials.law_watch
            if record.kind == FaultKind.HOST_LOST and watch is not None:
                blamed = watch.blame(record.message)  # the law's update during which the host stood still, named
                if blamed != record.message:
                    record.message, result.end_reason = blamed, EndReason.LAW_ERROR
            result.fault_record = record
            result.fault = record.message
            summary["faults"].append(record.as_dict())
            if record.position == Position.AFTER_LAST_TRIAL:
                summary["completed"] = True  # every trial was run and kept; the fault came after
            logger.info("fault (%s, trial %s): %s", record.position, record.trial, exc)  # the run's closing line says it
            if isinstance(exc, LawError) or record.kind == FaultKind.LEARNING_DIVERGED:
                result.end_reason = EndReason.LAW_ERROR
                self._law_traceback(exc)
        except KeyboardInterrupt as exc:  # Ctrl-C, or Interrupted from the SIGTERM/SIGINT handler
            self._mark_interrupted(signum_of(exc))
        self.finish()
        return None

    def _law_traceback(self, exc: BaseException) -> None:
        """The law's own traceback (its exception is the ``__cause__`` of the :class:`LawError`):
        always in the run's log ``<out>/logs/law-error.log``, on the terminal at DEBUG (``--debug``)."""
        text = "".join(traceback.format_exception(exc))
        logger.debug("the learning law failed:\n%s", text.rstrip())
        if self.out is None:
            return
        path = self.out / "logs" / LAW_ERROR_LOG
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, text)
            self.result.summary["law_error_log"] = str(path.relative_to(self.out))
        except OSError as err:
            logger.warning("the law's traceback could not be written to %s: %s", path, err)

    def end_by_user(self, exc: BaseException) -> ExperimentResult:
        """End the run for an exception of the caller's own code (the API's ``with`` block): a
        :class:`KeyboardInterrupt` is an interrupt between trials, anything else ``user_exception``
        with its type and first line in the summary.  Every kept trial stays; then :meth:`finish`."""
        if not self.finished:
            summary = self.result.summary
            if isinstance(exc, KeyboardInterrupt):
                if self.result.interrupted is None:
                    self._mark_interrupted(signum_of(exc))
            elif self.result.end_reason is None:
                self.result.end_reason = EndReason.USER_EXCEPTION
                text = str(exc)
                summary["user_exception"] = {
                    "type": type(exc).__qualname__,
                    "message": text.splitlines()[0] if text else "",
                    "after_trial": len(summary["iterations"]) - 1 if summary["iterations"] else None,
                }
        return self.finish()

    def _mark_interrupted(self, signum: int) -> None:
        """The interrupt in the result and the summary's ``interrupted`` marker, placed now; after
        the last trial was kept the run is also ``completed`` (every trial was run and kept)."""
        summary, name = self.result.summary, signal.Signals(signum).name
        self.result.interrupted = int(signum)
        summary["interrupted"] = self._where_now(name)
        if summary["interrupted"]["position"] == Position.AFTER_LAST_TRIAL:
            summary["completed"] = True
        logger.info("interrupted by %s (%s)", name, summary["interrupted"]["position"])

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
        end_of_run()  # before ``finished``: a signal that lands ahead of it ends the run through here again
        self.finished = True
        held, SHIELD.deferred = SHIELD.deferred, None  # a signal held while outputs were written, then a fault
        if held is not None and self.result.interrupted is None and not self.result.summary.get("completed"):
            self._mark_interrupted(held)
        # a signal from here on is logged, not raised or recorded: the final summary and the exit
        # code stay those of the run as it ended
        _finish(self.bench, self.result.summary, self.recorder, self.out, self.folder, self.result, self.trials)
        return self.result


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
    interrupted: KeyboardInterrupt | None = None,
) -> ExperimentResult:
    """Run ``plan.cfg.iterations`` trials on ``bench``; write ``summary.json`` before the first
    and after each.

    A fault (:class:`TrialFault`, a node that stopped answering, a failing write of the outputs)
    or an interrupt ends the run (module docstring): torque is removed by closing the bench, the
    completed trials are kept, the fault is in ``summary["faults"]`` / ``result.fault_record``, an
    interrupt in ``summary["interrupted"]`` / ``result.interrupted``.

    :param folder: the run folder's space reserve (given back on a full disk before the final write)
    :param on_trial: called after each trial with its metrics and its role (``learning`` / ``auxiliary``)
    :param interrupted: a signal that came while the caller made the outputs: the run ends at
        once, marked as interrupted before its first trial, its summary written
    """
    runner = TrialLoop(
        plan, bench, out_dir, mode=mode, on_trial=on_trial, keep_traces=keep_traces, recorder=recorder, folder=folder
    )
    if interrupted is not None:
        return runner.end_by_user(interrupted)
    try:
        while runner.step() is not None:
            pass
    except KeyboardInterrupt as exc:
        # a signal between the guarded parts of a step (after a trial was kept, before the law's
        # update): the same end as inside them, the interrupt marked, every kept trial kept
        return runner.end_by_user(exc)
    return runner.finish()


def _finish(
    bench: Bench,
    summary: dict[str, Any],
    recorder: TrialRecorder | None,
    out: Path | None,
    folder: RunFolder | None,
    result: ExperimentResult,
    trials: LoopState,
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
        summary["end_reason"] = str(end_reason(result))
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


def _closing_fault(bench: Bench, summary: dict[str, Any], result: ExperimentResult, trials: LoopState) -> None:
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
