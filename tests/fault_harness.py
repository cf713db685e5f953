"""Shared by the fault-matrix tests (tests/test_fault_matrix.py) and benchmarks/fault_matrix.py: run
``ilcrig run --inject SPEC`` as a real multi-process rig and take the outcome apart.

* :func:`run_rig` starts the launcher in its own session (so the whole session can be checked
  and, if a run hangs, killed) and waits for it to end;
* :class:`Outcome` is what came out: exit code, the terminal's lines, the summary, whether any
  process of the session is left, whether the hub's private folder is gone;
* :func:`status_pids`, :func:`host_pid`, :func:`printed_rows`: the processes of a run and the
  rows it printed, from its stdout and /proc;
* :func:`sim_digest` is ``trace_sha256`` of ``ilcrig sim`` with the same experiment and k trials
  (in process, cached): the kept trials of a faulted run must equal it.

Nothing here sleeps to wait for something: the launcher is waited for; "nothing left" is checked
once it has ended (its children are reaped before it exits).
"""

from __future__ import annotations

import functools
import json
import os
import re
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cli_util import ilcrig_argv

REPO = Path(__file__).resolve().parent.parent
#: the experiment of the matrix: short trials
EXPERIMENT = ["--cycle", "0.15"]


@dataclass
class Outcome:
    """One launcher run."""

    code: int
    stdout: str
    stderr: str
    out: Path
    summary: dict[str, Any] | None
    left: list[int]  # pids of the launcher's session still alive after it ended
    hub_dir: str | None  # the hub's private folder (from the status line)
    wall_s: float
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]

    @property
    def fault(self) -> dict[str, Any] | None:
        if self.summary and self.summary.get("faults"):
            return self.summary["faults"][0]
        return None

    @property
    def kept(self) -> int:
        return len(self.summary["iterations"]) if self.summary else 0


def session_pids(session_id: int) -> list[int]:
    """Pids of processes of session ``session_id`` that are alive (not zombies)."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[3]) == session_id and fields[0] not in ("Z", "X"):
            found.append(int(d.name))
    return found


def run_rig(out: Path, *args: str, iterations: int = 2, timeout_s: float = 300.0, on_line: Any = None) -> Outcome:
    """``python -m host.cli run --iterations N --cycle 0.15 --bus hub --out OUT ARGS`` in its own
    session; ``on_line(line, proc)`` sees every stdout line (e.g. to signal the launcher)."""
    cmd = ilcrig_argv("run", "--iterations", str(iterations), *EXPERIMENT, "--bus", "hub", "--out", str(out), *args)
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, start_new_session=True)
    try:
        if on_line is not None:
            out_lines = []
            assert proc.stdout is not None
            for line in proc.stdout:
                out_lines.append(line)
                on_line(line, proc)
            stdout = "".join(out_lines)
            stderr = proc.stderr.read() if proc.stderr is not None else ""
            proc.wait(timeout_s)
        else:
            stdout, stderr = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        raise AssertionError(f"the rig did not end within {timeout_s} s:\n{stdout[-2000:]}\n{stderr[-2000:]}") from None
    wall = time.monotonic() - t0
    left = session_pids(proc.pid)
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        summary = None
    m = re.search(r"\(unix:(\S+)/hub\.sock\)", stdout)
    return Outcome(proc.returncode, stdout, stderr, out, summary, left, m.group(1) if m else None, wall)


def status_pids(line: str) -> dict[str, int]:
    """name → pid of the launcher's status line (``processes: hub 12, plant 13, …``); {} for another line."""
    m = re.search(r"processes: (.*); role logs", line)
    return {n: int(p) for n, p in (part.split() for part in m.group(1).split(", "))} if m else {}


def host_pid(out: Path) -> int | None:
    """The host's pid, from /proc (the status line is printed before the host starts); None: none."""
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                argv = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"host" in argv and str(out).encode() in argv and b"host.cli" in argv:
                return int(d.name)
    return None


#: a trial's row on the host's stdout: its trial number first (``   0  0.26427  0.09146 …``)
ROW = re.compile(r"^\s+(\d+)\s+\d+\.\d+\s")


def printed_rows(stdout: str) -> list[int]:
    """The trials whose row was printed."""
    return [int(m.group(1)) for m in map(ROW.match, stdout.splitlines()) if m]


def kill_session(outcome: Outcome) -> None:
    """Clean up after a failed check (the launcher must have done it)."""
    for pid in outcome.left:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@functools.cache
def sim_digest(k: int) -> str:
    """``trace_sha256`` of ``ilcrig sim --iterations k`` with the matrix's experiment."""
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.experiment.trial_loop import run_experiment
    from host.sim.inprocess import InProcessBench

    cfg = build_config(None, {"iterations": max(k, 1), "cycle_s": 0.15})
    res = run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim")
    if k == 0:
        from host.learning.metrics import TraceDigest

        return TraceDigest().hexdigest()
    return str(res.summary["trace_sha256"])


def recorded_trials(rrd: Path) -> list[int]:
    """The iterations found in a recording (``/joint1/error/iter{k}``), read with rerun."""
    import warnings

    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a killed run's recording has no footer (read by a scan)
        ents = {c.entity_path for c in RrdReader(rrd).stream() if not c.is_static}  # the trials' data
    return sorted(int(e.rsplit("iter", 1)[1]) for e in ents if e.startswith("/joint1/error/iter"))
