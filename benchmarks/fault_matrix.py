"""Fault matrix benchmark: seeded random injections into real ``ilcrig run`` rigs.

``python benchmarks/fault_matrix.py [--runs 100] [--seed 9] [--iterations 3] [--cycle 0.15] [--kinds PATTERNS] [--out DIR]``

Each run draws a fault kind, a trial and a tick (seeded), runs the distributed rig (hub, plant, four
drives, host) with ``--inject`` and checks what came out: the fault was detected (exit code 3, one
``ilcrig: fault:`` line, a ``faults`` entry in ``summary.json``), how many completed trials were
lost (the trials before the injected one must all be kept, bit-identical to ``ilcrig sim`` with
that many trials), no process is left, and the detection latency (the ``faults`` entry's
``latency_ms``, measured from the injection record: monotonic clock across processes) and, for
frame faults, the tick latency (the tick the fault was reported at minus the injected tick).
Prints one row per run as it goes, then the table: injected, detected, completed trials lost,
latency p50 / p99 per kind.  Goal: every fault detected, no completed trial lost, latency within
3 heartbeat periods (600 ms) for lost or stalled processes, within 2 ticks for frame faults.

The ``robot-kill-*`` kinds do the same to ``ilcrig robot`` (no host; a python-canopen master holds
the enabled robot in CSP): a drive, the plant or the hub killed after a random number of periods;
detected = exit code 3 with the one line naming the process, nothing left running; latency = from
the kill to that line (the orderly stop of the other processes follows).  The ``robot-master-*``
kinds are the faults a foreign master causes on a running ``ilcrig robot``
(tests/robot_faults.py: its heartbeat lost, NMT STOP mid-motion, its RPDOs stopping, its SYNCs
stopping, an end stop): detected = the drives' (or the robot's) EMCY of the cause -- none for
NMT STOP, CiA 301 -- and a torque-free robot (every brake closed, the joints still), the robot
still running (it ends by SIGTERM, 143); latency = from the cause to the first EMCY (an end stop
is hit in the period that reaches it: its column is the periods from the start of the move),
tick latency = control periods from the cause to the torque-free robot.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from fault_harness import EXPERIMENT, kill_session, run_rig, sim_digest  # noqa: E402
from robot_faults import SCENARIOS, FaultMaster  # noqa: E402
from robot_util import RobotProcess, pid_alive, robot_fault_run  # noqa: E402

from bus.cia301.nmt import HOST_HEARTBEAT_MS  # noqa: E402

#: kind → spec template ({role}, {trial}, {tick}); process faults and frame faults
KINDS = {
    "kill-drive": "kill:{drive}@{trial}:{tick}",
    "kill-plant": "kill:plant@{trial}:{tick}",
    "kill-hub": "kill:hub@{trial}:{tick}",
    "kill-host": "kill:host@{trial}:{tick}",
    "stall-drive": "stall:{drive}@{trial}:{tick},for=2",
    "stall-plant": "stall:plant@{trial}:{tick},for=2",
    "stall-hub": "stall:hub@{trial}:{tick},for=2",
    "stall-host": "stall:host@{trial}:{tick},for=2",
    "drop-io": "drop:io@{trial}:{tick},seed={seed}",
    "corrupt-io": "corrupt:io@{trial}:{tick},seed={seed}",
    "duplicate-io": "duplicate:io@{trial}:{tick},seed={seed}",
    "delay-io": "delay:io@{trial}:{tick},seed={seed}",
    "emcy": "emcy:{drive}@{trial}:{tick}",
    "diskfull": "diskfull@{trial}",
    "robot-kill-drive": "{drive}",
    "robot-kill-plant": "plant",
    "robot-kill-hub": "hub",
    **{f"robot-master-{name}": name for name in SCENARIOS},
}
FRAME_KINDS = {"drop-io", "corrupt-io", "duplicate-io", "delay-io"}  # the lockstep faults: latency also in ticks


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, max(0, round(q / 100 * (len(v) - 1))))]


def robot_run(i: int, kind: str, victim: str, out: Path, periods_before: int) -> dict:
    """One ``robot-kill-*`` run (module docstring); its row."""
    t0 = time.monotonic()
    o = robot_fault_run(out, victim, periods_before=periods_before)
    detected = o["code"] == 3 and len(o["stderr"]) == 1 and o["stderr"][0].startswith(f"ilcrig: fault: {victim} (pid ")
    r = {
        "i": i,
        "kind": kind,
        "spec": f"kill:{victim} after {periods_before} periods",
        "code": o["code"],
        "detected": detected,
        "fault_kind": "process_died",
        "detected_by": "launcher",
        "latency_ms": o["latency_ms"],
        "tick_latency": None,
        "kept": 0,
        "expected_kept": 0,
        "lost": 0,
        "left": len(o["left"]),
        "safe": True,
        "wall_s": round(time.monotonic() - t0, 1),
    }
    print(
        f"{i:3d} {r['spec']:34s} exit {o['code']} {'detected' if detected else 'MISSED':8s} by launcher "
        f"{o['latency_ms']:7.0f} ms (exit after {o['exit_ms']:.0f} ms) left {len(o['left'])} ({r['wall_s']:.0f} s)",
        flush=True,
    )
    return r


def robot_master_run(i: int, kind: str, scenario: str, out: Path) -> dict:
    """One ``robot-master-*`` run (module docstring); its row."""
    t0 = time.monotonic()
    robot = RobotProcess(out, env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    try:
        where = robot.ready()
        master = FaultMaster(interface=where["interface"], channel=where["channel"])
        try:
            res = SCENARIOS[scenario](master)
        finally:
            master.close()
        left_running = [name for name, pid in where["pids"].items() if pid_alive(pid)]
        code = robot.stop()
    finally:
        robot.kill()
    safe = res.brakes == 0xF and res.still
    emcy = bool(res.emcy or res.robot_emcy) or scenario == "nmt-stop"
    detected = safe and emcy and len(left_running) == len(where["pids"]) and code == 143
    r = {
        "i": i,
        "kind": kind,
        "spec": f"master: {scenario}",
        "code": code,
        "detected": detected,
        "fault_kind": scenario,
        "detected_by": "plant" if res.robot_emcy else "drives",
        "latency_ms": res.latency_ms if res.latency_ms else None,
        "tick_latency": res.periods or None,
        "kept": 0,
        "expected_kept": 0,
        "lost": 0,
        "left": 0,
        "safe": safe,
        "wall_s": round(time.monotonic() - t0, 1),
    }
    lat = f"{res.latency_ms:7.0f} ms" if res.latency_ms else "      - ms"
    print(
        f"{i:3d} {r['spec']:34s} exit {code} {'detected' if detected else 'MISSED':8s} by {r['detected_by']:8s} "
        f"{lat} periods {res.periods} brakes 0x{res.brakes:X} ({r['wall_s']:.0f} s)",
        flush=True,
    )
    return r


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=100)
    p.add_argument("--seed", type=int, default=9)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--cycle", type=float, default=0.15)
    p.add_argument("--out", default=None, help="keep the run folders here (default: a temp folder, removed)")
    p.add_argument("--json", default=None, help="write every run's result to this file")
    p.add_argument("--kinds", default="*", help="only these kinds: comma-separated names or patterns (e.g. 'robot-*')")
    args = p.parse_args(argv)
    EXPERIMENT[:] = ["--cycle", repr(args.cycle)]
    n_ticks = round(2 * args.cycle / 0.001) + 1
    rng = random.Random(args.seed)
    kinds = [k for k in KINDS if any(fnmatch.fnmatchcase(k, pat.strip()) for pat in args.kinds.split(","))]
    if not kinds:
        p.error(f"--kinds {args.kinds}: no such kind; kinds: {', '.join(KINDS)}")
    plan = []
    for i in range(args.runs):
        kind = kinds[i % len(kinds)] if i < len(kinds) else rng.choice(kinds)  # every kind at least once
        plan.append(
            (kind, rng.randrange(args.iterations), rng.randrange(n_ticks), f"drive{rng.randint(1, 4)}", rng.randrange(1000))
        )
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ilcrig-faultmatrix-"))
    results = []
    t_start = time.monotonic()
    print(
        f"{args.runs} injections, {args.iterations} trials of N = {n_ticks} ticks; heartbeat {HOST_HEARTBEAT_MS} ms", flush=True
    )
    for i, (kind, trial, tick, drive, seed) in enumerate(plan):
        spec = KINDS[kind].format(drive=drive, trial=trial, tick=tick, seed=seed)
        if kind.startswith("robot-master-"):
            results.append(robot_master_run(i, kind, spec, base / f"run{i:03d}"))
            continue
        if kind.startswith("robot-"):
            results.append(robot_run(i, kind, spec, base / f"run{i:03d}", periods_before=tick + 1))
            continue
        expected_kept = trial + 1 if kind == "diskfull" else trial
        out = base / f"run{i:03d}"
        o = run_rig(out, "--inject", spec, iterations=args.iterations, timeout_s=600)
        kill_session(o)
        f = o.fault or {}
        detected = o.code == 3 and bool(f) and len(o.lines) == 1 and o.lines[0].startswith("ilcrig: fault:")
        kept_ok = o.summary is not None and o.summary.get("trace_sha256") == sim_digest(o.kept)
        lost = max(0, expected_kept - o.kept) + (0 if kept_ok else o.kept)
        tick_latency = (
            (f.get("tick") - tick)
            if (kind in FRAME_KINDS and isinstance(f.get("tick"), int) and f.get("trial") == trial)
            else None
        )
        safe = bool(o.summary) and all(
            e.get("torque") == "off" for e in o.summary.get("safe_state", []) if str(e.get("node", "")).startswith("drive")
        )
        r = {
            "i": i,
            "kind": kind,
            "spec": spec,
            "code": o.code,
            "detected": detected,
            "fault_kind": f.get("kind"),
            "detected_by": f.get("detected_by"),
            "latency_ms": f.get("latency_ms"),
            "tick_latency": tick_latency,
            "kept": o.kept,
            "expected_kept": expected_kept,
            "lost": lost,
            "left": len(o.left),
            "safe": safe,
            "wall_s": round(o.wall_s, 1),
        }
        results.append(r)
        lat = f"{r['latency_ms']:.0f} ms" if isinstance(r["latency_ms"], int | float) else "-"
        print(
            f"{i:3d} {spec:34s} exit {o.code} {'detected' if detected else 'MISSED':8s} {str(r['fault_kind']):14s} "
            f"by {str(r['detected_by']):8s} {lat:>7s} ticks {tick_latency if tick_latency is not None else '-':>3} "
            f"kept {o.kept}/{expected_kept} lost {lost} left {len(o.left)} safe {safe} ({o.wall_s:.0f} s)",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    print(f"\n{len(results)} runs in {(time.monotonic() - t_start) / 60:.1f} min\n")
    header = (
        "| kind | injected | detected | completed trials lost | processes left | drives not safe | "
        "latency p50 ms | latency p99 ms | tick latency p50/max |"
    )
    print(header)
    print("|---|---|---|---|---|---|---|---|---|")
    for kind in [*KINDS, "all"]:
        rs = [r for r in results if kind == "all" or r["kind"] == kind]
        if not rs:
            continue
        lats = [float(r["latency_ms"]) for r in rs if isinstance(r["latency_ms"], int | float)]
        ticks = [int(r["tick_latency"]) for r in rs if r["tick_latency"] is not None]
        tl = f"{statistics.median(ticks):.0f}/{max(ticks)}" if ticks else "-"
        print(
            f"| {kind} | {len(rs)} | {sum(r['detected'] for r in rs)} | {sum(r['lost'] for r in rs)} | "
            f"{sum(r['left'] for r in rs)} | {sum(not r['safe'] for r in rs)} | {pct(lats, 50):.0f} | "
            f"{pct(lats, 99):.0f} | {tl} |"
        )
    missed = sum(not r["detected"] for r in results)
    lost = sum(r["lost"] for r in results)
    return 0 if missed == 0 and lost == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
