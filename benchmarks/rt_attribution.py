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

``/proc/stat`` counts steal in 10 ms units over the whole machine, too coarse for a 1 ms tick:
here it is per CPU and per tick. Needs root (tracefs) and a kernel with
``CONFIG_PARAVIRT_TIME_ACCOUNTING`` (every KVM guest kernel of the usual distributions); the
tracing settings are restored afterwards.

    python benchmarks/rt_attribution.py [--out DIR] [--keep-trace] [-- ilcrig-run-options…]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.rig.miss_attribution import attribute_misses, parse_sched_trace, summarise_verdicts  # noqa: E402

TRACEFS = Path("/sys/kernel/tracing")
EVENTS = ("sched/sched_switch", "sched/sched_stat_runtime")
#: per CPU; a default run records about 5 MB per CPU per 10 s of trials
BUFFER_KB = 262_144


def _read(path: Path) -> str:
    return path.read_text().strip()


def _current_clock(text: str) -> str:
    return next((w.strip("[]") for w in text.split() if w.startswith("[")), "local")


@contextlib.contextmanager
def kernel_trace() -> Iterator[Path]:
    """Record the scheduler events for the ``with`` body; the settings are put back after."""
    if not (TRACEFS / "trace").exists():
        subprocess.run(["mount", "-t", "tracefs", "nodev", str(TRACEFS)], check=False, capture_output=True)
    if not (TRACEFS / "trace").exists():
        raise SystemExit(f"rt_attribution: no tracefs at {TRACEFS} (needs root and a kernel with ftrace)")
    saved = {
        "tracing_on": _read(TRACEFS / "tracing_on"),
        "trace_clock": _current_clock(_read(TRACEFS / "trace_clock")),
        "buffer_size_kb": _read(TRACEFS / "buffer_size_kb"),
        **{e: _read(TRACEFS / "events" / e / "enable") for e in EVENTS},
    }
    try:
        (TRACEFS / "tracing_on").write_text("0")
        (TRACEFS / "trace_clock").write_text("mono")
        (TRACEFS / "buffer_size_kb").write_text(str(BUFFER_KB))
        for e in EVENTS:
            (TRACEFS / "events" / e / "enable").write_text("1")
        (TRACEFS / "trace").write_text("")
        (TRACEFS / "tracing_on").write_text("1")
        yield TRACEFS / "trace"
    finally:
        (TRACEFS / "tracing_on").write_text("0")
        for e in EVENTS:
            (TRACEFS / "events" / e / "enable").write_text(saved[e])
        (TRACEFS / "trace_clock").write_text(saved["trace_clock"])
        (TRACEFS / "buffer_size_kb").write_text(saved["buffer_size_kb"])
        (TRACEFS / "tracing_on").write_text(saved["tracing_on"])


def _overruns() -> int:
    total = 0
    for stats in sorted((TRACEFS / "per_cpu").glob("cpu*/stats")):
        for line in stats.read_text().splitlines():
            if line.startswith("overrun:"):
                total += int(line.split()[1])
    return total


def main() -> None:
    argv = sys.argv[1:]
    run_opts: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, run_opts = argv[:i], argv[i + 1 :]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="run directory (default: a temporary one)")
    ap.add_argument("--keep-trace", action="store_true", help="keep the kernel trace as kernel-trace.txt in the run directory")
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        raise SystemExit("rt_attribution: the kernel trace needs root (tracefs)")
    with tempfile.TemporaryDirectory(prefix="ilcrig-rt-") as tmp:
        out = args.out or Path(tmp) / "run"
        cmd = [
            sys.executable,
            "-c",
            "import sys; from host.cli import main; sys.exit(main(sys.argv[1:]))",
            "run",
            "--realtime",
            "--out",
            str(out),
            *run_opts,
        ]
        with kernel_trace() as trace:
            rc = subprocess.run(cmd, check=False).returncode
            trace_text = trace.read_text()
            lost = _overruns()
        if args.keep_trace:
            (out / "kernel-trace.txt").write_text(trace_text)
        summary_path = out / "summary.json"
        if not summary_path.exists():
            raise SystemExit(f"rt_attribution: the run wrote no summary (exit {rc})")
        timing = json.loads(summary_path.read_text())["bench"]["timing"]
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
