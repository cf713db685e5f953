"""How an ``ilcrig run`` ends once the host has: its exit code, the summary's fault record and
evidence, the run folder as the summary says, and the one terminal line.

This module owns :class:`RunOutcome`, the launcher's exit paths:

* the host completed the run: exit 0 — unless a process of the run ended while the host was still
  finishing (after the last trial): then that is the run's fault, placed ``after_last_trial``, exit
  3 (``completed`` stays true: every trial was run and kept);
* the host completed the run but the launcher's heartbeat consumer (:mod:`host.rig.liveness`)
  found a node silent longer than its consumer time: before the host ended, the run's fault
  (exit 3); after, a ``liveness_incidents`` entry with an ``ilcrig: note:`` line (exit 0);
* the host refused the experiment: its ``ilcrig: error:`` line, exit 2;
* a fault: the record in ``summary.json`` — the host's own, or, when the host itself died or
  was stopped, a ``process_died`` record naming the process that ended, placed where the run was
  (the trials the summary kept, the trial and tick the io channel showed when the launcher noticed
  the end: :class:`host.rig.processes.Death`) with the latency of the launcher's notice — completed
  with what only the launcher knows (which process ended, the drives' ``SAFE-STATE`` records from
  their logs, :mod:`bus.safe_state`, after letting stalled processes resume and live drives
  react); ``report.md`` rewritten; the one line ``ilcrig: fault: <what>: <node>, trial k, tick n;
  …; its log: …``; exit 3;
* an interrupt: the summary marked ``interrupted`` by the launcher if the host did not mark it.

A summary always: when the host ended (or was stopped) before it wrote ``summary.json`` — killed
while it started up, the hub gone during bring-up, the bus never opened — the launcher writes the
one the host could not (:meth:`RunOutcome.launcher_summary`: the configuration, 0 trials kept, the
fault with kind, node and when; ``written_by: launcher``), atomically like every summary
(:func:`host.experiment.summary.write_summary`, :mod:`bus.atomic`), and ``report.md`` with it.

Records true: when the hub ended while the host ran, the bus was gone for every node: a record the
host made of what followed (an SDO request unanswered, nodes silent) is the hub's (``bus_lost``,
node ``hub``, the host's detection kept as ``host_saw``). Every record leaves with both detection
times (``t_detected_wall`` from ``t_detected_mono`` when only that one is known: one machine).

On every path the drives' safe state that the host could not show (``torque`` not ``off``) is
taken from their logs, and the run folder is made to hold what the summary says
(:meth:`RunOutcome.settle_folder`, :func:`host.rig.janitor.settle_run_folder`): ``recording.rrd``
cut back to the summary's trials, temporary files and trial arrays the summary does not hold
removed — the host may have died anywhere.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus.cia301.nmt import CONSUMER_TIME_MS
from bus.exit_codes import EXIT_FAULT, EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED, EXIT_USAGE
from bus.safe_state import last_state_in_log
from bus.units import timeout_scale
from host.experiment.fault_placement import place
from host.experiment.faults import (
    FaultKind,
    FaultRecord,
    Position,
    attach_injection,
    fault_line,
    position_of,
    read_injections,
)
from host.experiment.outputs import SUMMARY_NAME, read_summary
from host.rig.fault_classify import with_wall_time
from host.rig.processes import Child, Death, describe_status, node_id_of, tail
from host.rig.role_logs import log_started, safe_state_lines

logger = logging.getLogger(__name__)

__all__ = ["RunOutcome"]


@dataclass(eq=False)
class RunOutcome:
    """The end of one run (see the module docstring).

    :ivar out_dir: the run folder
    :ivar children: the role processes
    :ivar say_err: writes one line to the launcher's stderr
    :ivar resume_all: resumes every process an injection stalled (before the drives' evidence is read)
    :ivar config: the run's configuration (``config`` of a summary), for the summary the launcher
        writes when the host left none (called only then)
    """

    out_dir: Path
    children: Sequence[Child]
    say_err: Callable[[str], None]
    resume_all: Callable[[], None] | None = None
    config: Callable[[], dict[str, Any]] | None = None
    #: the run's ``--inject`` specs (:class:`bus.transports.fault_inject.FaultSpec`): each accounted for in the summary
    specs: Sequence[Any] = ()
    #: what the launcher's heartbeat consumer found (:class:`host.rig.liveness.Silence`), and when the host ended
    silences: Sequence[Any] = field(default=(), init=False)
    host_ended_mono: float = field(default=float("inf"), init=False)

    # -- the summary ----------------------------------------------------------------------
    def load_summary(self) -> dict[str, Any] | None:
        """The run's ``summary.json`` as the host left it (None: none, or unreadable)."""
        return read_summary(self.out_dir)

    def kept_now(self) -> int:
        """The trials the run's summary holds now (0: none yet)."""
        summary = self.load_summary()
        return len(summary["iterations"]) if summary is not None else 0

    def launcher_summary(self) -> dict[str, Any]:
        """The summary the host could not write (it ended before its first one): the run's
        configuration, no trials, no faults yet, ``completed`` false, ``written_by: launcher``."""
        from host.experiment.summary import SCHEMA

        config: dict[str, Any] = {}
        if self.config is not None:
            try:
                config = self.config()
            except Exception:  # noqa: BLE001 - checked in preflight; the fault must still be recorded
                logger.warning("the run's configuration is not in the launcher's summary", exc_info=True)
        return {
            "schema": SCHEMA,
            "mode": "rig",
            "config": config,
            "iterations": [],
            "ticks": 0,
            "faults": [],
            "completed": False,
            "written_by": "launcher",
        }

    def ensure_summary(self, code: int, launch_error: BaseException | None = None) -> bool:
        """A summary on every exit code: when the run ends and none was written — a process could
        not be started (exit 4, ``launch_error``), an interrupt before the host started, the
        launcher itself failed — the launcher's own (:meth:`launcher_summary`) with the fault (kind
        ``process_died`` of the process that could not start, before the first trial) or the
        ``interrupted`` marker, the injections accounted for, and ``report.md``. Returns whether it
        wrote one."""
        if (self.out_dir / SUMMARY_NAME).exists() or code in (EXIT_OK, EXIT_USAGE):
            return False
        summary = self.launcher_summary()
        now_mono, now_wall = time.monotonic(), time.time()
        planned = int(summary.get("config", {}).get("iterations", 1) or 1)
        if code in (EXIT_INTERRUPTED, EXIT_TERMINATED) or code > 128:
            position, trial = position_of(0, planned, False)
            signame = _signal_name(code - 128)
            summary["interrupted"] = {
                "signal": signame,
                "position": str(position),
                "trial": trial,
                "tick": None,
                "by": "launcher",
            }
            summary["end_reason"] = "interrupted"
        else:
            name = getattr(launch_error, "name", None) or "launcher"
            what = str(launch_error) if launch_error is not None else f"the launcher ended with exit code {code}"
            record = FaultRecord(
                FaultKind.PROCESS_DIED,
                what,
                node=name,
                node_id=node_id_of(name),
                detected_by="launcher",
                t_detected_mono=now_mono,
                t_detected_wall=now_wall,
                latency_ms=0.0,
                latency_basis="the start failed" if launch_error is not None else "same process",
            )
            place(record, None, 0, planned, False)
            summary["faults"] = [record.as_dict()]
            summary["end_reason"] = "fault"
        summary["exit_code"] = code
        self._complete_evidence(summary, now_mono)
        self.account(summary, ended_early=True)
        self.save(summary, report=True)
        return True

    def save(self, summary: dict[str, Any], report: bool = False) -> None:
        """Rewrite ``summary.json`` (and with ``report`` ``report.md``); failures are logged."""
        from host.experiment.summary import OutputError, write_summary

        try:
            write_summary(self.out_dir, summary)
        except OutputError as err:
            logger.error("cannot update the summary: %s", err)
            return
        if report:
            try:
                from host.analysis.run_report import write_run_report

                write_run_report(self.out_dir, summary)
            except Exception:  # noqa: BLE001 - the report must not hide the fault line
                logger.info("report.md not written", exc_info=True)

    def account(self, summary: dict[str, Any], *, ended_early: bool) -> list[dict[str, Any]]:
        """``summary["injections"]``: what each ``--inject`` spec did (:mod:`host.rig.injection_account`:
        a fault, tolerated, not injected); nothing without specs. Returns the entries."""
        if not self.specs:
            return []
        from host.rig.injection_account import account_injections

        planned = int(summary.get("config", {}).get("iterations", len(summary.get("iterations", []))) or 1)
        faults = summary.get("faults") or []
        entries = account_injections(self.specs, read_injections(self.out_dir), faults, planned=planned, ended_early=ended_early)
        summary["injections"] = entries
        return entries

    def settle_folder(self) -> None:
        """The run folder as its summary says (the host has ended): the recording cut back to its
        trials, leftovers removed (:func:`host.rig.janitor.settle_run_folder`). Never raises."""
        from host.rig.janitor import settle_run_folder

        for line in settle_run_folder(self.out_dir):
            logger.info("%s", line)

    def mark_interrupted(self, signal_name: str, where: Any = None) -> bool:
        """A run interrupted by ``signal_name``: the summary says so as the exit code will (if the
        host did not; placed with the io channel's position ``where``; after the last trial for a
        run that completed with a fault), the drives' safe state completed from their logs, the
        folder settled.  Returns False when the host had completed the run cleanly (every trial
        kept, no fault) before the signal: its records stay as they are, and so does its exit code
        (as a signal once a run's end began, :mod:`host.experiment.signal_shield`)."""
        summary = self.load_summary() or self.launcher_summary()
        if summary is not None and summary.get("completed") and not summary.get("faults") and not summary.get("interrupted"):
            self.settle_folder()
            return False
        if summary is not None:
            marked = not summary.get("interrupted")
            if marked:
                kept = len(summary["iterations"])
                planned = int(summary.get("config", {}).get("iterations", kept + 1))
                in_trial = where is not None and where.trial >= kept and kept < planned
                position, trial = position_of(kept, planned, in_trial)
                tick = (where.tick or 0) if in_trial else None
                summary["interrupted"] = {
                    "signal": signal_name,
                    "position": str(position),
                    "trial": trial,
                    "tick": tick,
                    "by": "launcher",
                }
                summary["end_reason"] = "interrupted"
            self._complete_evidence(summary, time.monotonic())
            self.account(summary, ended_early=True)
            self.save(summary, report=marked)  # report.md says how the run ended, as the summary does
        self.settle_folder()
        return True

    # -- the exit paths -------------------------------------------------------------------
    def conclude(
        self, host: Child, code: int, deaths: Sequence[Death], host_stopped: bool, host_death: Death | None = None
    ) -> int:
        """The run's exit code after the host ended with ``code``; ``deaths``: the processes that
        ended while it ran; ``host_stopped``: the launcher stopped it; ``host_death``: the host's
        end as the launcher noticed it."""
        if code != 0 and not host_stopped and code not in (EXIT_USAGE, EXIT_FAULT):
            host_death = host_death or Death("host", host.pid, describe_status(code), time.monotonic(), host.log_path, code)
        else:
            host_death = None
        if code == EXIT_USAGE:
            line = next((ln for ln in reversed(tail(host.log_path, 40)) if ln.startswith("ilcrig: error:")), None)
            self.say_err(line or f"ilcrig: error: the host refused the experiment; its log: {host.log_path}")
            return EXIT_USAGE
        summary = self.load_summary()
        if code == EXIT_OK and not deaths and summary is not None and self.silences:
            end = self._silences(summary, host)
            if end is not None:
                return end
        if code == EXIT_OK and not deaths:
            if summary is not None:
                changed = self._complete_evidence(summary, time.monotonic())
                entries = self.account(summary, ended_early=False)
                if changed or entries:
                    self.save(summary)
                from host.rig.injection_account import note_lines

                for line in note_lines(entries, str(self.out_dir / SUMMARY_NAME)):
                    self.say_err(line)
                for stall in summary.get("bench", {}).get("heartbeat", {}).get("host_stalls", []):
                    self.say_err(f"ilcrig: note: {stall['what']}; recorded in {self.out_dir / SUMMARY_NAME}")
            self.settle_folder()
            return EXIT_OK
        kept = len(summary["iterations"]) if summary is not None else 0
        first = deaths[0] if deaths else host_death
        if summary is None:
            summary = self.launcher_summary()  # the host ended before its first summary: a summary always
        if not summary.get("faults") and code == EXIT_FAULT and not deaths:
            # the host ended with a fault it did not put in a summary (e.g. it could not open the bus)
            summary["faults"].append(self._host_line_record(host).as_dict())
        record = self._record(summary, kept, host, code, first)
        if record.kind != FaultKind.PROCESS_DIED or record.node != "hub":
            record = hub_first(record, deaths)
        not_before_injection(record, summary.get("config", {}).get("n_ticks"))
        summary["completed"] = record.position == Position.AFTER_LAST_TRIAL  # every trial kept
        summary["faults"][0] = with_wall_time(record).as_dict()
        for i, entry in enumerate(summary["faults"][1:], 1):
            summary["faults"][i] = with_wall_time(FaultRecord.from_dict(entry)).as_dict()
        since = first.t_mono if first is not None else (record.t_detected_mono or time.monotonic())
        if record.injected and record.injected.get("t_mono") is not None:
            since = float(record.injected["t_mono"])
        self._complete_evidence(summary, since)
        self.account(summary, ended_early=True)
        self.save(summary, report=True)
        self.settle_folder()
        summary_path = self.out_dir / SUMMARY_NAME
        where = self._where(record, first, host)
        if summary.get("law_error_log") and first is None:  # the law failed: its own traceback, not the host's log
            where = f"the law's traceback: {self.out_dir / summary['law_error_log']}"
        self.say_err(fault_line(record, kept, summary_path=summary_path, extra=where))
        return EXIT_FAULT

    def _silences(self, summary: dict[str, Any], host: Child) -> int | None:
        """A completed run whose nodes the launcher's heartbeat consumer found silent
        (:mod:`host.rig.liveness`): a silence before the host ended is the run's fault (exit 3,
        ``completed`` as the host left it); after it, an incident in the summary with its line.
        None: the run ends as the host said (exit 0)."""
        from host.rig.liveness import judge_silences

        planned = int(summary.get("config", {}).get("iterations", len(summary["iterations"])))
        faults, incidents = judge_silences(list(self.silences), planned, self.host_ended_mono, read_injections(self.out_dir))
        if incidents:
            summary["liveness_incidents"] = incidents
            for inc in incidents:
                self.say_err(f"ilcrig: note: {inc['what']}; recorded in {self.out_dir / SUMMARY_NAME}")
        if not faults:
            self.save(summary)
            return None
        record = faults[0]
        summary["faults"] = [r.as_dict() for r in faults]
        self._complete_evidence(summary, record.t_detected_mono or time.monotonic())
        self.account(summary, ended_early=True)
        self.save(summary, report=True)
        self.settle_folder()
        kept = len(summary["iterations"])
        self.say_err(fault_line(record, kept, summary_path=self.out_dir / SUMMARY_NAME, extra=self._where(record, None, host)))
        return EXIT_FAULT

    def _host_line_record(self, host: Child) -> FaultRecord:
        """The fault the host ended with but did not record (its last ``ilcrig:`` line): before
        the first trial, detected by the host."""
        line = next((ln for ln in reversed(tail(host.log_path, 40)) if ln.startswith("ilcrig: ")), None)
        what = (line or f"the host ended the run with exit code {EXIT_FAULT}").split(": ", 2)[-1]
        bus = "cannot open the bus" in what
        now = time.monotonic()
        record = FaultRecord(
            FaultKind.BUS_LOST if bus else FaultKind.TRIAL_FAULT,
            what,
            node="hub" if bus and any(c.name == "hub" for c in self.children) else "host",
            detected_by="host",
            t_detected_mono=now,
            t_detected_wall=time.time(),
            extra={"host_log": str(host.log_path)},
        )
        place(record, None, 0, 1, False)
        return record

    def _record(self, summary: dict[str, Any] | None, kept: int, host: Child, code: int, first: Death | None) -> FaultRecord:
        """The run's fault: the host's first record, else a ``process_died`` one (added to the
        summary, placed where the run was when the launcher noticed the end); with the process
        that ended first attached."""
        if summary is not None and summary.get("faults"):
            record = FaultRecord.from_dict(summary["faults"][0])
        else:
            culprit = first or Death("host", host.pid, describe_status(code), time.monotonic(), host.log_path, code)
            record = FaultRecord(
                FaultKind.PROCESS_DIED,
                f"{culprit.name} (pid {culprit.pid}) {culprit.status}",
                node=culprit.name,
                node_id=node_id_of(culprit.name),
                detected_by="launcher",
                t_detected_mono=culprit.t_mono,
                latency_ms=1000.0 * culprit.latency_s if culprit.latency_s is not None else None,
                latency_basis="the process's end (the launcher's wait on it)",
            )
            planned = int(summary.get("config", {}).get("iterations", kept + 1)) if summary is not None else kept + 1
            where = culprit.where
            in_trial = where is not None and where.trial >= kept and kept < planned
            attach_injection(record, read_injections(self.out_dir))
            if in_trial and where is not None:
                injected = record.injected or {}
                record.tick = where.tick if where.tick is not None else injected.get("tick")
                n_ticks = summary.get("config", {}).get("n_ticks") if summary is not None else None
                if isinstance(record.tick, int) and isinstance(n_ticks, int):
                    record.tick = min(record.tick, n_ticks - 1)  # tick N on the io channel: the state after the last
            place(record, None, kept, planned, in_trial)
            if summary is not None:
                summary["faults"].append(record.as_dict())
        if first is not None:
            record.extra["process_ended"] = {
                "name": first.name,
                "pid": first.pid,
                "status": first.status,
                "log": str(first.log_path) if first.log_path else None,
            }
        return record

    def _where(self, record: FaultRecord, first: Death | None, host: Child) -> str:
        """The fault line's pointer: the log of the process concerned, or the one that ended."""
        concerned = next((c for c in self.children if c.name == record.node), None)
        if first is not None and record.kind == FaultKind.PROCESS_DIED and record.node == first.name:
            return f"its log: {first.log_path}"
        if first is not None:
            return first.describe()
        if concerned is not None and concerned.log_path is not None:
            return f"its log: {concerned.log_path}"
        if record.node == "hub":
            return f"its log: {self.out_dir / 'logs' / 'hub.log'}"
        return f"the host's log: {host.log_path}"

    def _complete_evidence(self, summary: dict[str, Any], since: float) -> bool:
        """The summary's ``safe_state`` with every drive the host could not show torque-free
        completed from the drives' logs (:meth:`drive_evidence`). Returns whether it changed."""
        entries = summary.get("safe_state") or []
        drives = {e.get("node"): e for e in entries if str(e.get("node", "")).startswith("drive")}
        if len(drives) == sum(c.name.startswith("drive") for c in self.children) and all(
            e.get("torque") == "off" for e in drives.values()
        ):
            return False
        summary["safe_state"] = self.drive_evidence(entries, since)
        return True

    def drive_evidence(self, entries: list[dict[str, Any]], since: float) -> list[dict[str, Any]]:
        """Complete the drives' safe-state entries from their logs (SAFE-STATE records): stalled
        processes resume first, live drives get a consumer time to react to a lost host."""
        if self.resume_all is not None:
            self.resume_all()
        by_node = {e.get("node"): dict(e) for e in entries}
        drives = [c for c in self.children if c.name.startswith("drive")]
        deadline = time.monotonic() + CONSUMER_TIME_MS / 1000.0 * timeout_scale() + 0.5
        while True:
            missing = []
            for c in drives:
                entry = by_node.setdefault(c.name, {"node": c.name, "node_id": node_id_of(c.name), "torque": "unknown"})
                if entry.get("torque") == "off" and "its log" not in str(entry.get("evidence", "")):
                    continue  # the host saw it on the bus
                lines = safe_state_lines(c.log_path)
                rec, on_after = last_state_in_log(lines, c.name)
                if rec is None and not on_after and lines is not None and log_started(c.log_path):
                    entry.update(torque="off", evidence="its log: its torque never came on (no TORQUE-ON record)")
                elif rec is not None and not on_after:
                    entry.update(
                        torque="off",
                        cia402=rec.get("cia402"),
                        nmt=rec.get("nmt"),
                        evidence=f"its log: SAFE-STATE reason={rec.get('reason')}, tick {rec.get('tick')}"
                        + (f", {1000 * (float(rec['t_mono']) - since):+.0f} ms after the fault" if "t_mono" in rec else ""),
                    )
                elif c.proc.poll() is not None:
                    entry.update(torque="off", evidence=f"the process {describe_status(c.proc.returncode)}: no power stage left")
                else:
                    missing.append(c)
            if not missing or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        return [by_node[c.name] for c in drives if c.name in by_node] + [
            e for n, e in by_node.items() if not str(n).startswith("drive")
        ]


def not_before_injection(record: FaultRecord, n_ticks: Any = None) -> FaultRecord:
    """A fault in a trial is not placed before the injection that caused it: a detector that saw the
    io channel late (the host's monitor a round behind when the hub, and with it the frames in
    flight, was killed) leaves an earlier tick than the one the injector acted at; the record takes
    the injection's tick then; and never after the trial's last tick, ``n_ticks`` − 1. Returns ``record``."""
    inj = record.injected or {}
    tick = inj.get("tick")
    if record.position != Position.IN_TRIAL:
        return record
    if inj.get("trial") == record.trial and isinstance(tick, int) and (record.tick is None or record.tick < tick):
        record.tick = tick
    if isinstance(record.tick, int) and isinstance(n_ticks, int):
        record.tick = min(record.tick, n_ticks - 1)  # tick N on the io channel: the state after the last
    return record


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


#: the kinds of record a lost bus leaves with the host: what it saw after the hub had ended
HUB_CONSEQUENCES = frozenset(
    {
        FaultKind.SDO_ERROR,
        FaultKind.NODE_LOST,
        FaultKind.BUS_LOST,
        FaultKind.BUS_SILENT,
        FaultKind.FRAME_LOST,
        FaultKind.PROCESS_DIED,
        FaultKind.TRIAL_FAULT,
    }
)


def hub_first(record: FaultRecord, deaths: Sequence[Death]) -> FaultRecord:
    """``record`` as the hub's when the hub ended while the host ran and the record is of what a
    lost bus leaves (:data:`HUB_CONSEQUENCES`): kind ``bus_lost``, node ``hub``, the host's own
    words kept as ``host_saw``; its trial, tick, position and detection times unchanged."""
    hub = next((d for d in deaths if d.name == "hub"), None)
    if hub is None or record.kind not in HUB_CONSEQUENCES or record.node == "hub":
        return record
    record.extra["host_saw"] = {"kind": record.kind, "node": record.node, "message": record.message}
    record.kind, record.node, record.node_id = FaultKind.BUS_LOST, "hub", None
    record.message = f"the hub (pid {hub.pid}) {hub.status}: the bus is gone"
    return record
