"""SIGINT / SIGTERM / SIGHUP during a run: raised as :class:`Interrupted` in the main thread, held
back while a trial's outputs are written, logged (not raised) once the run's end has begun.

Owns the one signal shield of the process (:data:`SHIELD`), the signals that end a run
(:data:`RUN_SIGNALS`; SIGHUP only where it is not ignored, :func:`hangup_ignored`: ``nohup``),
:func:`interrupt_on_signals` (the handlers of a run) and :func:`deferred_interrupts` (a block the
signals wait for).  Used by the trial
loop (:mod:`host.experiment.trial_loop`), ``ilcrig sim`` and the rig's host role.

May import: the standard library only.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator, Sequence

logger = logging.getLogger(__name__)

__all__ = [
    "Interrupted",
    "RUN_SIGNALS",
    "SHIELD",
    "Shield",
    "deferred_interrupts",
    "end_of_run",
    "hangup_ignored",
    "interrupt_on_signals",
    "signals_taken",
    "signum_of",
]

#: the signals that end a run: Ctrl-C, ``kill``'s default, the terminal hung up (its window closed,
#: the ssh connection lost) — SIGHUP only where it is not ignored (:func:`hangup_ignored`)
RUN_SIGNALS: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def hangup_ignored() -> bool:
    """SIGHUP is ignored in this process (``nohup``, or a parent that ignored it before ``exec``):
    the user asked for the command to outlive its terminal, and no handler of ours takes it."""
    return signal.getsignal(signal.SIGHUP) == signal.SIG_IGN


def signals_taken(signals: Sequence[int] = RUN_SIGNALS) -> list[int]:
    """The ones of ``signals`` a handler of ours may take now: all but an ignored SIGHUP
    (:func:`hangup_ignored`). Used by :func:`interrupt_on_signals` and the launchers' interrupts."""
    return [s for s in signals if not (s == signal.SIGHUP and hangup_ignored())]


class Interrupted(KeyboardInterrupt):
    """SIGINT / SIGTERM / SIGHUP during a run (raised by the signal handler of the process)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def signum_of(exc: BaseException) -> int:
    """The signal behind a :class:`KeyboardInterrupt`: an :class:`Interrupted`'s own, else SIGINT
    (Python's Ctrl-C)."""
    return int(getattr(exc, "signum", signal.SIGINT))


class Shield:
    """While :attr:`defer_depth` > 0 (a trial's outputs being written) the signal handler of
    :func:`interrupt_on_signals` keeps a signal in :attr:`deferred`, raised when the block ends
    (:func:`deferred_interrupts`); once :attr:`ended` (the run's end began: safe state, final
    summary, report) a signal is only logged until :func:`interrupt_on_signals` gives the handlers
    back — the run's records and exit code stay those of the run as it ended."""

    ended: bool = False
    defer_depth: int = 0
    deferred: int | None = None


SHIELD = Shield()


def end_of_run() -> None:
    """The run's work is over and its records are being made final (safe state, summary, report,
    a study's table): from now until :func:`interrupt_on_signals` gives the handlers back a
    signal is only logged, the records and the exit code stay those of the run."""
    SHIELD.ended = True


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold SIGINT / SIGTERM back while inside (the handler of :func:`interrupt_on_signals` keeps
    the signal); at the end raise :class:`Interrupted` for it — unless an exception is already on
    its way, then the run's end marks the signal (:meth:`host.experiment.trial_loop.TrialLoop.finish`)."""
    SHIELD.defer_depth += 1
    failed = False
    try:
        yield
    except BaseException:
        failed = True
        raise
    finally:
        SHIELD.defer_depth -= 1
        if SHIELD.defer_depth == 0 and SHIELD.deferred is not None and not failed:
            signum, SHIELD.deferred = SHIELD.deferred, None
            raise Interrupted(signum)


@contextlib.contextmanager
def interrupt_on_signals(signals: Sequence[int] = RUN_SIGNALS) -> Iterator[None]:
    """While inside: SIGINT / SIGTERM / SIGHUP raise :class:`Interrupted` in the main thread (the
    run then ends through its fault path: safe state, summary with an ``interrupted`` marker); a
    second signal during that shutdown, or any signal once the run has ended (:attr:`Shield.ended`:
    its report and closing lines are being written), is logged, not raised. An ignored SIGHUP
    (:func:`hangup_ignored`) stays ignored. Restores the handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum: int, _frame: object) -> None:
        if fired or SHIELD.ended:
            logger.warning("%s while the run ends: its records are finished first", signal.Signals(signum).name)
            return
        fired.append(signum)
        if SHIELD.defer_depth > 0:
            SHIELD.deferred = signum  # a trial's outputs are being written: raised when they are
            return
        raise Interrupted(signum)

    outer = SHIELD.ended, SHIELD.deferred  # an enclosing block's (a command around a library call)
    SHIELD.ended, SHIELD.deferred = False, None
    old = {s: signal.signal(s, handler) for s in signals_taken(signals)}
    try:
        yield
    finally:
        SHIELD.ended, SHIELD.deferred = outer
        for s, h in old.items():
            signal.signal(s, h)
