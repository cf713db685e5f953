"""What the trial loop needs from the things around it: a :class:`Bench` (four drives plus a
plant, whatever connects them), a :class:`TrialRecorder`, the pdo transport's per-tick
set-points and actuals, and :class:`TrialFault` (a trial that did not complete).

Implementations: :class:`host.sim.inprocess.InProcessBench` (``ilcrig sim``) and
:class:`host.rig.rig_bench.RigBench` (``ilcrig run``); recorders :class:`host.analysis.recording.RunRecorder`
and :class:`host.experiment.arrays.TrialArrays`.

May import: ``bus``, :mod:`host.experiment.faults`, :mod:`host.learning.metrics`,
:mod:`host.nodes.drive_client`, :mod:`host.planning`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from bus.errors import IlcrigError
from host.experiment.faults import FaultRecord
from host.learning.metrics import TrialMetrics
from host.nodes.drive_client import DriveClient
from host.planning.joint_reference import JointReference

__all__ = ["Bench", "CyclicActuals", "CyclicSetpoints", "TrialFault", "TrialRecorder"]


class TrialFault(IlcrigError):
    """A trial could not complete (drive fault, plant error, lost node); torque was removed.

    :ivar record: what the bench knows about it (kind, node, tick, who detected it), if anything
    """

    def __init__(self, message: str, record: FaultRecord | None = None) -> None:
        super().__init__(message)
        self.record = record


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
        bench saw after the trial loop's last step — while the run ended or while it closed),
        ``hold_heartbeat(seconds | None)`` (the host's heartbeat goes on that long without the
        interpreter while a law's code runs; None: as usual)."""
