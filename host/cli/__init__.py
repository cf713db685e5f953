"""The ``ilcrig`` command line.

Subcommands:

* ``sim``   — a whole experiment in one process (no bus), run by :mod:`host.sim` (not the public API);
* ``laws``  — the learning laws this installation knows (built-in and plug-ins);
* ``sweep`` — a grid and/or Monte Carlo draws of experiments on Dask distributed, ``tune`` — gains
  tuned with Optuna on the same engine, ``reproduce`` — the paper's experiments as a predefined
  sweep (:mod:`ilcrig.sweep`);
* ``run``   — the distributed rig: launches the bus hub (if the transport needs one), the plant,
  four drives and the host as separate processes, and cleans every one of them up;
* ``robot`` — the drives and the plant as a robot on the bus, without the ILC host, for any CANopen
  master (:mod:`host.rig.robot_launcher`, docs/robot.md);
* ``view`` — a run's ``recording.rrd`` in the Rerun viewer (:func:`host.analysis.recording.view_run`);
* ``drive``, ``plant``, ``host``, ``hub`` — one role each, to run the parts in separate terminals
  (or machines, over a transport that spans them).

This package owns the command line: :func:`build_parser` (one module per command, each with its
``add_parser(sub)``: :mod:`host.cli.sim`, :mod:`host.cli.run`, :mod:`host.cli.robot`,
:mod:`host.cli.host`, :mod:`host.cli.drive`, :mod:`host.cli.plant`, :mod:`host.cli.hub`,
:mod:`host.cli.laws`, :mod:`host.cli.view`, :mod:`host.cli.studies`; the option groups several of
them share, defined once, in :mod:`host.cli.options`), the one-line error parser, :func:`main`
with the error handling of every command (its console held by :mod:`host.cli.console`) and
:func:`command`, the console script; ``python -m host.cli`` is :mod:`host.cli.__main__`.  The
command lines of the ``python -m`` tools that are not ``ilcrig`` subcommands live here too:
:mod:`host.cli.dbc` (the DBC files), :mod:`host.cli.selfcheck` (the plant's check),
:mod:`host.cli.janitor` (the launcher's janitor process).
Below the command line the commands take typed options (frozen dataclasses: the experiment's
:class:`host.experiment.console.ExperimentOptions`, the launchers' :mod:`host.rig.options`, the
roles' own), never the parsed ``argparse.Namespace``: argparse lives only in this package.

Errors: bad input (:class:`bus.errors.InputError`, and argparse's own errors) is one line
``ilcrig: error: …`` with exit code 2 before anything moves; a bus a role cannot open is one line
and exit code 3; an unexpected exception (a bug) is one line ``ilcrig: internal error: …`` with
exit code 1 and its traceback in the log (printed with ``--debug``); so is a thread that ends with an
exception (``ilcrig: internal error in thread …``; a role logs it with its traceback:
:func:`report_thread_errors`).  The exit codes are the same
with and without ``--debug`` (:mod:`bus.exit_codes`).  A fault during a trial ends the run with
exit code 3 after the summary (with every completed trial) has been written.

May import: ``bus``, ``plant`` (the plant role), ``firmware_model`` (the drive role hands its whole
process to the firmware: :mod:`host.cli.drive`), every ``host`` subpackage; never the public API
``ilcrig``.  Kept import-light: every role parses the
command line, so commands import their work when they run.
"""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import sys
import threading
import traceback
from collections.abc import Sequence
from typing import NoReturn

from bus.errors import InputError
from bus.exit_codes import EXIT_ERROR, EXIT_FAULT, EXIT_USAGE, exit_code_of_signal
from host.cli.console import hold_console
from host.experiment.signal_shield import interrupt_on_signals, signum_of

__all__ = ["build_parser", "command", "main"]

logger = logging.getLogger(__name__)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"ilcrig: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    """The ``ilcrig`` parser: ``--debug`` and one subcommand per command module (imported here, so
    that :func:`main` holds the signals before any of them is)."""
    from host.cli import drive, host, hub, laws, plant, robot, run, sim, studies, view

    p = _Parser(prog="ilcrig", description="ILC on an emulated 4-DOF parallel robot with CAN servo drives")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging (exit codes unchanged)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sim.add_parser(sub)
    run.add_parser(sub)
    robot.add_parser(sub)
    host.add_parser(sub)
    drive.add_parser(sub)
    plant.add_parser(sub)
    laws.add_parser(sub)
    view.add_parser(sub)
    studies.add_reproduce_parser(sub)
    studies.add_sweep_parser(sub)
    studies.add_tune_parser(sub)
    hub.add_parser(sub)
    return p


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else ""


#: the role processes a launcher starts: their signals are their launcher's (Python's defaults until
#: their own handlers: the nodes' stop event, the hub's wake-up), so a role stopped while it starts
#: ends as the launcher expects
ROLE_COMMANDS = frozenset({"drive", "plant", "host", "hub"})


def report_thread_errors(*, debug: bool, role: bool) -> None:
    """A thread of this process that ends with an exception (a bug) says so as the main thread's
    errors do, never Python's traceback on a user's terminal nor a thread that ends unseen: a user's
    command writes one line ``ilcrig: internal error in thread <name>: …`` (its traceback in the log,
    printed with ``--debug``); a role (:data:`ROLE_COMMANDS`, whose output is its log file) logs it
    with its traceback.  The thread's own work is what it was: a watcher whose end matters declares
    it (e.g. the host's watchdog, :mod:`host.rig.watchdog`)."""

    def hook(args: threading.ExceptHookArgs) -> None:
        if args.exc_type is SystemExit:
            return
        name = args.thread.name if args.thread is not None else "?"
        exc = args.exc_value
        info = (args.exc_type, exc, args.exc_traceback) if exc is not None else None
        if role or debug:
            logger.error("thread %s failed", name, exc_info=info)
            return
        logger.debug("thread %s failed", name, exc_info=info)
        what = f"{args.exc_type.__name__}: {_first_line(exc)}" if exc is not None else args.exc_type.__name__
        sys.stderr.write(f"ilcrig: internal error in thread {name}: {what} (run with --debug for details)\n")

    threading.excepthook = hook


def _command_of(words: Sequence[str]) -> str | None:
    """The subcommand of a command line (its first word that is not an option)."""
    return next((w for w in words if not w.startswith("-")), None)


def main(argv: Sequence[str] | None = None, *, report_threads: bool = False) -> int:
    """``ilcrig [--debug] COMMAND …``; returns the exit code (:mod:`bus.exit_codes`).

    From its first statement to its return SIGINT, SIGTERM and SIGHUP end a user's command as
    ``ilcrig: interrupted (SIGINT)`` and exit code 130 / 143 / 129 (no traceback, no silent death)
    — while the command modules are imported, the command line is parsed and the command plans,
    before the command's own handling of signals (a run's, a launcher's) takes over; and a console
    whose reader went away is dropped, not an error (:mod:`host.cli.console`; for the role commands
    too, whose host writes a run's rows to the user's terminal). The role commands
    (:data:`ROLE_COMMANDS`) keep Python's default signal handling. ``report_threads``: once the
    command line is parsed, a thread that ends with an exception is said (:func:`report_thread_errors`;
    the console script's, for its whole process)."""
    words = list(sys.argv[1:] if argv is None else argv)
    if _command_of(words) in ROLE_COMMANDS:
        with hold_console():  # the host role writes the run's rows to the user's terminal
            return _main(words, report_threads)
    with hold_console(), interrupt_on_signals():
        try:
            _native_threads_without_signals()
            return _main(words, report_threads)
        except KeyboardInterrupt as exc:  # while the command starts, outside _main's own handling
            return _interrupted(exc)


def command() -> int:
    """The ``ilcrig`` console script and ``python -m host.cli``: :func:`main`, for a process that ends
    when it returns; its exit code.

    A thread of the process that ends with an exception is said as the main thread's errors are
    (``report_threads``: :func:`report_thread_errors`, for the process, once the command line is
    parsed; tests that call :func:`main` in their own process leave their hook alone). After it,
    every object alive is moved out of the cycle collector's reach (:func:`gc.freeze`): the
    collections of Python's finalization would otherwise traverse the whole heap of a process that
    imported numpy, scipy and numba, 0.24 s of CPU at the end of a launcher, and as long again in a
    host, on the run's path to its end (the launcher stops the other roles after the host's exit).
    Objects still freed by their references are freed as before; what the freeze leaves is cyclic
    garbage that Python's finalization does not promise to collect either. Files and records are
    closed by the code that wrote them, never by the collector."""
    code = main(report_threads=True)
    gc.freeze()
    return code


def _native_threads_without_signals() -> None:
    """numpy's thread pool (its BLAS threads, started when numpy is imported) starts with SIGINT
    and SIGTERM blocked, and its threads keep them blocked: the kernel gives a signal sent to this
    process to a thread that does not block it, and while the main thread blocks SIGINT
    (:func:`host.studies.dask_quiet.sigint_ignored`, as a sweep's cluster starts) one of the pool's
    would take it and drop it. A signal meanwhile is handled when the import is done."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        import numpy  # noqa: F401 - imported for its threads
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _interrupted(exc: KeyboardInterrupt) -> int:
    signum = signum_of(exc)  # SIGTERM's Interrupted (host.experiment.signal_shield): 143
    sys.stderr.write(f"ilcrig: interrupted ({signal.Signals(signum).name})\n")
    return exit_code_of_signal(signum)


def _main(argv: Sequence[str], report_threads: bool = False) -> int:
    from host.cli.options import BusUnavailable

    parser = build_parser()
    args = parser.parse_args(argv)
    if report_threads:
        report_thread_errors(debug=bool(args.debug), role=args.command in ROLE_COMMANDS)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except KeyboardInterrupt as exc:
        return _interrupted(exc)
    except BusUnavailable as exc:
        sys.stderr.write(f"ilcrig: error: {exc}\n")
        return EXIT_FAULT
    except InputError as exc:
        logger.debug("bad input", exc_info=True)
        sys.stderr.write(f"ilcrig: error: {_first_line(exc) or type(exc).__name__}\n")
        return EXIT_USAGE
    except Exception as exc:  # noqa: BLE001 - a bug: one line, the traceback in the log
        if args.debug:
            traceback.print_exc(file=sys.stderr)
        else:
            logger.debug("internal error", exc_info=True)
        hint = "" if args.debug else " (run with --debug for details)"
        sys.stderr.write(f"ilcrig: internal error: {type(exc).__name__}: {_first_line(exc)}{hint}\n")
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
