"""``ilcrig plant``: the plant (the robot simulator) as the plant node on the bus.

This module owns the ``plant`` subcommand's options (``--node-id``, ``--robot``, ``--trace``,
``--summary``, ``--disturbance``, the bus options) and :func:`cmd_plant`, which hands a typed
:class:`plant.plant_node.PlantOptions` to :func:`plant.plant_node.run_plant`.

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
from typing import Any

from bus.plant_objects import DEFAULT_PLANT_NODE_ID, DisturbanceKind
from host.cli.options import add_bus_args, bus_errors, role_logging, transport_of

__all__ = ["add_parser", "cmd_plant"]


def add_parser(sub: Any) -> None:
    """``plant`` on the subcommands ``sub``."""
    pp = sub.add_parser("plant", help="the plant (robot simulator) as the plant node on the bus")
    pp.add_argument(
        "--node-id", type=int, default=DEFAULT_PLANT_NODE_ID, help="CANopen node id of the plant node (default %(default)s)"
    )
    pp.add_argument(
        "--robot",
        choices=("sync", "realtime"),
        default=None,
        help="start as the robot (docs/robot.md): one control period per SYNC (sync), also paced to the wall clock (realtime)",
    )
    pp.add_argument("--trace", default=None, metavar="FILE", help="with --robot: write the period trace here")
    pp.add_argument("--summary", default=None, metavar="FILE", help="write the node's counters as JSON here on exit")
    pp.add_argument(
        "--disturbance",
        choices=tuple(k.label for k in DisturbanceKind),
        default=DisturbanceKind.BOTH.label,
        help="the disturbance kind the host will ask for, prepared before boot-up; another kind is computed "
        "when a trial asks for it, the first one paying for its imports (default: %(default)s, every kind)",
    )
    add_bus_args(pp)
    pp.set_defaults(func=cmd_plant)


def cmd_plant(args: argparse.Namespace) -> int:
    """``ilcrig plant``: the plant process (:func:`plant.plant_node.run_plant`)."""
    from bus.plant_objects import RobotMode
    from plant.plant_node import PlantOptions, run_plant

    role_logging()
    mode = {None: RobotMode.OFF, "sync": RobotMode.SYNC, "realtime": RobotMode.REALTIME}[args.robot]
    tc = transport_of(args)
    opts = PlantOptions(
        tc,
        node_id=args.node_id,
        robot_mode=mode,
        trace_path=args.trace,
        summary_path=args.summary,
        disturbance=args.disturbance,
    )
    with bus_errors(tc.name):
        return run_plant(opts)
