"""``ilcrig sim``: a whole experiment in one process (no bus).

This module owns the ``sim`` subcommand: its options (the experiment options, ``--view``,
``--firmware``) and
:func:`cmd_sim`, which checks the run folder, builds the configuration and hands a typed
:class:`host.sim.session.SimOptions` to :func:`host.sim.session.run_sim` (host code, not the
public API).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from host.cli.options import add_experiment_args, add_firmware_arg, add_view_arg, experiment_options
from host.experiment.console import experiment_config

__all__ = ["add_parser", "cmd_sim"]


def add_parser(sub: Any) -> None:
    """``sim`` on the subcommands ``sub``."""
    sp = sub.add_parser("sim", help="run an experiment in one process (no bus)")
    add_experiment_args(sp)
    add_view_arg(sp)
    add_firmware_arg(sp)
    sp.set_defaults(func=cmd_sim)


def cmd_sim(args: argparse.Namespace) -> int:
    """``ilcrig sim``: the experiment in this process (:func:`host.sim.session.run_sim`)."""
    from host.experiment.outputs import check_out_dir, default_run_folder
    from host.sim.session import SimOptions, run_sim

    out = Path(args.out) if args.out is not None else None  # None: a fresh runs/sim-<time>, made once the input is good
    named = args.out if args.out is not None else default_run_folder("sim", claim=False)
    check_out_dir(named, create=False, new_run=True)  # fast: before the configuration
    return run_sim(
        SimOptions(experiment_config(experiment_options(args)), out, view=bool(args.view), firmware=args.firmware),
        sys.stdout,
    )
