"""``ilcrig run``: an experiment on the distributed rig (hub, plant, four drives, host as processes).

This module owns the ``run`` subcommand's options (experiment, bus, rig with ``--firmware``,
``--inject``), their typed form (:func:`run_options`) and :func:`cmd_run`, which hands them to the launcher
(:func:`host.rig.launcher.launch_rig`: preflight, start, watch, clean up).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from host.cli.options import add_rig_experiment_args, experiment_options, options_of

if TYPE_CHECKING:
    from host.rig.options import RunOptions

__all__ = ["add_parser", "cmd_run", "run_options"]


def add_parser(sub: Any) -> None:
    """``run`` on the subcommands ``sub``."""
    rp = sub.add_parser("run", help="run an experiment on the distributed rig (6 processes over CAN)")
    add_rig_experiment_args(rp)
    rp.add_argument(
        "--inject",
        action="append",
        metavar="SPEC",
        help="inject a fault (repeatable): kill|stall:ROLE@WHEN[,for=S], "
        "drop|corrupt|overflow|duplicate|delay:io|fieldbus@WHEN[,rate=P,seed=K,count=C,id=COBID,ms=D], "
        "emcy:NODE@WHEN[,code=C], diskfull@WHEN; WHEN = TRIAL:TICK, TRIAL:end, before or after "
        "(docs/faults.md: Fault injection)",
    )
    rp.set_defaults(func=cmd_run)


def run_options(args: argparse.Namespace) -> RunOptions:
    """The typed options of a parsed ``ilcrig run`` command line."""
    from host.rig.options import RunOptions

    return options_of(RunOptions, args, inject=tuple(args.inject or ()), experiment=experiment_options(args))


def cmd_run(args: argparse.Namespace) -> int:
    """``ilcrig run``: the launcher validates everything (preflight) before anything starts."""
    from host.rig.launcher import launch_rig

    return launch_rig(run_options(args))
