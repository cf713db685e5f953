"""The launch core of ``ilcrig run`` and ``ilcrig robot``: what both launchers do alike.

This module owns :class:`LaunchCore`, the base of :class:`host.rig.launcher.RigLauncher` and
:class:`host.rig.robot_launcher.RobotLauncher`, with

* the run skeleton (:meth:`LaunchCore.run`): the interrupts installed (:mod:`host.rig.interrupts`),
  the launcher's own steps (``_launch_and_watch``), a :class:`host.rig.processes.LaunchError` as one
  line and exit code 4, and on *every* path the shutdown (:meth:`LaunchCore.shutdown`) and the
  launcher's closing step (``_closing``, with the exit code: 1 when the launcher itself failed);
* spawning: the hub (:func:`host.rig.processes.start_hub_process`) and the roles
  (:func:`host.rig.processes.spawn`, i.e. :func:`bus.processes.spawn_process`: one lifetime policy —
  a session of its own, SIGKILL when the launcher dies — for every process started);
* the scheduling of a real-time run or robot (:meth:`LaunchCore.schedule_realtime`): the lockstep
  processes in ``SCHED_FIFO`` where permitted, else the fair-scheduling fallback
  (:mod:`host.rig.fair_scheduling`) with, when there is a host, its policy; the idle-poll loops
  (:mod:`host.rig.idle_poll`) beside SCHED_FIFO only; idle CPUs kept out of halt where permitted
  (:mod:`host.rig.cpu_latency`); the mechanisms in force, for the summary;
* the janitor of the run folder (:mod:`host.rig.janitor`), when the launcher starts one;
* the shutdown: idle-poll loops stopped, the CPU latency request withdrawn, the launcher's watchers
  stopped, every child terminated (SIGTERM, grace, SIGKILL, reaped:
  :func:`host.rig.processes.terminate`), the hub stopped, the run folder settled and the janitor
  dismissed;
* the terminal lines (:class:`LauncherConsole`) and the run folder (:func:`make_run_folder`).

May import: bus, host.rig (the modules above), host.experiment (through them).
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from bus.errors import InputError
from bus.exit_codes import EXIT_CHILD_FAILED, EXIT_ERROR
from bus.lockstep_process import mechanisms_left_out
from bus.processes import DEFAULT_DEATH_SIGNAL
from bus.timer_slack import FINE_TIMER_SLACK_NS
from host.rig.cpu_latency import CpuLatencyRequest, request_cpu_latency
from host.rig.fair_scheduling import host_policy
from host.rig.idle_poll import AUTOGROUP_NICE, IdlePollers, idle_poll_available
from host.rig.interrupts import Interrupts
from host.rig.options import RigOptions
from host.rig.processes import Child, LaunchError, spawn, start_hub_process, terminate
from host.rig.realtime import DEFAULT_RT_PRIORITY, schedule_lockstep, scheduling_mechanisms

__all__ = ["TERMINATE_GRACE_S", "LaunchCore", "LauncherConsole", "make_run_folder"]

logger = logging.getLogger(__name__)

#: how long children get after SIGTERM before SIGKILL, s
TERMINATE_GRACE_S: float = 3.0


class LauncherConsole:
    """A launcher's two terminal streams: its lines go to ``stdout`` / ``stderr`` when given, else
    to ``sys.stdout`` / ``sys.stderr`` of the moment, each line flushed at once."""

    stdout: IO[str] | None
    stderr: IO[str] | None

    def _say_out(self, text: str) -> None:
        stream = self.stdout or sys.stdout
        stream.write(text + "\n")
        stream.flush()

    def _say_err(self, text: str) -> None:
        stream = self.stderr or sys.stderr
        stream.write(text + "\n")
        stream.flush()


def make_run_folder(out: str | None, kind: str) -> tuple[Path, Path]:
    """The run folder ``out`` (None: ``runs/<kind>-<local time>``) and its ``logs`` folder, both
    created; returns (run folder, logs folder).

    :raises ValueError: the folder cannot be created (one line naming ``--out``)
    """
    from host.experiment.outputs import default_run_folder

    out_dir = Path(out) if out is not None else default_run_folder(kind, claim=True)
    log_dir = out_dir / "logs"
    try:
        log_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"--out {out_dir}: cannot create the run folder: {err.strerror or err}") from err
    return out_dir, log_dir


def check_transport(options: RigOptions) -> None:
    """The transport of ``ilcrig run`` / ``ilcrig robot`` checked before any process starts
    (:meth:`bus.transports.config.TransportConfig.check_usable`: one that this machine cannot
    carry between processes, conflicting options, a hub socket folder that is missing or not the
    user's, a socket file there that is another user's).

    :raises bus.errors.InputError: one line naming the option
    """
    from bus.transports.config import transport_from_name

    tc = transport_from_name(options.bus, options.hub, options.allow_remote)
    tc.check_usable(hub_given=options.hub is not None)


@dataclass(eq=False)
class LaunchCore(LauncherConsole):
    """What ``ilcrig run`` and ``ilcrig robot`` share (module docstring).

    A launcher defines ``_launch_and_watch() -> int`` and may override the hooks ``_launch_failed``,
    ``_stop_watchers``, ``_children_ended``, ``_close_watchers`` and ``_closing``.

    :param options: the launcher's options
    :param stdout: stream of the launcher's lines (default ``sys.stdout``)
    :param stderr: stream of error / exit messages (default ``sys.stderr``)
    :param grace_s: SIGTERM → SIGKILL grace period, s
    :ivar children: every started role process, in start order
    :ivar hub: the hub handle while it runs
    :ivar hub_address: the hub's address (None without a hub)
    :ivar out_dir: the run folder
    """

    options: RigOptions
    stdout: IO[str] | None = None
    stderr: IO[str] | None = None
    grace_s: float = TERMINATE_GRACE_S
    children: list[Child] = field(default_factory=list, init=False)
    hub: Any = field(default=None, init=False)
    hub_address: str | None = field(default=None, init=False)
    out_dir: Path | None = field(default=None, init=False)
    interrupts: Interrupts = field(default_factory=Interrupts, init=False)
    _idle_pollers: IdlePollers | None = field(default=None, init=False, repr=False)
    _cpu_latency: CpuLatencyRequest | None = field(default=None, init=False, repr=False)
    _janitor: Any = field(default=None, init=False, repr=False)

    # -- the skeleton ---------------------------------------------------------------------------

    def run(self) -> int:
        """Launch, watch, clean up (on every path); the exit code."""
        self.interrupts.install()
        code = EXIT_CHILD_FAILED
        try:
            try:
                code = self._launch_and_watch()
            except LaunchError as err:
                self._launch_failed(err)
                self._say_err(f"ilcrig: error: {err}")
                code = EXIT_CHILD_FAILED
            except BaseException:
                code = EXIT_ERROR  # an internal error: the command line reports it (exit 1); the summary says so
                raise
            finally:
                self.shutdown()
                self._closing(code)
        finally:
            self.interrupts.restore()
        return code

    def _launch_and_watch(self) -> int:  # pragma: no cover - every launcher has its own
        raise NotImplementedError

    def _launch_failed(self, err: LaunchError) -> None:
        """Hook: a process could not be started (before the error line)."""

    def _stop_watchers(self) -> None:
        """Hook: stop what watches the children, before they are terminated."""

    def _children_ended(self) -> None:
        """Hook: every child was reaped (the hub still runs)."""

    def _close_watchers(self) -> None:
        """Hook: close what reads the bus, before the hub stops (on every path)."""

    def _closing(self, code: int) -> None:
        """Hook: after the shutdown, with the exit code (on every path)."""

    # -- interrupts -----------------------------------------------------------------------------

    def say_interrupted(self) -> int:
        """SIGINT / SIGTERM / SIGHUP came: the one line that says so (the signal, how many processes
        are being stopped: the hub and every role started so far) on stderr, as ``ilcrig run`` and
        ``ilcrig robot`` both say it; the exit code the signal calls for (130, 143, 129)."""
        self._say_err(f"ilcrig: interrupted ({self.interrupts.name}); stopping {len(self.lockstep_pids())} processes")
        return self.interrupts.exit_code()

    # -- spawning -------------------------------------------------------------------------------

    def start_hub(self, inject: str | None, log_path: Path, bus_time: dict[str, int] | None = None) -> str:
        """Start the hub on ``--hub`` (or a fresh private socket); its address."""
        self.hub = start_hub_process(self.options.hub, inject, log_path, bus_time=bus_time)
        self.hub_address = str(self.hub.address)
        return self.hub_address

    def spawn(
        self,
        name: str,
        argv: list[str],
        log_path: Path | None,
        *,
        stderr_only: bool = False,
        batch: bool = False,
        death_signal: int = DEFAULT_DEATH_SIGNAL,
    ) -> Child:
        """Start one role (:func:`host.rig.processes.spawn`) and keep it among :attr:`children`."""
        child = spawn(name, argv, log_path, stderr_only=stderr_only, batch=batch, death_signal=death_signal)
        self.children.append(child)
        return child

    def start_janitor(self, host_pid: int, robot: bool = False) -> None:
        """The run folder's janitor, watching ``host_pid`` (``robot``: the robot's plant; :mod:`host.rig.janitor`)."""
        from host.rig.janitor import start_janitor

        if self.out_dir is not None:
            self._janitor = start_janitor(self.out_dir, host_pid, robot)

    def lockstep_pids(self) -> dict[str, int]:
        """The hub (if any) and every child started so far: name → pid."""
        return ({"hub": self.hub.pid} if self.hub is not None else {}) | {c.name: c.pid for c in self.children}

    def pids_text(self) -> str:
        """``hub 12, plant 13, drive1 14 …`` for the launcher's status line."""
        return ", ".join(f"{name} {pid}" for name, pid in self.lockstep_pids().items())

    # -- real time ------------------------------------------------------------------------------

    def schedule_realtime(self, host_in_tick: bool | None = None) -> dict[str, Any]:
        """The scheduling of a real-time run, for the processes started so far (the lockstep ones):
        ``SCHED_FIFO`` where permitted, else normal scheduling with what an unprivileged process may
        use (:func:`host.rig.realtime.schedule_lockstep`); with a host to come (``host_in_tick`` not
        None: whether it is part of every tick), its policy (:func:`host.rig.fair_scheduling.host_policy`);
        the idle-poll loops; idle CPUs kept out of halt (:mod:`host.rig.cpu_latency`, where permitted).

        :return: the scheduling record (``bench.timing.scheduling`` of a run's summary, ``scheduling`` of the robot's)
        """
        without = mechanisms_left_out()
        priority = DEFAULT_RT_PRIORITY if self.options.rt_priority is None else self.options.rt_priority
        scheduling = schedule_lockstep(self.lockstep_pids(), priority, without)
        fifo = scheduling["policy"] == "SCHED_FIFO"
        if not fifo and host_in_tick is not None:
            scheduling["host"] = host_policy(host_in_tick, without)
        scheduling["idle_poll"] = self._start_idle_poll(fifo, without)
        if self._cpu_latency is not None:  # scheduled again: one request per launcher
            self._cpu_latency.release()
        self._cpu_latency, scheduling["cpu_latency"] = request_cpu_latency(without, self.options.no_idle_poll)
        scheduling["in_roles"] = {"heap_frozen": "gc" not in without, "timer_slack_ns": FINE_TIMER_SLACK_NS}
        scheduling["mechanisms"] = scheduling_mechanisms(scheduling)
        return scheduling

    def _start_idle_poll(self, fifo: bool, without: frozenset[str]) -> dict[str, Any]:
        """Keep the CPUs awake (:mod:`host.rig.idle_poll`), unless ``--no-idle-poll`` or the lockstep
        processes are in normal scheduling (the loops would compete with them: "Only beside SCHED_FIFO").

        :return: for the scheduling record: ``{"loops": n}``, or ``{"loops": 0, "reason": ...}``
        """
        if self.options.no_idle_poll:
            return {"loops": 0, "reason": "--no-idle-poll"}
        if not fifo and "idle-poll-fifo-only" not in without:
            return {"loops": 0, "reason": "not beside normal scheduling"}
        if not idle_poll_available():
            return {"loops": 0, "reason": "this system has no SCHED_IDLE"}
        try:
            self._idle_pollers = IdlePollers(autogroup_nice=None if "idle-nice" in without else AUTOGROUP_NICE)
        except OSError as err:
            logger.warning("cannot start the idle-poll loops: %s", err)
            return {"loops": 0, "reason": f"could not start them ({err.strerror or err})"}
        return {"loops": len(self._idle_pollers.pids)}

    # -- shutdown -------------------------------------------------------------------------------

    def shutdown(self) -> None:
        """Stop the idle-poll loops, withdraw the CPU latency request and stop the watchers, terminate
        every child, stop the hub, settle the run folder (when a janitor watches it) and dismiss the janitor."""
        self.interrupts.stopping = True
        try:
            if self._cpu_latency is not None:  # first: nothing below can keep it
                self._cpu_latency.release()
            if self._idle_pollers is not None:
                self._idle_pollers.stop()
            self._stop_watchers()
            terminate(self.children, self.grace_s, lambda: self.interrupts.hurry)
            self._children_ended()
        finally:
            try:
                self._close_watchers()
            finally:
                try:
                    if self.hub is not None:
                        try:
                            self.hub.stop()
                        finally:
                            self.hub = None
                finally:
                    self._dismiss_janitor()

    def _dismiss_janitor(self) -> None:
        if self._janitor is None:
            return
        if self.out_dir is not None and not self._janitor.robot:
            from host.rig.janitor import settle_run_folder

            settle_run_folder(self.out_dir)  # every path: also a launch that failed half way
        self._janitor.done()
        self._janitor = None
