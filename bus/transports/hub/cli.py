"""The hub's command line: ``ilcrig hub`` and ``python -m bus.transports.hub.cli``.

This module owns :func:`main`: it parses the options (listen addresses, ``--ready``,
``--exit-on-stdin-eof``, ``--allow-remote``, ``--inject``, ``--bus-time``, ``--remove-dir``),
builds a :class:`bus.transports.hub.server.HubServer` and serves until SIGTERM/SIGINT or, with
``--exit-on-stdin-eof``, until stdin closes (the child-process API of
:mod:`bus.transports.hub.process` relies on it).  Bad input — an option, a listen address, a folder
or socket of another user — is one line ``ilcrig: error: …`` and exit code 2, as for every
``ilcrig`` command.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Sequence
from typing import NoReturn

from bus.exit_codes import EXIT_USAGE
from bus.lockstep_process import freeze_heap
from bus.transports.hub.addresses import default_hub_address
from bus.transports.hub.bus_time import parse_bus_time
from bus.transports.hub.process import READY_PREFIX
from bus.transports.hub.server import HubServer
from bus.transports.hub.wire import HubAddressError, HubAddressInUseError

logger = logging.getLogger(__name__)


#: the exit code of bad input (as ``ilcrig``'s)


class _Parser(argparse.ArgumentParser):
    """argparse with the one-line error of every ``ilcrig`` command."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"ilcrig: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bus.transports.hub.cli --listen unix:/path [--listen tcp:127.0.0.1:0]``; returns the exit code."""
    parser = _Parser(prog="python -m bus.transports.hub.cli", description="ilcrig zero-privilege CAN hub")
    parser.add_argument(
        "--listen",
        action="append",
        help=f"unix:/path or tcp:127.0.0.1:PORT (repeatable; default {default_hub_address()})",
    )
    parser.add_argument("--ready", action="store_true", help=f"print '{READY_PREFIX} <addresses>' when listening")
    parser.add_argument("--exit-on-stdin-eof", action="store_true", help="exit when stdin closes")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="accept non-loopback TCP listen addresses (the hub then serves other machines)",
    )
    parser.add_argument("--inject", default=None, help='frame faults (JSON: {"specs": [...], "log": path})')
    parser.add_argument("--remove-dir", default=None, help="a private folder to remove on exit")
    parser.add_argument(
        "--bus-time",
        action="append",
        default=[],
        metavar="BUS=BIT_S",
        help="deliver logical bus BUS in bus time at BIT_S bit/s: arbitration order, each frame after its bit time (repeatable)",
    )
    args = parser.parse_args(argv)
    try:
        bus_time = parse_bus_time(args.bus_time)
    except ValueError as err:
        parser.error(str(err))
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s hub %(levelname)s %(message)s")
    hook = None
    if args.inject:
        from bus.transports.fault_inject import FrameFaultInjector

        hook = FrameFaultInjector.from_json(args.inject)
    try:
        server = HubServer(
            args.listen or [default_hub_address()], allow_remote=args.allow_remote, frame_hook=hook, bus_time=bus_time
        )
        if args.allow_remote:
            logger.warning("hub accepts remote members on %s (unauthenticated)", ", ".join(map(str, server.addresses)))
    except (HubAddressError, HubAddressInUseError, OSError) as err:
        text = str(err) if isinstance(err, HubAddressError | HubAddressInUseError) else f"cannot listen: {err.strerror or err}"
        sys.stderr.write(f"ilcrig: error: {text}\n")
        return EXIT_USAGE
    signal.signal(signal.SIGTERM, lambda *_: server.wake())
    signal.signal(signal.SIGINT, lambda *_: server.wake())
    try:
        if args.ready:
            print(READY_PREFIX, *map(str, server.addresses), flush=True)
        freeze_heap("hub")  # a lockstep process: no full collection of the start-up heap mid-run
        server.serve_forever(watch_fd=sys.stdin.fileno() if args.exit_on_stdin_eof else None)
    finally:
        server.close()
        if args.remove_dir:
            with contextlib.suppress(OSError):
                os.rmdir(args.remove_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
