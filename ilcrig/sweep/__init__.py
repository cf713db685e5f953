"""ilcrig.sweep: sweeps, Monte Carlo robustness studies and gain tuning on Dask distributed.

Owns, one module per concern:

* :mod:`ilcrig.sweep.spec` — :class:`SweepSpec` (base options, grid, seeded Monte Carlo draws; from a
  TOML spec and the command line's ``--set`` / ``--vary``) and :class:`Point`;
* :mod:`ilcrig.sweep.point` — what a worker runs for a point (:func:`run_point`, the experiment
  through :class:`ilcrig.Experiment`) and the point's folder in the sweep (atomic commit, resume);
* :mod:`ilcrig.sweep.engine` — :class:`Engine` (a loopback ``LocalCluster`` or an existing
  ``dask scheduler``) and :func:`run_points` (resumable, progress bar, Ctrl-C keeps what finished);
* :mod:`ilcrig.sweep.table` — the tidy table ``results.parquet`` (one row per point, trial, joint);
* :mod:`ilcrig.sweep.report` — ``report.md`` of a sweep with its figures;
* :mod:`ilcrig.sweep.tune` — gain tuning with Optuna on the same engine (``ilcrig tune``);
* :mod:`ilcrig.sweep.reproduce` — ``ilcrig reproduce`` as a predefined sweep;
* :mod:`ilcrig.sweep.commands` — what the command line's ``sweep``, ``tune`` and ``reproduce`` do.

docs/sweeps.md explains them with commands.  May import what :mod:`ilcrig` may import (``host``,
``plant``, ``bus``; the points run through :mod:`ilcrig.experiment`), and dask, distributed, optuna,
pyarrow.
"""

from __future__ import annotations

from ilcrig.sweep.engine import Engine, SweepOutcome, run_points
from ilcrig.sweep.point import load_point, run_point
from ilcrig.sweep.spec import Point, SweepSpec

__all__ = ["Engine", "Point", "SweepOutcome", "SweepSpec", "load_point", "run_point", "run_points"]
