"""The role processes of ``ilcrig run`` as OS processes: started, described, stopped.

This module owns

* :func:`spawn` — start one role with the lifetime policy of :func:`bus.processes.spawn_process`
  (its own session, so its whole process group can be signalled; ``PR_SET_PDEATHSIG`` = SIGKILL,
  so it dies with the launcher; stdin closed) and its output in its log file (:class:`Child`);
* :class:`Death` — a process that ended while the host ran, with how and when it was noticed;
* :func:`start_hub_process` — the bus hub (:func:`bus.transports.hub.process.start_hub`, a
  session of its own: a terminal's Ctrl-C reaches the launcher only), its stderr in its log;
* :func:`terminate` — SIGTERM every child's process group, wait a grace period, SIGKILL, reap;
* small helpers: an exit status in words (:func:`describe_status`), the last lines of a log
  (:func:`tail`), a role's node id (:func:`node_id_of`), the launcher's CPU time (:func:`cpu_s`).
"""

from __future__ import annotations

import logging
import os
import resource
import shlex
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bus.cia301.nmt import HOST_NODE_ID
from bus.plant_objects import DEFAULT_PLANT_NODE_ID
from bus.processes import DEFAULT_DEATH_SIGNAL, killpg, spawn_process

logger = logging.getLogger(__name__)

__all__ = [
    "Child",
    "Death",
    "LaunchError",
    "cpu_s",
    "describe_status",
    "node_id_of",
    "spawn",
    "start_hub_process",
    "tail",
    "terminate",
]


class LaunchError(RuntimeError):
    """A role process or the hub could not be started.

    :ivar name: which (``hub``, ``plant``, ``drive1`` … ``drive4``, ``host``; None: not known)
    """

    def __init__(self, message: str, name: str | None = None) -> None:
        super().__init__(message)
        self.name = name


@dataclass
class Child:
    """One started role process.

    :ivar name: ``host``, ``plant``, ``drive1`` … ``drive4``
    :ivar log_path: where its output goes (the host: its stderr only; None: the launcher's terminal)
    """

    name: str
    proc: subprocess.Popen[bytes]
    argv: list[str]
    log_path: Path | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid


@dataclass
class Death:
    """A process of the run that ended while the host ran (or the host itself).

    :ivar t_mono: when the launcher noticed it, ``time.monotonic()``
    :ivar latency_s: at most how long after its end the launcher noticed it, s (None: not known)
    :ivar where: the io channel's position then (a :class:`host.rig.run_watch.Where`), if followed
    """

    name: str
    pid: int
    status: str
    t_mono: float
    log_path: Path | None
    returncode: int
    latency_s: float | None = None
    where: Any = None

    def describe(self) -> str:
        where = f"; its log: {self.log_path}" if self.log_path else ""
        return f"{self.name} (pid {self.pid}) {self.status}{where}"


def node_id_of(name: str) -> int | None:
    """The node id of a role (``drive2`` → 2, ``plant``, ``host``), None for others (``hub``)."""
    if name.startswith("drive") and name[5:].isdigit():
        return int(name[5:])
    return {"plant": DEFAULT_PLANT_NODE_ID, "host": HOST_NODE_ID}.get(name)


def describe_status(code: int) -> str:
    """``exited with code N`` or ``was killed by SIGNAME`` for a Popen return code."""
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


def tail(path: Path | None, n: int) -> list[str]:
    """The last ``n`` non-blank lines of the file (its last 8 KiB), [] if unreadable."""
    if path is None:
        return []
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - 8192))
            lines = fh.read().decode(errors="replace").splitlines()
    except OSError:
        return []
    return [ln for ln in lines if ln.strip()][-n:]


def cpu_s() -> float:
    """CPU time (user + system) this process used so far, s."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def spawn(
    name: str,
    argv: list[str],
    log_path: Path | None,
    *,
    stderr_only: bool = False,
    batch: bool = False,
    death_signal: int = DEFAULT_DEATH_SIGNAL,
) -> Child:
    """Start one role (see the module docstring).

    :param log_path: its stdout and stderr go here (None: the launcher's)
    :param stderr_only: only its stderr goes to the log, its stdout to the launcher's (the host)
    :param batch: start it in ``SCHED_BATCH`` (its threads inherit it; a real-time run's host,
        :mod:`host.rig.fair_scheduling`)
    :raises LaunchError: it could not be started
    """
    log = open(log_path, "ab") if log_path is not None else None  # noqa: SIM115 - closed below
    try:
        proc = spawn_process(
            argv,
            stdout=None if stderr_only else log,
            stderr=log if stderr_only else (subprocess.STDOUT if log is not None else None),
            batch=batch,
            death_signal=death_signal,
        )
    except OSError as err:
        raise LaunchError(f"cannot start {name} ({shlex.join(argv[:4])} …): {err}", name) from err
    finally:
        if log is not None:
            log.close()  # the child has its own descriptor
    logger.debug("started %s pid %d: %s", name, proc.pid, shlex.join(argv))
    return Child(name, proc, argv, log_path)


def start_hub_process(
    address: str | None, inject: str | None = None, log_path: Path | None = None, bus_time: dict[str, int] | None = None
) -> Any:
    """Start the bus hub (see the module docstring); returns its handle.

    :param address: where it listens (None: ``hub.sock`` in a fresh private temp dir)
    :param inject: its frame faults (JSON, ``--inject`` of the hub)
    :param log_path: its stderr goes here
    :param bus_time: logical bus → bit rate, bit/s (``--bus-time``)
    :raises LaunchError: it did not start
    :raises ValueError: a bad address
    """
    from bus.transports.hub.process import start_hub
    from bus.transports.hub.wire import HubError

    # The hub is in a session of its own (bus.processes.spawn_process): a terminal Ctrl-C reaches
    # only the launcher, and the hub lives until the roles are stopped (then stdin EOF stops it).
    log = open(log_path, "ab") if log_path is not None else None  # noqa: SIM115 - closed below
    try:
        hub = start_hub(address, inject=inject, stderr=log, bus_time=bus_time)
    except HubError as err:
        if isinstance(err, ValueError):
            raise
        raise LaunchError(f"cannot start the bus hub{f' on {address}' if address else ''}: {err}", "hub") from err
    finally:
        if log is not None:
            log.close()  # the hub has its own descriptor
    logger.info("hub pid %d on %s", hub.pid, hub.address)
    return hub


def terminate(children: Sequence[Child], grace_s: float, hurry: Callable[[], bool]) -> None:
    """SIGTERM every child's process group (SIGCONT too: a stopped process must run to see it),
    wait up to ``grace_s`` seconds (less once ``hurry()`` is true), SIGKILL the groups, reap."""
    if not children:
        return
    for c in children:
        if c.proc.returncode is None:
            killpg(c.pid, signal.SIGTERM)
            killpg(c.pid, signal.SIGCONT)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and not hurry():
        if all(c.proc.poll() is not None for c in children):
            break
        time.sleep(0.02)
    for c in children:
        if c.proc.poll() is None:
            logger.info("%s (pid %d) ignored SIGTERM for %.1f s: SIGKILL", c.name, c.pid, grace_s)
        killpg(c.pid, signal.SIGKILL)  # also any process a role left behind in its group
    for c in children:
        c.proc.wait()
        logger.debug("%s (pid %d) reaped: %s", c.name, c.pid, describe_status(c.proc.returncode))
