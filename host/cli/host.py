"""``ilcrig host``: the host role alone (it expects four drives and the plant on the bus; also what
``ilcrig run`` starts).

This module owns the ``host`` subcommand's options (experiment, bus, rig, the launcher's hidden
``--rt-scheduling`` and ``--inject-disk-full``, ``--wait``, ``--pause``, ``--recover``) and
:func:`cmd_host`, which hands a typed :class:`host.rig.host_role.HostOptions` to
:func:`host.rig.host_role.run_host_role`.

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bus.errors import InputError
from host.cli.options import HOST_INFO_LOGGERS, add_rig_experiment_args, experiment_options, role_logging, transport_of
from host.experiment.console import experiment_config

if TYPE_CHECKING:
    from host.rig.host_role import HostOptions

__all__ = ["add_parser", "cmd_host", "host_options"]


def add_parser(sub: Any) -> None:
    """``host`` on the subcommands ``sub``."""
    hp = sub.add_parser("host", help="the host role alone (expects 4 drives and the plant on the bus)")
    add_rig_experiment_args(hp)
    hp.add_argument("--rt-scheduling", default=None, help=argparse.SUPPRESS)  # the launcher's: what --realtime got
    hp.add_argument(
        "--wait",
        type=float,
        default=120.0,
        help="seconds to wait for the nodes to answer (default 120: a first run compiles the numba kernels)",
    )
    hp.add_argument(
        "--pause", type=float, default=0.0, help="seconds to pause between trials (e.g. to restart a drive, with --recover)"
    )
    hp.add_argument(
        "--recover",
        type=float,
        default=0.0,
        help="> 0: a node lost or rebooted between trials is waited for (up to --wait) and set up again "
        "instead of ending the run (default 0: every lost node is a fault)",
    )
    hp.add_argument("--inject-disk-full", default=None, metavar="SPEC", help=argparse.SUPPRESS)  # the launcher's diskfull@…
    hp.set_defaults(func=cmd_host)


def host_options(args: argparse.Namespace) -> HostOptions:
    """The typed options of a parsed ``host`` command line."""
    from host.rig.host_role import HostOptions

    try:
        rt_scheduling = json.loads(args.rt_scheduling) if args.rt_scheduling else None
    except json.JSONDecodeError as exc:
        raise InputError(f"--rt-scheduling: not JSON: {exc}") from None
    return HostOptions(
        out=Path(args.out) if args.out is not None else None,
        wait_s=args.wait,
        pause_s=args.pause,
        recover_s=args.recover or 0.0,
        realtime=bool(args.realtime),
        rt_scheduling=rt_scheduling,
        io_bitrate=args.io_bitrate,
        bus_time=bool(args.bus_time),
        view=bool(args.view),
        inject_disk_full=args.inject_disk_full,
        firmware=args.firmware,
    )


def cmd_host(args: argparse.Namespace) -> int:
    """``ilcrig host``: :func:`host.rig.host_role.run_host_role` with typed options."""
    from host.rig.host_role import run_host_role

    role_logging(HOST_INFO_LOGGERS)
    return run_host_role(host_options(args), experiment_config(experiment_options(args)), transport_of(args))
