"""``ilcrig hub``: the zero-privilege CAN hub (also how :func:`bus.transports.hub.process.start_hub`
starts it as a child process).

This module owns the ``hub`` subcommand's options (``--listen``, ``--allow-remote``, and the
child-process options ``--ready``, ``--exit-on-stdin-eof``, ``--log-level``, ``--inject``,
``--bus-time``, ``--remove-dir``) and :func:`cmd_hub`, which hands a typed
:class:`bus.transports.hub.serve.HubOptions` to :func:`bus.transports.hub.serve.run_hub`.

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
from typing import Any

from host.cli.options import options_of

__all__ = ["add_parser", "cmd_hub"]


def add_parser(sub: Any) -> None:
    """``hub`` on the subcommands ``sub``."""
    bp = sub.add_parser("hub", help="the zero-privilege CAN hub (loopback / Unix socket unless --allow-remote)")
    bp.add_argument(
        "--listen",
        action="append",
        help="unix:/path or tcp:127.0.0.1:PORT (repeatable; default: $ILCRIG_HUB or hub.sock in this user's "
        "private folder, $XDG_RUNTIME_DIR/ilcrig or $TMPDIR/ilcrig-<uid>)",
    )
    bp.add_argument(
        "--allow-remote",
        action="store_true",
        help="also accept a non-loopback tcp:ADDRESS:PORT, to serve roles on other machines",
    )
    bp.add_argument(
        "--bus-time",
        action="append",
        default=[],
        metavar="BUS=BIT_S",
        help="deliver logical bus BUS in bus time at BIT_S bit/s: arbitration order, each frame after its bit time (repeatable)",
    )
    bp.add_argument("--log-level", default=None, help="the hub's log level (default: WARNING, DEBUG with --debug)")
    # the child-process API of bus.transports.hub.process (start_hub)
    bp.add_argument("--ready", action="store_true", help=argparse.SUPPRESS)
    bp.add_argument("--exit-on-stdin-eof", action="store_true", help=argparse.SUPPRESS)
    bp.add_argument("--inject", default=None, help=argparse.SUPPRESS)  # frame faults, JSON
    bp.add_argument("--remove-dir", default=None, help=argparse.SUPPRESS)
    bp.set_defaults(func=cmd_hub)


def cmd_hub(args: argparse.Namespace) -> int:
    """``ilcrig hub``: :func:`bus.transports.hub.serve.run_hub`."""
    from bus.transports.hub.serve import HubOptions, run_hub

    return run_hub(options_of(HubOptions, args, listen=tuple(args.listen or ()), bus_time=tuple(args.bus_time)))
