"""``ilcrig robot``: the four drives and the plant as a robot on the bus, for any CANopen master.

This module owns :func:`launch_robot` and :class:`RobotLauncher` (docs/robot.md): no ILC host runs;
the robot waits at its home pose, its drives in Switch on disabled (the joints held by their
brakes), for a master — a PLC, ros2_canopen, a python-canopen script — and runs until Ctrl-C /
SIGTERM (exit 130 / 143) or a fault of one of its own processes (exit 3, one line
``ilcrig: fault: …``).  It reuses the processes of ``ilcrig run``:

* the transport as ``ilcrig run`` chooses it (``--bus``: SocketCAN vcan0/vcan1 when both exist,
  else the zero-privilege hub on a fresh private socket, or ``--hub ADDRESS``), the hub started
  with :func:`host.rig.processes.start_hub_process`;
* the plant (``ilcrig plant --robot sync|realtime``: one control period per SYNC,
  :mod:`plant.plant_node_robot`; its period trace ``trace.bin`` and its session summary
  ``plant.json``) and the drives ``ilcrig drive --node 1..4 --lockstep`` (drives of a SYNC-stepped
  plant; ``--param-dir`` passed on), started and stopped by the launch core
  (:class:`host.rig.launch_core.LaunchCore`: own sessions, dying with the launcher, reaped on every
  path); with ``--realtime`` the scheduling of ``ilcrig run --realtime``: SCHED_FIFO where
  permitted, else the fair-scheduling fallback (:mod:`host.rig.fair_scheduling`), and the
  idle-poll loops beside SCHED_FIFO;
* two passive channel monitors (:class:`host.rig.monitor.ChannelMonitor`) write the candump logs
  ``fieldbus.log`` and ``io.log`` and feed :class:`host.rig.robot_watch.RobotBusWatch` (boot-ups:
  the robot is announced once all five nodes booted; SYNCs; EMCYs; with ``--view`` the live view
  :class:`host.analysis.live_view.RobotLiveView`).  A bus error frame a monitor hears (a frame
  damaged on the wire, or lost in the monitor's own receiver: udp_multicast reports a datagram the
  kernel dropped so) means that log and the counts it feeds miss frames: one console line per
  channel as it is heard, its count in the summary (``bus.channels.<name>.error_frames``); heard on
  the fieldbus while the nodes boot (a boot-up may be among the frames lost) it ends the start as a
  fault (exit 3) instead of a wait for a boot-up already sent.

The run folder (``--out``, default ``runs/robot-<time>``): ``logs/<role>.log``, ``trace.bin``,
``fieldbus.log``, ``io.log``, ``plant.json`` and, on every exit, ``summary.json`` (schema
``ilcrig.robot/1``: how it ended, the transport and processes, the plant's session — periods
stepped, SYNCs seen, late / missing SYNCs, overruns, faults — and what the monitors saw).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus.atomic import atomic_write
from bus.errors import InputError
from bus.exit_codes import EXIT_CHILD_FAILED, EXIT_FAULT
from bus.objects import DRIVE_EDS_PATH, DRIVE_NODE_IDS
from bus.plant_objects import DEFAULT_PLANT_NODE_ID, PLANT_EDS_PATH
from bus.transports.config import FIELDBUS, HUB_INTERFACE, TransportConfig
from bus.transports.config import IO as IO_CHANNEL
from bus.units import timeout_scale
from host.experiment.outputs import SUMMARY_NAME, RunFolder, check_out_dir
from host.rig.janitor import plant_session
from host.rig.launch_core import LaunchCore, check_transport, make_run_folder
from host.rig.monitor import ChannelMonitor
from host.rig.options import RobotOptions
from host.rig.processes import Death, LaunchError, describe_status
from host.rig.realtime import scheduling_text
from host.rig.robot_watch import RobotBusWatch, robot_fault_of
from host.rig.role_commands import child_argv

logger = logging.getLogger(__name__)

__all__ = ["BOOT_TIMEOUT_S", "SUMMARY_SCHEMA", "RobotLauncher", "launch_robot"]

#: how long the nodes get to boot (a first start compiles the numba kernels), s (× scale)
BOOT_TIMEOUT_S: float = 120.0
#: watch-loop period, s
POLL_S: float = 0.05
#: how long a fault waits to see whether the hub ended too (then that is the fault: it takes every
#: member's bus with it), s
HUB_DEATH_WAIT_S: float = 0.5
SUMMARY_SCHEMA = "ilcrig.robot/1"
#: the control period the robot starts with (the plant's 0x2400:1 default), s
DEFAULT_TS_S: float = 1e-3


@dataclass(eq=False)
class RobotLauncher(LaunchCore):
    """Starts, announces, watches and stops the robot (see the module docstring).

    :param options: the robot's options
    :param stdout: stream of the announcement and the closing line (default ``sys.stdout``)
    :param stderr: stream of the fault / error line (default ``sys.stderr``)
    :param grace_s: SIGTERM → SIGKILL grace period, s
    :ivar children: the plant and the drives, in start order
    :ivar out_dir: the run folder
    """

    options: RobotOptions
    transport: TransportConfig | None = field(default=None, init=False)
    watch: RobotBusWatch = field(default_factory=RobotBusWatch, init=False)
    monitors: list[ChannelMonitor] = field(default_factory=list, init=False)
    deaths: list[Death] = field(default_factory=list, init=False)
    live: Any = field(default=None, init=False)
    #: the channels whose bus error frames the console was told of
    _errors_said: set[str] = field(default_factory=set, init=False, repr=False)
    _t0: float = field(default_factory=time.time, init=False, repr=False)
    _end: dict[str, Any] = field(default_factory=lambda: {"reason": "starting"}, init=False, repr=False)
    _scheduling: dict[str, Any] | None = field(default=None, init=False, repr=False)
    #: the run folder's space reserve (given back for the last records after a full disk)
    _space: RunFolder | None = field(default=None, init=False, repr=False)
    #: the ready lines were printed (the robot took SYNCs from then on)
    _ready: bool = field(default=False, init=False, repr=False)

    # ------------------------------------------------------------------ run

    def _launch_failed(self, err: LaunchError) -> None:
        self._end = {"reason": "launch failed", "error": str(err)}

    def _launch_and_watch(self) -> int:
        from bus.transports.config import transport_from_name

        opts = self.options
        debug = opts.debug
        tc = transport_from_name(opts.bus, opts.hub, opts.allow_remote)
        out, log_dir = make_run_folder(opts.out or None, "robot")
        self.out_dir = out
        self._space = RunFolder(out, 0)
        self._space.reserve()  # room for the last records after a full disk (_records_failed)
        bus_args = ["--bus", tc.name]
        if tc.needs_hub:
            bus_args += ["--hub", self.start_hub(None, log_dir / "hub.log")]
            tc = transport_from_name(tc.name, self.hub_address)
        self.transport = tc
        if opts.view:
            self._start_view()
        self._open_monitors(tc, out)
        if self.interrupts.signum is not None:
            return self._interrupted()
        mode = "realtime" if opts.realtime else "sync"
        plant_extra = ["--robot", mode, "--trace", str(out / "trace.bin"), "--summary", str(out / "plant.json")]
        # SIGTERM when the launcher dies: the plant ends its session (plant.json, the trace) for the janitor
        plant = self.spawn(
            "plant",
            child_argv("plant", bus_args, extra=plant_extra, debug=debug),
            log_dir / "plant.log",
            death_signal=signal.SIGTERM,
        )
        self.start_janitor(plant.pid, robot=True)
        # drives of a SYNC-stepped plant: a SYNC's TPDOs carry its control cycle (docs/robot.md, Time)
        param_dir = opts.param_dir
        drive_extra = ["--lockstep"] + (["--param-dir", str(Path(param_dir).resolve())] if param_dir else [])
        drive_extra += ["--firmware", opts.firmware] if opts.firmware != "python" else []  # (the default)
        for node in DRIVE_NODE_IDS:
            argv = child_argv("drive", bus_args, node=node, extra=drive_extra, debug=debug)
            self.spawn(f"drive{node}", argv, log_dir / f"drive{node}.log")
        self._write_summary(None)  # "starting": what a killed launcher leaves for the janitor to end
        code = self._wait_booted()
        if code is not None:
            return code
        if opts.realtime:
            self._scheduling = self.schedule_realtime()  # no host: SCHED_FIFO, else the fair-scheduling fallback
        self._end = {"reason": "running"}
        self._write_summary(None)
        self._announce(tc, mode)
        return self._watch()

    def _open_monitors(self, tc: TransportConfig, out: Path) -> None:
        """The candump logs and the watch, joined before the nodes start (their boot-ups are seen)."""
        w = self.watch
        for name, one, many in ((FIELDBUS, w.fieldbus_frame, w.fieldbus_frames), (IO_CHANNEL, w.io_frame, w.io_frames)):
            bulk = tc.channel(name).interface == HUB_INTERFACE
            self.monitors.append(
                ChannelMonitor(tc.open(name, passive=True), name, out / f"{name}.log", one, bulk=bulk, classify_frames=many)
            )

    def _start_view(self) -> None:
        from host.analysis.live_view import LiveView, RobotLiveView

        live = LiveView()
        self.live = RobotLiveView(live, DEFAULT_TS_S)
        self.watch.on_period = self.live.on_period
        self.watch.follow_targets(self.live.add_targets)
        self._say_out(live.open_viewer())

    def _wait_booted(self) -> int | None:
        """Until all five nodes booted; an exit code if a signal, a death or the timeout came first."""
        deadline = time.monotonic() + BOOT_TIMEOUT_S * timeout_scale()
        while not self.watch.wait_booted(POLL_S):
            if self.interrupts.signum is not None:
                return self._interrupted()
            if self._note_deaths():
                return self._fault()
            fieldbus = next((m for m in self.monitors if m.name == FIELDBUS and m.error_frames), None)
            if fieldbus is not None and not self.watch.wait_booted(0):
                missing = self._not_booted()
                self._end = {
                    "reason": "fault",
                    "channel": FIELDBUS,
                    "error_frames": fieldbus.error_frames,
                    "missing_nodes": missing,
                }
                self._say_err(
                    f"ilcrig: fault: bus error frame on {FIELDBUS} while the nodes booted (frames lost or damaged; "
                    f"the boot-up of node(s) {missing} may be among them); the robot stopped, every process of it ended"
                )
                return EXIT_FAULT
            self._say_monitor_errors()
            if self._records_lost() is not None:
                return self._records_failed()
            if time.monotonic() > deadline:
                missing = self._not_booted()
                self._end = {"reason": "boot timeout", "missing_nodes": missing}
                self._say_err(
                    f"ilcrig: error: node(s) {missing} did not boot within {BOOT_TIMEOUT_S * timeout_scale():.0f} s; "
                    f"their logs: {self._log('')}"
                )
                return EXIT_CHILD_FAILED
        return None

    def _not_booted(self) -> list[int]:
        """The node ids of the robot whose boot-up the watch has not seen."""
        return sorted((set(DRIVE_NODE_IDS) | {DEFAULT_PLANT_NODE_ID}) - self.watch.booted)

    def _announce(self, tc: TransportConfig, mode: str) -> None:
        self._ready = True
        fb = tc.channel(FIELDBUS)
        if fb.interface == HUB_INTERFACE:
            where = (
                f"  connect: python-can interface={HUB_INTERFACE} channel={fb.channel}\n"
                f'    (python canopen: network.connect(interface="{HUB_INTERFACE}", channel="{fb.channel}"))\n'
            )
        else:
            where = f"  connect: python-can interface={fb.interface} channel={fb.channel}\n"
        time_mode = (
            "one control period per SYNC (COB-ID 0x080), paced to the wall clock (--realtime)"
            if mode == "realtime"
            else "one control period per SYNC (COB-ID 0x080), deterministic"
        )
        # real time: how the processes are scheduled, in the words of ilcrig run --realtime's timing line
        sched = "" if self._scheduling is None else f"  scheduling: {scheduling_text(self._scheduling)}\n"
        self._say_out(
            f"ilcrig robot: ready: drives = nodes {', '.join(map(str, DRIVE_NODE_IDS))} (joints 1-4), "
            f"plant = node {DEFAULT_PLANT_NODE_ID}; transport {tc.name}\n"
            + where
            + f"  EDS: drives {DRIVE_EDS_PATH}, plant {PLANT_EDS_PATH}\n"
            f"  time: {time_mode}; the robot stands at its home pose, drives in Switch on disabled, brakes closed\n"
            + sched
            + f"  run folder {self.out_dir} (processes: {self.pids_text()}); Ctrl-C to stop"
        )

    def _watch(self) -> int:
        emcys_seen = 0
        while True:
            if self.interrupts.signum is not None:
                return self._interrupted()
            if self._note_deaths():
                return self._fault()
            emcys_seen = self._say_robot_faults(emcys_seen)
            self._say_monitor_errors()
            if self._records_lost() is not None:
                return self._records_failed()
            time.sleep(POLL_S)

    def _records_lost(self) -> ChannelMonitor | None:
        """The first monitor that stopped keeping the session's records: its candump log failed (a
        full disk) or its bus did (the hub drops a member that stopped reading: a launcher stopped
        with Ctrl-Z for long enough), if any."""
        return next((m for m in self.monitors if m.log_error is not None or m.bus_error is not None), None)

    def _records_failed(self) -> int:
        """A channel's records stopped (:meth:`_records_lost`): the session's records would be
        incomplete from there, so the session ends as a fault — one line, exit 3 —, the space
        reserve given back first so that the plant's session and the summary still fit."""
        m = self._records_lost()
        assert m is not None
        if m.log_error is None and self._hub_death_within(HUB_DEATH_WAIT_S):
            return self._fault()  # the hub ended, and the monitor's bus with it: that is the fault
        if self._space is not None:
            self._space.release_last()
        if m.log_error is not None:
            self._end = {
                "reason": "fault",
                "records": f"{m.name}.log",
                "error": m.log_error,
                "disk_full": m.log_disk_full,
                "t_mono": m.log_error_t,
            }
            what = f"cannot write {m.name}.log in {self.out_dir} ({m.log_error})"
        else:
            self._end = {"reason": "fault", "records": f"{m.name} monitor", "error": m.bus_error, "t_mono": m.bus_error_t}
            what = f"the {m.name} channel's monitor lost its bus ({m.bus_error}; a hub drops a reader that stops reading)"
        self._say_err(
            f"ilcrig: fault: {what}: the session's records would stop there; the robot stopped, every process of it ended"
        )
        return EXIT_FAULT

    def _hub_death_within(self, timeout_s: float) -> bool:
        """Whether the hub ended (noted among :attr:`deaths`) within ``timeout_s``: a hub that stops
        closes its members' connections first — the drives, the plant and the monitors lose their
        bus at once, and a drive may exit before the hub's own exit is seen."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._note_deaths()
            if any(d.name == "hub" for d in self.deaths):
                return True
            if self.hub is None or time.monotonic() >= deadline:
                return False
            time.sleep(0.01)

    def _say_monitor_errors(self) -> None:
        """One console line per channel whose monitor heard its first bus error frame since the
        last look: its candump log and the counts it feeds miss frames from there on."""
        for m in self.monitors:
            if m.error_frames and m.name not in self._errors_said:
                self._errors_said.add(m.name)
                what = (
                    "frames lost in a receiver's full queue (receive overflow)"
                    if m.overflow_frames == m.error_frames
                    else "a frame damaged on the wire, or lost in the monitor's receiver"
                )
                self._say_err(
                    f"ilcrig robot: bus error frame on {m.name} ({what}): "
                    f"{m.name}.log and the bus counts of summary.json miss frames"
                )

    def _say_robot_faults(self, start: int) -> int:
        """One console line per robot fault the plant reported by EMCY since the ``start``-th EMCY
        (never a silent fault: the robot stays up, torque-free, until the master resets it)."""
        with self.watch.lock:
            new = self.watch.emcys[start:]
        for emcy in new:
            text = robot_fault_of(emcy)
            if text is not None:
                self._say_err(f"ilcrig robot: {text}; joints braked, torques not applied until 0x2450:2 = 1 (fault reset)")
        return start + len(new)

    def _note_deaths(self) -> bool:
        """Note every process (the hub too) that ended since the last look; True if any did."""
        noted = {d.name for d in self.deaths}
        now = time.monotonic()
        if self.hub is not None and "hub" not in noted and not self.hub.alive:
            code = self.hub.process.returncode
            self.deaths.append(Death("hub", self.hub.pid, describe_status(code), now, self._log("hub"), code))
        for c in self.children:
            if c.name not in noted:
                code = c.proc.poll()
                if code is not None:
                    self.deaths.append(Death(c.name, c.pid, describe_status(code), now, c.log_path, code))
        return bool(self.deaths)

    def _log(self, name: str) -> Path | None:
        """The log of process ``name`` (``""``: the logs folder)."""
        if self.out_dir is None:
            return None
        return self.out_dir / "logs" / f"{name}.log" if name else self.out_dir / "logs"

    def _fault(self) -> int:
        """A process of the robot ended: one line, exit 3 (the rest is stopped by the shutdown). The
        hub's end is the fault when it ended too (it takes the others' buses with it): it gets
        :data:`HUB_DEATH_WAIT_S` to be seen."""
        self._hub_death_within(HUB_DEATH_WAIT_S)
        hub = next((d for d in self.deaths if d.name == "hub"), None)
        first = hub or self.deaths[0]
        self._end = {"reason": "fault", "process": first.name, "pid": first.pid, "status": first.status}
        self._say_err(f"ilcrig: fault: {first.describe()}; the robot stopped, every process of it ended")
        return EXIT_FAULT

    def _interrupted(self) -> int:
        self._end = {"reason": "interrupted", "signal": self.interrupts.name}
        return self.say_interrupted()

    # ------------------------------------------------------------------ shutdown

    def _children_ended(self) -> None:
        for m in self.monitors:
            m.catch_up(timeout_s=1.0)

    def _close_watchers(self) -> None:
        """The monitors (before the hub: its end is not a failure of theirs) and the live view."""
        try:
            for m in self.monitors:
                m.close()
        finally:
            if self.live is not None:
                self.live.close()

    def _closing(self, code: int) -> None:
        if self._space is not None:
            self._space.release_last()  # every process has ended: the summary is the last write
        written = self._write_summary(code)
        if written is not None:
            self._say_closing(*written)

    def _write_summary(self, code: int | None) -> tuple[Path, dict[str, Any] | None] | None:
        """``summary.json`` of the session (module docstring) as it stands: written when the
        processes are started (``end`` ``starting``, ``exit_code`` null), when the robot is ready
        (``running``) and on every exit (the exit code); its path and the robot's session (None: no
        folder, or the write failed: said on stderr at the exit)."""
        out = self.out_dir
        if out is None:
            return None
        robot, plant = plant_session(out) if code is not None else (None, None)
        channels = {
            m.name: m.counter.as_dict() | {"error_frames": m.error_frames, "overflow_frames": m.overflow_frames}
            for m in self.monitors
        }
        summary = {
            "schema": SUMMARY_SCHEMA,
            "exit_code": code,
            "end": self._end,
            "started": self._t0,
            "duration_s": time.time() - self._t0,
            "mode": "realtime" if self.options.realtime else "sync",
            "firmware": self.options.firmware,
            "transport": self.transport.as_dict() if self.transport is not None else None,
            "processes": {c.name: c.pid for c in self.children} | ({"hub": self.hub_address} if self.hub_address else {}),
            "deaths": [{"name": d.name, "pid": d.pid, "status": d.status} for d in self.deaths],
            "scheduling": self._scheduling,
            "robot": robot,
            "plant": plant,
            "bus": self.watch.info() | {"channels": channels},
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        }
        path = out / SUMMARY_NAME
        text = json.dumps(summary, indent=2, default=str) + "\n"
        try:
            atomic_write(path, text, fsync=True)
        except OSError as err:
            if code is None:
                logger.warning("cannot write %s: %s", path, err)
                return None
            # the last word: the summary kept while the robot ran says it still runs — never leave
            # that behind; its space may be what this one needs
            with contextlib.suppress(OSError):
                path.unlink()
            try:
                atomic_write(path, text, fsync=True)
            except OSError:
                self._say_err(f"ilcrig: error: cannot write {path}: {err.strerror or err}; the session left no summary")
                return None
        return path, robot

    def _say_closing(self, path: Path, robot: dict[str, Any] | None) -> None:
        """The closing line on stdout: the periods stepped and the SYNCs seen, or why there are none."""
        if robot is not None:
            rt = robot.get("realtime") or {}
            late = (
                f", late SYNCs {rt.get('late_syncs', 0)}, missing {rt.get('missing_syncs', 0)}, "
                f"late periods {rt.get('late_periods', 0)}"
                if rt
                else ""
            )
            trace = robot.get("trace") or {}
            lost = f"; trace.bin holds {trace['records']} of them ({trace['error']})" if trace.get("error") is not None else ""
            self._say_out(
                f"ilcrig robot: {robot['periods']} periods stepped, {robot['syncs']} SYNCs seen "
                f"({robot['sync_overruns']} overruns{late}), {robot['faults_total']} robot faults{lost}; summary: {path}"
            )
        elif not self._ready:  # it ended while starting: say how, not that a summary is missing
            end = self._end
            how = f"interrupted ({end['signal']})" if end["reason"] == "interrupted" else str(end["reason"])
            self._say_out(f"ilcrig robot: {how} before the robot was ready: no period stepped; summary: {path}")
        else:
            self._say_out(f"ilcrig robot: the plant left no session summary; summary: {path}")


def launch_robot(options: RobotOptions) -> int:
    """``ilcrig robot``: check the options, then run the robot until a signal or a fault (the
    module docstring); returns the exit code.

    :raises ValueError: bad input (the CLI's one line, exit code 2), before anything starts
    """
    if options.rt_priority is not None and not options.realtime:
        raise InputError(f"--rt-priority {options.rt_priority}: the priority of a real-time robot; add --realtime")
    if options.no_idle_poll and not options.realtime:
        raise InputError("--no-idle-poll: the CPUs are kept awake only in real time; add --realtime")
    if options.param_dir and Path(options.param_dir).exists() and not Path(options.param_dir).is_dir():
        raise InputError(f"--param-dir {options.param_dir}: not a folder")
    if options.out:  # one session, one folder: never a second session over the records of another
        check_out_dir(options.out, create=False, new_run=True, iterations=0)
    check_transport(options)
    if not options.debug:
        # a monitor whose bus ends with a process of the robot is part of that fault, which the
        # launcher reports in its one line
        logging.getLogger("host.rig.monitor").setLevel(logging.ERROR)
    return RobotLauncher(options).run()
