"""ilcrig.sweep: sweeps, Monte Carlo robustness studies and gain tuning on Dask distributed — the
public face of :mod:`host.studies`.

Owns nothing but the names users import (docs/sweeps.md §6), re-exported from the studies:

* :class:`SweepSpec` and :class:`Point` (:mod:`host.studies.spec`: base options, grid, seeded
  Monte Carlo draws);
* :class:`Engine` (a loopback ``LocalCluster`` or an existing ``dask scheduler``),
  :func:`run_points` (resumable, progress bar, Ctrl-C keeps what finished) and
  :class:`SweepOutcome`, :class:`ClusterLost` (the cluster gone; also ``ilcrig.ClusterLost``)
  (:mod:`host.studies.engine`);
* :func:`run_point` and :func:`load_point` (:mod:`host.studies.point`: a point on a worker, its
  folder in the sweep);
* :func:`write_table` (:mod:`host.studies.table`: ``results.parquet``) and :func:`write_report`
  (:mod:`host.studies.report`: ``report.md``).

``ilcrig sweep``, ``ilcrig tune`` and ``ilcrig reproduce`` are the command line's
(:mod:`host.studies.commands`).  May import :mod:`host.studies` (and what :mod:`ilcrig` may import);
``import ilcrig`` does not import this package (nor Dask).
"""

from __future__ import annotations

from host.studies.engine import ClusterLost, Engine, SweepOutcome, run_points
from host.studies.point import load_point, run_point
from host.studies.report import write_report
from host.studies.spec import Point, SweepSpec
from host.studies.table import write_table

__all__ = [
    "ClusterLost",
    "Engine",
    "Point",
    "SweepOutcome",
    "SweepSpec",
    "load_point",
    "run_point",
    "run_points",
    "write_report",
    "write_table",
]
