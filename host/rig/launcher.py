"""The process launcher of ``ilcrig run``: starts the distributed rig and always cleans it up.

This module owns the lifecycle of the processes of one ``ilcrig run``:

* the bus hub (only when the transport is ``hub``), started with :func:`bus.transports.hub_server.start_hub` on a
  fresh private Unix socket (a temp directory per run, so concurrent runs never collide) unless
  ``--hub ADDR`` names the address it must listen on;
* the plant (``ilcrig plant``), four drives (``ilcrig drive --node 1..4``) and the host
  (``ilcrig host <the same experiment options> --out DIR``), each started as
  ``[sys.executable, "-m", "host.cli", ROLE, ...]`` with the same ``--bus``/``--hub``.

Output
    The host inherits the launcher's stdout/stderr (it prints the progress table). The plant's
    and the drives' stdout+stderr go to log files ``<out>/logs/<name>.log`` (``plant``,
    ``drive1`` … ``drive4``) so the terminal stays readable; when one of them ends early the
    launcher prints a one-line message naming it and its exit code, followed by the last lines
    of its log (so a crash's traceback is visible). One status line naming the transport and
    the pids is printed before the host starts.

Lifetime
    Every child runs in its own session (``setsid``: a terminal Ctrl-C reaches only the
    launcher, which then stops the children in order) and has ``PR_SET_PDEATHSIG = SIGKILL``
    (set with ``prctl`` through ctypes in ``preexec_fn``), so a SIGKILLed launcher still takes
    them down; the hub exits when its stdin (a pipe from the launcher) reaches EOF, and is
    started with SIGINT/SIGHUP blocked, so a terminal Ctrl-C does not close it under the roles'
    feet. In every
    other exit path — host finished, a child ended early, SIGINT/SIGTERM/SIGHUP, an exception —
    the launcher sends SIGTERM to every child's process group, waits up to
    :data:`TERMINATE_GRACE_S`, sends SIGKILL to what is left, reaps every child and stops the
    hub (which removes its socket). A second signal during that grace period skips to SIGKILL.

Exit code
    The host's exit code (0 ok, 2 bad input, 3 trial fault; 128+N if a signal N killed it);
    :data:`EXIT_CHILD_FAILED` (4) when the plant or a drive ended while the host was running,
    or a process could not be started; 130 / 143 / 129 after SIGINT / SIGTERM / SIGHUP.

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

from bus.objects import DRIVE_NODE_IDS
from host.experiment.console import EXIT_CHILD_FAILED, EXIT_INTERRUPTED, EXIT_TERMINATED, experiment_actions

__all__ = [
    "EXIT_CHILD_FAILED",
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
    "rig_role_args",
    "role_command",
]

logger = logging.getLogger(__name__)

#: exit code when the plant or a drive ended while the host ran, or a process did not start
#: watch-loop period, s
POLL_S: float = 0.05
#: how long children get after SIGTERM before SIGKILL, s
TERMINATE_GRACE_S: float = 3.0
#: the drives' node ids (one per joint)
#: lines of a failed child's log shown on the terminal
LOG_TAIL_LINES: int = 8
#: environment variable prefix of the role-command test hook
ROLE_ENV_PREFIX: str = "ILCRIG_ROLE_CMD_"
#: test hook: role name ("host", "plant", "drive", "drive1" …) → argv prefix replacing
#: ``[sys.executable, "-m", "host.cli", ROLE]``
ROLE_COMMAND: dict[str, list[str]] = {}

_SIGNAL_EXIT: dict[int, int] = {signal.SIGINT: EXIT_INTERRUPTED, signal.SIGTERM: EXIT_TERMINATED,
                                 signal.SIGHUP: 128 + signal.SIGHUP}
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
    """The rig options of ``args`` (``--realtime``, ``--io-bitrate``) that the host role takes too
    (``--fieldbus-bitrate`` is an experiment option and goes with :func:`host_role_args`)."""
    argv = ["--realtime"] if args.realtime else []
    if args.io_bitrate is not None:
        argv += ["--io-bitrate", str(args.io_bitrate)]
    return argv


def child_argv(role: str, bus_args: Sequence[str], *, node: int | None = None, extra: Sequence[str] = (),
               debug: bool = False) -> list[str]:
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
    :ivar log_path: where its stdout/stderr go (None: the launcher's terminal)
    """

    name: str
    proc: subprocess.Popen[bytes]
    argv: list[str]
    log_path: Path | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid


@dataclass
class RigLauncher:
    """Starts and supervises the processes of one ``ilcrig run`` (see the module docstring).

    :param args: the parsed ``ilcrig run`` Namespace
    :param stdout: stream of the status line (default ``sys.stdout``)
    :param stderr: stream of error / exit messages (default ``sys.stderr``)
    :param grace_s: SIGTERM → SIGKILL grace period, s
    :ivar children: every started role process, in start order (the host last)
    :ivar hub: the hub handle while it runs
    :ivar watch_cpu_s: CPU time (user+sys) the launcher used while watching, s
    :ivar watch_wall_s: wall time of the watch loop, s
    """

    args: argparse.Namespace
    stdout: IO[str] | None = None
    stderr: IO[str] | None = None
    grace_s: float = TERMINATE_GRACE_S
    children: list[Child] = field(default_factory=list)
    hub: Any = None
    transport_name: str = ""
    hub_address: str | None = None
    out_dir: Path | None = None
    watch_cpu_s: float = 0.0
    watch_wall_s: float = 0.0
    _signal: int | None = None
    _escalate: bool = False
    _stopping: bool = False

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
            raise ValueError("the virtual transport works inside one process only; use hub, socketcan, "
                             "udp_multicast or can_config with `ilcrig run`")
        self.transport_name = tc.name
        self.out_dir = Path(args.out) if args.out else Path("runs") / time.strftime("run-%Y%m%d-%H%M%S")
        log_dir = self.out_dir / "logs"
        try:
            log_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ValueError(f"cannot create the run folder {log_dir}: {err.strerror or err}") from err

        bus_args = ["--bus", tc.name]
        if tc.needs_hub:
            self._start_hub(args.hub)
            bus_args += ["--hub", str(self.hub_address)]
        if self._signal is not None:
            return self._signal_exit()

        self._spawn("plant", child_argv("plant", bus_args, debug=debug), log_dir / "plant.log")
        for node in DRIVE_NODE_IDS:
            if self._signal is not None:
                return self._signal_exit()
            self._spawn(f"drive{node}", child_argv("drive", bus_args, node=node, debug=debug),
                        log_dir / f"drive{node}.log")
        if self._signal is not None:
            return self._signal_exit()

        where = f" ({self.hub_address})" if self.hub_address else ""
        pids = ([f"hub {self.hub.pid}"] if self.hub is not None else []) + [f"{c.name} {c.pid}" for c in self.children]
        self._say_out(f"ilcrig run: transport {tc.name}{where}; processes: {', '.join(pids)}; "
                      f"role logs in {log_dir}; starting host")
        host_extra = host_role_args(args) + rig_role_args(args) + ["--out", str(self.out_dir)]
        host = self._spawn("host", child_argv("host", bus_args, extra=host_extra, debug=debug), None)
        logger.info("host pid %d: %s", host.pid, " ".join(host.argv))
        return self._watch(host)

    def _start_hub(self, address: str | None) -> None:
        from bus.transports.hub_server import HubError, start_hub

        # The hub stays in the launcher's process group (start_hub's Popen); with SIGINT/SIGHUP
        # blocked across fork+exec (the signal mask is inherited), a terminal Ctrl-C reaches only
        # the launcher, and the hub lives until the roles are stopped (then stdin EOF stops it).
        old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, _HUB_BLOCKED_SIGNALS)
        try:
            self.hub = start_hub(address)  # None: hub.sock in a fresh private temp directory
        except HubError as err:
            if isinstance(err, ValueError):
                raise
            raise LaunchError(f"cannot start the bus hub{f' on {address}' if address else ''}: {err}") from err
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a pending Ctrl-C is handled now
        self.hub_address = self.hub.address
        logger.info("hub pid %d on %s", self.hub.pid, self.hub_address)

    def _spawn(self, name: str, argv: list[str], log_path: Path | None) -> Child:
        log = open(log_path, "ab") if log_path is not None else None  # noqa: SIM115 - closed below
        try:
            proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT if log is not None else None,
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

    def _watch(self, host: Child) -> int:
        others = [c for c in self.children if c is not host]
        cpu0, wall0 = _cpu_s(), time.monotonic()
        try:
            while True:
                if self._signal is not None:  # first: the roles may fail because of the same Ctrl-C
                    return self._signal_exit()
                code = host.proc.poll()
                if code is not None:
                    for c in others:  # a role that died first probably caused the host's end
                        if c.proc.poll() is not None:
                            self._say_err(f"ilcrig: note: {c.name} (pid {c.pid}) {_describe_status(c.proc.returncode)} "
                                          "before the host finished")
                    if code < 0:
                        self._say_err(f"ilcrig: host (pid {host.pid}) {_describe_status(code)}")
                        return 128 - code
                    return code
                for c in others:
                    if c.proc.poll() is not None:
                        self._report_early_exit(c)
                        return EXIT_CHILD_FAILED
                time.sleep(POLL_S)
        finally:
            self.watch_cpu_s, self.watch_wall_s = _cpu_s() - cpu0, time.monotonic() - wall0
            logger.info("launcher used %.3f s CPU in %.1f s of watching", self.watch_cpu_s, self.watch_wall_s)

    def _report_early_exit(self, c: Child) -> None:
        where = f"; its log: {c.log_path}" if c.log_path else ""
        self._say_err(f"ilcrig: error: {c.name} (pid {c.pid}) {_describe_status(c.proc.returncode)} "
                      f"while the host was running; stopping the rig{where}")
        for line in _tail(c.log_path, LOG_TAIL_LINES):
            self._say_err(f"  {c.name}| {line}")

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
        deadline = time.monotonic() + self.grace_s
        while time.monotonic() < deadline and not self._escalate:
            if all(c.proc.poll() is not None for c in self.children):
                break
            time.sleep(0.02)
        for c in self.children:
            if c.proc.poll() is None:
                logger.warning("%s (pid %d) ignored SIGTERM for %.1f s: SIGKILL", c.name, c.pid, self.grace_s)
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


def launch_rig(args: argparse.Namespace) -> int:
    """``ilcrig run``: launch hub (if needed), plant, four drives and the host; return the
    host's exit code after every process is gone (see the module docstring).

    :raises ValueError: bad transport / hub address (reported by the CLI, exit code 2)
    """
    return RigLauncher(args).run()
