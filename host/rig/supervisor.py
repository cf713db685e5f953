"""Supervising a running ``ilcrig run``: the host and every other process until the host ends.

This module owns :class:`Supervisor`, the launcher's watch loop: it waits for the end of any
process of the run — the host, the other roles, the hub — on their pidfds (``poll``, woken by the
end itself; where the kernel has no pidfd, it looks every :data:`POLL_S`), and at least every
:data:`POLL_S` for a signal.  A process that ends meanwhile is noted as a
:class:`host.rig.processes.Death` — when, at most how long after its end (the wait it ended), and
where the run was (the trial and tick of :class:`host.rig.run_watch.RunProgress`) — and gives the
host a grace period to notice it on the bus and record it (the host's watchdog takes about three
heartbeat periods); a host that does not end by then is stopped (:meth:`Supervisor.stop_host`:
signal, wait, SIGKILL its group).  A node whose heartbeat nobody hears yet (``heard``: the
launcher's :class:`host.rig.liveness.LivenessWatch`; a node that died before its boot-up, or before
the host configured its heartbeat) cannot be noticed by the host, which would await its boot-up:
then the grace is :data:`UNHEARD_GRACE_S` (× ``ILCRIG_TIMEOUT_SCALE``), enough for a heartbeat
configured a moment ago, not the host's whole grace period in silence.  With a :class:`host.rig.liveness.StopWatch` it also looks,
every round, at which processes are stopped.  A signal to the launcher (:class:`host.rig.interrupts.Interrupts`)
ends the watch at once.  The CPU and wall time the watch took are kept.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus.cia301.nmt import HOST_NODE_ID
from bus.processes import killpg
from bus.units import timeout_scale
from host.rig.interrupts import Interrupts
from host.rig.processes import Child, Death, cpu_s, describe_status, node_id_of

logger = logging.getLogger(__name__)

__all__ = ["POLL_S", "UNHEARD_GRACE_S", "Supervisor"]

#: watch-loop period, s
POLL_S: float = 0.05
#: the host's grace after the end of a node whose heartbeat was not heard yet, s (× scale)
UNHEARD_GRACE_S: float = 3.0


@dataclass(eq=False)
class Supervisor:
    """Watches the processes of one run (see the module docstring).

    :param children: the role processes (the list the launcher keeps; the host among them)
    :param hub: the hub's handle (``alive``, ``pid``, ``process``), None without a hub
    :param hub_log: the hub's log file
    :param host_grace_s: how long the host gets to end after another process ended, or after a signal, s
    :param interrupts: the launcher's signal state
    :param where: the run's position now (:meth:`host.rig.run_watch.RunProgress.where`), or None
    :ivar deaths: the processes that ended while the host ran, in the order noticed
    :ivar host_stopped: the supervisor stopped the host after its grace period
    :ivar watch_cpu_s: CPU time (user+sys) the launcher used while watching, s
    :ivar watch_wall_s: wall time of the watch loop, s
    """

    children: list[Child]
    hub: Any
    hub_log: Path | None
    host_grace_s: float
    interrupts: Interrupts
    where: Callable[[], Any] | None = None
    #: looks at which processes are stopped (:class:`host.rig.liveness.StopWatch`), or None
    stops: Any = None
    #: whether a node's heartbeat is heard now (node id → bool; :meth:`host.rig.liveness.LivenessWatch.heard`), or None
    heard: Callable[[int], bool] | None = None
    deaths: list[Death] = field(default_factory=list, init=False)
    host_stopped: bool = field(default=False, init=False)
    watch_cpu_s: float = field(default=0.0, init=False)
    watch_wall_s: float = field(default=0.0, init=False)
    _pidfds: dict[int, int] = field(default_factory=dict, init=False, repr=False)
    #: the start of the wait a process end is noticed in
    _since: float = field(default_factory=time.monotonic, init=False, repr=False)

    def watch(self, host: Child) -> int:
        """Until the host ends (its exit code) or a signal comes (then -1). A process that ends
        meanwhile gives the host :attr:`host_grace_s` to record it; then the host is stopped."""
        cpu0, wall0 = cpu_s(), time.monotonic()
        deadline: float | None = None
        grace = self.host_grace_s
        self._since = wall0
        try:
            while True:
                if self.interrupts.signum is not None:  # first: the roles may fail because of the same Ctrl-C
                    return -1
                code = host.proc.poll()
                if code is not None:
                    self.note_deaths(host)
                    return code
                self.note_deaths(host)
                if self.stops is not None:
                    self.stops.look(self._running())
                if self.deaths and deadline is None:
                    grace = self._grace(self.deaths[0])
                    deadline = time.monotonic() + grace
                if deadline is not None and time.monotonic() > deadline:
                    logger.info("the host did not end within %.1f s of %s: stopping it", grace, self.deaths[0].describe())
                    self.host_stopped = True
                    return self.stop_host(host, signal.SIGTERM)
                self._wait(host)
        finally:
            self.watch_cpu_s, self.watch_wall_s = cpu_s() - cpu0, time.monotonic() - wall0
            logger.info("launcher used %.3f s CPU in %.1f s of watching", self.watch_cpu_s, self.watch_wall_s)
            for fd in self._pidfds.values():
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._pidfds.clear()

    def _grace(self, death: Death) -> float:
        """How long the host gets to notice ``death`` on the bus (module docstring), s."""
        node_id = node_id_of(death.name)
        if self.heard is None or node_id is None or node_id == HOST_NODE_ID or self.heard(node_id):
            return self.host_grace_s
        grace = min(self.host_grace_s, UNHEARD_GRACE_S * timeout_scale())
        logger.info("%s: its heartbeat was not heard yet; the host gets %.1f s to notice", death.describe(), grace)
        return grace

    def _wait(self, host: Child) -> None:
        """Up to :data:`POLL_S` for the end of a process of the run, on their pidfds: a process
        that ends wakes the wait (or ends it at once, if it ended just before), so an end noticed
        next happened after the wait returned (:attr:`_since`; the latency of a notice is bounded
        by the launcher's own steps since). Without pidfds: a sleep of :data:`POLL_S`, and the
        bound is from its start."""
        pids = [c.pid for c in self.children if c.proc.returncode is None]
        if self.hub is not None and self.hub.alive:
            pids.append(self.hub.pid)
        fds = [fd for fd in (self._pidfd(p) for p in pids) if fd is not None]
        if not fds:
            self._since = time.monotonic()
            time.sleep(POLL_S)
            return
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        poller.poll(1000 * POLL_S)
        self._since = time.monotonic()

    def _running(self) -> dict[str, int]:
        """Every process of the run still running (the hub included): name → pid."""
        procs = {c.name: c.pid for c in self.children if c.proc.returncode is None}
        if self.hub is not None and self.hub.alive:
            procs["hub"] = self.hub.pid
        return procs

    def _pidfd(self, pid: int) -> int | None:
        if pid not in self._pidfds:
            try:
                self._pidfds[pid] = os.pidfd_open(pid)
            except (AttributeError, OSError):
                return None  # no pidfds here, or the process is gone already (its end is seen by poll())
        return self._pidfds[pid]

    def note_deaths(self, host: Child) -> None:
        """Note every process (not the host) that ended since the last look, the hub included."""
        noted = {d.name for d in self.deaths}
        now = time.monotonic()
        latency = now - self._since
        where = self.where() if self.where is not None else None
        for c in self.children:
            if c is host or c.name in noted:
                continue
            code = c.proc.poll()
            if code is not None:
                self.deaths.append(Death(c.name, c.pid, describe_status(code), now, c.log_path, code, latency, where))
                logger.info("%s (pid %d) %s while the host was running", c.name, c.pid, describe_status(code))
        if self.hub is not None and "hub" not in noted and not self.hub.alive:
            code = self.hub.process.returncode
            self.deaths.append(Death("hub", self.hub.pid, describe_status(code), now, self.hub_log, code, latency, where))
            logger.info("the hub (pid %d) %s while the host was running", self.hub.pid, describe_status(code))

    def host_death(self, host: Child, code: int) -> Death:
        """The host's own end as a :class:`Death` (noticed now, in the current wait)."""
        now = time.monotonic()
        where = self.where() if self.where is not None else None
        return Death("host", host.pid, describe_status(code), now, host.log_path, code, now - self._since, where)

    def stop_host(self, host: Child, signum: int) -> int:
        """Signal the host alone and wait up to :attr:`host_grace_s` (a second signal: at once) for
        it to end; SIGKILL its group after that. Returns its exit code."""
        with contextlib.suppress(ProcessLookupError):
            os.kill(host.pid, signum)
        deadline = time.monotonic() + self.host_grace_s
        while host.proc.poll() is None and time.monotonic() < deadline and not self.interrupts.hurry:
            time.sleep(0.02)
        if host.proc.poll() is None:
            killpg(host.pid, signal.SIGKILL)
        return host.proc.wait()
