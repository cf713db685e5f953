"""The tidy table of a sweep: ``results.parquet``, one row per point, trial and joint.

This module owns the table's columns (:data:`METRIC_COLUMNS`, :func:`option_columns`), building its
rows from the points' folders (:func:`sweep_rows`), writing it atomically with pyarrow
(:func:`write_table`) and the per-point summary the reports use (:func:`final_metrics`).

Columns:

* ``point`` (id), ``index`` (order in the sweep), ``sample`` (Monte Carlo sample, or null);
* the point's options, one column each: ``law``, ``iterations``, ``path``, ``cycle_s``, ``profile``,
  ``disturbance``, ``seed``, ``ts_s``, ``substeps``, ``ff0``, ``ff_transport``, ``gains.<key>`` for
  every gain (``gains.preset``), ``plant.<factor>`` for the four plant factors, ``law_options.<key>``
  for the options any point has;
* ``trial``, ``role`` (``learning`` / ``auxiliary``), ``final`` (the point's last learning trial),
  ``joint`` (1–4), ``rmse_deg``, ``max_abs_deg``, ``mae_deg``, ``peak_torque_nm``;
* ``digest`` (the run's trace_sha256), ``completed``, ``fault`` (null or one line), ``error`` (a
  point that could not run has one row, with null trial, joint and metrics).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from host.experiment.config import PLANT_KEYS
from host.learning.gains import GainSpec
from host.studies.point import PointRecord, load_point, run_dir
from host.studies.spec import Point

logger = logging.getLogger(__name__)

__all__ = ["METRIC_COLUMNS", "option_columns", "sweep_rows", "write_table", "read_table", "final_metrics", "TABLE_FILE"]

TABLE_FILE = "results.parquet"
#: the per-trial metrics, per joint (deg; peak torque N·m)
METRIC_COLUMNS: tuple[str, ...] = ("rmse_deg", "max_abs_deg", "mae_deg", "peak_torque_nm")
_TOP = ("law", "iterations", "path", "cycle_s", "profile", "disturbance", "seed", "ts_s", "substeps", "ff0", "ff_transport")
_GAINS = tuple(f.name for f in dataclasses.fields(GainSpec) if f.name != "name")


def option_columns(config: dict[str, Any]) -> dict[str, Any]:
    """A configuration (``ExperimentConfig.as_dict()``) as flat option columns (module docstring)."""
    cols: dict[str, Any] = {k: config.get(k) for k in _TOP}
    gains = config.get("gains", {})
    cols["gains.preset"] = str(gains.get("name", "normalized")).split("+")[0]
    for k in _GAINS:
        cols[f"gains.{k}"] = gains.get(k)
    plant = config.get("plant") or {}
    for k in PLANT_KEYS:
        cols[f"plant.{k}"] = float(plant.get(k, 1.0))
    for k, v in (config.get("law_options") or {}).items():
        cols[f"law_options.{k}"] = v
    return cols


def _point_rows(p: Point, rec: PointRecord | None) -> list[dict[str, Any]]:
    base: dict[str, Any] = {"point": p.id, "index": p.index, "sample": p.labels.get("sample")}
    base |= option_columns(p.config.as_dict())
    if rec is None or rec.summary is None:
        error = "not run" if rec is None else (rec.error or "could not run")
        return [
            base
            | {"trial": None, "role": None, "final": None, "joint": None, "digest": None, "completed": False}
            | {m: None for m in METRIC_COLUMNS}
            | {"fault": None, "error": error}
        ]
    s = rec.summary
    faults = s.get("faults") or []
    fault = str(faults[0].get("message")) if faults else None
    its = s.get("iterations") or []
    learning = [k for k, it in enumerate(its) if it.get("role", "learning") == "learning"]
    last = learning[-1] if learning else None
    tail = {"digest": s.get("trace_sha256"), "completed": bool(s.get("completed")), "fault": fault, "error": None}
    if not its:
        return [base | {"trial": None, "role": None, "final": None, "joint": None} | {m: None for m in METRIC_COLUMNS} | tail]
    rows = []
    for k, it in enumerate(its):
        for j in range(4):
            row = base | {"trial": k, "role": it.get("role", "learning"), "final": k == last, "joint": j + 1}
            for m in METRIC_COLUMNS:
                vals = it.get(m)
                row[m] = None if vals is None or vals[j] is None else float(vals[j])
            rows.append(row | tail)
    return rows


def sweep_rows(out: Path, points: Sequence[Point]) -> list[dict[str, Any]]:
    """The table's rows for ``points`` from their folders in sweep folder ``out`` (a point that did
    not run has one row with its ``error``: ``not run`` or why it could not)."""
    rows: list[dict[str, Any]] = []
    for p in points:
        rows += _point_rows(p, load_point(run_dir(out, p.id)))
    return rows


def write_table(out: Path, points: Sequence[Point]) -> Path:
    """Write ``out/results.parquet`` (temporary file, then renamed)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows = sweep_rows(out, points)
    names: dict[str, None] = {}
    for r in rows:
        names.update(dict.fromkeys(r))
    columns = {n: [r.get(n) for r in rows] for n in names}
    table = pa.table({n: _array(pa, n, v) for n, v in columns.items()})
    path = Path(out) / TABLE_FILE
    tmp = path.with_name(path.name + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path


def _array(pa: Any, name: str, values: list[Any]) -> Any:
    """A column: its values' own type, or strings when they are mixed (a varied law_option)."""
    try:
        return pa.array(values)
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        logger.info("column %s has mixed types: written as strings", name)
        return pa.array([None if v is None else str(v) for v in values], type=pa.string())


def read_table(out: Path) -> Any:
    """``out/results.parquet`` as a pyarrow table."""
    import pyarrow.parquet as pq

    return pq.read_table(Path(out) / TABLE_FILE)


def final_metrics(out: Path, points: Sequence[Point]) -> dict[str, dict[str, Any]]:
    """Per point id: ``rmse_deg`` (K, 4) history of the learning trials, ``final_rmse_deg`` (4,),
    ``final_max_abs_deg`` (4,), ``fault``, ``error``, ``digest`` (what the reports and the tuner use)."""
    res: dict[str, dict[str, Any]] = {}
    for p in points:
        rec = load_point(run_dir(out, p.id))
        res[p.id] = metrics_of(rec.summary if rec is not None else None, None if rec is not None else "not run", rec)
    return res


def metrics_of(summary: dict[str, Any] | None, error: str | None = None, rec: PointRecord | None = None) -> dict[str, Any]:
    """The metrics of one run's summary (see :func:`final_metrics`)."""
    if summary is None:
        return {
            "rmse_deg": np.zeros((0, 4)),
            "final_rmse_deg": None,
            "final_max_abs_deg": None,
            "fault": None,
            "error": error or (rec.error if rec is not None else None) or "could not run",
            "digest": None,
        }
    its = [it for it in summary.get("iterations") or [] if it.get("role", "learning") == "learning"]
    rmse = np.array([[np.nan if v is None else v for v in it["rmse_deg"]] for it in its], dtype=float).reshape(-1, 4)
    maxe = np.array([[np.nan if v is None else v for v in it["max_abs_deg"]] for it in its], dtype=float).reshape(-1, 4)
    faults = summary.get("faults") or []
    return {
        "rmse_deg": rmse,
        "final_rmse_deg": rmse[-1] if len(rmse) else None,
        "final_max_abs_deg": maxe[-1] if len(maxe) else None,
        "fault": str(faults[0].get("message")) if faults else None,
        "error": None,
        "digest": summary.get("trace_sha256"),
    }
