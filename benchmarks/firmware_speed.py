"""Benchmark: the drive firmware's control period in Python (the numba kernel) and in C (the extension
``firmware_model._fwcore``, ``--firmware c``), in-process and in the rig.

* per tick, in-process: the cost of one call of each kernel from Python, as a drive pays it (the PD
  loop and the cascade, a tick that records), median of ``--rounds`` rounds of ``--calls`` calls;
* ``ilcrig sim``: ticks/s of the default experiment with each firmware (the whole in-process run:
  plant, four drives, host);
* the rig: ``ilcrig run`` over the hub (4 drive + plant + host processes, 1001-tick trials, cycle
  0.5 s) with each firmware, lockstep ticks/s as the plant measures them (summary
  ``bench.timing``), beside the floor of the same minutes (the bare 5-process io lockstep,
  benchmarks/transport_speed.py); floor, python and c are measured ``--repeat`` times, alternately,
  and the best of each is printed (a shared machine disturbs single runs).

    python benchmarks/firmware_speed.py [--repeat 2] [--iterations 3] [--no-rig]

On a heavily loaded machine give the rig's timeouts room with ``ILCRIG_TIMEOUT_SCALE`` (e.g. 4).

Both firmwares give the same results bit for bit (tests/test_firmware_c.py); this measures only time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO))

from firmware_model import control_law as cl  # noqa: E402
from firmware_model.firmware_select import c_available, control_tick_for  # noqa: E402

FIRMWARES = ("python", "c")


def per_tick_ns(kind: str, loop: int, calls: int, rounds: int) -> float:
    """Median cost of one kernel call, ns (a recording tick of a 1001-column trial)."""
    tick = control_tick_for(kind, 1)
    st = cl.new_state()
    st[cl.P_LOOP] = loop
    st[cl.P_KP], st[cl.P_KD], st[cl.P_TLIM] = 78539816, 1570796, 264_600_000
    st[cl.P_KPP], st[cl.P_KVP], st[cl.P_KVI] = 5242880, 2356194, 235619
    tables, rec = cl.new_tables(1001), cl.new_recorder(1001)
    tables[0, :1001] = range(1001)
    tick(0, 0, 0, st, tables, rec)  # compiled / loaded before timing
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter_ns()
        for n in range(calls):
            tick(n, n % 1001, n % 1001, st, tables, rec)
        times.append((time.perf_counter_ns() - t0) / calls)
    return statistics.median(times)


def sim_ticks_per_s(kind: str) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "host.cli", "sim", "--firmware", kind, "--out", str(Path(tmp) / "run")]
        res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
        if res.returncode != 0:
            raise RuntimeError((res.stderr or res.stdout).strip().splitlines()[-1])
        return float(json.loads((Path(tmp) / "run" / "summary.json").read_text())["ticks_per_s"])


def rig_ticks_per_s(kind: str, iterations: int) -> tuple[float, str]:
    """(the plant's lockstep ticks/s, the trace digest) of ``ilcrig run --firmware kind`` over the hub
    (the run of benchmarks/rig_speed.py)."""
    import rig_speed

    r = rig_speed.rig("hub", iterations, options=("--firmware", kind))
    if "error" in r:
        raise RuntimeError(" ".join(r["error"]))
    return float(r["lockstep_ticks_per_s"]), str(r["trace_sha256"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="alternating floor/python/c rig measurements")
    ap.add_argument("--iterations", type=int, default=3, help="trials per rig run")
    ap.add_argument("--calls", type=int, default=100_000, help="kernel calls per round (in-process)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--no-rig", action="store_true", help="only the in-process figures")
    args = ap.parse_args()
    if not c_available():
        sys.exit("firmware_speed: the C firmware (firmware_model._fwcore) is not built")
    print(f"ilcrig firmware benchmark; {os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f}")
    print("per tick, one kernel call from Python (median of rounds), ns:")
    for loop, name in ((cl.LOOP_PD, "PD"), (cl.LOOP_CASCADE, "cascade")):
        row = "  ".join(f"{kind} {per_tick_ns(kind, loop, args.calls, args.rounds):7.0f}" for kind in FIRMWARES)
        print(f"  {name:<8} {row}")
    print("ilcrig sim (default experiment, 10 trials x 501 ticks), ticks/s:")
    print("  " + "  ".join(f"{kind} {sim_ticks_per_s(kind):8,.0f}" for kind in FIRMWARES))
    if args.no_rig:
        return
    import rig_speed

    floors: list[float] = []
    rigs: dict[str, list[float]] = {kind: [] for kind in FIRMWARES}
    digests: set[str] = set()
    load0 = os.getloadavg()[0]
    for _ in range(args.repeat):
        bare = (rig_speed.floor("hub-unix").get("io") or {}).get("ticks_per_s")
        if bare:
            floors.append(float(bare))
        for kind in FIRMWARES:
            try:
                tps, digest = rig_ticks_per_s(kind, args.iterations)
            except RuntimeError as exc:  # a busy machine can starve a run (ILCRIG_TIMEOUT_SCALE helps): say so, go on
                print(f"  a {kind} rig run failed: {exc}")
                continue
            rigs[kind].append(tps)
            digests.add(digest)
    load1 = os.getloadavg()[0]
    best_floor = max(floors) if floors else float("nan")
    print(f"ilcrig run over the hub ({args.iterations} x 1001-tick trials), lockstep ticks/s, best of {args.repeat}:")
    print(f"  floor {best_floor:8,.0f}   (all: {' '.join(f'{x:,.0f}' for x in floors)})")
    for kind in FIRMWARES:
        if not rigs[kind]:
            continue
        best = max(rigs[kind])
        print(f"  {kind:<6}{best:8,.0f}   {best / best_floor:.2f} x floor   (all: {' '.join(f'{x:,.0f}' for x in rigs[kind])})")
    print(f"  load average {load0:.1f} -> {load1:.1f}; trace digests equal: {len(digests) == 1}")


if __name__ == "__main__":
    main()
