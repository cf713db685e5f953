"""One trial of the rig, from the host: start it on the plant node, stream it (``--ff-transport
pdo``), wait for its end, and keep its timing.

This module owns :class:`TrialRunner`: per trial it sends TRIAL_START to the plant node (which
then leads the lockstep on the io channel), streams the SYNC/RPDO set-points through a
:class:`host.rig.pdo_stream.SyncProducer` when the trial has cyclic set-points, and waits for the
plant node to report the trial done.  A fault during the trial ends as one
:class:`host.experiment.bench.TrialFault` carrying the watchdog's record (or the record of the
exception, :meth:`host.rig.watchdog.Watchdog.describe`).  After each trial it keeps the plant
node's :class:`bus.plant_objects.TrialTiming`, the ticks that missed their deadline (only when
some did) and the CPU time the hypervisor took meanwhile (:func:`host.rig.realtime.steal_during`).

The trial's boundary
    A trial is kept once the channel monitors have processed every frame of it (a full disk that
    stopped a log inside the trial, a bus error frame in its last tick, belong to it).  The runner
    waits for explicit end-of-trial markers (:class:`TrialEndMarks`, the rig's
    :class:`host.rig.channels.RigChannels`): the io channel's TRIAL_STOP of this trial, and on the
    fieldbus a frame received after the host learnt that the trial ended (the plant's timing, read
    anyway, is that frame).  Per trial the host's time is split into set-up (the start command),
    the ticks (until the plant reports DONE) and the end (markers, the plant's timing):
    :attr:`TrialRunner.boundaries`, in the summary's ``timing.host``
    (:func:`host.rig.realtime.timing_summary`).
"""

from __future__ import annotations

import gc
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from bus.errors import SdoAbort
from bus.plant_objects import DeadlineMisses, TrialTiming
from host.experiment.bench import CyclicActuals, CyclicSetpoints, TrialFault
from host.nodes.plant_client import PlantClient, PlantClientError
from host.nodes.sdo_access import SdoTransportError
from host.rig.pdo_stream import SyncProducer
from host.rig.realtime import HostBoundary, MachineSteal, steal_during, timing_summary
from host.rig.watchdog import Watchdog

logger = logging.getLogger(__name__)

__all__ = ["TrialEndMarks", "TrialRunner"]


class TrialEndMarks(Protocol):
    """Who tells when every frame of a trial has been seen (:class:`host.rig.channels.RigChannels`)."""

    def next_trial(self) -> int:
        """The channel's index of the trial about to start."""
        ...

    def wait_trial_end(self, io_trial: int, end_stamp: float, timeout_s: float = 2.0) -> bool:
        """Wait for the markers of the end of trial ``io_trial`` (frames received from
        ``end_stamp``, ``time.time()`` scale, on); whether they came."""
        ...


@dataclass(eq=False)
class TrialRunner:
    """Runs the trials on the plant node (see the module docstring).

    :ivar plant: the plant node's client
    :ivar watchdog: marks the trial as running, and declares the faults
    :ivar streamer: the SYNC producer of cyclic trials (None: the drives play their tables)
    :ivar marks: the end-of-trial markers the runner waits for before a trial is kept (see the
        module docstring; None: none waited for)
    :ivar timings: per completed trial, the plant node's timing
    :ivar misses: per completed trial, its missed ticks (None: none missed, or not paced)
    :ivar steal: per completed trial, the CPU time the hypervisor took meanwhile (None: not counted)
    :ivar boundaries: per completed trial, the host's time of its set-up, ticks and end
    """

    plant: PlantClient
    watchdog: Watchdog
    streamer: SyncProducer | None = None
    marks: TrialEndMarks | None = None
    timings: list[TrialTiming] = field(default_factory=list, init=False)
    misses: list[DeadlineMisses | None] = field(default_factory=list, init=False)
    steal: list[MachineSteal | None] = field(default_factory=list, init=False)
    boundaries: list[HostBoundary] = field(default_factory=list, init=False)
    _gc_frozen: bool = field(default=False, init=False)

    def run(
        self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray, cyclic: CyclicSetpoints | None = None
    ) -> CyclicActuals | None:
        """Reset the plant to (q0, qd0) and run ``n_ticks`` lockstep ticks; with ``cyclic`` stream its
        set-points and return the TPDO actuals.

        :raises TrialFault: the trial did not complete (the fault's record attached)
        """
        watchdog = self.watchdog
        watchdog.trial = trial
        watchdog.raise_if_fault()
        self._freeze_gc()
        actuals = None
        io_trial = self.marks.next_trial() if self.marks is not None else 0
        t = [time.perf_counter()]

        def trial_body() -> None:
            nonlocal actuals
            self.plant.start_trial(trial, n_ticks, q0, qd0)
            t.append(time.perf_counter())
            if cyclic is not None:
                if self.streamer is None:
                    raise TrialFault(f"trial {trial}: cyclic set-points, but the drives' PDOs are not configured")
                actuals = self.streamer.stream(trial, n_ticks, cyclic)
            # generous: lockstep over a loaded 2-core machine; faults come back much sooner
            self.plant.wait_trial(timeout_s=60.0 + n_ticks * 0.01, poll_s=0.02)
            t.append(time.perf_counter())

        with watchdog.during_trial(trial):
            try:
                steal = steal_during(trial_body)
            except (PlantClientError, SdoAbort, SdoTransportError) as exc:
                watchdog.settle_and_check()
                record = watchdog.describe(exc, trial)
                raise TrialFault(record.message if record else f"trial {trial}: {exc}", record) from exc
        end_stamp = time.time()
        watchdog.raise_if_fault()
        try:  # one request the host makes anyway: on the fieldbus, frames after the trial's end
            timing = self.plant.trial_timing()
        except (PlantClientError, SdoAbort, SdoTransportError) as exc:
            watchdog.settle_and_check()
            record = watchdog.describe(exc, trial)
            raise TrialFault(record.message if record else f"trial {trial}: {exc}", record) from exc
        if self.marks is not None:  # what the monitors noted at a tick of this trial belongs to it
            self.marks.wait_trial_end(io_trial, end_stamp)
        watchdog.watch_round()
        watchdog.raise_if_fault()
        self.timings.append(timing)
        # which ticks missed, only when some did: a run that keeps up moves the same frames as before
        self.misses.append(self.plant.deadline_misses() if timing.paced and timing.deadline_misses else None)
        self.steal.append(steal)
        t.append(time.perf_counter())
        self.boundaries.append(HostBoundary(setup_s=t[1] - t[0], ticks_s=t[2] - t[1], end_s=t[3] - t[2]))
        return actuals

    def explain_missing_tpdo(self, scale: float) -> None:
        """Before a missing TPDO is reported: give the plant node a moment to end the trial with
        its own fault (which then explains it)."""
        self.plant.wait_trial(timeout_s=1.0 * scale)

    def timing(self, ts_s: float, realtime: bool, scheduling: dict[str, Any] | None) -> dict[str, Any]:
        """The summary's timing of the trials so far (:func:`host.rig.realtime.timing_summary`)."""
        return timing_summary(self.timings, ts_s, realtime, scheduling, self.steal, self.misses, self.boundaries)

    def _freeze_gc(self) -> None:
        """What the host holds at its first trial (numba, scipy, canopen, rerun, pyarrow: about a
        million objects) lives as long as the process: frozen out of the cycle collector's reach,
        a full collection during a trial costs about a millisecond instead of 50-150 ms of one of
        the two cores the lockstep needs (refcounting still frees them). No gc.collect() first: it
        would hold the GIL for that long itself (seconds in an emulated VM, near the drives'
        heartbeat consumer time); the little garbage frozen with the rest is kept once."""
        if not self._gc_frozen:
            gc.freeze()
            self._gc_frozen = True
