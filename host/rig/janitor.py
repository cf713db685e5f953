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
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

from bus.processes import spawn_process

logger = logging.getLogger(__name__)

__all__ = ["DONE", "HOST_WAIT_S", "Janitor", "mark_launcher_lost", "run_janitor", "settle_run_folder", "start_janitor"]

#: what the launcher writes when it has settled the folder itself
DONE = b"done\n"
#: longest the janitor waits for the host to be gone after the launcher died, s
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


class Janitor:
    """The janitor process of one run (:func:`start_janitor`)."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.proc = proc

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


def start_janitor(out_dir: Path, host_pid: int) -> Janitor | None:
    """Start the janitor of the run folder ``out_dir`` whose host is ``host_pid`` (None: it could
    not be started; logged — the run goes on without it)."""
    argv = [sys.executable, "-P", "-m", "host.cli.janitor", "--out", str(out_dir), "--wait", str(host_pid)]
    try:
        # a session of its own (a terminal's Ctrl-C is the launcher's) and no death signal: it outlives the launcher
        proc = spawn_process(argv, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, death_signal=None)
    except OSError as err:
        logger.warning("cannot start the run folder's janitor: %s", err)
        return None
    return Janitor(proc)


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


def _wait_for(pidfd: int | None, pid: int, timeout_s: float) -> None:
    """Until process ``pid`` is gone (its pidfd readable; without one: /proc says so), ≤ ``timeout_s``."""
    if pidfd is not None:
        select.select([pidfd], [], [], timeout_s)
        return
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return
        if state in ("Z", "X"):
            return
        time.sleep(0.05)


def run_janitor(out: str | Path, host_pid: int) -> int:
    """The janitor process of the run folder ``out`` whose host is ``host_pid`` (module docstring);
    its exit code."""
    try:
        pidfd: int | None = os.pidfd_open(host_pid)
    except (AttributeError, OSError):
        pidfd = None  # no pidfds here, or the host is gone already
    if not _launcher_gone(sys.stdin.buffer):
        return 0
    _wait_for(pidfd, host_pid, HOST_WAIT_S)
    done = settle_run_folder(out)
    marked = mark_launcher_lost(out)
    if marked is not None:
        done.append(marked)
    if done:
        logs = Path(out) / "logs"
        with contextlib.suppress(OSError), open(logs / "janitor.log", "a", encoding="utf-8") as fh:
            stamp = time.strftime("%Y-%m-%d %H:%M:%S")
            fh.writelines(f"{stamp} janitor: the launcher was killed; {line}\n" for line in done)
    return 0
