"""The process launcher of ``ilcrig run``: starts the distributed rig and always cleans it up.

This module owns the lifecycle of the processes of one ``ilcrig run``:

* the bus hub (only when the transport is ``hub``), started with :func:`bus.transports.hub_server.start_hub` on a
  fresh private Unix socket (a temp directory per run, so concurrent runs never collide) unless
  ``--hub ADDR`` names the address it must listen on;
* the plant (``ilcrig plant``), four drives (``ilcrig drive --node 1..4``) and the host
  (``ilcrig host <the same experiment options> --out DIR``), each started as
  ``[sys.executable, "-m", "host.cli", ROLE, ...]`` with the same ``--bus``/``--hub``.

Before anything starts
    ``ilcrig run`` validates the whole experiment first (:func:`preflight`: the configuration,
    :func:`host.experiment.plan.prepare` with the trajectory's feasibility, ``--out``, every
    ``--inject`` spec): bad input is one line and exit code 2 with no process started.

Output
    The host's stdout goes to the terminal (the plan and one row per trial); every role's stderr,
    the host's too, and the plant's and drives' stdout go to log files ``<out>/logs/<name>.log``
    (``host``, ``hub``, ``plant``, ``drive1`` … ``drive4``), so no traceback of any role reaches the
    terminal. One status line naming the transport and the pids is printed before the host starts.

One fault path
    When a role (or the hub) ends while the host runs, the launcher notes it and gives the host
    :data:`HOST_GRACE_S` to notice it on the bus and record it (the host's watchdog takes about
    three heartbeat periods); a host that does not end by then is stopped.  When the host itself
    dies, the launcher records the fault in ``summary.json`` (``faults``, ``completed: false``).
    Either way the launcher then adds the evidence of the drives' safe state that only the roles'
    logs hold (their ``SAFE-STATE`` records, :mod:`bus.safe_state`, after letting stalled processes
    resume and live drives react), names the process that ended, rewrites ``report.md`` and prints
    the run's one line ``ilcrig: fault: <what>: <node>, trial k, tick n; …; its log: …``.

Fault injection
    ``--inject SPEC`` (repeatable, :mod:`bus.transports.fault_inject`): frame faults are done by
    the hub (``--inject`` of the hub process), kill / stall / EMCY by the launcher's
    :class:`host.rig.inject.ProcessInjector`, a full disk by the host (``--inject-disk-full``).

The watch loop polls the children every :data:`POLL_S` (50 ms): a few µs of CPU per wake-up.

Test hook
    The command of a role can be replaced, for tests with fake role scripts, by the module
    dict :data:`ROLE_COMMAND` (role → argv prefix) or by the environment variables
    ``ILCRIG_ROLE_CMD_<ROLE>`` (``HOST``, ``PLANT``, ``DRIVE``, and ``DRIVE1`` … ``DRIVE4`` for
    one drive; a shell-like string split with :func:`shlex.split`). The environment wins. The
    role's arguments (e.g. ``--node 2 --bus hub --hub unix:…``) are appended to the override.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import logging
import os
import resource
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from bus.busload import DEFAULT_BITRATE_BPS
from bus.cia301.nmt import CONSUMER_TIME_MS, HOST_NODE_ID
from bus.objects import DRIVE_NODE_IDS
from bus.plant_objects import DEFAULT_PLANT_NODE_ID
from bus.safe_state import last_state_in_log
from bus.transports.config import FIELDBUS
from bus.transports.config import IO as IO_CHANNEL
from bus.transports.fault_inject import FRAME_ACTIONS, FaultSpec, FaultSpecError, parse_specs
from bus.units import timeout_scale
from host.experiment.console import (
    EXIT_CHILD_FAILED,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_TERMINATED,
    EXIT_USAGE,
    experiment_actions,
)
from host.experiment.faults import FaultKind, FaultRecord, attach_injection, fault_line, read_injections
from host.rig.idle_poll import IdlePollers, idle_poll_available
from host.rig.realtime import DEFAULT_RT_PRIORITY, raise_lockstep_priority

__all__ = [
    "EXIT_CHILD_FAILED",
    "HOST_GRACE_S",
    "POLL_S",
    "ROLE_COMMAND",
    "ROLE_ENV_PREFIX",
    "TERMINATE_GRACE_S",
    "Child",
    "LaunchError",
    "RigLauncher",
    "child_argv",
    "host_role_args",
    "launch_rig",
    "preflight",
    "rig_role_args",
    "role_command",
]

logger = logging.getLogger(__name__)

#: exit code when the plant or a drive ended while the host ran, or a process did not start
#: watch-loop period, s
POLL_S: float = 0.05
#: how long children get after SIGTERM before SIGKILL, s
TERMINATE_GRACE_S: float = 3.0
#: how long the host gets to record a fault (another process ended) or an interrupt, s (× scale)
HOST_GRACE_S: float = 20.0
#: the drives' node ids (one per joint)
#: environment variable prefix of the role-command test hook
ROLE_ENV_PREFIX: str = "ILCRIG_ROLE_CMD_"
#: test hook: role name ("host", "plant", "drive", "drive1" …) → argv prefix replacing
#: ``[sys.executable, "-m", "host.cli", ROLE]``
ROLE_COMMAND: dict[str, list[str]] = {}

_SIGNAL_EXIT: dict[int, int] = {
    signal.SIGINT: EXIT_INTERRUPTED,
    signal.SIGTERM: EXIT_TERMINATED,
    signal.SIGHUP: 128 + signal.SIGHUP,
}
_HANDLED_SIGNALS: tuple[int, ...] = tuple(_SIGNAL_EXIT)
_PR_SET_PDEATHSIG = 1
_HUB_BLOCKED_SIGNALS = frozenset({signal.SIGINT, signal.SIGHUP})
# options of the experiment that are not passed through generically


class LaunchError(RuntimeError):
    """A role process or the hub could not be started."""


# ---------------------------------------------------------------------------------------
# command lines
# ---------------------------------------------------------------------------------------


def role_command(role: str, node: int | None = None, *, debug: bool = False) -> list[str]:
    """argv prefix of ``role`` (``host``, ``plant``, ``drive``), honouring the test hooks.

    :param node: the drive's node id (selects ``ILCRIG_ROLE_CMD_DRIVE<node>`` first)
    :param debug: pass ``--debug`` to the real ``ilcrig`` command
    """
    keys = ([f"{role}{node}"] if node is not None else []) + [role]
    for key in keys:
        env = os.environ.get(ROLE_ENV_PREFIX + key.upper())
        if env:
            return shlex.split(env)
    for key in keys:
        if key in ROLE_COMMAND:
            return list(ROLE_COMMAND[key])
    return [sys.executable, "-m", "host.cli"] + (["--debug"] if debug else []) + [role]


def host_role_args(args: argparse.Namespace) -> list[str]:
    """The experiment options of ``args`` (a parsed ``run`` Namespace) as host-role arguments.

    Only options that were given (not ``None``) are passed; ``--out``, ``--bus`` and ``--hub``
    are added by :func:`child_argv`. Floats keep their exact value (``repr`` round-trips).
    """
    argv: list[str] = []
    for action in experiment_actions():
        value = getattr(args, action.dest, None)
        if value is None or value is False:
            continue
        flag = next((o for o in action.option_strings if o.startswith("--")), action.option_strings[0])
        if action.nargs == 0:  # store_true / store_const
            if value is True or value == action.const:
                argv.append(flag)
            continue
        argv += [flag, repr(value) if isinstance(value, float) else str(value)]
    return argv


def rig_role_args(args: argparse.Namespace) -> list[str]:
    """The rig options of ``args`` (``--realtime``, ``--bus-time``, ``--io-bitrate``) that the host role takes too
    (``--fieldbus-bitrate`` is an experiment option and goes with :func:`host_role_args`)."""
    argv = ["--realtime"] if args.realtime else []
    if getattr(args, "bus_time", False):
        argv.append("--bus-time")
    if args.io_bitrate is not None:
        argv += ["--io-bitrate", str(args.io_bitrate)]
    return argv


def child_argv(
    role: str, bus_args: Sequence[str], *, node: int | None = None, extra: Sequence[str] = (), debug: bool = False
) -> list[str]:
    """Complete argv of one role: command (or test override) + role args + bus args."""
    own = ["--node", str(node)] if node is not None else []
    return role_command(role, node, debug=debug) + own + list(extra) + list(bus_args)


# ---------------------------------------------------------------------------------------
# process-level helpers
# ---------------------------------------------------------------------------------------


def _make_preexec() -> Callable[[], None] | None:
    """``preexec_fn`` setting PR_SET_PDEATHSIG = SIGKILL (None where prctl is unavailable).

    The libc function is looked up here, in the parent, so the child only calls it. If the
    parent already died between fork and prctl, the child kills itself.
    """
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # pragma: no cover - glibc/musl always have prctl
        logger.warning("prctl unavailable: children will not die with a SIGKILLed launcher")
        return None
    prctl.restype = ctypes.c_int
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    parent = os.getpid()
    sigkill = int(signal.SIGKILL)

    def preexec() -> None:
        prctl(_PR_SET_PDEATHSIG, sigkill, 0, 0, 0)
        if os.getppid() != parent:  # the launcher died before prctl took effect
            os.kill(os.getpid(), sigkill)

    return preexec


def _describe_status(code: int) -> str:
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


def _tail(path: Path | None, n: int) -> list[str]:
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
    """

    name: str
    pid: int
    status: str
    t_mono: float
    log_path: Path | None
    returncode: int

    def describe(self) -> str:
        where = f"; its log: {self.log_path}" if self.log_path else ""
        return f"{self.name} (pid {self.pid}) {self.status}{where}"


def _node_id(name: str) -> int | None:
    if name.startswith("drive") and name[5:].isdigit():
        return int(name[5:])
    return {"plant": DEFAULT_PLANT_NODE_ID, "host": HOST_NODE_ID}.get(name)


def preflight(args: argparse.Namespace) -> list[FaultSpec]:
    """Everything ``ilcrig run`` checks before it starts a process: the experiment (configuration
    and :func:`host.experiment.plan.prepare`, i.e. trajectory, feasibility, gains, memory),
    ``--out`` and the ``--inject`` specs. Returns the specs.

    :raises ValueError: one line naming the option or file (the CLI's exit code 2).
    """
    from host.experiment.outputs import check_out_dir

    specs = parse_specs(getattr(args, "inject", None))
    if args.out:
        check_out_dir(args.out, create=False)  # fast: before the configuration and the preparation
    from host.experiment.console import experiment_config

    cfg = experiment_config(args)
    if args.out:
        check_out_dir(args.out, iterations=cfg.iterations, create=False)
    _check_specs(specs, args.bus, cfg.iterations)
    if getattr(args, "bus_time", False) and args.bus not in ("hub", "auto"):
        raise ValueError(f"--bus-time: bus time is kept by the hub; the transport {args.bus} has none: use --bus hub")
    if getattr(args, "rt_priority", None) is not None and not args.realtime:
        raise ValueError(f"--rt-priority {args.rt_priority}: the priority of a real-time run; add --realtime")
    if getattr(args, "no_idle_poll", False) and not args.realtime:
        raise ValueError("--no-idle-poll: the CPUs are kept awake only in a real-time run; add --realtime")
    from host.experiment.plan import prepare

    prepare(cfg)
    return specs


def _check_specs(specs: list[FaultSpec], bus: str, iterations: int) -> None:
    for spec in specs:
        if spec.action in FRAME_ACTIONS and bus not in ("hub", "auto"):
            raise FaultSpecError(f"--inject {spec.text}: frame faults are done by the hub: use --bus hub")
        if spec.trial >= iterations:
            raise FaultSpecError(
                f"--inject {spec.text}: trial {spec.trial} is beyond the run's {iterations} trials (0..{iterations - 1})"
            )


@dataclass
class RigLauncher:
    """Starts and supervises the processes of one ``ilcrig run`` (see the module docstring).

    :param args: the parsed ``ilcrig run`` Namespace
    :param stdout: stream of the status line (default ``sys.stdout``)
    :param stderr: stream of error / exit messages (default ``sys.stderr``)
    :param grace_s: SIGTERM → SIGKILL grace period, s
    :param host_grace_s: how long the host gets to record a fault or an interrupt, s
        (default :data:`HOST_GRACE_S` × ``ILCRIG_TIMEOUT_SCALE``)
    :ivar children: every started role process, in start order (the host last)
    :ivar hub: the hub handle while it runs
    :ivar deaths: the processes that ended while the host ran, in the order noticed
    :ivar watch_cpu_s: CPU time (user+sys) the launcher used while watching, s
    :ivar watch_wall_s: wall time of the watch loop, s
    """

    args: argparse.Namespace
    stdout: IO[str] | None = None
    stderr: IO[str] | None = None
    grace_s: float = TERMINATE_GRACE_S
    host_grace_s: float | None = None
    children: list[Child] = field(default_factory=list)
    hub: Any = None
    transport_name: str = ""
    hub_address: str | None = None
    out_dir: Path | None = None
    deaths: list[Death] = field(default_factory=list)
    watch_cpu_s: float = 0.0
    watch_wall_s: float = 0.0
    _signal: int | None = None
    _escalate: bool = False
    _stopping: bool = False
    _hub_pid: int | None = None
    _host_stopped: bool = False
    _injector: Any = None
    _idle_pollers: IdlePollers | None = None

    # -- public ----------------------------------------------------------------------------

    def run(self) -> int:
        """Launch, watch, clean up. Returns the exit code (module docstring)."""
        old_handlers = self._install_signal_handlers()
        try:
            try:
                return self._launch_and_watch()
            except LaunchError as err:
                self._say_err(f"ilcrig: error: {err}")
                return EXIT_CHILD_FAILED
            finally:
                self._shutdown()
        finally:
            for signum, handler in old_handlers.items():
                signal.signal(signum, handler)

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
        for spec in specs:
            if spec.action in FRAME_ACTIONS and not tc.needs_hub:
                raise FaultSpecError(f"--inject {spec.text}: frame faults are done by the hub: use --bus hub")
            if spec.target == "hub" and not tc.needs_hub:
                raise FaultSpecError(f"--inject {spec.text}: the transport {tc.name} has no hub")
        self.transport_name = tc.name
        if self.host_grace_s is None:
            self.host_grace_s = HOST_GRACE_S * timeout_scale()
        self.out_dir = Path(args.out) if args.out else Path("runs") / time.strftime("run-%Y%m%d-%H%M%S")
        log_dir = self.out_dir / "logs"
        try:
            log_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ValueError(f"--out {self.out_dir}: cannot create the run folder: {err.strerror or err}") from err

        bus_args = ["--bus", tc.name]
        if tc.needs_hub:
            frame_specs = [sp.text for sp in specs if sp.action in FRAME_ACTIONS]
            inject = json.dumps({"specs": frame_specs, "log": str(log_dir / "injections-hub.jsonl")}) if frame_specs else None
            self._start_hub(args.hub, inject, log_dir / "hub.log", bus_time=bus_time_rates(args))
            bus_args += ["--hub", str(self.hub_address)]
        if self._signal is not None:
            return self._signal_exit()

        self._spawn("plant", child_argv("plant", bus_args, debug=debug), log_dir / "plant.log")
        for node in DRIVE_NODE_IDS:
            if self._signal is not None:
                return self._signal_exit()
            self._spawn(f"drive{node}", child_argv("drive", bus_args, node=node, debug=debug), log_dir / f"drive{node}.log")
        if self._signal is not None:
            return self._signal_exit()

        where = f" ({self.hub_address})" if self.hub_address else ""
        pids = ([f"hub {self.hub.pid}"] if self.hub is not None else []) + [f"{c.name} {c.pid}" for c in self.children]
        self._say_out(
            f"ilcrig run: transport {tc.name}{where}; processes: {', '.join(pids)}; role logs in {log_dir}; starting host"
        )
        host_extra = host_role_args(args) + rig_role_args(args) + ["--out", str(self.out_dir)]
        if args.realtime:
            lockstep = ({"hub": self.hub.pid} if self.hub is not None else {}) | {c.name: c.pid for c in self.children}
            priority = DEFAULT_RT_PRIORITY if args.rt_priority is None else args.rt_priority
            scheduling = raise_lockstep_priority(lockstep, priority) | {"idle_poll": self._start_idle_poll(args)}
            host_extra += ["--rt-scheduling", json.dumps(scheduling)]
        disk = [sp.trial for sp in specs if sp.action == "diskfull"]
        if disk:
            host_extra += ["--inject-disk-full", str(min(disk))]
        host = self._spawn(
            "host", child_argv("host", bus_args, extra=host_extra, debug=debug), log_dir / "host.log", stderr_only=True
        )
        logger.info("host pid %d: %s", host.pid, " ".join(host.argv))
        if any(sp.action in ("kill", "stall", "emcy") for sp in specs):
            from host.rig.inject import ProcessInjector

            run_tc = transport_from_name(tc.name, self.hub_address) if tc.needs_hub else tc
            self._injector = ProcessInjector(specs, run_tc, self._pid_of, log_dir / "injections-launcher.jsonl")
            self._injector.start()
        code = self._watch(host)
        if self._signal is not None:
            return self._interrupted(host)
        return self._conclude(host, code)

    def _start_idle_poll(self, args: argparse.Namespace) -> dict[str, Any]:
        """Keep the CPUs awake for a real-time run (host/rig/idle_poll.py), unless ``--no-idle-poll``.

        :return: for the summary's scheduling record: ``{"loops": n}``, or ``{"loops": 0, "reason": ...}``
        """
        if getattr(args, "no_idle_poll", False):
            return {"loops": 0, "reason": "--no-idle-poll"}
        if not idle_poll_available():
            return {"loops": 0, "reason": "this system has no SCHED_IDLE"}
        try:
            self._idle_pollers = IdlePollers()
        except OSError as err:
            logger.warning("cannot start the idle-poll loops: %s", err)
            return {"loops": 0, "reason": f"could not start them ({err.strerror or err})"}
        return {"loops": len(self._idle_pollers.pids)}

    def _pid_of(self, name: str) -> int | None:
        if name == "hub":
            return self._hub_pid
        child = next((c for c in self.children if c.name == name), None)
        return child.pid if child is not None and child.proc.poll() is None else None

    def _start_hub(
        self, address: str | None, inject: str | None = None, log_path: Path | None = None, bus_time: dict[str, int] | None = None
    ) -> None:
        from bus.transports.hub.process import start_hub
        from bus.transports.hub.wire import HubError

        # The hub stays in the launcher's process group (start_hub's Popen); with SIGINT/SIGHUP
        # blocked across fork+exec (the signal mask is inherited), a terminal Ctrl-C reaches only
        # the launcher, and the hub lives until the roles are stopped (then stdin EOF stops it).
        old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, _HUB_BLOCKED_SIGNALS)
        log = open(log_path, "ab") if log_path is not None else None  # noqa: SIM115 - closed below
        try:
            # address None: hub.sock in a fresh private temp dir
            self.hub = start_hub(address, inject=inject, stderr=log, bus_time=bus_time)
        except HubError as err:
            if isinstance(err, ValueError):
                raise
            raise LaunchError(f"cannot start the bus hub{f' on {address}' if address else ''}: {err}") from err
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a pending Ctrl-C is handled now
            if log is not None:
                log.close()  # the hub has its own descriptor
        self.hub_address = self.hub.address
        self._hub_pid = self.hub.pid
        logger.info("hub pid %d on %s", self.hub.pid, self.hub_address)

    def _spawn(self, name: str, argv: list[str], log_path: Path | None, *, stderr_only: bool = False) -> Child:
        log = open(log_path, "ab") if log_path is not None else None  # noqa: SIM115 - closed below
        try:
            proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=None if stderr_only else log,
                stderr=log if stderr_only else (subprocess.STDOUT if log is not None else None),
                start_new_session=True,
                preexec_fn=_make_preexec(),
                close_fds=True,
            )
        except OSError as err:
            raise LaunchError(f"cannot start {name} ({shlex.join(argv[:4])} …): {err}") from err
        finally:
            if log is not None:
                log.close()  # the child has its own descriptor
        child = Child(name, proc, argv, log_path)
        self.children.append(child)
        logger.debug("started %s pid %d: %s", name, proc.pid, shlex.join(argv))
        return child

    def _note_deaths(self, host: Child) -> None:
        """Note every process (not the host) that ended since the last look, the hub included."""
        noted = {d.name for d in self.deaths}
        now = time.monotonic()
        for c in self.children:
            if c is host or c.name in noted:
                continue
            code = c.proc.poll()
            if code is not None:
                self.deaths.append(Death(c.name, c.pid, _describe_status(code), now, c.log_path, code))
                logger.info("%s (pid %d) %s while the host was running", c.name, c.pid, _describe_status(code))
        if self.hub is not None and "hub" not in noted and not self.hub.alive:
            code = self.hub.process.returncode
            log = self.out_dir / "logs" / "hub.log" if self.out_dir is not None else None
            self.deaths.append(Death("hub", self.hub.pid, _describe_status(code), now, log, code))
            logger.info("the hub (pid %d) %s while the host was running", self.hub.pid, _describe_status(code))

    def _watch(self, host: Child) -> int:
        """Until the host ends (its exit code) or a signal comes (then -1). A process that ends
        meanwhile gives the host :attr:`host_grace_s` to record it; then the host is stopped."""
        cpu0, wall0 = _cpu_s(), time.monotonic()
        deadline: float | None = None
        try:
            while True:
                if self._signal is not None:  # first: the roles may fail because of the same Ctrl-C
                    return -1
                code = host.proc.poll()
                if code is not None:
                    self._note_deaths(host)
                    return code
                self._note_deaths(host)
                if self.deaths and deadline is None:
                    deadline = time.monotonic() + float(self.host_grace_s or 0.0)
                if deadline is not None and time.monotonic() > deadline:
                    logger.info(
                        "the host did not end within %.1f s of %s: stopping it", self.host_grace_s, self.deaths[0].describe()
                    )
                    self._host_stopped = True
                    return self._stop_host(host, signal.SIGTERM)
                time.sleep(POLL_S)
        finally:
            self.watch_cpu_s, self.watch_wall_s = _cpu_s() - cpu0, time.monotonic() - wall0
            logger.info("launcher used %.3f s CPU in %.1f s of watching", self.watch_cpu_s, self.watch_wall_s)

    def _stop_host(self, host: Child, signum: int) -> int:
        """Signal the host alone and wait up to :attr:`host_grace_s` (a second signal: at once) for
        it to end; SIGKILL its group after that. Returns its exit code."""
        with contextlib.suppress(ProcessLookupError):
            os.kill(host.pid, signum)
        deadline = time.monotonic() + float(self.host_grace_s or 0.0)
        while host.proc.poll() is None and time.monotonic() < deadline and not self._escalate:
            time.sleep(0.02)
        if host.proc.poll() is None:
            _killpg(host.pid, signal.SIGKILL)
        return host.proc.wait()

    def _interrupted(self, host: Child) -> int:
        """SIGINT / SIGTERM / SIGHUP: the host first (it marks the summary), then the rest."""
        assert self._signal is not None
        exit_code = self._signal_exit()
        if host.proc.poll() is None:
            self._stop_host(host, signal.SIGINT if self._signal == signal.SIGINT else signal.SIGTERM)
        summary = self._load_summary()
        if summary is not None and not summary.get("interrupted") and not summary.get("completed"):
            summary["interrupted"] = {
                "signal": signal.Signals(self._signal).name,
                "trial": len(summary["iterations"]),
                "tick": None,
                "by": "launcher",
            }
            self._save(summary)
        return exit_code

    # -- the end of a run --------------------------------------------------------------------

    def _load_summary(self) -> dict[str, Any] | None:
        if self.out_dir is None:
            return None
        try:
            data = json.loads((self.out_dir / "summary.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) and isinstance(data.get("iterations"), list) else None

    def _save(self, summary: dict[str, Any], report: bool = False) -> None:
        from host.experiment.summary import OutputError, write_summary

        assert self.out_dir is not None
        try:
            write_summary(self.out_dir, summary)
        except OutputError as err:
            logger.error("cannot update the summary: %s", err)
            return
        if report:
            try:
                from host.analysis.run_report import write_run_report

                write_run_report(self.out_dir, summary)
            except Exception:  # noqa: BLE001 - the report must not hide the fault line
                logger.info("report.md not written", exc_info=True)

    def _conclude(self, host: Child, code: int) -> int:
        """The exit code, the summary's fault record and evidence, and the one terminal line."""
        host_death = None
        if code != 0 and not self._host_stopped and code not in (EXIT_USAGE, EXIT_FAULT):
            host_death = Death("host", host.pid, _describe_status(code), time.monotonic(), host.log_path, code)
        if code == EXIT_OK and not self.deaths:
            return EXIT_OK
        if code == EXIT_OK:  # the run completed; something ended afterwards
            self._say_err(f"ilcrig: note: {self.deaths[0].describe()} after the last trial")
            return EXIT_OK
        if code == EXIT_USAGE:
            line = next((ln for ln in reversed(_tail(host.log_path, 40)) if ln.startswith("ilcrig: error:")), None)
            self._say_err(line or f"ilcrig: error: the host refused the experiment; its log: {host.log_path}")
            return EXIT_USAGE
        summary = self._load_summary()
        kept = len(summary["iterations"]) if summary is not None else 0
        first = self.deaths[0] if self.deaths else host_death
        record = None
        if summary is not None and summary.get("faults"):
            record = FaultRecord.from_dict(summary["faults"][0])
        elif code == EXIT_FAULT and not self.deaths:  # the host ended with a fault it did not put in a summary
            line = next((ln for ln in reversed(_tail(host.log_path, 40)) if ln.startswith("ilcrig: ")), None)
            self._say_err(
                f"{line}; the host's log: {host.log_path}"
                if line
                else f"ilcrig: fault: the host ended the run with exit code {code}; its log: {host.log_path}"
            )
            return EXIT_FAULT
        if record is None:
            culprit = first or Death("host", host.pid, _describe_status(code), time.monotonic(), host.log_path, code)
            record = FaultRecord(
                FaultKind.PROCESS_DIED,
                f"{culprit.name} (pid {culprit.pid}) {culprit.status}",
                node=culprit.name,
                node_id=_node_id(culprit.name),
                trial=kept,
                detected_by="launcher",
                t_detected_mono=culprit.t_mono,
                latency_basis="process exit",
            )
            if self.out_dir is not None:
                attach_injection(record, read_injections(self.out_dir))
            if record.tick is None and record.injected and record.injected.get("trial") == record.trial:
                record.tick = record.injected.get("tick")
            if summary is not None:
                summary["faults"].append(record.as_dict())
        if first is not None:
            record.extra["process_ended"] = {
                "name": first.name,
                "pid": first.pid,
                "status": first.status,
                "log": str(first.log_path) if first.log_path else None,
            }
        if summary is not None:
            summary["completed"] = False
            summary["faults"][0] = record.as_dict()
            since = first.t_mono if first is not None else (record.t_detected_mono or time.monotonic())
            if record.injected and record.injected.get("t_mono") is not None:
                since = float(record.injected["t_mono"])
            summary["safe_state"] = self._drive_evidence(summary.get("safe_state") or [], since)
            self._save(summary, report=True)
        concerned = next((c for c in self.children if c.name == record.node), None)
        if first is not None and record.kind == FaultKind.PROCESS_DIED and record.node == first.name:
            extra = f"its log: {first.log_path}"
        elif first is not None:
            extra = first.describe()
        elif concerned is not None and concerned.log_path is not None:
            extra = f"its log: {concerned.log_path}"
        elif record.node == "hub" and self.out_dir is not None:
            extra = f"its log: {self.out_dir / 'logs' / 'hub.log'}"
        else:
            extra = f"the host's log: {host.log_path}"
        summary_path = self.out_dir / "summary.json" if summary is not None and self.out_dir is not None else None
        self._say_err(fault_line(record, kept, summary_path=summary_path, extra=extra))
        return EXIT_FAULT

    def _drive_evidence(self, entries: list[dict[str, Any]], since: float) -> list[dict[str, Any]]:
        """Complete the drives' safe-state entries from their logs (SAFE-STATE records): stalled
        processes resume first, live drives get a consumer time to react to a lost host."""
        if self._injector is not None:
            self._injector.resume_all()
        by_node = {e.get("node"): dict(e) for e in entries}
        drives = [c for c in self.children if c.name.startswith("drive")]
        deadline = time.monotonic() + CONSUMER_TIME_MS / 1000.0 * timeout_scale() + 0.5
        while True:
            missing = []
            for c in drives:
                entry = by_node.setdefault(c.name, {"node": c.name, "node_id": _node_id(c.name), "torque": "unknown"})
                if entry.get("torque") == "off" and "its log" not in str(entry.get("evidence", "")):
                    continue  # the host saw it on the bus
                rec, on_after = last_state_in_log(_tail(c.log_path, 400), c.name)
                if rec is not None and not on_after:
                    entry.update(
                        torque="off",
                        cia402=rec.get("cia402"),
                        nmt=rec.get("nmt"),
                        evidence=f"its log: SAFE-STATE reason={rec.get('reason')}, tick {rec.get('tick')}"
                        + (f", {1000 * (float(rec['t_mono']) - since):+.0f} ms after the fault" if "t_mono" in rec else ""),
                    )
                elif c.proc.poll() is not None:
                    entry.update(torque="off", evidence=f"the process {_describe_status(c.proc.returncode)}: no power stage left")
                else:
                    missing.append(c)
            if not missing or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        return [by_node[c.name] for c in drives if c.name in by_node] + [
            e for n, e in by_node.items() if not str(n).startswith("drive")
        ]

    def _signal_exit(self) -> int:
        assert self._signal is not None
        name = signal.Signals(self._signal).name
        self._say_err(f"ilcrig: interrupted ({name}); stopping {len(self.children)} processes")
        return _SIGNAL_EXIT.get(self._signal, 128 + self._signal)

    # -- shutdown --------------------------------------------------------------------------

    def _shutdown(self) -> None:
        """SIGTERM every child's process group, wait ``grace_s``, SIGKILL, reap; stop the hub."""
        self._stopping = True
        try:
            if self._idle_pollers is not None:
                self._idle_pollers.stop()
            if self._injector is not None:
                self._injector.stop()  # resumes stalled processes
            self._terminate_children()
        finally:
            if self.hub is not None:
                try:
                    self.hub.stop()
                finally:
                    self.hub = None

    def _terminate_children(self) -> None:
        if not self.children:
            return
        for c in self.children:
            if c.proc.returncode is None:
                _killpg(c.pid, signal.SIGTERM)
                _killpg(c.pid, signal.SIGCONT)  # a stopped process must run to see its SIGTERM
        deadline = time.monotonic() + self.grace_s
        while time.monotonic() < deadline and not self._escalate:
            if all(c.proc.poll() is not None for c in self.children):
                break
            time.sleep(0.02)
        for c in self.children:
            if c.proc.poll() is None:
                logger.info("%s (pid %d) ignored SIGTERM for %.1f s: SIGKILL", c.name, c.pid, self.grace_s)
            _killpg(c.pid, signal.SIGKILL)  # also any process a role left behind in its group
        for c in self.children:
            c.proc.wait()
            logger.debug("%s (pid %d) reaped: %s", c.name, c.pid, _describe_status(c.proc.returncode))

    # -- signals and output ------------------------------------------------------------------

    def _install_signal_handlers(self) -> dict[int, Any]:
        if threading.current_thread() is not threading.main_thread():
            logger.debug("not the main thread: signals are not intercepted")
            return {}
        old = {}
        for signum in _HANDLED_SIGNALS:
            old[signum] = signal.signal(signum, self._on_signal)
        return old

    def _on_signal(self, signum: int, frame: object) -> None:
        if self._signal is None and not self._stopping:
            self._signal = signum
        else:
            self._escalate = True  # a signal while stopping: no grace period

    def _say_out(self, text: str) -> None:
        stream = self.stdout or sys.stdout
        stream.write(text + "\n")
        stream.flush()

    def _say_err(self, text: str) -> None:
        stream = self.stderr or sys.stderr
        stream.write(text + "\n")
        stream.flush()


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _killpg(pgid: int, signum: int) -> None:
    """Signal a child's process group (its own session); the child alone if that fails."""
    try:
        os.killpg(pgid, signum)
    except ProcessLookupError:
        pass
    except PermissionError:  # pragma: no cover - setsid failed: pgid is not ours
        with contextlib.suppress(ProcessLookupError):
            os.kill(pgid, signum)


def bus_time_rates(args: argparse.Namespace) -> dict[str, int] | None:
    """``--bus-time``: the hub's bit rate per channel (``--io-bitrate``, the experiment's fieldbus bit
    rate), None without the option."""
    if not getattr(args, "bus_time", False):
        return None
    from host.experiment.console import experiment_config

    return {FIELDBUS: int(experiment_config(args).fieldbus_bitrate), IO_CHANNEL: int(args.io_bitrate or DEFAULT_BITRATE_BPS)}


def launch_rig(args: argparse.Namespace) -> int:
    """``ilcrig run``: check everything (:func:`preflight`), then launch hub (if needed), plant,
    four drives and the host; return the run's exit code after every process is gone (see the
    module docstring).

    :raises ValueError: bad input (reported by the CLI in one line, exit code 2)
    """
    preflight(args)
    return RigLauncher(args).run()
