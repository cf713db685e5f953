"""The hub process: serve a :class:`bus.transports.hub.server.HubServer` until told to stop.

This module owns :class:`HubOptions` (listen addresses, ``ready``, ``exit_on_stdin_eof``,
``allow_remote``, frame faults, bus time, a folder to remove on exit, the log level) and
:func:`run_hub`: it builds the server and serves until SIGTERM/SIGINT or, with
``exit_on_stdin_eof``, until stdin closes (the child-process API of
:mod:`bus.transports.hub.process` relies on it).  The command line is ``ilcrig hub``
(:mod:`host.cli.hub`; :func:`bus.transports.hub.process.start_hub` starts ``python -m host.cli hub``).
Bad input — a listen address, a bus-time rate, a folder or socket of another user — is
:class:`bus.errors.InputError` (``ilcrig: error: …``, exit code 2).

May import: ``bus`` and :mod:`bus.transports` (the transport package's hub).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
from dataclasses import dataclass
from typing import TextIO

from bus.errors import InputError
from bus.exit_codes import EXIT_OK
from bus.lockstep_process import freeze_heap
from bus.transports.hub.addresses import default_hub_address
from bus.transports.hub.bus_time import parse_bus_time
from bus.transports.hub.process import READY_PREFIX
from bus.transports.hub.server import HubServer
from bus.transports.hub.wire import HubAddressError, HubAddressInUseError

logger = logging.getLogger(__name__)

__all__ = ["HubOptions", "run_hub"]


@dataclass(frozen=True)
class HubOptions:
    """The hub process's options (``ilcrig hub``)."""

    #: listen addresses, ``unix:/path`` or ``tcp:HOST:PORT`` (empty: the default address)
    listen: tuple[str, ...] = ()
    #: print ``READY_PREFIX <addresses>`` on stdout when listening
    ready: bool = False
    #: exit when stdin closes
    exit_on_stdin_eof: bool = False
    #: accept non-loopback TCP listen addresses
    allow_remote: bool = False
    #: frame faults (JSON of :meth:`bus.transports.fault_inject.FrameFaultInjector.from_json`)
    inject: str | None = None
    #: a private folder to remove on exit
    remove_dir: str | None = None
    #: ``BUS=BIT_S`` items: logical buses delivered in bus time at that bit rate
    bus_time: tuple[str, ...] = ()
    #: the process's log level (None: as the command line set it); records then carry ``hub``
    log_level: str | None = None


def _configure_logging(level: str) -> None:
    root = logging.getLogger()
    try:
        root.setLevel(level.upper())
    except ValueError:
        raise InputError(f"--log-level {level!r}: not a log level (DEBUG, INFO, WARNING, ERROR)") from None
    for handler in root.handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s hub %(levelname)s %(message)s"))


def run_hub(opts: HubOptions, stdout: TextIO | None = None) -> int:
    """Serve the hub of ``opts`` until SIGTERM/SIGINT (or stdin's end); returns the exit code.

    :param stdout: where the ready line goes (default ``sys.stdout``)
    :raises InputError: a bad option, listen address or bus-time rate, or an address that cannot be
        listened on
    """
    try:
        bus_time = parse_bus_time(list(opts.bus_time))
    except ValueError as err:
        raise InputError(str(err)) from None
    if opts.log_level is not None:
        _configure_logging(opts.log_level)
    hook = None
    if opts.inject:
        from bus.transports.fault_inject import FrameFaultInjector

        hook = FrameFaultInjector.from_json(opts.inject)
    try:
        server = HubServer(
            list(opts.listen) or [default_hub_address()], allow_remote=opts.allow_remote, frame_hook=hook, bus_time=bus_time
        )
    except (HubAddressError, HubAddressInUseError) as err:
        raise InputError(str(err)) from None
    except OSError as err:
        raise InputError(f"cannot listen: {err.strerror or err}") from None
    if opts.allow_remote:
        logger.warning("hub accepts remote members on %s (unauthenticated)", ", ".join(map(str, server.addresses)))
    signal.signal(signal.SIGTERM, lambda *_: server.wake())
    signal.signal(signal.SIGINT, lambda *_: server.wake())
    out = stdout if stdout is not None else sys.stdout
    try:
        if opts.ready:
            out.write(" ".join([READY_PREFIX, *map(str, server.addresses)]) + "\n")
            out.flush()
        freeze_heap("hub")  # a lockstep process: no full collection of the start-up heap mid-run
        server.serve_forever(watch_fd=sys.stdin.fileno() if opts.exit_on_stdin_eof else None)
    finally:
        server.close()
        if opts.remove_dir:
            with contextlib.suppress(OSError):
                os.rmdir(opts.remove_dir)
    return EXIT_OK
