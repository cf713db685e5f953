"""One point of a sweep: running it (on a worker) and keeping its result (in the sweep folder).

This module owns :func:`run_point` — the function a worker runs: the experiment in-process with the
composition of ``ilcrig sim`` and of ``ilcrig.Experiment`` (:func:`plan_of`, then
:class:`host.sim.inprocess.InProcessBench` and :func:`host.experiment.trial_loop.run_experiment`,
so its digest is the one of ``ilcrig sim`` with the same options), returning its summary, optionally
its errors, and the warnings it logged; it never raises for the experiment's own failures (an
infeasible task or a bad law is the point's ``error``) — and :func:`commit`, :func:`is_finished`
and :func:`load_point`: the point's folder in the sweep::

    <out>/runs/<point id>/point.json     the point: options, labels, worker, wall time, warnings
    <out>/runs/<point id>/summary.json   the run's summary (host.experiment.summary schema)
    <out>/runs/<point id>/errors.npy     (K, N, 4) float32 joint errors q_d − q, rad (when asked for)
    <out>/runs/<point id>/error.txt      instead of the summary: why the point could not run

A result travels back to the client, which writes the folder (the workers need no shared file
system): into a temporary folder beside it, then renamed into place, so a folder is either a
complete result or absent.  A point is deterministic: running it twice (a retry after a lost
worker) gives the same folder.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import socket
import time
import traceback
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bus.errors import InputError
from host.experiment.config import ExperimentConfig, build_config
from host.experiment.outputs import read_summary
from host.experiment.plan import Plan, prepare
from host.experiment.summary import jsonable, write_summary

logger = logging.getLogger(__name__)

__all__ = [
    "run_point",
    "plan_of",
    "commit",
    "is_finished",
    "load_point",
    "PointRecord",
    "POINT_FILE",
    "run_dir",
]

POINT_FILE = "point.json"
#: at most this many warnings of a point are kept (a diverging law can log one per trial)
MAX_WARNINGS = 20


class _Collect(logging.Handler):
    """Collects the WARNING and ERROR records of a point's run (instead of the worker's stderr)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.lines) < MAX_WARNINGS:
            self.lines.append(f"{record.levelname} {record.name}: {record.getMessage()}")


def plan_of(options: dict[str, Any]) -> Plan:
    """The plan of the experiment of ``options`` (the keys of ``ilcrig.Experiment``).

    :raises InputError: a bad key or value, or an infeasible experiment (the first line of the
        configuration's or the plan's message, as ``ilcrig.Experiment`` raises it)."""
    try:
        return prepare(build_config(None, dict(options)))
    except (ValueError, FileNotFoundError) as exc:
        raise InputError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None


def run_point(point_id: str, options: dict[str, Any], save_errors: bool) -> dict[str, Any]:
    """Run one point's experiment in this process (a worker) and return its result:
    ``{"id", "summary", "errors", "error", "traceback", "wall_s", "worker", "warnings"}``.

    ``errors`` is the (K, N, 4) float32 error array when ``save_errors``, else None; ``error`` is
    None, or one line saying why the experiment could not run (then ``summary`` is None)."""
    from host.experiment.trial_loop import run_experiment
    from host.sim.inprocess import InProcessBench

    t0 = time.perf_counter()
    collect = _Collect()
    root = logging.getLogger()
    root.addHandler(collect)
    out: dict[str, Any] = {
        "id": point_id,
        "summary": None,
        "errors": None,
        "error": None,
        "traceback": None,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }
    try:
        plan = plan_of(options)
        res = run_experiment(plan, InProcessBench(plan.cfg), None, mode="sim")
        out["summary"] = jsonable(res.summary)
        if save_errors:
            errs = res.errors
            n = plan.n_ticks
            out["errors"] = np.stack(errs).astype(np.float32) if errs else np.zeros((0, n, 4), np.float32)
    except Exception as exc:  # noqa: BLE001 - infeasible task, bad law, bug: the point's error, the sweep goes on
        out["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": ")
        out["traceback"] = traceback.format_exc()
    finally:
        root.removeHandler(collect)
    out["wall_s"] = time.perf_counter() - t0
    out["warnings"] = collect.lines
    return out


def run_dir(out: Path, point_id: str) -> Path:
    """The folder of point ``point_id`` in sweep folder ``out``."""
    return Path(out) / "runs" / point_id


def is_finished(folder: Path, cfg: ExperimentConfig, need_errors: bool = True) -> bool:
    """True if ``folder`` holds the finished run (completed, or ended by a recorded fault: both
    deterministic results) of exactly ``cfg``, with its errors file (``errors.npy``) if ``need_errors``."""
    s = read_summary(folder)
    if s is None or not (s.get("completed") or s.get("faults")):
        return False
    stored = {k: v for k, v in s.get("config", {}).items() if k not in ("n_ticks", "trial_s")}
    if stored != json.loads(json.dumps(cfg.as_dict())):
        return False
    return not need_errors or (Path(folder) / "errors.npy").is_file()


def commit(out: Path, point_id: str, point: dict[str, Any], result: dict[str, Any]) -> Path:
    """Write ``result`` (of :func:`run_point`) as the folder of point ``point_id``: a temporary
    folder beside it, renamed into place (module docstring).  ``point`` is what ``point.json``
    says about the point (options, labels, index)."""
    target = run_dir(out, point_id)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{point_id}.tmp-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    try:
        doc = dict(point) | {
            "id": point_id,
            "worker": result.get("worker"),
            "wall_s": result.get("wall_s"),
            "warnings": result.get("warnings", []),
            "error": result.get("error"),
        }
        (tmp / POINT_FILE).write_text(json.dumps(jsonable(doc), indent=2) + "\n", encoding="utf-8")
        if result.get("error") is not None or result.get("summary") is None:
            (tmp / "error.txt").write_text(f"{result.get('error')}\n\n{result.get('traceback') or ''}", encoding="utf-8")
        else:
            if result.get("errors") is not None:
                with open(tmp / "errors.npy", "wb") as fh:
                    np.save(fh, result["errors"])
            write_summary(tmp, result["summary"])  # fsync'ed, written last
        _replace_dir(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _replace_dir(tmp: Path, target: Path) -> None:
    """Put folder ``tmp`` at ``target``, replacing what is there (a stale or earlier result)."""
    try:
        os.rename(tmp, target)
        return
    except OSError:
        pass  # target exists (not empty)
    old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:12]}"
    with contextlib.suppress(FileNotFoundError):
        os.rename(target, old)
    os.rename(tmp, target)
    shutil.rmtree(old, ignore_errors=True)


@dataclass
class PointRecord:
    """A point's folder as read back: ``point.json``, the summary (None: it could not run) and
    the error line."""

    folder: Path
    point: dict[str, Any]
    summary: dict[str, Any] | None
    error: str | None


def load_point(folder: Path) -> PointRecord | None:
    """The point in ``folder``, or None when there is none (never run, or being replaced)."""
    try:
        point = json.loads((folder / POINT_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return PointRecord(folder, point, read_summary(folder), point.get("error"))
