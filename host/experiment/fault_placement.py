"""A fault as the run's record: what it was (:func:`fault_record_of`: the bench's own description,
or one made from the exception), where the run was when it came (:func:`place`: position, trial,
tick), and a failing write of the final outputs as the run's fault (:func:`record_output_fault`).

May import: ``bus``, :mod:`host.experiment` (bench, faults, outputs, loop_state), :mod:`host.nodes`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from bus.errors import IlcrigError, SdoAbort
from host.experiment.bench import Bench, TrialFault
from host.experiment.faults import (
    FaultKind,
    FaultRecord,
    Position,
    attach_injection,
    node_name,
    position_of,
    read_injections,
)
from host.experiment.loop_state import ExperimentResult
from host.experiment.outputs import OutputError
from host.nodes.sdo_access import SdoTransportError

__all__ = ["fault_record_of", "place", "record_output_fault"]


def fault_record_of(
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
