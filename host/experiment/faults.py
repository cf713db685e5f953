"""Faults of a run: the summary's ``faults`` entries, the injection records, the one terminal line.

This module owns

* :class:`FaultKind` — the vocabulary of fault kinds (a lost node, a lost or silent bus, a lost,
  late, duplicated or damaged io frame, an EMCY, a full disk …);
* :class:`FaultRecord` — one ``faults`` entry of ``summary.json``: kind, node, where in the run
  (:class:`Position`: before the first trial, in a trial with its tick, between trials, after the
  last trial), who detected it and the detection latency in ms (with what the latency was
  measured against);
* :func:`position_of` — the position of a fault from what the run had kept when it ended;
* :func:`node_name` — ``drive1`` … ``drive4``, ``plant``, ``host`` for a CANopen node id;
* the injection records that ``ilcrig run --inject`` leaves in ``RUN_DIR/logs/injections*.jsonl``
  (one JSON object per line: ``kind``, ``target``, ``trial``, ``tick``, ``t_mono``, ``t_wall``, …) and
  :func:`attach_injection`, which measures a detection against the injection that caused it;
* :func:`fault_line` — the one line ``ilcrig: fault: …`` a faulted run ends with.

Latency: ``t_mono`` values are ``time.monotonic()`` (CLOCK_MONOTONIC, one clock for every process
of the machine), ``t_wall`` values ``time.time()``; a latency is taken on the monotonic clock when
both ends have it, else on the wall clock.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from bus.cia301.nmt import HOST_NODE_ID
from bus.objects import DRIVE_NODE_IDS
from bus.plant_objects import DEFAULT_PLANT_NODE_ID

logger = logging.getLogger(__name__)

__all__ = [
    "FaultKind",
    "FaultRecord",
    "Position",
    "attach_injection",
    "fault_line",
    "node_name",
    "position_of",
    "read_injections",
    "INJECTION_LOG_GLOB",
]

#: where the injectors write their records, relative to the run folder
INJECTION_LOG_GLOB = "logs/injections*.jsonl"


class FaultKind(StrEnum):
    """What went wrong (``faults[].kind`` in the summary)."""

    PROCESS_DIED = "process_died"  #: a role process ended (seen by the launcher)
    NODE_LOST = "node_lost"  #: a node's heartbeat stopped (host heartbeat consumer): a dead or stalled node
    HOST_LOST = "host_lost"  #: the host's heartbeat stopped (the nodes' consumer, EMCY 0x8130)
    BUS_LOST = "bus_lost"  #: the bus itself failed (the hub is gone)
    BUS_SILENT = "bus_silent"  #: no node heard at all (the hub stalled)
    FRAME_LOST = "frame_lost"  #: frames lost: an io frame lost or late at a tick's deadline, or a receiver overflowed
    FRAME_SEQUENCE = "frame_sequence"  #: an io frame duplicated, stale or out of sequence
    FRAME_ERROR = "frame_error"  #: an io frame damaged on the wire (bus error frame) or malformed
    EMCY = "emcy"  #: a node reported a fault (drive following error, …)
    PLANT_ERROR = "plant_error"  #: the plant model failed
    LEARNING_DIVERGED = "learning_diverged"  #: the learned feed-forward is not finite or beyond the drive's table range
    SDO_ERROR = "sdo_error"  #: a node refused or did not answer an SDO request
    DISK_FULL = "disk_full"  #: the run folder's filesystem is full
    OUTPUT_ERROR = "output_error"  #: another failing write of the run's outputs
    TRIAL_FAULT = "trial_fault"  #: anything else that ended a trial


def node_name(node_id: int) -> str:
    """``drive1`` … ``drive4``, ``plant`` (the plant node), ``host`` (127), else ``node N``."""
    if node_id in DRIVE_NODE_IDS:
        return f"drive{node_id}"
    if node_id == DEFAULT_PLANT_NODE_ID:
        return "plant"
    if node_id == HOST_NODE_ID:
        return "host"
    return f"node {node_id}"


class Position(StrEnum):
    """Where in the run a fault happened (``faults[].position``).

    ``trial`` of the record then is: in a trial, that trial (not kept); before the first trial,
    0; between trials, the next trial (every earlier one kept); after the last trial, the last
    trial (kept, like every other). ``tick`` is the tick of that trial in a trial, else null.
    """

    BEFORE_FIRST_TRIAL = "before_first_trial"  #: while the nodes are brought up and configured
    IN_TRIAL = "in_trial"  #: from the trial's first tick until its data is in the summary
    BETWEEN_TRIALS = "between_trials"  #: after a trial is in the summary, before the next one's first tick
    AFTER_LAST_TRIAL = "after_last_trial"  #: after the last trial is in the summary: shutdown, final outputs


def position_of(kept: int, planned: int, in_trial: bool) -> tuple[Position, int]:
    """The position and the ``trial`` of a fault when ``kept`` of ``planned`` trials are in the
    summary and a trial is (``in_trial``) or is not running (its ticks, or its data not yet kept)."""
    if in_trial:
        return Position.IN_TRIAL, kept
    if kept <= 0:
        return Position.BEFORE_FIRST_TRIAL, 0
    if kept >= planned:
        return Position.AFTER_LAST_TRIAL, planned - 1
    return Position.BETWEEN_TRIALS, kept


@dataclass
class FaultRecord:
    """One fault of a run (an entry of ``summary["faults"]``).

    :ivar kind: a :class:`FaultKind` value
    :ivar message: one line saying what happened
    :ivar node: the node or process it concerns: ``drive1`` … ``drive4``, ``plant``, ``hub``, ``host``
    :ivar node_id: its CANopen node id, if it has one
    :ivar trial: the trial it concerns (0-based; see :class:`Position`)
    :ivar tick: the tick of that trial in a trial (None outside a trial)
    :ivar position: a :class:`Position` value (None until the run's fault path placed it)
    :ivar detected_by: who noticed: ``host``, ``plant``, ``drive2``, ``launcher`` …
    :ivar latency_ms: detection latency, ms (None if nothing to measure it against)
    :ivar latency_basis: what the latency was measured from (``injection``, ``process exit``, …)
    """

    kind: str
    message: str
    node: str | None = None
    node_id: int | None = None
    trial: int | None = None
    tick: int | None = None
    position: str | None = None
    detected_by: str = "host"
    latency_ms: float | None = None
    latency_basis: str | None = None
    t_detected_mono: float | None = None
    t_detected_wall: float | None = None
    injected: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (no NaN)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "extra"}
        d.update(self.extra)
        if d["latency_ms"] is not None:
            d["latency_ms"] = round(float(d["latency_ms"]), 3) if math.isfinite(d["latency_ms"]) else None
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FaultRecord:
        names = {f.name for f in dataclasses.fields(cls)} - {"extra"}
        rec = cls(**{k: v for k, v in d.items() if k in names})
        rec.extra = {k: v for k, v in d.items() if k not in names}
        return rec

    def where(self) -> str:
        """``drive2 (node 2), trial 1, tick 150`` in a trial; ``drive2, between trials 0 and 1
        (trial 1 not started)``, ``…, before the first trial (trial 0 not started)``, ``…, after
        the last trial (trial 2, kept)`` outside one (the parts that are known)."""
        parts = []
        if self.node:
            parts.append(
                self.node
                + (f" (node {self.node_id})" if self.node_id is not None and not self.node.endswith(str(self.node_id)) else "")
            )
        parts.append(position_words(self.position, self.trial, self.tick))
        return ", ".join(parts)


def position_words(position: str | None, trial: int | None, tick: int | None) -> str:
    """Where in a run something happened, in words (a fault's or an interrupt's ``position``,
    ``trial``, ``tick``): ``trial 1, tick 150``, ``between trials 0 and 1 (trial 1 not started)``,
    ``before the first trial (trial 0 not started)``, ``after the last trial (trial 2, kept)``."""
    shown = trial if trial is not None else "?"
    if position == Position.BEFORE_FIRST_TRIAL:
        return f"before the first trial (trial {shown} not started)"
    if position == Position.BETWEEN_TRIALS and isinstance(trial, int):
        return f"between trials {trial - 1} and {trial} (trial {trial} not started)"
    if position == Position.AFTER_LAST_TRIAL:
        return f"after the last trial (trial {shown}, kept)"
    return f"trial {shown}, " + (f"tick {tick}" if tick is not None else "tick unknown")


def fault_line(record: FaultRecord, kept: int, *, summary_path: str | Path | None = None, extra: str = "") -> str:
    """The one terminal line of a faulted run: ``ilcrig: fault: <what>: <node>, trial k, tick n; …``."""
    latency = f" after {record.latency_ms:.0f} ms" if record.latency_ms is not None else ""
    kept_text = f"{kept} completed trial{'s' if kept != 1 else ''} kept"
    if record.position == Position.AFTER_LAST_TRIAL:
        kept_text = f"all {kept} trials kept"
    text = (
        f"ilcrig: fault: {record.message} [{record.kind}]: {record.where()}; detected by {record.detected_by}"
        f"{latency}; torque removed, {kept_text}"
    )
    if extra:
        text += f"; {extra}"
    if summary_path is not None:
        text += f"; summary: {summary_path}"
    return text


def read_injections(run_dir: str | Path) -> list[dict[str, Any]]:
    """Every injection record of a run folder (``logs/injections*.jsonl``), oldest first."""
    out: list[dict[str, Any]] = []
    for path in sorted(Path(run_dir).glob(INJECTION_LOG_GLOB)):
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except OSError as err:
            logger.warning("cannot read %s: %s", path, err)
            continue
        for line in lines:
            try:
                rec = json.loads(line)
            except ValueError:
                continue  # a torn last line of a killed injector
            if isinstance(rec, dict):
                out.append(rec)
    out.sort(key=lambda r: float(r.get("t_mono", r.get("t_wall", 0.0)) or 0.0))
    return out


def attach_injection(record: FaultRecord, injections: list[dict[str, Any]]) -> FaultRecord:
    """Measure ``record``'s detection against the earliest injection before it (if any): sets
    ``injected``, ``latency_ms`` and ``latency_basis = "injection"``. Returns ``record``."""
    best = None
    for inj in injections:
        if record.t_detected_mono is not None and inj.get("t_mono") is not None:
            if float(inj["t_mono"]) <= record.t_detected_mono + 1e-3:
                best = inj
                break
        elif record.t_detected_wall is not None and inj.get("t_wall") is not None:
            if float(inj["t_wall"]) <= record.t_detected_wall + 1e-3:
                best = inj
                break
    if best is None:
        return record
    record.injected = {k: best[k] for k in ("spec", "kind", "target", "trial", "tick", "by", "t_mono") if k in best}
    if record.t_detected_mono is not None and best.get("t_mono") is not None:
        record.latency_ms = max(0.0, 1000.0 * (record.t_detected_mono - float(best["t_mono"])))
    elif record.t_detected_wall is not None and best.get("t_wall") is not None:
        record.latency_ms = max(0.0, 1000.0 * (record.t_detected_wall - float(best["t_wall"])))
    record.latency_basis = "injection"
    return record
