"""``ilcrig run``: check the experiment, start the distributed rig, watch it, always clean it up.

This module owns :func:`launch_rig`, :func:`preflight` and :class:`RigLauncher`, which puts the
run's processes together: what is particular to an ILC run (the host role, the run's outcome, the
injections); what ``ilcrig robot`` does alike — spawning under one lifetime policy, the real-time
scheduling with its fallbacks, the idle-poll loops, the interrupts, the shutdown and the janitor —
is :class:`host.rig.launch_core.LaunchCore`'s. Its options are :class:`host.rig.options.RunOptions`.

* the bus hub (only when the transport is ``hub``), started with :func:`bus.transports.hub.process.start_hub` on a
  fresh private Unix socket (a temp directory per run, so concurrent runs never collide) unless
  ``--hub ADDR`` names the address it must listen on;
* the plant (``ilcrig plant``), four drives (``ilcrig drive --node 1..4``) and the host
  (``ilcrig host <the same experiment options> --out DIR``), each started as
  ``[sys.executable, "-P", "-m", "host.cli", ROLE, ...]`` with the same ``--bus``/``--hub``
  (:mod:`host.rig.role_commands`; ``-P``: the working folder cannot shadow the project's modules,
  the hub is started the same way) as processes of their own
  (:mod:`host.rig.processes`, :mod:`bus.processes`);
* with ``--realtime``, SCHED_FIFO for the lockstep processes where permitted, else the
  fair-scheduling fallback, and the idle-poll loops (:meth:`host.rig.launch_core.LaunchCore.schedule_realtime`);
  with ``--inject`` the launcher's injections
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
    :data:`HOST_GRACE_S` to notice it on the bus and record it (a node whose heartbeat was not
    heard yet a few seconds: :data:`host.rig.supervisor.UNHEARD_GRACE_S`); when the host itself dies, the
    launcher records the fault in ``summary.json`` (``faults``, ``completed: false``). Either way
    the run ends with the one line ``ilcrig: fault: <what>: <node>, trial k, tick n; …; its log: …``
    (:mod:`host.rig.run_outcome`).
"""

from __future__ import annotations

import json
import logging
import signal
import time
from dataclasses import dataclass, field
from typing import Any

from bus.errors import InputError
from bus.exit_codes import EXIT_OK
from bus.objects import DRIVE_NODE_IDS
from bus.transports.fault_inject import FRAME_ACTIONS, FaultSpec, check_specs, parse_specs
from bus.units import timeout_scale
from host.experiment.outputs import SUMMARY_NAME
from host.rig.launch_core import LaunchCore, check_transport, make_run_folder
from host.rig.liveness import LivenessWatch, StopWatch
from host.rig.options import RunOptions
from host.rig.processes import Child, Death, LaunchError
from host.rig.role_commands import bus_time_rates, child_argv, host_role_args, rig_role_args
from host.rig.run_outcome import RunOutcome
from host.rig.run_watch import RunProgress
from host.rig.supervisor import Supervisor

__all__ = ["HOST_GRACE_S", "RigLauncher", "launch_rig", "preflight"]

logger = logging.getLogger(__name__)

#: how long the host gets to record a fault (another process ended) or an interrupt, s (× scale)
HOST_GRACE_S: float = 20.0


def preflight(options: RunOptions) -> list[FaultSpec]:
    """Everything ``ilcrig run`` checks before it starts a process: the experiment (configuration
    and :func:`host.experiment.plan.prepare`, i.e. trajectory, feasibility, gains, memory),
    ``--out`` and the ``--inject`` specs (:func:`bus.transports.fault_inject.check_specs`: inside
    the experiment's trials and ticks, possible on the transport). Returns the specs.

    :raises ValueError: one line naming the option or file (the CLI's exit code 2).
    """
    from host.experiment.outputs import check_out_dir

    specs = parse_specs(options.inject)
    if options.out is not None:
        check_out_dir(options.out, create=False, new_run=True)  # fast: before the configuration and the preparation
    from host.experiment.console import experiment_config
    from host.experiment.plan import check_config_limits

    cfg = experiment_config(options.experiment)
    check_config_limits(cfg, rig=True)  # the trial length and the memory before the disk space
    if options.out is not None:
        check_out_dir(options.out, iterations=cfg.iterations, n_ticks=cfg.n_ticks, create=False)
    check_specs(specs, iterations=cfg.iterations, n_ticks=cfg.n_ticks, hub=options.bus in ("hub", "auto"))
    if options.bus_time and options.bus not in ("hub", "auto"):
        raise InputError(f"--bus-time: bus time is kept by the hub; the transport {options.bus} has none: use --bus hub")
    if options.rt_priority is not None and not options.realtime:
        raise InputError(f"--rt-priority {options.rt_priority}: the priority of a real-time run; add --realtime")
    if options.no_idle_poll and not options.realtime:
        raise InputError("--no-idle-poll: the CPUs are kept awake only in a real-time run; add --realtime")
    check_transport(options)
    from host.experiment.plan import prepare

    prepare(cfg, rig=True)
    return specs


@dataclass(eq=False)
class RigLauncher(LaunchCore):
    """Starts and supervises the processes of one ``ilcrig run`` (see the module docstring).

    :param options: the run's options
    :param stdout: stream of the status line (default ``sys.stdout``)
    :param stderr: stream of error / exit messages (default ``sys.stderr``)
    :param grace_s: SIGTERM → SIGKILL grace period, s
    :param host_grace_s: how long the host gets to record a fault or an interrupt, s
        (default :data:`HOST_GRACE_S` × ``ILCRIG_TIMEOUT_SCALE``)
    :ivar children: every started role process, in start order (the host last)
    """

    options: RunOptions
    host_grace_s: float | None = None
    transport_name: str = field(default="", init=False)
    supervisor: Supervisor | None = field(default=None, init=False)
    _injector: Any = field(default=None, init=False, repr=False)
    _progress: RunProgress | None = field(default=None, init=False, repr=False)
    _liveness: LivenessWatch | None = field(default=None, init=False, repr=False)
    _outcome: RunOutcome | None = field(default=None, init=False, repr=False)
    _launch_error: LaunchError | None = field(default=None, init=False, repr=False)

    @property
    def deaths(self) -> list[Death]:
        """The processes that ended while the host ran, in the order noticed."""
        return self.supervisor.deaths if self.supervisor is not None else []

    # -- steps -----------------------------------------------------------------------------

    def _launch_and_watch(self) -> int:
        from bus.transports.config import transport_from_name

        opts = self.options
        debug = opts.debug
        check_transport(opts)  # also in preflight; here for a launcher run without it
        tc = transport_from_name(opts.bus, opts.hub, opts.allow_remote)
        specs = parse_specs(opts.inject)
        iterations = self._iterations(specs)
        if specs:
            from host.experiment.console import experiment_config

            cfg = experiment_config(opts.experiment)
            check_specs(specs, iterations=cfg.iterations, n_ticks=cfg.n_ticks, hub=tc.needs_hub)
        self.transport_name = tc.name
        if self.host_grace_s is None:
            self.host_grace_s = HOST_GRACE_S * timeout_scale()
        out_dir, log_dir = make_run_folder(opts.out, "run")
        self.out_dir = out_dir
        outcome = RunOutcome(out_dir, self.children, self._say_err, self._resume_stalled, self._config_dict, specs=specs)
        self._outcome = outcome

        bus_args = ["--bus", tc.name]
        if tc.needs_hub:
            frame_specs = [sp.text for sp in specs if sp.action in FRAME_ACTIONS]
            inject = (
                json.dumps(
                    {
                        "specs": frame_specs,
                        "log": str(log_dir / "injections-hub.jsonl"),
                        "iterations": iterations,
                        "summary": str(out_dir / SUMMARY_NAME),
                    }
                )
                if frame_specs
                else None
            )
            bus_args += ["--hub", self.start_hub(inject, log_dir / "hub.log", bus_time_rates(opts))]
        run_tc = transport_from_name(tc.name, self.hub_address) if tc.needs_hub else tc
        self._progress = RunProgress(run_tc)
        self._progress.start()
        self.supervisor = supervisor = Supervisor(
            self.children, self.hub, log_dir / "hub.log", float(self.host_grace_s), self.interrupts, self._progress.where
        )
        self._liveness = LivenessWatch(run_tc, self._progress.where, outcome.kept_now, self.lockstep_pids)
        self._liveness.start()
        supervisor.heard = self._liveness.heard
        supervisor.stops = StopWatch(self._progress.where, outcome.kept_now)
        if self.interrupts.signum is not None:
            return self.say_interrupted()
        # the plant prepares the run's disturbance alone (scipy's filter design only when it needs it)
        plant_extra = ["--disturbance", self._disturbance()]
        self.spawn("plant", child_argv("plant", bus_args, extra=plant_extra, debug=debug), log_dir / "plant.log")
        for node in DRIVE_NODE_IDS:
            if self.interrupts.signum is not None:
                return self.say_interrupted()
            firmware = ["--firmware", opts.firmware] if opts.firmware != "python" else []  # (the default)
            drive_argv = child_argv("drive", bus_args, node=node, extra=firmware, debug=debug)
            self.spawn(f"drive{node}", drive_argv, log_dir / f"drive{node}.log")
        if self.interrupts.signum is not None:
            return self.say_interrupted()

        where = f" ({self.hub_address})" if self.hub_address else ""
        self._say_out(
            f"ilcrig run: transport {tc.name}{where}; processes: {self.pids_text()}; role logs in {log_dir}; starting host"
        )
        host_extra = host_role_args(opts.experiment) + rig_role_args(opts) + ["--out", str(out_dir)]
        host_batch = False
        if opts.realtime:
            scheduling = self._schedule_run()
            host_batch = scheduling.get("host", {}).get("policy") == "SCHED_BATCH"
            host_extra += ["--rt-scheduling", json.dumps(scheduling)]
        disk = [sp for sp in specs if sp.action == "diskfull"]
        if disk:
            host_extra += ["--inject-disk-full", disk[0].text]
        host = self.spawn(
            "host",
            child_argv("host", bus_args, extra=host_extra, debug=debug),
            log_dir / "host.log",
            stderr_only=True,
            batch=host_batch,
        )
        logger.info("host pid %d: %s", host.pid, " ".join(host.argv))
        self.start_janitor(host.pid)
        if any(sp.action in ("kill", "stall", "emcy") for sp in specs):
            from host.rig.inject import ProcessInjector

            self._injector = ProcessInjector(
                specs,
                run_tc,
                self._pid_of,
                log_dir / "injections-launcher.jsonl",
                iterations=iterations or 1,
                summary_path=out_dir / SUMMARY_NAME,
            )
            self._injector.start()
        code = supervisor.watch(host)
        if self.interrupts.signum is not None:
            return self._interrupted(host, supervisor, outcome)
        host_death = supervisor.host_death(host, code)
        if code == 0 and not supervisor.deaths:  # every node heard once more after the host's end
            outcome.host_ended_mono = time.monotonic()
            outcome.silences = self._liveness.settle(outcome.host_ended_mono) + supervisor.stops.silences
        return outcome.conclude(host, code, supervisor.deaths, supervisor.host_stopped, host_death)

    def _iterations(self, specs: list[FaultSpec]) -> int | None:
        """The run's trials, when an injection needs them (``@after``); else None (not computed)."""
        if not any(sp.when in ("after", "end") for sp in specs):
            return None
        from host.experiment.console import experiment_config

        return experiment_config(self.options.experiment).iterations

    def _disturbance(self) -> str:
        """The disturbance kind of the run's trials (``--disturbance`` of the experiment)."""
        from host.experiment.console import experiment_config

        return experiment_config(self.options.experiment).disturbance

    def _schedule_run(self) -> dict[str, Any]:
        """A real-time run's scheduling, before the host starts (:meth:`LaunchCore.schedule_realtime`,
        the host in the tick with ``--ff-transport pdo``), and whether the plant spins.

        :return: the scheduling record (``bench.timing.scheduling`` of the summary)
        """
        from bus.lockstep_process import mechanisms_left_out
        from host.experiment.console import experiment_config
        from host.rig.realtime import scheduling_mechanisms

        scheduling = self.schedule_realtime(host_in_tick=experiment_config(self.options.experiment).ff_transport == "pdo")
        spins = scheduling["policy"] == "SCHED_FIFO" or "sleep-wait" in mechanisms_left_out()
        scheduling["in_roles"]["plant_spins"] = spins
        scheduling["mechanisms"] = scheduling_mechanisms(scheduling)
        return scheduling

    def _config_dict(self) -> dict[str, Any]:
        """The run's configuration as a summary holds it (for the summary the launcher writes when
        the host left none)."""
        from host.experiment.console import experiment_config

        cfg = experiment_config(self.options.experiment)
        return cfg.as_dict() | {"n_ticks": cfg.n_ticks}

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

    def _interrupted(self, host: Child, supervisor: Supervisor, outcome: RunOutcome) -> int:
        """SIGINT / SIGTERM / SIGHUP: the host first, with the same signal (it marks the summary with
        it, as the exit code says it), then the rest."""
        exit_code = self.say_interrupted()
        if host.proc.poll() is None:
            supervisor.stop_host(host, signal.Signals(self.interrupts.signum or signal.SIGTERM))
        if outcome.mark_interrupted(self.interrupts.name, self._progress.where() if self._progress is not None else None):
            return exit_code
        self._say_err(
            f"ilcrig: the run had completed before {self.interrupts.name}: every trial kept; "
            f"summary: {outcome.out_dir / SUMMARY_NAME}"
        )
        return EXIT_OK

    def _launch_failed(self, err: LaunchError) -> None:
        self._launch_error = err  # its summary once every process is gone (_closing)

    def _closing(self, code: int) -> None:
        """A summary on every exit code (:meth:`host.rig.run_outcome.RunOutcome.ensure_summary`):
        also when a process could not be started (exit 4) or the run ended before the host did."""
        if self._outcome is not None:
            self._outcome.ensure_summary(code, self._launch_error)

    def _stop_watchers(self) -> None:
        """The injector (it resumes stalled processes) and the run's progress."""
        if self._injector is not None:
            self._injector.stop()
        if self._progress is not None:
            self._progress.stop()
        if self._liveness is not None:
            self._liveness.stop()


def launch_rig(options: RunOptions) -> int:
    """``ilcrig run``: check everything (:func:`preflight`), then launch hub (if needed), plant,
    four drives and the host; return the run's exit code after every process is gone (see the
    module docstring).

    :raises ValueError: bad input (reported by the CLI in one line, exit code 2)
    """
    preflight(options)
    return RigLauncher(options).run()
