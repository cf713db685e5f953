"""The signals that interrupt ``ilcrig run``: SIGINT (Ctrl-C), SIGTERM, SIGHUP.

This module owns :class:`Interrupts`: while installed (main thread only) it notes the first of
these signals (the launcher then stops the host first, then the rest) and whether a second one
came while the launcher was already stopping (then no grace period is waited), and maps the
signal to the run's exit code (130 for SIGINT, 143 for SIGTERM, 128 + n otherwise). An ignored
SIGHUP (``nohup``) stays ignored: the run outlives its terminal.
"""

from __future__ import annotations

import logging
import signal
import threading
from typing import Any

from bus.exit_codes import EXIT_HANGUP, EXIT_INTERRUPTED, EXIT_TERMINATED
from host.experiment.signal_shield import hangup_ignored

logger = logging.getLogger(__name__)

__all__ = ["HANDLED_SIGNALS", "Interrupts"]

_SIGNAL_EXIT: dict[int, int] = {
    signal.SIGINT: EXIT_INTERRUPTED,
    signal.SIGTERM: EXIT_TERMINATED,
    signal.SIGHUP: EXIT_HANGUP,
}
#: the signals the launcher intercepts
HANDLED_SIGNALS: tuple[int, ...] = tuple(_SIGNAL_EXIT)


class Interrupts:
    """The launcher's signal state (see the module docstring).

    :ivar signum: the first signal received (None: none)
    :ivar hurry: a further signal came while stopping: wait no more grace periods
    :ivar stopping: the launcher is stopping the processes (a signal now only hurries it)
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self.hurry = False
        self.stopping = False
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        """Intercept :data:`HANDLED_SIGNALS` (only in the main thread; elsewhere nothing happens) —
        SIGHUP not where it is ignored (``nohup``: the run outlives its terminal)."""
        if threading.current_thread() is not threading.main_thread():
            logger.debug("not the main thread: signals are not intercepted")
            return
        for signum in HANDLED_SIGNALS:
            if signum == signal.SIGHUP and hangup_ignored():
                logger.debug("SIGHUP is ignored (nohup): the run outlives its terminal")
                continue
            self._old[signum] = signal.signal(signum, self._on_signal)

    def restore(self) -> None:
        """Put the previous handlers back."""
        for signum, handler in self._old.items():
            signal.signal(signum, handler)
        self._old = {}

    def _on_signal(self, signum: int, frame: object) -> None:
        if self.signum is None and not self.stopping:
            self.signum = signum
        else:
            self.hurry = True

    @property
    def name(self) -> str:
        """The first signal's name (``SIGINT`` …)."""
        assert self.signum is not None
        return signal.Signals(self.signum).name

    def exit_code(self) -> int:
        """The run's exit code for the first signal."""
        assert self.signum is not None
        return _SIGNAL_EXIT.get(self.signum, 128 + self.signum)
