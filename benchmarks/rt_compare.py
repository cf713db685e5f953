"""Late ticks of ``ilcrig run --realtime`` with and without SCHED_FIFO, alternating, beside the machine's floor.

Per round: the machine's own floor (``benchmarks/timer_latency.py --json``: a lone periodic loop,
once as the lockstep processes are scheduled with ``SCHED_FIFO``, once as they are in normal
scheduling), then one ``ilcrig run --realtime`` per variant — by default ``fifo`` (the default
``--rt-priority``) and ``normal`` (``--rt-priority 0``: what every user without ``CAP_SYS_NICE``
or ``RLIMIT_RTPRIO`` gets) — in an order rotated from round to round, so that every variant
meets the machine's moods alike. Per run it prints the 1-minute load average before it, the
ticks late (deadline misses) and their share, the lateness p50 / p99 / max, the CPU time the
hypervisor took during the trials (steal, ``bench.timing.machine_steal``) and the ratio of the
run's lateness p99 to the floor's p99 of the same scheduling class in the same round (the floor
taken as at least 10 µs: a spinning wait's p99 is about 0); at the end, per variant, the median
and the worst.

Attribution: ``--without MECH`` adds a variant in normal scheduling with the mechanism ``MECH``
left out (``ILCRIG_RT_WITHOUT``, docs/timing.md §1: ``slice``, ``host``, ``gc``, ``sleep-wait``,
``idle-poll-fifo-only`` (left out: the loops also beside normal scheduling), ``idle-nice``, ``cpu-latency``;
comma-separated for several); ``--variant NAME=OPTIONS[@WITHOUT]`` adds any other (``OPTIONS``:
``ilcrig run`` options after ``--realtime``).

    python benchmarks/rt_compare.py [--rounds 3] [--without MECH] [--variant NAME=OPTS[@WITHOUT]] [--out DIR]
                                    [-- ilcrig-run-options…]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bus.lockstep_process import WITHOUT_ENV  # noqa: E402

#: the periodic loop of the floor: periods per measurement, and the spinning test's length, s
FLOOR_PERIODS = 3000
FLOOR_SPIN_S = 1.0
#: the floor's p99 is taken as at least this in the ratio (a spinning wait's is ~0), s
FLOOR_RESOLUTION_S = 10e-6


def split_run_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """A script's command line as (its own arguments, the ``ilcrig run`` options after ``--``)."""
    if "--" not in argv:
        return argv, []
    i = argv.index("--")
    return argv[:i], argv[i + 1 :]


def realtime_run_cmd(out_dir: Path, *options: str) -> list[str]:
    """``ilcrig run --realtime --out OUT_DIR OPTIONS…`` as a child of this interpreter."""
    return [
        sys.executable,
        "-c",
        "import sys; from host.cli import main; sys.exit(main(sys.argv[1:]))",
        "run",
        "--realtime",
        "--out",
        str(out_dir),
        *options,
    ]


@dataclass(frozen=True)
class Variant:
    """One way to run ``ilcrig run --realtime``."""

    name: str
    options: list[str]
    without: str = ""
    #: SCHED_FIFO expected (the floor it is compared with)
    fifo: bool = field(default=False)


def parse_variant(text: str) -> Variant:
    """``NAME=OPTIONS[@WITHOUT]`` (see the module docstring)."""
    name, _, rest = text.partition("=")
    if not name or not _:
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME=OPTIONS[@WITHOUT]")
    opts, _, without = rest.partition("@")
    options = shlex.split(opts)
    return Variant(name, options, without, fifo=not _normal(options))


def _normal(options: list[str]) -> bool:
    return any(a == "--rt-priority" and b == "0" for a, b in zip(options, options[1:], strict=False)) or (
        "--rt-priority=0" in options
    )


def floor(rt_priority: int) -> dict[str, Any]:
    """The machine's floor now (``timer_latency.py --json``) for the scheduling class of ``rt_priority``."""
    cmd = [
        sys.executable,
        str(ROOT / "benchmarks" / "timer_latency.py"),
        "--json",
        "--periods",
        str(FLOOR_PERIODS),
        "--spin-s",
        str(FLOOR_SPIN_S),
        "--rt-priority",
        str(rt_priority),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def run_once(variant: Variant, out_dir: Path, extra: list[str]) -> dict[str, Any]:
    """One ``ilcrig run --realtime`` of ``variant``: its timing figures (or why there are none)."""
    env = dict(os.environ)
    if variant.without:
        env[WITHOUT_ENV] = variant.without
    else:
        env.pop(WITHOUT_ENV, None)
    cmd = realtime_run_cmd(out_dir, *variant.options, *extra)
    load = os.getloadavg()[0]
    t0 = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env, cwd=str(ROOT))
    row: dict[str, Any] = {"variant": variant.name, "load_average_1min": load, "exit": done.returncode}
    row["wall_s"] = time.monotonic() - t0
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
        timing = summary["bench"]["timing"]
    except (OSError, KeyError, ValueError) as err:
        row["error"] = f"no timing ({err}); exit {done.returncode}: {done.stderr.strip()[-300:]}"
        return row
    steal = timing.get("machine_steal")
    row |= {
        "ticks": timing["ticks"],
        "late": timing["deadline_misses"],
        "late_percent": timing["deadline_miss_percent"],
        "p50_s": timing["lateness_p50_s"],
        "p99_s": timing["lateness_p99_s"],
        "max_s": timing["lateness_max_s"],
        "steal_s": steal["seconds"] if steal else None,
        "scheduling": timing.get("scheduling", {}),
        "trace_sha256": summary.get("trace_sha256"),
    }
    return row


def _ms(x: float | None) -> str:
    return "    -" if x is None else f"{x * 1e3:7.3f}"


def line(row: dict[str, Any], floors: dict[bool, dict[str, Any]], variant: Variant) -> str:
    if "error" in row:
        return f"{row['variant']:<24} load {row['load_average_1min']:4.1f}  {row['error']}"
    fl = floors.get(row["scheduling"].get("policy") == "SCHED_FIFO", {})
    ratio = row["p99_s"] / max(fl["lateness_p99_s"], FLOOR_RESOLUTION_S) if "lateness_p99_s" in fl else float("nan")
    steal = "    -" if row["steal_s"] is None else f"{row['steal_s'] * 1e3:5.0f}"
    return (
        f"{row['variant']:<24} load {row['load_average_1min']:4.1f}  late {row['late']:5d}/{row['ticks']} "
        f"({row['late_percent']:5.2f} %)  p50 {_ms(row['p50_s'])}  p99 {_ms(row['p99_s'])}  max {_ms(row['max_s'])} ms  "
        f"steal {steal} ms  p99/floor {ratio:6.1f}"
    )


def main() -> None:
    argv, extra = split_run_options(sys.argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--without", action="append", default=[], metavar="MECH", help="add a normal-scheduling variant without MECH")
    ap.add_argument("--variant", action="append", default=[], type=parse_variant, metavar="NAME=OPTS[@WITHOUT]")
    ap.add_argument("--no-default", action="store_true", help="only the variants given (not fifo and normal)")
    ap.add_argument("--out", type=Path, default=None, help="keep the run folders and results.jsonl here")
    args = ap.parse_args(argv)
    variants: list[Variant] = []
    if not args.no_default:
        variants += [Variant("fifo", [], fifo=True), Variant("normal", ["--rt-priority", "0"])]
    variants += [Variant(f"normal without {m}", ["--rt-priority", "0"], m) for m in args.without]
    variants += args.variant
    if not variants:
        raise SystemExit("rt_compare: no variant to run")
    with tempfile.TemporaryDirectory(prefix="ilcrig-rt-compare-") as tmp:
        base = args.out or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        rows: list[dict[str, Any]] = []
        print(f"rt_compare: {args.rounds} rounds of {', '.join(v.name for v in variants)}; {os.cpu_count()} CPUs")
        for r in range(args.rounds):
            floors = {True: floor(10), False: floor(0)}
            for fifo, f in floors.items():
                steal = "-" if f.get("steal_s") is None else f"{f['steal_s'] * 1e3:.0f}"
                print(
                    f"round {r + 1} floor {'fifo' if fifo else 'normal':<8} load {f['load_average_1min']:4.1f}  "
                    f"{f['scheduling']}: wake-up lateness p50 {_ms(f['lateness_p50_s'])} p99 {_ms(f['lateness_p99_s'])} "
                    f"max {_ms(f['lateness_max_s'])} ms, {f['later_than_one_period']} of {f['periods']} later than a "
                    f"period; spinning {f.get('spin_s', 0):g} s: {f.get('gaps_s', 0) * 1e3:.1f} ms not run, steal {steal} ms"
                )
            order = variants[r % len(variants) :] + variants[: r % len(variants)]
            for v in order:
                row = run_once(v, base / f"round{r + 1}-{v.name.replace(' ', '-')}", extra)
                row |= {"round": r + 1, "floor": floors[v.fifo]}
                rows.append(row)
                print(f"round {r + 1} {line(row, floors, v)}", flush=True)
                if args.out is not None:
                    with open(base / "results.jsonl", "a") as fh:
                        fh.write(json.dumps(row) + "\n")
        print("per variant (median over the rounds; worst):")
        for v in variants:
            got = [x for x in rows if x["variant"] == v.name and "error" not in x]
            if not got:
                print(f"  {v.name:<24} no run completed")
                continue
            med = statistics.median
            steals = [x["steal_s"] for x in got if x["steal_s"] is not None]
            late = [x["late_percent"] for x in got]
            p99 = [x["p99_s"] * 1e3 for x in got]
            digests = sorted({str(x["trace_sha256"])[:16] for x in got})
            print(
                f"  {v.name:<24} late {med(late):6.2f} % (worst {max(late):.2f} %), p99 {med(p99):.3f} ms (worst "
                f"{max(p99):.3f}), max {max(x['max_s'] for x in got) * 1e3:.3f} ms; steal {sum(steals) * 1e3:.0f} ms in "
                f"{len(got)} runs; load {med(x['load_average_1min'] for x in got):.1f}; digests {digests}"
            )


if __name__ == "__main__":
    main()
