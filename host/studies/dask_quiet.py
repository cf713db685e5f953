"""The local cluster's Dask classes: quiet on the terminal, no HTTP listener unless asked.

This module owns :class:`QuietWorker` (a Dask worker that ignores SIGINT: Ctrl-C on the terminal is
the command's, which cancels the points and closes the cluster — no worker prints a traceback),
:class:`NoHttpWorker` and :class:`NoHttpScheduler` (their HTTP server is made but never listens:
Dask's scheduler would otherwise serve its HTTP routes on 8787 and every worker on a port of its
own, dashboard or not), the nannies that start those workers (:class:`QuietNanny`,
:class:`NoHttpNanny`) and :class:`QuietLocalCluster` (a ``LocalCluster`` whose scheduler class is
chosen).  Imported by :mod:`host.studies.engine` when a local cluster starts (it imports Dask);
the worker classes are module-level so the worker processes import them by name.

May import: ``distributed``, ``tornado`` (nothing of ilcrig).
"""

from __future__ import annotations

import contextlib
import signal
from typing import Any

from distributed import LocalCluster, Nanny, Scheduler, Worker
from distributed.http.routing import RoutingApplication
from tornado.httpserver import HTTPServer

__all__ = ["QuietWorker", "NoHttpWorker", "NoHttpScheduler", "QuietNanny", "NoHttpNanny", "QuietLocalCluster"]


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
