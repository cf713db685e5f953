"""A law's code on the rig, watched: its time limit, and how long the host's threads stood still meanwhile.

This module owns :class:`LawWatch`.  On the rig (``ilcrig run``, :class:`ilcrig.RigRun`) the trial
loop runs the law's code between trials — ``update`` and ``auxiliary_input`` — in a worker thread
while the loop's thread waits for it in short slices, so:

* a law may take as long as it needs, up to :data:`LAW_UPDATE_LIMIT_S` (``$ILCRIG_LAW_UPDATE_LIMIT_S``
  overrides it): past the limit the run ends with a fault of the law (a
  :class:`host.learning.laws.checked.LawError` naming the law, the limit, and where the law's code
  was: its stack in ``logs/law-error.log``);
* the host's heartbeat goes on meanwhile, also through a single call that holds the interpreter
  (the GIL) without letting it switch — a C extension's long loop, ``sum(range(10**9))`` — and on
  a machine without a CPU to spare for the host's threads: a thread of C writes it, and the watch
  holds its lease for the limit (``hold``: the bench's ``hold_heartbeat``;
  :mod:`host.rig.host_heartbeat`);
* where a Python thread sends the heartbeat (a transport other than the hub, or a hub client
  without its C core) such a call stops it: the nodes then lose the host after their consumer time
  (:data:`bus.cia301.nmt.CONSUMER_TIME_MS`).  The waiting thread measures the longest time the
  host's threads did not run (it cannot wake meanwhile, whichever the cause); one longer than the
  consumer time is logged, and a host-lost fault that follows names the law's update and both
  possible causes (:meth:`LawWatch.blame`).

In process (``ilcrig sim``, the API's sessions) the law runs in the loop's own thread, unwatched.
May import: ``bus``, ``numpy``, :mod:`host.learning`.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bus.cia301.nmt import CONSUMER_TIME_MS
from bus.units import timeout_scale
from host.learning.laws.checked import LawError

logger = logging.getLogger(__name__)

__all__ = ["LAW_LIMIT_ENV", "LAW_UPDATE_LIMIT_S", "LawWatch", "law_update_limit_s"]

#: the longest a law's update (or ``auxiliary_input``) may run on the rig, s (docs/api.md)
LAW_UPDATE_LIMIT_S = 600.0
#: the environment variable that sets another limit, s
LAW_LIMIT_ENV = "ILCRIG_LAW_UPDATE_LIMIT_S"
#: how often the waiting thread wakes while the law runs, s (its longest sleep is the measure of a
#: hold of the interpreter)
WAKE_S = 0.1


def law_update_limit_s() -> float:
    """The limit in force, s: ``$ILCRIG_LAW_UPDATE_LIMIT_S`` or :data:`LAW_UPDATE_LIMIT_S`."""
    raw = os.environ.get(LAW_LIMIT_ENV, "").strip()
    if not raw:
        return LAW_UPDATE_LIMIT_S
    try:
        value = float(raw)
    except ValueError:
        value = 0.0
    if not value > 0.0:
        logger.warning("%s=%r is not a positive number of seconds: the limit stays %g s", LAW_LIMIT_ENV, raw, LAW_UPDATE_LIMIT_S)
        return LAW_UPDATE_LIMIT_S
    return value


@dataclass
class LastCall:
    """The law's last call: after which trial, how long it ran, and the longest the host's threads did
    not run meanwhile (``held_s``), s."""

    after_trial: int
    seconds: float
    held_s: float


class LawWatch:
    """Runs the law's calls of one run in a worker thread with a time limit (module docstring).

    :param law_name: the law's name, for the messages
    :param limit_s: the limit, s (default :func:`law_update_limit_s`)
    :param hold: ``hold(seconds)`` before each call keeps the host's heartbeat going that long
        without the interpreter, ``hold(None)`` after it (None: nothing to hold)
    """

    def __init__(self, law_name: str, limit_s: float | None = None, hold: Callable[[float | None], None] | None = None) -> None:
        self.law_name = law_name
        self.hold = hold
        self.limit_s = law_update_limit_s() if limit_s is None else float(limit_s)
        #: the nodes' heartbeat consumer time, s: a longer hold of the interpreter loses the host
        self.consumer_s = CONSUMER_TIME_MS * timeout_scale() / 1000.0
        self.last: LastCall | None = None

    def call(self, fn: Callable[[], Any], after_trial: int) -> Any:
        """``fn()`` (the law's call after trial ``after_trial``) in a worker thread; its value or its
        exception.

        :raises LawError: ``fn`` ran longer than the limit (the run ends; the worker is left to end
            with the process)
        """
        box: dict[str, Any] = {}

        def work() -> None:
            try:
                box["value"] = fn()
            except BaseException as exc:  # noqa: BLE001 - handed to the loop's thread as it is
                box["error"] = exc

        worker = threading.Thread(target=work, name=f"law {self.law_name}", daemon=True)
        if self.hold is not None:
            self.hold(self.limit_s + self.consumer_s)  # past the limit this thread ends the run
        try:
            t0 = time.monotonic()
            worker.start()  # may return only once the law's code lets go of the interpreter
            last = time.monotonic()
            held = last - t0
            while worker.is_alive():
                worker.join(WAKE_S)
                now = time.monotonic()
                held = max(held, now - last - WAKE_S)
                last = now
                if worker.is_alive() and now - t0 > self.limit_s:
                    self.last = LastCall(after_trial, now - t0, held)
                    raise self._over_limit(worker, after_trial, now - t0)
        finally:
            if self.hold is not None:
                self.hold(None)
        self.last = LastCall(after_trial, time.monotonic() - t0, max(held, 0.0))
        logger.debug(
            "law %s after trial %d: %.3f s, held the interpreter %.3f s",
            self.law_name,
            after_trial,
            self.last.seconds,
            self.last.held_s,
        )
        if self.last.held_s > self.consumer_s:
            logger.warning(
                "during law %s's update after trial %d the host's threads did not run for %.2f s (longer than the "
                "nodes' heartbeat consumer time, %.2f s: they lose the host unless a thread of C writes its "
                "heartbeat): a call that holds the GIL, or no CPU to spare for the host (docs/api.md)",
                self.law_name,
                after_trial,
                self.last.held_s,
                self.consumer_s,
            )
        if "error" in box:
            raise box["error"]
        return box["value"]

    def _over_limit(self, worker: threading.Thread, after_trial: int, seconds: float) -> LawError:
        frame = sys._current_frames().get(worker.ident or -1)
        where = "".join(traceback.format_stack(frame)) if frame is not None else "(its stack is gone)\n"
        err = LawError(
            f"law {self.law_name} did not return from its update after trial {after_trial} within the limit on "
            f"the rig ({self.limit_s:g} s, {LAW_LIMIT_ENV}; docs/api.md)"
        )
        err.__cause__ = TimeoutError(f"the law's code was here after {seconds:.1f} s:\n{where.rstrip()}")
        return err

    def blame(self, message: str) -> str:
        """A host-lost fault's ``message`` with its cause when the host's threads did not run for
        longer than the consumer time during the law's last call, else ``message``."""
        last = self.last
        if last is None or last.held_s <= self.consumer_s:
            return message
        return (
            f"{message}: during law {self.law_name}'s update after trial {last.after_trial} the host's threads did "
            f"not run for {last.held_s:.1f} s (longer than the heartbeat consumer time, {self.consumer_s:.2f} s): a "
            "call of the law that holds the GIL, or no CPU to spare for the host (docs/api.md)"
        )
