"""A sweep folder's ``sweep.json``: what its commands ran.

This module owns :data:`SWEEP_SCHEMA` and :func:`record_call`: every call of ``ilcrig sweep`` and
``ilcrig reproduce`` on a sweep folder adds an entry (the call, the points run, skipped and failed,
whether it was interrupted, where it ran, its wall time in s) to the file's ``history``, the file
itself written atomically.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from bus.atomic import atomic_write
from host.studies.engine import SweepOutcome

logger = logging.getLogger(__name__)

__all__ = ["SWEEP_SCHEMA", "record_call"]

#: the format of ``sweep.json``
SWEEP_SCHEMA = "ilcrig.sweep/1"


def record_call(out: Path, doc: dict[str, Any], call: dict[str, Any], where: dict[str, Any], outcome: SweepOutcome) -> None:
    """Add one call of a sweep command to ``out/sweep.json``, atomically: the file becomes ``doc``
    with its ``history`` so far and this call's entry (``call``, the outcome's counts, ``where``,
    the wall time in s) at its end."""
    path = out / "sweep.json"
    try:
        prev = json.loads(path.read_text())
    except (OSError, ValueError):
        prev = {}
    history = list(prev.get("history", []))
    counts = {
        "ran": len(outcome.ran),
        "skipped": len(outcome.skipped),
        "errors": outcome.errors,
        "interrupted": outcome.interrupted,
    }
    history.append(call | counts | where | {"wall_s": round(outcome.wall_s, 3)})
    atomic_write(path, json.dumps(doc | {"history": history}, indent=2, default=str))
