"""``ilcrig robot``: the four drives and the plant as a robot on the bus, for any CANopen master.

This module owns the ``robot`` subcommand's options (bus, real-time, ``--out``, ``--param-dir``,
``--view``, ``--firmware``) and :func:`cmd_robot`, which hands them to the launcher
(:func:`host.rig.robot_launcher.launch_robot`, docs/robot.md).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
from typing import Any

from host.cli.options import add_bus_args, add_firmware_arg, add_realtime_args, add_view_arg

__all__ = ["add_parser", "cmd_robot"]


def add_parser(sub: Any) -> None:
    """``robot`` on the subcommands ``sub``."""
    op = sub.add_parser(
        "robot", help="the four drives and the plant as a robot on the bus, for any CANopen master (docs/robot.md)"
    )
    add_bus_args(op)
    op.add_argument("--out", default=None, metavar="DIR", help="run folder (default runs/robot-<time>)")
    add_realtime_args(
        op,
        "pace the robot's periods to the wall clock (period n not before t0 + n·Ts) and count late and missing SYNCs",
    )
    op.add_argument(
        "--param-dir",
        default=None,
        metavar="DIR",
        help="folder where the drives keep the parameters a master saves with 0x1010 (default: in memory, one session)",
    )
    add_view_arg(op)
    add_firmware_arg(op)
    op.set_defaults(func=cmd_robot)


def cmd_robot(args: argparse.Namespace) -> int:
    """``ilcrig robot``: :func:`host.rig.robot_launcher.launch_robot`."""
    from host.rig.options import RobotOptions
    from host.rig.robot_launcher import launch_robot

    return launch_robot(RobotOptions.from_args(args))
