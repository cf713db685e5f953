"""The sweep engine: points run on Dask distributed, from a laptop to a cluster.

This module owns :class:`Engine` (the Dask client: a ``LocalCluster`` started here, or an existing
scheduler), :class:`PointQueue` (the one submit loop: points as tasks, their results written as they
complete, a lost point's error record) and :func:`run_points` (a resumable run of a list of points
with a progress bar).  It knows nothing of what a study does with the results.

* **Local** (default): ``LocalCluster`` (:mod:`host.studies.dask_quiet`) with one worker process
  per core (``workers``), one thread each, everything listening on 127.0.0.1 only; the dashboard
  (when its optional dependency bokeh is installed) on 127.0.0.1 too, its address logged and kept
  in :attr:`Engine.dashboard`.  Without a dashboard (``dashboard=False``) no process of the cluster
  opens an HTTP listener at all (Dask's scheduler would serve its HTTP routes on 8787 and every
  worker on a port of its own).  The workers ignore SIGINT: Ctrl-C on the terminal reaches this
  process only, which cancels the points and closes the cluster (no worker prints a traceback).
* **A cluster**: ``scheduler="tcp://HOST:PORT"`` connects to a running ``dask scheduler`` with
  ``dask worker`` processes (docs/sweeps.md: on a private network; the workers need ilcrig
  installed, not the sweep folder: results come back to this process).

A point is a task (:func:`host.studies.point.run_point`); its result is written here, atomically,
as soon as it arrives (:func:`host.studies.point.commit`).  A worker that dies takes no result with
it: the scheduler runs its points elsewhere (``distributed.scheduler.allowed-failures``), and a
point that kills every worker it lands on ends as that point's error.  A lost scheduler (its
connection gone) or a cluster without workers (none within ``wait_workers_s``, said on the
terminal) is :class:`ClusterLost`, never a point's error: :func:`run_points` and the tuner stop,
cancel what has not finished, keep every finished point and set :attr:`SweepOutcome.cluster_lost`
(``ilcrig`` exits with ``EXIT_CLUSTER_LOST``, 5).  Resume: a point whose folder holds its
finished run is not submitted (unless ``fresh``).  Ctrl-C or SIGTERM: what has
not finished is cancelled, the local cluster is closed (its worker processes end), every finished
point is kept, and :attr:`SweepOutcome.interrupted` is set.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus.errors import InputError
from host.experiment.signal_shield import interrupt_on_signals, signum_of
from host.studies.point import commit, is_finished, run_dir, run_point
from host.studies.spec import Point

logger = logging.getLogger(__name__)

__all__ = [
    "Engine",
    "ClusterLost",
    "WAIT_WORKERS_S",
    "SweepOutcome",
    "PointQueue",
    "run_points",
    "point_doc",
    "lost_point",
    "LOOPBACK",
    "dashboard_available",
]

#: the only address the processes this module starts listen on
LOOPBACK = "127.0.0.1"
#: seconds to wait for a scheduler given by address
CONNECT_TIMEOUT_S = 30.0
#: seconds to wait for a worker when the cluster has none (at the start or later), said on the terminal
WAIT_WORKERS_S = 60.0
#: seconds between two looks at the cluster (its connection, its workers) while waiting for a point
POLL_S = 1.0
#: the Dask task group of the points (the first element of their keys)
TASK_GROUP = "ilcrig-point"
#: Dask settings of the local cluster: a point is seconds of Python, so what Dask does in the
#: background on every process costs more than it gives — no statistical profiler (it samples the
#: running point's stack every 10 ms), no work stealing (the points are queued on the scheduler
#: and handed out as workers free up), the monitors (event-loop tick, system, memory) polled every
#: second or two instead of every 20–500 ms, and the workers' environment without Dask's
#: ``MALLOC_TRIM_THRESHOLD_`` (returning freed memory to the system at once costs a point's numpy
#: temporaries several per cent of its time) but with one BLAS thread per worker (one worker per core)
WORKER_CONFIG: dict[str, Any] = {
    "distributed.worker.profile.enabled": False,
    "distributed.scheduler.work-stealing": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.nanny.pre-spawn-environ": {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1},
}


class ClusterLost(Exception):  # noqa: N818 - what happened, not an error of the user's
    """The cluster is gone: the scheduler's connection lost, or no worker within the wait.
    ``str(exc)`` is the one line the command prints."""


def dashboard_available() -> bool:
    """True when Dask's dashboard can be served (its optional dependency bokeh is installed)."""
    return importlib.util.find_spec("bokeh") is not None


class Engine:
    """A Dask client for sweeps (module docstring); a context manager.

    :param workers: worker processes of the local cluster (default: the number of cores)
    :param scheduler: ``tcp://HOST:PORT`` of a running scheduler instead of a local cluster
    :param dashboard: serve the local cluster's dashboard on 127.0.0.1 (when bokeh is installed);
        ``"127.0.0.1:PORT"`` picks its port; False: no HTTP listener at all
    :param wait_workers_s: how long to wait for a worker when the cluster has none (s)
    """

    def __init__(
        self,
        workers: int | None = None,
        scheduler: str | None = None,
        dashboard: bool | str = True,
        wait_workers_s: float = WAIT_WORKERS_S,
    ) -> None:
        if workers is not None and workers < 1:
            raise InputError(f"--workers must be >= 1, got {workers}")
        if scheduler is not None and workers is not None:
            raise InputError("--workers starts a local cluster; with --scheduler the cluster's own workers run the points")
        if scheduler is not None and not scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
            raise InputError(f"--scheduler must be an address such as tcp://HOST:PORT, got {scheduler!r}")
        if isinstance(dashboard, str) and not dashboard.startswith(("127.", "localhost")):
            raise InputError(f"--dashboard {dashboard!r}: the dashboard listens on loopback only (127.0.0.1:PORT)")
        if not wait_workers_s > 0:
            raise InputError(f"--wait-workers must be > 0 s, got {wait_workers_s}")
        self.wait_workers_s = float(wait_workers_s)
        self.workers = workers if workers is not None else (os.cpu_count() or 1)
        self.scheduler = scheduler
        self.dashboard_option = dashboard
        self.dashboard: str | None = None
        self.cluster: Any = None
        self.client: Any = None
        self._log_levels: dict[str, int] = {}

    def __enter__(self) -> Engine:
        try:
            self.start()
        except BaseException:  # a signal or an error while the cluster starts: none of it is left
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Start the local cluster, or connect to the scheduler."""
        from distributed import Client

        from host.studies.dask_quiet import quiet_dask_logs

        quiet_dask_logs(self._log_levels)  # Dask's log lines are not the user's business
        if self.scheduler is not None:
            try:
                self.client = Client(self.scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise InputError(f"--scheduler {self.scheduler}: cannot connect ({exc})") from None
            self.dashboard = self._link()
            return
        import dask

        serve = dashboard_available() and self.dashboard_option is not False
        address = self.dashboard_option if isinstance(self.dashboard_option, str) else f"{LOOPBACK}:0"
        from host.studies.dask_quiet import (
            NoHttpLocalCluster,
            NoHttpNanny,
            QuietLocalCluster,
            QuietNanny,
            dask_log_level,
            sigint_ignored,
        )

        http = self.dashboard_option is not False  # --no-dashboard: no HTTP listener at all
        cluster_cls, nanny_cls = (QuietLocalCluster, QuietNanny) if http else (NoHttpLocalCluster, NoHttpNanny)
        # the worker processes are spawned with SIGINT ignored (inherited): Ctrl-C is this process's
        with sigint_ignored(), dask.config.set(WORKER_CONFIG):
            self.cluster = cluster_cls(
                n_workers=self.workers,
                threads_per_worker=1,
                processes=True,
                host=LOOPBACK,
                worker_class=nanny_cls,
                dashboard_address=address if serve else None,
                silence_logs=dask_log_level(),  # the workers' log level (their stderr is the terminal's)
            )
        quiet_dask_logs(self._log_levels)  # the cluster set the level of this process's Dask loggers
        self.client = Client(self.cluster, set_as_default=False)
        self.dashboard = self._link() if serve else None

    def await_workers(self) -> None:
        """Return when the cluster has a worker; without one, say so on the terminal and wait up to
        :attr:`wait_workers_s`.

        :raises ClusterLost: no worker came (or the scheduler went away)."""
        if self.n_workers:
            return
        sys.stderr.write(f"ilcrig: {self.name()} has no workers; waiting up to {self.wait_workers_s:.0f} s for one\n")
        deadline = time.monotonic() + self.wait_workers_s
        while time.monotonic() < deadline:
            if self.client is None or self.client.status not in ("running", "newly-created"):
                raise ClusterLost(f"lost the connection to the scheduler {self.scheduler or 'of the local cluster'}")
            if self.n_workers:
                return
            time.sleep(0.5)
        raise ClusterLost(f"no worker joined {self.name()} within {self.wait_workers_s:.0f} s")

    def _link(self) -> str | None:
        try:
            link = self.client.dashboard_link
        except Exception:  # noqa: BLE001 - a scheduler without a dashboard
            return None
        return str(link) if link else None

    @property
    def n_workers(self) -> int:
        """Workers connected now (0 when the scheduler cannot be asked)."""
        if self.client is None:
            return 0
        try:
            return len(self.client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # noqa: BLE001 - a lost scheduler has no workers
            return 0

    def describe(self) -> str:
        """One line: where the points run."""
        if self.scheduler is not None:
            return f"the cluster at {self.scheduler} ({self.n_workers} workers)"
        return f"a local cluster of {self.workers} worker process(es) on {LOOPBACK}"

    def name(self) -> str:
        """The cluster in a few words: ``the cluster at ADDRESS`` or ``the local cluster``."""
        return f"the cluster at {self.scheduler}" if self.scheduler is not None else "the local cluster"

    def lost(self) -> str | None:
        """Why the cluster is gone (the client's connection to the scheduler lost), or None."""
        if self.client is None:
            return "the cluster was closed"
        if self.client.status in ("running", "newly-created"):
            return None
        return f"lost the connection to the scheduler {self.scheduler or 'of the local cluster'}"

    def submit(self, fn: Callable[..., Any], *args: Any, key: tuple[str, ...], priority: int = 0) -> Any:
        """Submit one task (``pure=False``: a point is run when asked).  Keys are tuples
        (:data:`TASK_GROUP`, point id, …): every point is in one task group, so the scheduler
        queues them and hands them out in priority order as workers free up."""
        return self.client.submit(fn, *args, key=key, pure=False, priority=priority, retries=1)

    def close(self) -> None:
        """Close the client and the local cluster (its worker processes end); never raises."""
        for what in (self.client, self.cluster):
            if what is None:
                continue
            try:
                what.close()
            except Exception:  # noqa: BLE001 - closing must not hide the outcome
                logger.debug("closing %s failed", what, exc_info=True)
        self.client = self.cluster = None
        for name, level in self._log_levels.items():
            logging.getLogger(name).setLevel(level)
        self._log_levels = {}


@dataclass
class SweepOutcome:
    """What :func:`run_points` did: point ids run, skipped (finished before), failed (id → why);
    ``cluster_lost``: why the cluster went away (the points not finished were not run)."""

    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    errors: dict[str, str] = field(default_factory=dict)
    #: the signal that interrupted it (SIGINT for Ctrl-C, SIGTERM); None: not interrupted
    signum: int | None = None
    cluster_lost: str | None = None
    wall_s: float = 0.0

    @property
    def interrupted(self) -> bool:
        """A signal ended it (:attr:`signum`)."""
        return self.signum is not None


#: the function a worker runs for a point (a test may put a wrapper in its place)
POINT_FUNCTION: Callable[[str, dict[str, Any], bool], dict[str, Any]] = run_point


def point_doc(p: Point) -> dict[str, Any]:
    """What ``point.json`` says about ``p`` (besides the result)."""
    return {"index": p.index, "labels": p.labels, "options": p.options, "config": p.config.as_dict()}


def lost_point(p: Point, exc: BaseException) -> dict[str, Any]:
    """The result of a point whose task raised instead of returning one (``KilledWorker``: the
    point ended every worker it landed on; cancelled): the point's error record."""
    return {"id": p.id, "error": f"{type(exc).__name__}: {exc}", "summary": None, "wall_s": 0.0}


class PointQueue:
    """The engine's one submit loop: points submitted as tasks (any time, also while others run),
    their results taken as they complete — each written into the sweep folder (:func:`commit`)
    before it is handed back — and tasks dropped or cancelled.  :func:`run_points` and the tuner
    (:mod:`host.studies.tune`) run their points through it.

    :param save_errors: the points keep their error arrays (``errors.npy``)
    """

    def __init__(self, engine: Engine, out: Path, *, save_errors: bool = False) -> None:
        from distributed import as_completed

        self.engine, self.out, self.save_errors = engine, Path(out), save_errors
        self._pending: dict[Any, tuple[Point, dict[str, Any], Any]] = {}
        self._completed = as_completed([], loop=engine.client.loop)

    def __len__(self) -> int:
        """Points submitted and not yet taken (or dropped)."""
        return len(self._pending)

    def submit(
        self, p: Point, *, tag: str | None = None, priority: int = 0, doc: dict[str, Any] | None = None, owner: Any = None
    ) -> Any:
        """Submit point ``p`` (its key: :data:`TASK_GROUP`, its id and ``tag``); ``doc`` is what its
        ``point.json`` says besides the result (default :func:`point_doc`); ``owner`` comes back with
        its result (the tuner's trial).  Returns its future."""
        key = (TASK_GROUP, p.id) if tag is None else (TASK_GROUP, p.id, tag)
        fut = self.engine.submit(POINT_FUNCTION, p.id, p.options, self.save_errors, key=key, priority=priority)
        self._pending[fut] = (p, point_doc(p) if doc is None else doc, owner)
        self._completed.add(fut)
        return fut

    def _next_done(self) -> Any:
        """The next completed future, looking at the cluster every :data:`POLL_S` s meanwhile.

        :raises ClusterLost: the scheduler's connection lost, or no worker for ``wait_workers_s``."""
        from distributed import wait

        engine = self.engine
        no_workers_since: float | None = None
        said = False
        while True:
            if self._completed.has_ready():
                return next(self._completed)
            why = engine.lost()
            if why is not None:
                raise ClusterLost(why)
            if engine.n_workers:
                no_workers_since = None
            elif no_workers_since is None:
                no_workers_since = time.monotonic()
            elif not said and time.monotonic() - no_workers_since > 2.0:  # a local worker restarting takes ~1 s
                said = True
                sys.stderr.write(f"ilcrig: {engine.name()} has no workers; waiting up to {engine.wait_workers_s:.0f} s for one\n")
            elif time.monotonic() - no_workers_since > engine.wait_workers_s:
                raise ClusterLost(f"{engine.name()} has had no workers for {engine.wait_workers_s:.0f} s")
            if not self._pending:
                time.sleep(0.01)
                continue
            try:  # returns as soon as one completes (then as_completed has it a moment later)
                wait(list(self._pending), timeout=POLL_S, return_when="FIRST_COMPLETED")
                time.sleep(0.002)
            except TimeoutError:
                pass
            except Exception:  # noqa: BLE001 - the client going away: engine.lost() says so next
                logger.debug("waiting for the points failed", exc_info=True)
                time.sleep(0.1)

    def next(self) -> tuple[Point, dict[str, Any], Any]:
        """Wait for the next point to complete: the point, its result (:func:`run_point`'s, or
        :func:`lost_point`'s), written into its folder, and its ``owner``.  Tasks dropped meanwhile
        are skipped.

        :raises ClusterLost: the cluster went away (the point's task cancelled with it: not its error)."""
        from distributed.client import FutureCancelledError

        while True:
            fut = self._next_done()
            if fut not in self._pending:
                continue  # dropped
            p, doc, owner = self._pending[fut]
            try:
                result = fut.result()
            except FutureCancelledError as exc:  # not by us (ours are dropped first): the scheduler went away
                raise ClusterLost(self.engine.lost() or f"the cluster cancelled the points ({exc})") from None
            except Exception as exc:  # noqa: BLE001 - KilledWorker (the point ended every worker)
                result = lost_point(p, exc)
            del self._pending[fut]
            fut.release()
            commit(self.out, p.id, doc, result)
            return p, result, owner

    def drop(self, futures: Sequence[Any]) -> None:
        """Forget these tasks and cancel them (a pruned trial's points)."""
        for f in futures:
            if self._pending.pop(f, None) is not None:
                with contextlib.suppress(Exception):
                    f.cancel()

    def cancel(self) -> None:
        """Cancel every task not taken yet (a task running on a worker of another's cluster runs on;
        its result is dropped)."""
        futures = list(self._pending)
        self._pending.clear()
        if not futures or self.engine.client is None:
            return
        try:
            self.engine.client.cancel(futures, force=True)
        except Exception:  # noqa: BLE001 - the cluster may be going away
            logger.debug("cancelling failed", exc_info=True)


def run_points(
    engine: Engine,
    out: Path,
    points: Sequence[Point],
    *,
    save_errors: bool = False,
    fresh: bool = False,
    progress: bool = True,
    desc: str = "sweep",
    on_result: Callable[[Point, dict[str, Any]], None] | None = None,
) -> SweepOutcome:
    """Run the points of ``points`` not finished in sweep folder ``out`` (all of them if ``fresh``),
    in their order (the first ones first), writing each result as it arrives.

    Ctrl-C / SIGTERM while it runs: cancels what has not finished and returns with
    ``interrupted`` (the caller closes the engine, which ends a local cluster's workers)."""
    from tqdm import tqdm

    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    outcome = SweepOutcome()
    todo: list[Point] = []
    for p in points:
        if not fresh and is_finished(run_dir(out, p.id), p.config, save_errors):
            outcome.skipped.append(p.id)
        else:
            todo.append(p)
    logger.info("%s: %d points, %d finished before, %d to run", desc, len(points), len(outcome.skipped), len(todo))
    if not todo:
        return outcome
    t0 = time.perf_counter()
    try:
        with interrupt_on_signals():
            engine.await_workers()
    except ClusterLost as exc:
        outcome.cluster_lost = str(exc)
        return outcome
    except KeyboardInterrupt as exc:
        outcome.signum = signum_of(exc)
        return outcome
    bar = tqdm(total=len(todo), desc=desc, unit="pt", file=sys.stderr, disable=not progress, dynamic_ncols=True)
    queue = PointQueue(engine, out, save_errors=save_errors)
    try:
        with interrupt_on_signals():
            try:
                for i, p in enumerate(todo):  # the first points first (reproduce: the slowest)
                    queue.submit(p, priority=len(todo) - i)
                while len(queue):
                    p, result, _ = queue.next()
                    outcome.ran.append(p.id)
                    if result.get("error"):
                        outcome.errors[p.id] = str(result["error"])
                        bar.write(f"ilcrig {desc}: {p.id} could not run: {result['error']}", file=sys.stderr)
                    if on_result is not None:
                        on_result(p, result)
                    bar.set_postfix_str(p.id, refresh=False)
                    bar.update(1)
            except KeyboardInterrupt as exc:
                outcome.signum = signum_of(exc)
                queue.cancel()
            except ClusterLost as exc:
                outcome.cluster_lost = str(exc)
                queue.cancel()
    finally:
        bar.close()
        outcome.wall_s = time.perf_counter() - t0
    return outcome
