"""Whose were the deadline misses of ``ilcrig run --realtime``: a kernel trace beside the plant's list.

Runs ``ilcrig run --realtime`` (the default experiment, or the options given after ``--``) while
the kernel records every context switch and the run time it accounts to each task (ftrace:
``sched:sched_switch``, ``sched:sched_stat_runtime``, on ``CLOCK_MONOTONIC``, the clock the plant
stamps its ticks with). Then it puts each tick the plant reported late (``summary.json``:
``bench.timing.per_trial[k].missed_ticks``, from 0x2441) beside the CPU time the hypervisor took
from the machine during that tick, and says whose the miss was (:mod:`host.rig.miss_attribution`):
``steal`` (the hypervisor's: without it the tick would have kept its deadline), ``knock-on`` (late
because the tick before it was), ``other`` (more than the steal: the rig's own time, or a stall
the trace does not show).

``--waits`` records the wake-ups instead (``sched:sched_wakeup``, ``sched:sched_switch`` with the
thread group of every task) and says where the lockstep processes waited
(:mod:`host.rig.wake_waits`): per role, how long a woken task waited for a CPU (p50 / p99 / max,
and how many waits were longer than 0.2 ms), which processes held the CPU meanwhile (``idle``: the
CPU was free — the wake-up itself was slow), the stretches a lockstep process ran for more than
2 ms without a break, and who preempted a lockstep process. The roles are found by their command
lines while the run lasts (``host.cli ROLE``, the hub, the idle-poll loops). This is the view for
normal scheduling (``-- --rt-priority 0``), where a late tick is a lockstep process waiting for a CPU.

``/proc/stat`` counts steal in 10 ms units over the whole machine, too coarse for a 1 ms tick:
here it is per CPU and per tick. Needs root (tracefs) and, for the steal, a kernel with
``CONFIG_PARAVIRT_TIME_ACCOUNTING`` (every KVM guest kernel of the usual distributions); the
tracing settings are restored afterwards.

    python benchmarks/rt_attribution.py [--waits] [--out DIR] [--keep-trace] [-- ilcrig-run-options…]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rt_compare import realtime_run_cmd, split_run_options  # noqa: E402

from host.rig.miss_attribution import attribute_misses, parse_sched_trace, summarise_verdicts  # noqa: E402
from host.rig.wake_waits import parse_waits, summarise_waits  # noqa: E402

TRACEFS = Path("/sys/kernel/tracing")
EVENTS = ("sched/sched_switch", "sched/sched_stat_runtime")
WAIT_EVENTS = ("sched/sched_switch", "sched/sched_wakeup")
#: per CPU; a default run records about 5 MB per CPU per 10 s of trials
BUFFER_KB = 262_144


def _read(path: Path) -> str:
    return path.read_text().strip()


def _current_clock(text: str) -> str:
    return next((w.strip("[]") for w in text.split() if w.startswith("[")), "local")


@contextlib.contextmanager
def kernel_trace(events: Sequence[str] = EVENTS, record_tgid: bool = False) -> Iterator[Path]:
    """Record ``events`` for the ``with`` body; the settings are put back after."""
    if not (TRACEFS / "trace").exists():
        subprocess.run(["mount", "-t", "tracefs", "nodev", str(TRACEFS)], check=False, capture_output=True)
    if not (TRACEFS / "trace").exists():
        raise SystemExit(f"rt_attribution: no tracefs at {TRACEFS} (needs root and a kernel with ftrace)")
    tgid_option = TRACEFS / "options" / "record-tgid"
    saved: dict[str, str] = {
        "tracing_on": _read(TRACEFS / "tracing_on"),
        "trace_clock": _current_clock(_read(TRACEFS / "trace_clock")),
        # "1408" or, before the buffer was first used, "7 (expanded: 1408)"
        "buffer_size_kb": _read(TRACEFS / "buffer_size_kb").split()[-1].strip(")"),
        "record-tgid": _read(tgid_option) if tgid_option.exists() else "",
        **{e: _read(TRACEFS / "events" / e / "enable") for e in events},
    }
    try:
        (TRACEFS / "tracing_on").write_text("0")
        (TRACEFS / "trace_clock").write_text("mono")
        (TRACEFS / "buffer_size_kb").write_text(str(BUFFER_KB))
        if record_tgid and tgid_option.exists():
            tgid_option.write_text("1")
        for e in events:
            (TRACEFS / "events" / e / "enable").write_text("1")
        (TRACEFS / "trace").write_text("")
        (TRACEFS / "tracing_on").write_text("1")
        yield TRACEFS / "trace"
    finally:
        (TRACEFS / "tracing_on").write_text("0")
        for e in events:
            (TRACEFS / "events" / e / "enable").write_text(saved[e])
        (TRACEFS / "trace_clock").write_text(saved["trace_clock"])
        (TRACEFS / "buffer_size_kb").write_text(saved["buffer_size_kb"])
        if saved["record-tgid"]:
            tgid_option.write_text(saved["record-tgid"])
        (TRACEFS / "trace").write_text("")  # the buffer's memory back
        (TRACEFS / "tracing_on").write_text(saved["tracing_on"])


def _role_of(argv: list[str]) -> str | None:
    """The rig role of a process from its command line (None: not one)."""
    text = " ".join(argv)
    if "SCHED_IDLE" in text:
        return "idle-poll"
    if "bus.transports.hub_server" in text:
        return "hub"
    if "host.cli" in argv:
        rest = argv[argv.index("host.cli") + 1 :]
        rest = [a for a in rest if a != "--debug"]
        if rest and rest[0] == "drive" and "--node" in rest:
            return f"drive{rest[rest.index('--node') + 1]}"
        if rest and rest[0] in ("plant", "host", "hub"):
            return rest[0]
    return None


def _is_launcher(argv: list[str]) -> bool:
    """``ilcrig run`` or ``ilcrig robot`` as ``python -m host.cli run|robot …`` (how the benchmarks start it)."""
    return "host.cli" in argv and argv[argv.index("host.cli") + 1 :][:1] in (["run"], ["robot"])


class RoleWatcher(threading.Thread):
    """Maps the pids of the rig's processes to their roles while the run lasts (``/proc/*/cmdline``),
    and the launcher's (``ilcrig run`` / ``ilcrig robot``) to ``launcher`` in :attr:`names` (a holder of
    CPUs, not a lockstep role)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.roles: dict[int, str] = {}
        self.names: dict[int, str] = {}
        self.root = 0  # only descendants of this process (other runs on the machine are not ours)
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(0.5):
            for entry in os.listdir("/proc"):
                if not entry.isdigit() or int(entry) in self.roles:
                    continue
                try:
                    argv = Path(f"/proc/{entry}/cmdline").read_bytes().decode(errors="replace").split("\0")[:-1]
                except OSError:
                    continue
                role = _role_of(argv)
                if role is not None and _descends_from(int(entry), self.root):
                    self.roles[int(entry)] = role
                elif _is_launcher(argv) and _descends_from(int(entry), self.root):
                    self.names[int(entry)] = "launcher"


def _descends_from(pid: int, root: int) -> bool:
    while pid > 1:
        if pid == root:
            return True
        try:
            pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            return False
    return False


def trace_overruns() -> int:
    """Trace events the kernel dropped (its per-CPU buffers were full)."""
    total = 0
    for stats in sorted((TRACEFS / "per_cpu").glob("cpu*/stats")):
        for line in stats.read_text().splitlines():
            if line.startswith("overrun:"):
                total += int(line.split()[1])
    return total


def print_waits(summary: dict, headline: str, lost: int) -> None:
    """Where the lockstep processes waited (:func:`host.rig.wake_waits.summarise_waits`'s ``summary``),
    after ``headline`` (what ran and how it went); ``lost``: trace events the kernel dropped. Also
    ``benchmarks/robot_speed.py --waits``."""
    dropped = f"; {lost:,} trace events LOST (buffer too small)" if lost else ""
    print(f"{headline}; load average {os.getloadavg()[0]:.1f}{dropped}")
    thr = summary["threshold_s"] * 1e3
    print(f"wake-up -> on a CPU, per role: wake-ups, p50 / p99 / max ms, waits > {thr:g} ms")
    for role, w in summary["waits"].items():
        print(
            f"  {role:<9} {w['wakeups']:>7}  {w['p50_s'] * 1e3:7.3f} {w['p99_s'] * 1e3:7.3f} {w['max_s'] * 1e3:8.3f}  "
            f"{w['over_threshold']:>6}"
        )
    print(f"who held the CPU while a lockstep process waited > {thr:g} ms (ms of CPU time; idle: the CPU was free):")
    for who, sec in list(summary["held_while_waiting_s"].items())[:12]:
        print(f"  {who:<24} {sec * 1e3:9.1f}")
    runs = summary["long_runs_s"]
    print(
        "lockstep runs > 2 ms without a break: "
        + (", ".join(f"{r} {len(v)} (longest {v[0] * 1e3:.1f} ms)" for r, v in runs.items()) or "none")
    )
    pre = summary["lockstep_preempted_by"]
    print("lockstep processes preempted by: " + (", ".join(f"{k} {v}" for k, v in list(pre.items())[:10]) or "nobody"))


def main() -> None:
    argv, run_opts = split_run_options(sys.argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="run directory (default: a temporary one)")
    ap.add_argument("--keep-trace", action="store_true", help="keep the kernel trace as kernel-trace.txt in the run directory")
    ap.add_argument("--waits", action="store_true", help="where the lockstep processes waited for a CPU (wake-ups)")
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        raise SystemExit("rt_attribution: the kernel trace needs root (tracefs)")
    with tempfile.TemporaryDirectory(prefix="ilcrig-rt-") as tmp:
        out = args.out or Path(tmp) / "run"
        cmd = realtime_run_cmd(out, *run_opts)
        watcher = RoleWatcher()
        with kernel_trace(WAIT_EVENTS if args.waits else EVENTS, record_tgid=args.waits) as trace:
            proc = subprocess.Popen(cmd)
            watcher.root = proc.pid
            watcher.names |= {proc.pid: "launcher", os.getpid(): "rt_attribution"}  # holders, not lockstep roles
            watcher.start()
            rc = proc.wait()
            watcher.done.set()
            trace_text = trace.read_text()
            lost = trace_overruns()
        if args.keep_trace:
            (out / "kernel-trace.txt").write_text(trace_text)
        summary_path = out / "summary.json"
        if not summary_path.exists():
            raise SystemExit(f"rt_attribution: the run wrote no summary (exit {rc})")
        timing = json.loads(summary_path.read_text())["bench"]["timing"]
        if args.waits:
            ts = timing["control_period_s"]
            windows = [
                (r["t0_monotonic_s"] - ts, r["t0_monotonic_s"] + (r["ticks"] + 1) * ts)
                for r in timing["per_trial"]
                if "t0_monotonic_s" in r
            ]
            if not windows:
                raise SystemExit("rt_attribution --waits: no trial with missed ticks, so no trial times: nothing to look at")
            waits = parse_waits(trace_text.splitlines(), windows)
            headline = (
                f"rt_attribution --waits: {' '.join(['ilcrig run --realtime', *run_opts])} (exit {rc}): "
                f"{timing['deadline_misses']} of {timing['ticks']} ticks missed their deadline, lateness p99 "
                f"{timing['lateness_p99_s'] * 1e3:.3f} ms"
            )
            print_waits(summarise_waits(waits, watcher.roles, names=watcher.names), headline, lost)
            return
        stretches = parse_sched_trace(trace_text.splitlines())
        verdicts = attribute_misses(stretches, timing["per_trial"], timing["control_period_s"])
    listed = sum(len(r.get("missed_ticks") or []) for r in timing["per_trial"])
    print(
        f"rt_attribution: {' '.join(['ilcrig run --realtime', *run_opts])} (exit {rc}): {timing['deadline_misses']} of "
        f"{timing['ticks']} ticks missed their deadline, {listed} listed by the plant; kernel trace of "
        f"{len(stretches):,} run stretches" + (f", {lost:,} events LOST (buffer too small)" if lost else "")
    )
    if verdicts:
        print(f"{'trial':>5} {'tick':>5} {'started late µs':>15} {'overrun µs':>10} {'steal µs':>8}  verdict")
        for v in verdicts:
            print(
                f"{v.trial:>5} {v.tick:>5} {v.started_late_s * 1e6:>15.0f} {v.overrun_s * 1e6:>10.0f} "
                f"{v.steal_s * 1e6:>8.0f}  {v.verdict}"
            )
    s = summarise_verdicts(verdicts)
    print(
        f"verdicts: {s['verdicts']['steal']} steal, {s['verdicts']['knock-on']} knock-on, {s['verdicts']['other']} "
        f"other; chains started by steal {s['chains']['steal']} ({s['misses_by_cause']['steal']} misses), by "
        f"other {s['chains']['other']} ({s['misses_by_cause']['other']} misses)"
    )


if __name__ == "__main__":
    main()
