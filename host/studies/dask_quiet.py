"""The local cluster's Dask classes: quiet on the terminal, no HTTP listener unless asked.

This module owns :class:`QuietWorker` (a Dask worker that ignores SIGINT: Ctrl-C on the terminal is
the command's, which cancels the points and closes the cluster — no worker prints a traceback),
:class:`NoHttpWorker` and :class:`NoHttpScheduler` (their HTTP server is made but never listens:
Dask's scheduler would otherwise serve its HTTP routes on 8787 and every worker on a port of its
own, dashboard or not), the nannies that start those workers (:class:`QuietNanny`,
:class:`NoHttpNanny`) and :class:`QuietLocalCluster` (a ``LocalCluster`` whose scheduler class is
chosen), and the quiet of this process: :func:`quiet_dask_logs` (Dask's log lines and the
tracebacks it logs when a connection goes silenced, unless ``--debug``) and :func:`sigint_ignored`
(the worker processes are spawned with SIGINT ignored).  Imported by :mod:`host.studies.engine`
when the engine starts (it imports Dask); the worker classes are module-level so the worker
processes import them by name.

May import: ``distributed``, ``tornado`` (nothing of ilcrig).
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from multiprocessing import resource_tracker
from typing import Any

from distributed import LocalCluster, Nanny, Scheduler, Worker
from distributed.http.routing import RoutingApplication
from tornado.httpserver import HTTPServer

__all__ = [
    "QuietWorker",
    "NoHttpWorker",
    "NoHttpScheduler",
    "QuietNanny",
    "NoHttpNanny",
    "QuietLocalCluster",
    "NoHttpLocalCluster",
    "dask_log_level",
    "quiet_dask_logs",
    "sigint_ignored",
]


def dask_log_level() -> int:
    """ERROR with ``ilcrig --debug`` (the root logger at DEBUG), else above CRITICAL: nothing."""
    return logging.ERROR if logging.getLogger().getEffectiveLevel() <= logging.DEBUG else logging.CRITICAL + 1


def quiet_dask_logs(saved: dict[str, int]) -> None:
    """Silence ``distributed`` and every child logger Dask gave a level of its own (to
    :func:`dask_log_level`); their levels before go into ``saved`` (first call wins), for the caller
    to restore."""
    level = dask_log_level()
    names = ["distributed"] + [
        n
        for n, lg in logging.root.manager.loggerDict.items()
        if n.startswith("distributed.") and isinstance(lg, logging.Logger) and lg.level != logging.NOTSET
    ]
    for name in names:
        lg = logging.getLogger(name)
        saved.setdefault(name, lg.level)
        lg.setLevel(max(level, lg.level))


@contextlib.contextmanager
def sigint_ignored() -> Iterator[None]:
    """While inside (main thread only): SIGINT ignored — processes spawned meanwhile inherit it —
    and blocked in this thread and the threads it starts meanwhile, so that a Ctrl-C then is not
    lost: Linux keeps a blocked signal pending even when it is ignored, and it is handled when the
    block ends, after this process's own handler is back.

    Two things would end the block early, and are ruled out before it begins: multiprocessing's
    resource tracker, started on the first spawn, unblocks SIGINT and SIGTERM in the thread that
    starts it (``SIG_UNBLOCK`` after its spawn, not the mask it found: CPython 3.11), so it is
    started first; and a thread that does not block SIGINT takes it and drops it — numpy's thread
    pool is started with it blocked by :func:`host.cli.main`. A program of a user's that calls the
    engine may have such threads, and a Ctrl-C in this window is then lost, as it was."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    resource_tracker.ensure_running()
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a SIGINT that came meanwhile is handled now


class _NoHttpListener:
    """Mixin: the node's HTTP server is made (Dask's code uses its application) but never listens."""

    def start_http_server(self, routes: Any, dashboard_address: Any, default_port: int = 0, ssl_options: Any = None) -> None:
        self.http_application = RoutingApplication(routes)
        self.http_server = HTTPServer(self.http_application)  # not listening: stop() has nothing to close


class QuietWorker(Worker):
    """A worker that ignores SIGINT (the process group's Ctrl-C is the command's to handle)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        with contextlib.suppress(ValueError):  # not the process's main thread: inherited SIG_IGN holds
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        super().__init__(*args, **kwargs)


class NoHttpWorker(_NoHttpListener, QuietWorker):
    """:class:`QuietWorker` without an HTTP listener."""


class NoHttpScheduler(_NoHttpListener, Scheduler):
    """A scheduler without an HTTP listener (no dashboard, no routes)."""


class QuietNanny(Nanny):
    """A nanny whose worker process runs :class:`QuietWorker`."""

    worker_cls: type = QuietWorker

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("worker_class", self.worker_cls)
        super().__init__(*args, **kwargs)


class NoHttpNanny(QuietNanny):
    """A nanny whose worker process runs :class:`NoHttpWorker`."""

    worker_cls = NoHttpWorker


class QuietLocalCluster(LocalCluster):
    """``LocalCluster`` with the scheduler class ``scheduler_cls`` (a class attribute: the cluster
    starts inside ``__init__``)."""

    scheduler_cls: type = Scheduler

    async def _start(self) -> None:
        self.scheduler_spec["cls"] = self.scheduler_cls
        await super()._start()


class NoHttpLocalCluster(QuietLocalCluster):
    """:class:`QuietLocalCluster` with :class:`NoHttpScheduler`."""

    scheduler_cls = NoHttpScheduler
