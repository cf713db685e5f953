"""What outlives a killed ``ilcrig run``: its run folder made to hold what its summary says, and
the summary made to say how the run ended.

This module owns :func:`settle_run_folder` — ``recording.rrd`` cut back to the trials of
``summary.json`` (:func:`host.analysis.recording_segments.cut_back`), the temporary files of atomic writes
and the trial arrays the summary does not hold removed (:func:`host.experiment.outputs.remove_leftovers`)
—, :func:`mark_launcher_lost` (a summary the host could not finish: ``end_reason``
``launcher_lost``) and the janitor process that does both when nobody else can (``python -P -m host.cli.janitor
--out DIR --wait PID``: :func:`run_janitor`; :func:`start_janitor` / :class:`Janitor`).

The launcher settles the folder itself on every exit path it lives through (the host killed
included: :class:`host.rig.run_outcome.RunOutcome`).  A SIGKILL of the launcher ends the host too
(``PR_SET_PDEATHSIG``), possibly between its recording's write and its summary's: then the
janitor, started right after the host in a session of its own with a pipe from the launcher on its
stdin, sees that pipe close without the launcher's ``done``, waits for the host to be gone (a
pidfd opened while the host ran), settles the folder, marks the summary if the host had not
ended the run (a launcher killed by SIGKILL, SIGQUIT — Ctrl-\\ —, or any crash: otherwise its
``end_reason`` would stay empty, as in a run still going), writes what it did to
``logs/janitor.log`` and exits.  The space reserve needs nobody: it is a file without a name held open by the host
(:class:`host.experiment.outputs.RunFolder`).

``ilcrig robot`` has a janitor too (``--robot``), watching the plant: a killed robot launcher
ends the drives (SIGKILL) and the plant (SIGTERM, so that it writes its session, ``plant.json``,
and closes its trace); the janitor waits for the plant to be gone (SIGKILL after
:data:`HOST_WAIT_S`), then ends the ``summary.json`` the launcher keeps while the robot runs
(``end`` ``starting`` or ``running``, ``exit_code`` null): :func:`mark_robot_launcher_lost`, with
the plant's session read by :func:`plant_session` (the launcher's own summary reads it there too).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import IO, Any

from bus.processes import spawn_process

logger = logging.getLogger(__name__)

__all__ = [
    "DONE",
    "HOST_WAIT_S",
    "Janitor",
    "mark_launcher_lost",
    "mark_robot_launcher_lost",
    "plant_session",
    "run_janitor",
    "settle_run_folder",
    "start_janitor",
]

#: what the launcher writes when it has settled the folder itself
DONE = b"done\n"
#: longest the janitor waits for the host (the robot's plant) to be gone after the launcher died, s
HOST_WAIT_S = 30.0


def settle_run_folder(out_dir: str | Path) -> list[str]:
    """Make the run folder hold what its ``summary.json`` says (module docstring); returns what was
    done, one line each. Never raises (a failure is logged)."""
    from host.analysis.recording_segments import cut_back
    from host.experiment.outputs import read_summary, remove_leftovers

    d = Path(out_dir)
    done: list[str] = []
    try:
        summary = read_summary(d)
        kept = len(summary["iterations"]) if summary is not None else None
        rec = summary.get("recording") if summary is not None else None
        if isinstance(rec, dict) and isinstance(rec.get("bytes"), int):
            path = d / str(rec.get("file", "recording.rrd"))
            if cut_back(path, rec["bytes"]):
                done.append(f"cut {path} back to {rec['bytes']} bytes: the summary's {kept} trial(s)")
        done += [f"removed {p}" for p in remove_leftovers(d, kept)]
    except Exception:  # noqa: BLE001 - tidying must not raise
        logger.warning("cannot settle the run folder %s", d, exc_info=True)
    return done


def mark_launcher_lost(out_dir: str | Path) -> str | None:
    """The summary of a run whose launcher died before the run had ended (its ``end_reason`` still
    empty): ``end_reason`` ``launcher_lost`` and ``launcher_lost`` (when it was noticed, by whom,
    the trials kept); ``completed`` as the host left it. Returns the line that says so (None: the
    run had ended, or there is no summary). Never raises (a failure is logged)."""
    from host.experiment.loop_state import EndReason
    from host.experiment.outputs import read_summary
    from host.experiment.summary import write_summary

    d = Path(out_dir)
    try:
        summary = read_summary(d)
        if summary is None or summary.get("end_reason"):
            return None
        kept = len(summary.get("iterations") or [])
        summary["end_reason"] = str(EndReason.LAUNCHER_LOST)
        summary["launcher_lost"] = {"noticed_wall": time.time(), "noticed_by": "janitor", "trials_kept": kept}
        write_summary(d, summary)
    except Exception:  # noqa: BLE001 - tidying must not raise
        logger.warning("cannot mark the summary of %s", d, exc_info=True)
        return None
    return f"marked the summary: end_reason launcher_lost, {kept} trial(s) kept"


def plant_session(out: Path) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """The robot's session and the plant node's other counters, from the ``plant.json`` the plant
    writes as it ends (``summary.json``'s ``robot`` and ``plant``; None where it left none)."""
    try:
        plant = json.loads((out / "plant.json").read_text())
    except (OSError, ValueError):
        return None, None
    if not isinstance(plant, dict):
        return None, None
    return plant.get("robot"), {k: v for k, v in plant.items() if k != "robot"} or None


def mark_robot_launcher_lost(out_dir: str | Path) -> str | None:
    """The ``summary.json`` of a robot session whose launcher died while starting or running it
    (``exit_code`` still null): ``end`` ``{"reason": "launcher_lost", "was": …, "noticed_wall": …,
    "noticed_by": "janitor"}``, the plant's session (``robot``, ``plant``: what the plant wrote as it
    ended), the duration up to now; ``exit_code`` stays null (the launcher never exited). Returns the
    line that says so (None: the launcher ended the session itself, or there is no summary). Never
    raises (a failure is logged)."""

    from bus.atomic import atomic_write
    from host.experiment.outputs import SUMMARY_NAME

    d = Path(out_dir)
    path = d / SUMMARY_NAME
    try:
        summary = json.loads(path.read_text())
        if not isinstance(summary, dict) or summary.get("exit_code") is not None:
            return None
        now = time.time()
        was = (summary.get("end") or {}).get("reason")
        summary["end"] = {"reason": "launcher_lost", "was": was, "noticed_wall": now, "noticed_by": "janitor"}
        summary["robot"], summary["plant"] = plant_session(d)
        if isinstance(summary.get("started"), int | float):
            summary["duration_s"] = now - summary["started"]
        atomic_write(path, json.dumps(summary, indent=2, default=str) + "\n", fsync=True)
    except Exception:  # noqa: BLE001 - tidying must not raise
        logger.warning("cannot mark the summary of %s", d, exc_info=True)
        return None
    robot = summary["robot"]
    stepped = f"{robot['periods']} periods stepped, {robot['syncs']} SYNCs seen" if robot else "the plant left no session"
    return f"marked the summary: end launcher_lost (the robot was {was}); {stepped}"


class Janitor:
    """The janitor process of one run (:func:`start_janitor`); ``robot``: of an ``ilcrig robot``
    session (nothing to settle in its folder)."""

    def __init__(self, proc: subprocess.Popen[bytes], robot: bool = False) -> None:
        self.proc = proc
        self.robot = robot

    @property
    def pid(self) -> int:
        return self.proc.pid

    def done(self, timeout_s: float = 2.0) -> None:
        """The launcher settled the folder: the janitor exits without touching it (reaped here)."""
        if self.proc.stdin is not None:
            with contextlib.suppress(OSError):
                self.proc.stdin.write(DONE)
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def start_janitor(out_dir: Path, host_pid: int, robot: bool = False) -> Janitor | None:
    """Start the janitor of the run folder ``out_dir`` whose host is ``host_pid`` (``robot``: of the
    robot session whose plant is ``host_pid``); None: it could not be started (logged — the run goes
    on without it)."""
    argv = [sys.executable, "-P", "-m", "host.cli.janitor", "--out", str(out_dir), "--wait", str(host_pid)]
    argv += ["--robot"] if robot else []
    try:
        # a session of its own (a terminal's Ctrl-C is the launcher's) and no death signal: it outlives the launcher
        proc = spawn_process(argv, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, death_signal=None)
    except OSError as err:
        logger.warning("cannot start the run folder's janitor: %s", err)
        return None
    return Janitor(proc, robot)


def _launcher_gone(stdin: IO[bytes]) -> bool:
    """Block until the launcher writes ``done`` (False) or its end of the pipe closes first (True)."""
    data = b""
    while True:
        chunk = os.read(stdin.fileno(), 64)
        if not chunk:
            return not data.startswith(DONE.strip())
        data += chunk
        if data.startswith(DONE.strip()):
            return False


def _wait_for(pidfd: int | None, pid: int, timeout_s: float) -> bool:
    """Until process ``pid`` is gone (its pidfd readable; without one: /proc says so), ≤ ``timeout_s``;
    whether it is gone."""
    if pidfd is not None:
        return bool(select.select([pidfd], [], [], timeout_s)[0])
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return True
        if state in ("Z", "X"):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)


def run_janitor(out: str | Path, host_pid: int, robot: bool = False) -> int:
    """The janitor process of the run folder ``out`` whose host (``robot``: the robot's plant) is
    ``host_pid`` (module docstring); its exit code."""
    try:
        pidfd: int | None = os.pidfd_open(host_pid)
    except (AttributeError, OSError):
        pidfd = None  # no pidfds here, or the host is gone already
    if not _launcher_gone(sys.stdin.buffer):
        return 0
    done: list[str] = []
    if not _wait_for(pidfd, host_pid, HOST_WAIT_S):
        done.append(f"process {host_pid} still ran {HOST_WAIT_S:.0f} s after the launcher died: killed")
        with contextlib.suppress(OSError):
            if pidfd is not None:
                signal.pidfd_send_signal(pidfd, signal.SIGKILL)
            else:
                os.kill(host_pid, signal.SIGKILL)
        _wait_for(pidfd, host_pid, HOST_WAIT_S)
    if not robot:
        done += settle_run_folder(out)
    marked = mark_robot_launcher_lost(out) if robot else mark_launcher_lost(out)
    if marked is not None:
        done.append(marked)
    if done:
        logs = Path(out) / "logs"
        with contextlib.suppress(OSError), open(logs / "janitor.log", "a", encoding="utf-8") as fh:
            stamp = time.strftime("%Y-%m-%d %H:%M:%S")
            fh.writelines(f"{stamp} janitor: the launcher was killed; {line}\n" for line in done)
    return 0
