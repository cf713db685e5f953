"""The launcher's part of ``ilcrig run --inject``: kill or stall a role, spoof an EMCY, at a trial
and tick.

This module owns :class:`ProcessInjector`, a thread of the launcher that sends SIGKILL or SIGSTOP
(SIGCONT after the stall) to a role's process — the launcher owns the processes — or an EMCY frame
on the fieldbus as if the node had sent it, when the spec's moment comes:

* in a trial (``@T:N``): it joins the io channel as an ordinary (filtered) bus member and follows
  the plant's trials and ticks (:class:`bus.io_frames.TrialTickFollower`): tick N of trial T;
* after a trial (``@T:end``; ``@after``: the last trial): when the run's ``summary.json`` holds
  trial T (:class:`bus.transports.fault_inject.SummaryTrials`, the hub's frame faults look the
  same way; the thread looks every :data:`SUMMARY_POLL_S`);
* before the first trial (``@before``): when the host starts the nodes (its first NMT START on the
  fieldbus, which the thread joins with a filter for NMT).

Every injection is recorded (:func:`bus.transports.fault_inject.write_record`,
``logs/injections-launcher.jsonl``, with the trials the summary held then: ``kept``) so the host
and the launcher can measure how fast it was detected.  The frame faults are the hub's
(:mod:`bus.transports.fault_inject`), a full disk the host's.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import can

from bus import io_frames
from bus.cia301.emcy import emcy_cob_id, encode_emcy
from bus.cia301.nmt import NmtCommand
from bus.plant_objects import DEFAULT_PLANT_NODE_ID
from bus.transports.config import TransportConfig
from bus.transports.fault_inject import WHEN_BEFORE, WHEN_END, WHEN_TICK, FaultSpec, SummaryTrials, write_record

logger = logging.getLogger(__name__)

__all__ = ["SUMMARY_POLL_S", "ProcessInjector"]

#: how often the injector looks at the summary while an ``@T:end`` injection waits, s
SUMMARY_POLL_S = 0.002
#: the longest wait for an io frame while nothing else is due, s
IO_WAIT_S = 0.1


class ProcessInjector(threading.Thread):
    """Kill / stall / EMCY injections of one run (see the module docstring).

    :param specs: the injections (frame faults and ``diskfull`` are ignored here)
    :param transport: the run's transport (the injector opens its own io / fieldbus buses)
    :param pid_of: role name → pid (None if not running)
    :param log_path: the injection records' file
    :param iterations: the run's trials (``@after`` is after the last one)
    :param summary_path: the run's ``summary.json`` (``@T:end``)
    """

    def __init__(
        self,
        specs: Sequence[FaultSpec],
        transport: TransportConfig,
        pid_of: Callable[[str], int | None],
        log_path: Path | None,
        *,
        iterations: int = 1,
        summary_path: Path | None = None,
    ) -> None:
        super().__init__(name="injector", daemon=True)
        self.pending = [s.resolved(iterations) for s in specs if s.action in ("kill", "stall", "emcy")]
        self.summary_path = summary_path
        self._summary_trials = SummaryTrials(summary_path, poll_s=0.0)
        self.transport = transport
        self.pid_of = pid_of
        self.log_path = log_path
        self.follower = io_frames.TrialTickFollower()
        self.stalled: dict[int, threading.Timer] = {}
        self.records: list[dict[str, object]] = []
        self.error: str | None = None
        self._stop_event = threading.Event()
        self._lock = threading.Lock()
        self._io: can.BusABC | None = None
        self._fieldbus: can.BusABC | None = None

    def run(self) -> None:
        try:
            if any(s.when == WHEN_TICK for s in self.pending):
                self._io = self.transport.open("io")
                self._io.set_filters(
                    [
                        {"can_id": io_frames.CONTROL_COB_ID, "can_mask": 0x7FF},
                        {"can_id": io_frames.ENCODER_COB_BASE, "can_mask": 0x7FF},
                    ]
                )
            if any(s.action == "emcy" or s.when == WHEN_BEFORE for s in self.pending):
                self._fieldbus = self.transport.open("fieldbus")
                self._fieldbus.set_filters([{"can_id": 0x000, "can_mask": 0x7FF}])  # NMT only: its EMCY goes out anyway
            while self.pending and not self._stop_event.is_set():
                self._step()
        except (can.CanError, OSError, ValueError) as exc:
            if not self._stop_event.is_set():
                self.error = f"{type(exc).__name__}: {exc}"
                logger.info("injector stopped: %s", self.error)  # e.g. it killed the hub itself
        finally:
            for bus in (self._io, self._fieldbus):
                if bus is not None:
                    with contextlib.suppress(can.CanError, OSError):
                        bus.shutdown()

    def _step(self) -> None:
        """One look at what is due: the nodes started (NMT START), the summary's trials, io ticks."""
        soon = any(s.when != WHEN_TICK for s in self.pending)
        if self._fieldbus is not None and any(s.when == WHEN_BEFORE for s in self.pending):
            msg = self._fieldbus.recv(timeout=0.0)
            while msg is not None:
                if msg.arbitration_id == 0 and msg.data[:1] == bytes([NmtCommand.START]):
                    for spec in [s for s in self.pending if s.when == WHEN_BEFORE]:
                        self.pending.remove(spec)
                        self._inject(spec, None, kept=0)
                    break
                msg = self._fieldbus.recv(timeout=0.0)
        if any(s.when == WHEN_END for s in self.pending):
            kept = self._summary_trials()
            for spec in [s for s in self.pending if s.when == WHEN_END and kept > s.trial]:
                self.pending.remove(spec)
                self._inject(spec, None, kept=kept)
        if self._io is None:
            self._stop_event.wait(SUMMARY_POLL_S)
            return
        msg = self._io.recv(timeout=SUMMARY_POLL_S if soon else IO_WAIT_S)
        if msg is None:
            return
        tick = self.follower.on_frame(msg.arbitration_id, msg.data)
        if tick is None:
            return
        for spec in [s for s in self.pending if s.when == WHEN_TICK]:
            if self.follower.trial > spec.trial or (self.follower.trial == spec.trial and tick >= spec.tick):
                self.pending.remove(spec)
                self._inject(spec, tick, kept=self.follower.trial)

    def _inject(self, spec: FaultSpec, tick: int | None, *, kept: int) -> None:
        record: dict[str, object] = {
            "by": "launcher",
            "spec": spec.text,
            "kind": spec.action,
            "target": spec.target,
            "trial": self.follower.trial if spec.when == WHEN_TICK else kept,
            "tick": tick,
            "kept": kept,
            "when": spec.when,
        }
        if spec.action == "emcy":
            node_id = DEFAULT_PLANT_NODE_ID if spec.target == "plant" else int(spec.target.removeprefix("drive"))
            msg = can.Message(
                arbitration_id=emcy_cob_id(node_id), is_extended_id=False, data=encode_emcy(spec.emcy_code, 0x01, bytes(5))
            )
            self.records.append(write_record(self.log_path, record | {"code": spec.emcy_code}))
            if self._fieldbus is not None:
                self._fieldbus.send(msg)
            return
        pid = self.pid_of(spec.target)
        if pid is None:
            logger.warning("injection %s: %s is not running", spec.text, spec.target)
            return
        record["pid"] = pid
        if spec.action == "kill":
            self.records.append(write_record(self.log_path, record))
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        else:
            self.records.append(write_record(self.log_path, record | {"for_s": spec.stall_s}))
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGSTOP)
            timer = threading.Timer(spec.stall_s, self._resume, args=(pid,))
            timer.daemon = True
            with self._lock:
                self.stalled[pid] = timer
            timer.start()

    def _resume(self, pid: int) -> None:
        with self._lock:
            self.stalled.pop(pid, None)
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
        logger.info("injector: pid %d resumed", pid)

    def resume_all(self) -> list[int]:
        """SIGCONT every process still stalled now (the run is ending); returns their pids."""
        with self._lock:
            stalled, self.stalled = dict(self.stalled), {}
        for pid, timer in stalled.items():
            timer.cancel()
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        return list(stalled)

    def stop(self) -> None:
        """Stop watching (pending injections are dropped) and resume stalled processes."""
        self._stop_event.set()
        self.resume_all()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=2.0)

    def waiting(self) -> bool:
        """True while injections are still to come."""
        return bool(self.pending) and self.is_alive()
