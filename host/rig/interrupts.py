"""The signals that interrupt ``ilcrig run``: SIGINT (Ctrl-C), SIGTERM, SIGHUP.

This module owns :class:`Interrupts`: while installed (main thread only) it notes the first of
these signals (the launcher then stops the host first, then the rest) and whether a second one
came while the launcher was already stopping (then no grace period is waited), and maps the
signal to the run's exit code (:func:`bus.exit_codes.exit_code_of_signal`: 130, 143, 129). The
signals are the runs' own (:data:`host.experiment.signal_shield.RUN_SIGNALS`); an ignored SIGHUP
(``nohup``) stays ignored: the run outlives its terminal.
"""

from __future__ import annotations

import logging
import signal
import threading
from typing import Any

from bus.exit_codes import exit_code_of_signal
from host.experiment.signal_shield import RUN_SIGNALS, signals_taken

logger = logging.getLogger(__name__)

__all__ = ["HANDLED_SIGNALS", "Interrupts"]

#: the signals the launcher intercepts
HANDLED_SIGNALS: tuple[int, ...] = RUN_SIGNALS


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
        for signum in signals_taken(HANDLED_SIGNALS):
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
        return exit_code_of_signal(self.signum)
