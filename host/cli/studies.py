"""``ilcrig sweep``, ``ilcrig tune``, ``ilcrig reproduce``: studies of many experiments on Dask
distributed (:mod:`ilcrig.sweep`, docs/sweeps.md).

This module owns the three subcommands' options and their handlers :func:`cmd_sweep`,
:func:`cmd_tune`, :func:`cmd_reproduce`, as they were in the one-module command line.
TEMPORARY: the handlers call :mod:`ilcrig.sweep.commands` (the public API's package), which makes
this module the one importer of ``ilcrig`` below it (tests/test_architecture.py); the studies move
to ``host/studies/`` with their own ``add_sweep_parser``/``add_tune_parser``/``add_reproduce_parser``.

May import: what ``host.cli`` may, and (TEMPORARY) :mod:`ilcrig.sweep`.
"""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["add_reproduce_parser", "add_sweep_parser", "add_tune_parser", "cmd_reproduce", "cmd_sweep", "cmd_tune"]


def cmd_reproduce(args: argparse.Namespace) -> int:
    from ilcrig.sweep.commands import reproduce_main

    return int(reproduce_main(args))


def cmd_sweep(args: argparse.Namespace) -> int:
    """``ilcrig sweep``: a grid and/or Monte Carlo draws of experiments on Dask (:mod:`ilcrig.sweep`)."""
    from ilcrig.sweep.commands import sweep_main

    return int(sweep_main(args))


def cmd_tune(args: argparse.Namespace) -> int:
    """``ilcrig tune``: gains tuned with Optuna on the sweep engine (:mod:`ilcrig.sweep.tune`)."""
    from ilcrig.sweep.commands import tune_main

    return int(tune_main(args))


def _add_engine_args(p: argparse.ArgumentParser, workers_flag: str = "--workers") -> None:
    """Where the points run: a local cluster (``workers_flag``) or ``--scheduler``; progress, dashboard."""
    p.add_argument(
        workers_flag,
        type=int,
        default=None,
        dest="jobs" if workers_flag == "--jobs" else "workers",
        metavar="N",
        help="worker processes of the local Dask cluster, on 127.0.0.1 (default: number of cores)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="tcp://HOST:PORT",
        help="run on an existing Dask cluster (`dask scheduler` + `dask worker` on a private network; docs/sweeps.md)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-dashboard", action="store_true", help="do not serve the local cluster's dashboard")
    p.add_argument(
        "--dashboard", default=None, metavar="127.0.0.1:PORT", help="the local cluster's dashboard address (loopback only)"
    )


def _add_spec_args(p: argparse.ArgumentParser, sections: str = "[base], [vary], [monte_carlo]") -> None:
    """The points' options: a spec file, an experiment file, ``--set`` and ``--vary``."""
    p.add_argument("--spec", metavar="TOML", help=f"spec file: {sections} (docs/sweeps.md)")
    p.add_argument("--config", metavar="TOML", help="experiment file under the spec's [base] (keys as `ilcrig sim --config`)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="an option of every point (repeatable), e.g. law=pd-ilc-q, gains.alpha=3, plant.mass_scale=1.1",
    )


def add_reproduce_parser(sub: Any) -> None:
    """``reproduce`` on the subcommands ``sub``."""
    xp = sub.add_parser("reproduce", help="run the paper's experiments (Tables 2-6, Figs. 8 and 10) and beyond")
    xp.add_argument("--out", default="runs/reproduce", help="sweep folder (default runs/reproduce); reused to resume")
    _add_engine_args(xp, "--jobs")
    xp.add_argument("--iterations", type=int, default=10, help="trials per experiment (default 10)")
    xp.add_argument("--only", default=None, help="comma-separated subset: table2,table3,table4,table5,table6,figs,beyond")
    xp.add_argument("--fresh", action="store_true", help="ignore finished experiments in --out and redo all")
    xp.set_defaults(func=cmd_reproduce)


def add_sweep_parser(sub: Any) -> None:
    """``sweep`` on the subcommands ``sub``."""
    wp = sub.add_parser("sweep", help="run a grid / Monte Carlo sweep of experiments on Dask (docs/sweeps.md)")
    _add_spec_args(wp)
    wp.add_argument(
        "--vary",
        action="append",
        metavar="KEY=V1,V2,…",
        help="values of one option (repeatable: the product of all), e.g. gains.alpha=2,3,4 or law=pd-ilc,pd-ilc-q",
    )
    wp.add_argument(
        "--samples",
        type=int,
        default=None,
        metavar="N",
        help="Monte Carlo samples per grid point (the spec's [monte_carlo] samples)",
    )
    wp.add_argument("--out", default=None, help="sweep folder (default runs/sweep-<time>); reused to resume")
    wp.add_argument("--save-errors", action="store_true", help="keep each point's error signals (errors.npy)")
    wp.add_argument("--fresh", action="store_true", help="run every point again, finished or not")
    _add_engine_args(wp)
    wp.set_defaults(func=cmd_sweep)


def add_tune_parser(sub: Any) -> None:
    """``tune`` on the subcommands ``sub``."""
    tp = sub.add_parser("tune", help="tune gains with Optuna on the sweep engine (docs/sweeps.md)")
    _add_spec_args(tp, "[base], [tune], [objective], [monte_carlo]")
    tp.add_argument(
        "--param",
        action="append",
        metavar="KEY=LOW:HIGH[:log|:int]",
        help="a gain to tune and its range (repeatable), e.g. gains.alpha=1.5:6 or gains.lp_norm=1e-4:5e-3:log",
    )
    tp.add_argument("--budget", type=int, default=None, help="trials of the study in all, resumed ones included (default 30)")
    tp.add_argument(
        "--settle-weight",
        type=float,
        default=None,
        metavar="DEG",
        help="objective = final RMSE (deg, mean over joints) + this × the settle iteration (default 0)",
    )
    tp.add_argument(
        "--plants", type=int, default=None, help="Monte Carlo plants per trial (the spec's draws; default 0: the robot as built)"
    )
    tp.add_argument("--aggregate", choices=("mean", "max"), default=None, help="over the plants: mean or worst (default mean)")
    tp.add_argument(
        "--require-check",
        action="store_true",
        default=None,
        help="gains whose convergence check fails (spectral radius or predicted error ratio >= 1) are infeasible, not run",
    )
    tp.add_argument("--sampler-seed", type=int, default=0, help="seed of Optuna's sampler (default 0)")
    tp.add_argument(
        "--out", default=None, help="tuning folder: study.db, runs/, best.toml (default runs/tune-<time>); reused to resume"
    )
    _add_engine_args(tp)
    tp.set_defaults(func=cmd_tune)
