"""``ilcrig drive``: one servo-drive node (the firmware) on the bus.

This module owns the ``drive`` subcommand's options (``--node``, ``--param-dir``, ``--lockstep``,
``--firmware``, the bus options) and :func:`cmd_drive`, which resolves the transport and hands the whole process to
the firmware with a typed :class:`firmware_model.drive_node.DriveOptions`
(:func:`firmware_model.drive_node.run_drive`).  It is why ``host.cli`` may import
``firmware_model`` (tests/test_architecture.py).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
from typing import Any

from bus.errors import InputError
from host.cli.options import add_bus_args, add_firmware_arg, bus_errors, role_logging, transport_of

__all__ = ["add_parser", "cmd_drive"]


def add_parser(sub: Any) -> None:
    """``drive`` on the subcommands ``sub``."""
    dp = sub.add_parser("drive", help="one servo-drive node (firmware) on the bus")
    dp.add_argument("--node", type=int, required=True, help="CANopen node id (1-4 for the robot's joints)")
    dp.add_argument(
        "--param-dir",
        default=None,
        metavar="DIR",
        help="folder of the parameters 0x1010 saves (node<id>.json; default: in memory)",
    )
    dp.add_argument(
        "--lockstep",
        action="store_true",
        help="a drive of a SYNC-stepped plant (ilcrig robot): a SYNC's TPDOs carry its control cycle, "
        "the PDO timers count control periods (docs/robot.md)",
    )
    add_firmware_arg(dp)
    add_bus_args(dp)
    dp.set_defaults(func=cmd_drive)


def cmd_drive(args: argparse.Namespace) -> int:
    """``ilcrig drive``: the drive process (:func:`firmware_model.drive_node.run_drive`)."""
    from bus.transports.config import resolve_bus_config
    from firmware_model.drive_node import DriveOptions, run_drive

    tc = transport_of(args)
    if not 1 <= args.node <= 127:
        raise InputError(f"node id must be 1..127, got {args.node}")
    opts = DriveOptions(
        args.node,
        resolve_bus_config(tc.fieldbus),
        resolve_bus_config(tc.io),
        param_dir=args.param_dir,
        lockstep=args.lockstep,
        firmware=args.firmware,
    )
    role_logging()
    with bus_errors(tc.name):
        return run_drive(opts)
