"""``ilcrig run``: check the experiment, start the distributed rig, watch it, always clean it up.

This module owns :func:`launch_rig` and :class:`RigLauncher`, which puts the run's processes
together (its terminal lines, :class:`LauncherConsole`, and its run folder, :func:`make_run_folder`,
serve ``ilcrig robot`` too):

* the bus hub (only when the transport is ``hub``), started with :func:`bus.transports.hub.process.start_hub` on a
  fresh private Unix socket (a temp directory per run, so concurrent runs never collide) unless
  ``--hub ADDR`` names the address it must listen on;
* the plant (``ilcrig plant``), four drives (``ilcrig drive --node 1..4``) and the host
  (``ilcrig host <the same experiment options> --out DIR``), each started as
  ``[sys.executable, "-P", "-m", "host.cli", ROLE, ...]`` with the same ``--bus``/``--hub``
  (:mod:`host.rig.role_commands`; ``-P``: the working folder cannot shadow the project's modules,
  the hub is started the same way) as processes of their own
  (:mod:`host.rig.processes`);
* with ``--realtime``, SCHED_FIFO for the lockstep processes (:mod:`host.rig.realtime`) and the
  idle-poll loops (:mod:`host.rig.idle_poll`); with ``--inject`` the launcher's injections
  (:class:`host.rig.inject.ProcessInjector`: kill / stall / EMCY; frame faults are the hub's, a
  full disk the host's ``--inject-disk-full``);
* the run's position on the io channel (:class:`host.rig.run_watch.RunProgress`), the watch until
  the host ends (:class:`host.rig.supervisor.Supervisor`), the run's end
  (:class:`host.rig.run_outcome.RunOutcome`) and, on every path, the cleanup: SIGTERM, grace,
  SIGKILL and reaping of every child, the hub stopped (:func:`host.rig.processes.terminate`), the
  run folder settled; the janitor (:mod:`host.rig.janitor`) does that last part if the launcher
  itself is killed.

Before anything starts
    ``ilcrig run`` validates the whole experiment first (:func:`preflight`: the configuration,
    :func:`host.experiment.plan.prepare` with the trajectory's feasibility, ``--out``, every
    ``--inject`` spec against the experiment's trials and ticks): bad input is one line and exit
    code 2 with no process started.

Output
    The host's stdout goes to the terminal (the plan and one row per trial); every role's stderr,
    the host's too, and the plant's and drives' stdout go to log files ``<out>/logs/<name>.log``
    (``host``, ``hub``, ``plant``, ``drive1`` … ``drive4``), so no traceback of any role reaches the
    terminal. One status line naming the transport and the pids is printed before the host starts.

One fault path
    When a role (or the hub) ends while the host runs, the launcher gives the host
    :data:`HOST_GRACE_S` to notice it on the bus and record it; when the host itself dies, the
    launcher records the fault in ``summary.json`` (``faults``, ``completed: false``). Either way
    the run ends with the one line ``ilcrig: fault: <what>: <node>, trial k, tick n; …; its log: …``
    (:mod:`host.rig.run_outcome`).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import time
from pathlib import Path
from typing import IO, Any

from bus.exit_codes import EXIT_CHILD_FAILED
from bus.lockstep_process import mechanisms_left_out
from bus.objects import DRIVE_NODE_IDS
from bus.timer_slack import FINE_TIMER_SLACK_NS
from bus.transports.fault_inject import FRAME_ACTIONS, FaultSpec, check_specs, parse_specs
from bus.units import timeout_scale
from host.rig.fair_scheduling import host_policy
from host.rig.idle_poll import AUTOGROUP_NICE, IdlePollers, idle_poll_available
from host.rig.interrupts import Interrupts
from host.rig.processes import Child, Death, LaunchError, spawn, start_hub_process, terminate
from host.rig.realtime import DEFAULT_RT_PRIORITY, schedule_lockstep, scheduling_mechanisms
from host.rig.role_commands import bus_time_rates, child_argv, host_role_args, rig_role_args
from host.rig.run_outcome import RunOutcome
from host.rig.run_watch import RunProgress
from host.rig.supervisor import Supervisor

__all__ = [
    "HOST_GRACE_S",
    "TERMINATE_GRACE_S",
    "LauncherConsole",
    "RigLauncher",
    "launch_rig",
    "make_run_folder",
    "preflight",
]

logger = logging.getLogger(__name__)

#: how long children get after SIGTERM before SIGKILL, s
TERMINATE_GRACE_S: float = 3.0
#: how long the host gets to record a fault (another process ended) or an interrupt, s (× scale)
HOST_GRACE_S: float = 20.0


def preflight(args: argparse.Namespace) -> list[FaultSpec]:
    """Everything ``ilcrig run`` checks before it starts a process: the experiment (configuration
    and :func:`host.experiment.plan.prepare`, i.e. trajectory, feasibility, gains, memory),
    ``--out`` and the ``--inject`` specs (:func:`bus.transports.fault_inject.check_specs`: inside
    the experiment's trials and ticks, possible on the transport). Returns the specs.

    :raises ValueError: one line naming the option or file (the CLI's exit code 2).
    """
    from host.experiment.outputs import check_out_dir

    specs = parse_specs(getattr(args, "inject", None))
    if args.out is not None:
        check_out_dir(args.out, create=False)  # fast: before the configuration and the preparation
    from host.experiment.console import experiment_config

    cfg = experiment_config(args)
    if args.out is not None:
        check_out_dir(args.out, iterations=cfg.iterations, n_ticks=cfg.n_ticks, create=False)
    check_specs(specs, iterations=cfg.iterations, n_ticks=cfg.n_ticks, hub=args.bus in ("hub", "auto"))
    _check_hub_path(getattr(args, "hub", None))
    if getattr(args, "bus_time", False) and args.bus not in ("hub", "auto"):
        raise ValueError(f"--bus-time: bus time is kept by the hub; the transport {args.bus} has none: use --bus hub")
    if getattr(args, "rt_priority", None) is not None and not args.realtime:
        raise ValueError(f"--rt-priority {args.rt_priority}: the priority of a real-time run; add --realtime")
    if getattr(args, "no_idle_poll", False) and not args.realtime:
        raise ValueError("--no-idle-poll: the CPUs are kept awake only in a real-time run; add --realtime")
    from host.experiment.plan import prepare

    prepare(cfg, rig=True)
    return specs


def _check_hub_path(address: str | None) -> None:
    """``--hub unix:PATH`` where another user's socket (or a link, a file) is: refused now, in one
    line (the hub would refuse it too, but only in its log).

    :raises HubOwnerError: (a ValueError) naming the path and its owner
    """
    if not address:
        return
    import os

    from bus.transports.hub.addresses import parse_address
    from bus.transports.hub.owner import check_socket_file

    addr = parse_address(address, allow_remote=True)
    if addr.kind == "unix" and os.path.lexists(addr.path):
        check_socket_file(addr.path)


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
    out_dir = Path(out) if out is not None else Path("runs") / time.strftime(f"{kind}-%Y%m%d-%H%M%S")
    log_dir = out_dir / "logs"
    try:
        log_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {out_dir}: cannot create the run folder: {err.strerror or err}") from err
    return out_dir, log_dir


class RigLauncher(LauncherConsole):
    """Starts and supervises the processes of one ``ilcrig run`` (see the module docstring).

    :param args: the parsed ``ilcrig run`` Namespace
    :param stdout: stream of the status line (default ``sys.stdout``)
    :param stderr: stream of error / exit messages (default ``sys.stderr``)
    :param grace_s: SIGTERM → SIGKILL grace period, s
    :param host_grace_s: how long the host gets to record a fault or an interrupt, s
        (default :data:`HOST_GRACE_S` × ``ILCRIG_TIMEOUT_SCALE``)
    :ivar children: every started role process, in start order (the host last)
    :ivar hub: the hub handle while it runs
    :ivar hub_address: the hub's address (None without a hub)
    :ivar out_dir: the run folder
    """

    def __init__(
        self,
        args: argparse.Namespace,
        stdout: IO[str] | None = None,
        stderr: IO[str] | None = None,
        grace_s: float = TERMINATE_GRACE_S,
        host_grace_s: float | None = None,
    ) -> None:
        self.args = args
        self.stdout = stdout
        self.stderr = stderr
        self.grace_s = grace_s
        self.host_grace_s = host_grace_s
        self.children: list[Child] = []
        self.hub: Any = None
        self.hub_address: str | None = None
        self.transport_name = ""
        self.out_dir: Path | None = None
        self.interrupts = Interrupts()
        self.supervisor: Supervisor | None = None
        self._injector: Any = None
        self._idle_pollers: IdlePollers | None = None
        self._progress: RunProgress | None = None
        self._janitor: Any = None

    @property
    def deaths(self) -> list[Death]:
        """The processes that ended while the host ran, in the order noticed."""
        return self.supervisor.deaths if self.supervisor is not None else []

    def run(self) -> int:
        """Launch, watch, clean up. Returns the exit code (module docstring)."""
        self.interrupts.install()
        try:
            try:
                return self._launch_and_watch()
            except LaunchError as err:
                self._say_err(f"ilcrig: error: {err}")
                return EXIT_CHILD_FAILED
            finally:
                self._shutdown()
        finally:
            self.interrupts.restore()

    # -- steps -----------------------------------------------------------------------------

    def _launch_and_watch(self) -> int:
        from bus.transports.config import transport_from_name

        args = self.args
        debug = bool(getattr(args, "debug", False))
        tc = transport_from_name(args.bus, args.hub)  # ValueError subclasses on bad input
        if tc.name == "virtual":
            raise ValueError(
                "the virtual transport works inside one process only; use hub, socketcan, "
                "udp_multicast or can_config with `ilcrig run`"
            )
        specs = parse_specs(getattr(args, "inject", None))
        iterations = self._iterations(specs)
        if specs:
            from host.experiment.console import experiment_config

            cfg = experiment_config(args)
            check_specs(specs, iterations=cfg.iterations, n_ticks=cfg.n_ticks, hub=tc.needs_hub)
        self.transport_name = tc.name
        if self.host_grace_s is None:
            self.host_grace_s = HOST_GRACE_S * timeout_scale()
        out_dir, log_dir = make_run_folder(args.out, "run")
        self.out_dir = out_dir

        bus_args = ["--bus", tc.name]
        if tc.needs_hub:
            frame_specs = [sp.text for sp in specs if sp.action in FRAME_ACTIONS]
            inject = (
                json.dumps({"specs": frame_specs, "log": str(log_dir / "injections-hub.jsonl"), "iterations": iterations})
                if frame_specs
                else None
            )
            self.hub = start_hub_process(args.hub, inject, log_dir / "hub.log", bus_time=bus_time_rates(args))
            self.hub_address = self.hub.address
            bus_args += ["--hub", str(self.hub_address)]
        run_tc = transport_from_name(tc.name, self.hub_address) if tc.needs_hub else tc
        self._progress = RunProgress(run_tc)
        self._progress.start()
        self.supervisor = supervisor = Supervisor(
            self.children, self.hub, log_dir / "hub.log", float(self.host_grace_s), self.interrupts, self._progress.where
        )
        outcome = RunOutcome(out_dir, self.children, self._say_err, self._resume_stalled)
        if self.interrupts.signum is not None:
            return self._signal_exit()
        self._spawn("plant", child_argv("plant", bus_args, debug=debug), log_dir / "plant.log")
        for node in DRIVE_NODE_IDS:
            if self.interrupts.signum is not None:
                return self._signal_exit()
            self._spawn(f"drive{node}", child_argv("drive", bus_args, node=node, debug=debug), log_dir / f"drive{node}.log")
        if self.interrupts.signum is not None:
            return self._signal_exit()

        where = f" ({self.hub_address})" if self.hub_address else ""
        pids = ([f"hub {self.hub.pid}"] if self.hub is not None else []) + [f"{c.name} {c.pid}" for c in self.children]
        self._say_out(
            f"ilcrig run: transport {tc.name}{where}; processes: {', '.join(pids)}; role logs in {log_dir}; starting host"
        )
        host_extra = host_role_args(args) + rig_role_args(args) + ["--out", str(out_dir)]
        host_batch = False
        if args.realtime:
            scheduling = self._schedule_realtime(args)
            host_batch = scheduling.get("host", {}).get("policy") == "SCHED_BATCH"
            host_extra += ["--rt-scheduling", json.dumps(scheduling)]
        disk = [sp for sp in specs if sp.action == "diskfull"]
        if disk:
            host_extra += ["--inject-disk-full", disk[0].text]
        host = self._spawn(
            "host",
            child_argv("host", bus_args, extra=host_extra, debug=debug),
            log_dir / "host.log",
            stderr_only=True,
            batch=host_batch,
        )
        logger.info("host pid %d: %s", host.pid, " ".join(host.argv))
        from host.rig.janitor import start_janitor

        self._janitor = start_janitor(out_dir, host.pid)
        if any(sp.action in ("kill", "stall", "emcy") for sp in specs):
            from host.rig.inject import ProcessInjector

            self._injector = ProcessInjector(
                specs,
                run_tc,
                self._pid_of,
                log_dir / "injections-launcher.jsonl",
                iterations=iterations or 1,
                summary_path=out_dir / "summary.json",
            )
            self._injector.start()
        code = supervisor.watch(host)
        if self.interrupts.signum is not None:
            return self._interrupted(host, supervisor, outcome)
        host_death = supervisor.host_death(host, code)
        return outcome.conclude(host, code, supervisor.deaths, supervisor.host_stopped, host_death)

    def _iterations(self, specs: list[FaultSpec]) -> int | None:
        """The run's trials, when an injection needs them (``@after``); else None (not computed)."""
        if not any(sp.when in ("after", "end") for sp in specs):
            return None
        from host.experiment.console import experiment_config

        return experiment_config(self.args).iterations

    def _spawn(
        self, name: str, argv: list[str], log_path: Path | None, *, stderr_only: bool = False, batch: bool = False
    ) -> Child:
        child = spawn(name, argv, log_path, stderr_only=stderr_only, batch=batch)
        self.children.append(child)
        return child

    def _schedule_realtime(self, args: argparse.Namespace) -> dict[str, Any]:
        """A real-time run's scheduling, before the host starts: the lockstep processes (hub,
        plant, drives) in SCHED_FIFO or, where that is not permitted, in normal scheduling with
        what an unprivileged process may use (:func:`host.rig.realtime.schedule_lockstep`), the
        host's policy (:func:`host.rig.fair_scheduling.host_policy`), the idle-poll loops.

        :return: the scheduling record (``bench.timing.scheduling`` of the summary)
        """
        without = mechanisms_left_out()
        lockstep = ({"hub": self.hub.pid} if self.hub is not None else {}) | {c.name: c.pid for c in self.children}
        priority = DEFAULT_RT_PRIORITY if args.rt_priority is None else args.rt_priority
        scheduling = schedule_lockstep(lockstep, priority, without)
        fifo = scheduling["policy"] == "SCHED_FIFO"
        if not fifo:
            from host.experiment.console import experiment_config

            scheduling["host"] = host_policy(experiment_config(args).ff_transport == "pdo", without)
        scheduling["idle_poll"] = self._start_idle_poll(args, fifo, without)
        scheduling["in_roles"] = {
            "heap_frozen": "gc" not in without,
            "timer_slack_ns": FINE_TIMER_SLACK_NS,
            "plant_spins": fifo or "sleep-wait" in without,
        }
        scheduling["mechanisms"] = scheduling_mechanisms(scheduling)
        return scheduling

    def _start_idle_poll(self, args: argparse.Namespace, fifo: bool, without: frozenset[str]) -> dict[str, Any]:
        """Keep the CPUs awake for a real-time run (host/rig/idle_poll.py), unless ``--no-idle-poll``
        or the lockstep processes are in normal scheduling (the loops would compete with them:
        :mod:`host.rig.idle_poll`, "Only beside SCHED_FIFO").

        :return: for the summary's scheduling record: ``{"loops": n}``, or ``{"loops": 0, "reason": ...}``
        """
        if getattr(args, "no_idle_poll", False):
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

    def _pid_of(self, name: str) -> int | None:
        """The pid of a running role or of the hub (None: not running), for the injector."""
        if name == "hub":
            return self.hub.pid if self.hub is not None else None
        child = next((c for c in self.children if c.name == name), None)
        return child.pid if child is not None and child.proc.poll() is None else None

    def _resume_stalled(self) -> None:
        if self._injector is not None:
            self._injector.resume_all()

    # -- interrupts and shutdown ---------------------------------------------------------------

    def _signal_exit(self) -> int:
        self._say_err(f"ilcrig: interrupted ({self.interrupts.name}); stopping {len(self.children)} processes")
        return self.interrupts.exit_code()

    def _interrupted(self, host: Child, supervisor: Supervisor, outcome: RunOutcome) -> int:
        """SIGINT / SIGTERM / SIGHUP: the host first (it marks the summary), then the rest."""
        exit_code = self._signal_exit()
        if host.proc.poll() is None:
            supervisor.stop_host(host, signal.SIGINT if self.interrupts.signum == signal.SIGINT else signal.SIGTERM)
        outcome.mark_interrupted(self.interrupts.name, self._progress.where() if self._progress is not None else None)
        return exit_code

    def _shutdown(self) -> None:
        """Stop the idle-poll loops and the injector, terminate every child, stop the hub."""
        self.interrupts.stopping = True
        try:
            if self._idle_pollers is not None:
                self._idle_pollers.stop()
            if self._injector is not None:
                self._injector.stop()  # resumes stalled processes
            if self._progress is not None:
                self._progress.stop()
            terminate(self.children, self.grace_s, lambda: self.interrupts.hurry)
        finally:
            try:
                if self.hub is not None:
                    try:
                        self.hub.stop()
                    finally:
                        self.hub = None
            finally:
                if self._janitor is not None:
                    if self.out_dir is not None:
                        from host.rig.janitor import settle_run_folder

                        settle_run_folder(self.out_dir)  # every path: also a launch that failed half way
                    self._janitor.done()
                    self._janitor = None


def launch_rig(args: argparse.Namespace) -> int:
    """``ilcrig run``: check everything (:func:`preflight`), then launch hub (if needed), plant,
    four drives and the host; return the run's exit code after every process is gone (see the
    module docstring).

    :raises ValueError: bad input (reported by the CLI in one line, exit code 2)
    """
    preflight(args)
    return RigLauncher(args).run()
