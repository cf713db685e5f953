"""host.studies: many experiments at once — sweeps, Monte Carlo robustness studies, gain tuning —
on Dask distributed, and the paper's study (:mod:`host.studies.paper`).

Owns, one module per concern (docs/sweeps.md explains them with commands):

* :mod:`host.studies.spec` — :class:`SweepSpec` (base options, grid, seeded Monte Carlo draws; from
  a TOML spec and the command line's ``--set`` / ``--vary``) and :class:`Point`;
* :mod:`host.studies.point` — what a worker runs for a point (:func:`run_point`: the experiment with
  the composition of ``ilcrig sim``) and the point's folder in the sweep (atomic commit, resume);
* :mod:`host.studies.engine` — :class:`Engine` (a loopback ``LocalCluster`` or an existing ``dask
  scheduler``), :class:`PointQueue` (the one submit loop) and :func:`run_points` (resumable,
  progress bar, Ctrl-C keeps what finished, a lost cluster is :class:`ClusterLost`); generic: it
  knows nothing of what a study is for;
* :mod:`host.studies.dask_quiet` — the local cluster's Dask classes (workers that ignore SIGINT; no
  HTTP listener without a dashboard);
* :mod:`host.studies.table` — the tidy table ``results.parquet`` (one row per point, trial, joint);
* :mod:`host.studies.report` — ``report.md`` of a sweep with its figures;
* :mod:`host.studies.sweep_record` — the sweep folder's ``sweep.json`` (the calls of its commands)
  and one study, one folder (an ``--out`` holding a run or another study is refused);
* :mod:`host.studies.settling` — the definitions on RMSE histories (settle iteration, floor, block
  windows, repeatable error) the tuner's objective and the paper's verdicts use;
* :mod:`host.studies.tune_params` — the settings of ``ilcrig tune`` (tuned keys and ranges, the
  objective); :mod:`host.studies.tune` — the Optuna study on the engine and its outputs;
* :mod:`host.studies.commands` — the command line's ``sweep``, ``tune`` and ``reproduce``: their
  options and handlers (the CLI only adds them);
* :mod:`host.studies.paper` — ``ilcrig reproduce``: the paper's plan, claims, verdicts, published
  numbers and report.

The public face is :mod:`ilcrig.sweep` (it re-exports the names users import).  May import ``bus``,
``plant``, :mod:`host.planning`, :mod:`host.learning`, :mod:`host.experiment` (the points run
in-process through it) and :mod:`host.analysis` (figures, number formatting), and dask,
distributed, optuna, pyarrow; :mod:`host.studies.paper` only in :mod:`host.studies.commands`.
Never the rig, never ``ilcrig``.
"""
