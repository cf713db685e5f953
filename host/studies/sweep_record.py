"""A sweep folder's ``sweep.json``: what its commands ran.

This module owns :data:`SWEEP_SCHEMA`, :func:`record_call` and :func:`check_study_folder`: every
call of ``ilcrig sweep`` and ``ilcrig reproduce`` on a sweep folder adds an entry (the call, the
points run, skipped and failed, whether it was interrupted, whether the cluster was lost, where it
ran, its wall time in s) to the file's ``history``, the file itself written atomically.  One study,
one folder: :func:`check_study_folder` refuses, before anything starts, an ``--out`` that holds a
run, another kind of study or a sweep of another spec (resuming the same sweep stays).

May import: ``bus``, :mod:`host.experiment.outputs` (what a run leaves in its folder),
:mod:`host.studies.engine`.
"""

from __future__ import annotations

import json
import logging
import signal
from pathlib import Path
from typing import Any

from bus.atomic import atomic_write
from bus.errors import InputError
from host.experiment.outputs import RUN_FOLDER_MARKERS
from host.studies.engine import SweepOutcome

logger = logging.getLogger(__name__)

__all__ = ["SWEEP_SCHEMA", "SWEEP_FILE", "STUDY_DB", "record_call", "check_study_folder"]

#: the format of ``sweep.json``
SWEEP_SCHEMA = "ilcrig.sweep/1"
#: a sweep folder's record (``ilcrig sweep``, ``ilcrig reproduce``)
SWEEP_FILE = "sweep.json"
#: a tuning folder's study (``ilcrig tune``; :data:`host.studies.tune.STUDY_FILE`)
STUDY_DB = "study.db"


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON (tuples and lists alike, numbers as written)."""
    return bool(json.loads(json.dumps(a, default=str)) == json.loads(json.dumps(b, default=str)))


def check_study_folder(out: Path, kind: str, spec: dict[str, Any] | None = None, *, option: str = "--out") -> None:
    """Refuse ``out`` for a study of ``kind`` (``"sweep"`` or ``"tune"``) when it holds something
    else: a run (:data:`host.experiment.outputs.RUN_FOLDER_MARKERS`), the other kind of study, or
    (``kind="sweep"`` with ``spec``) a sweep whose recorded spec differs.  A folder of the same
    study — the same sweep's ``sweep.json``, a tuning folder's ``study.db`` (whose identity the
    tuner checks) — is a resume and passes; so do a new and an empty folder.

    :raises InputError: one line naming ``option``, the folder and what it holds (exit 2).
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{option} {out}: exists and is not a folder (give a new or an empty folder)")
    if not out.is_dir():
        return
    sweep, study = out / SWEEP_FILE, out / STUDY_DB
    if kind == "sweep" and sweep.is_file():
        if spec is not None:
            try:
                stored = json.loads(sweep.read_text()).get("spec")
            except (OSError, ValueError) as exc:
                raise InputError(f"{option} {out}: its {SWEEP_FILE} cannot be read ({exc}); give another folder") from None
            if stored is not None and not _same(stored, spec):
                raise InputError(
                    f"{option} {out}: holds a sweep of another spec ({SWEEP_FILE}); give a new or an empty folder "
                    "(the same spec resumes it)"
                )
        return
    if kind == "tune" and study.is_file():
        return
    if kind == "sweep" and study.is_file():
        raise InputError(f"{option} {out}: holds a tuning study ({STUDY_DB}); give a new or an empty folder")
    if kind == "tune" and sweep.is_file():
        raise InputError(f"{option} {out}: holds a sweep ({SWEEP_FILE}); give a new or an empty folder")
    held = [m for m in RUN_FOLDER_MARKERS if (out / m).exists()]
    if held:
        raise InputError(f"{option} {out}: holds a run ({', '.join(held)}); give a new or an empty folder, or remove that run")


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
        "signal": signal.Signals(outcome.signum).name if outcome.signum is not None else None,
        "cluster_lost": outcome.cluster_lost,
    }
    history.append(call | counts | where | {"wall_s": round(outcome.wall_s, 3)})
    atomic_write(path, json.dumps(doc | {"history": history}, indent=2, default=str))
