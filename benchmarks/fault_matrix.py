"""Fault matrix benchmark: seeded random injections over the whole of real ``ilcrig run`` rigs.

``python benchmarks/fault_matrix.py [--runs 200] [--seed 9] [--iterations 3] [--cycle 0.15] [--kinds PATTERNS]
[--out DIR] [--json FILE]``

Each run draws a fault kind and a position in the run (seeded) — before the first trial, in a
trial at a tick, between two trials, after the last trial, as far as the kind can happen there
(io frames flow only in a trial) — runs the distributed rig (hub, plant, four drives, host) with
``--inject`` and checks what came out:

* detected and reported: exit code 3, one ``ilcrig: fault:`` line, a ``faults`` entry;
* completed trials lost: the trials the summary held when the fault was injected (the injection
  record's ``kept``; a trial in progress is not completed) must all be kept, bit-identical to
  ``ilcrig sim`` with that many trials;
* null fields: ``kind``, ``node``, ``trial``, ``position``, ``detected_by``, ``latency_ms`` never
  null, ``tick`` given exactly in a trial; every drive's ``safe_state`` ``torque: off``;
* unreadable recordings: ``recording.rrd`` opens with rerun's ``RrdReader`` and holds exactly the
  summary's trials;
* files left: no process of the run's session, no hub folder, no temporary or reserve file, no
  trial arrays beyond the summary's.

Prints one row per run as it goes, then the table per kind and per position (of the fault as
recorded), and the load average.

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
import os
import random
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from fault_harness import EXPERIMENT, Outcome, kill_session, run_rig, sim_digest  # noqa: E402
from robot_faults import SCENARIOS, FaultMaster  # noqa: E402
from robot_util import RobotProcess, pid_alive, robot_fault_run  # noqa: E402

from bus.cia301.nmt import HOST_HEARTBEAT_MS  # noqa: E402
from host.experiment.faults import read_injections  # noqa: E402

#: kind → (spec template, the positions it can be injected at); {when} is before, T:N, T:end or after
KINDS: dict[str, tuple[str, tuple[str, ...]]] = {
    "kill-drive": ("kill:{drive}@{when}", ("before", "tick", "end", "after")),
    "kill-plant": ("kill:plant@{when}", ("before", "tick", "end", "after")),
    "kill-hub": ("kill:hub@{when}", ("before", "tick", "end", "after")),
    "kill-host": ("kill:host@{when}", ("before", "tick", "end", "after")),
    "stall-drive": ("stall:{drive}@{when},for=2", ("before", "tick", "end", "after")),
    "stall-plant": ("stall:plant@{when},for=2", ("before", "tick", "end", "after")),
    "stall-hub": ("stall:hub@{when},for=2", ("before", "tick", "end", "after")),
    "stall-host": ("stall:host@{when},for=2", ("before", "tick", "end", "after")),
    "emcy": ("emcy:{drive}@{when}", ("before", "tick", "end", "after")),
    "drop-io": ("drop:io@{when},seed={seed}", ("tick",)),
    "corrupt-io": ("corrupt:io@{when},seed={seed}", ("tick",)),
    "overflow-io": ("overflow:io@{when},seed={seed}", ("tick",)),
    "duplicate-io": ("duplicate:io@{when},seed={seed}", ("tick",)),
    "delay-io": ("delay:io@{when},seed={seed}", ("tick",)),
    "corrupt-fieldbus": ("corrupt:fieldbus@{when}", ("before", "tick", "end", "after")),
    "drop-sdo": ("drop:fieldbus@{when},id={sdo_id},count=100000", ("before", "end")),
    "diskfull": ("diskfull@{when}", ("before", "tick", "end", "after")),
}
#: the lockstep faults: their latency is also counted in ticks
FRAME_KINDS = {"drop-io", "corrupt-io", "overflow-io", "duplicate-io", "delay-io"}
#: what a record must give, never null
FIELDS = ("kind", "node", "trial", "position", "detected_by", "latency_ms")
POSITIONS = ("before_first_trial", "in_trial", "between_trials", "after_last_trial")
#: ``ilcrig robot``'s kinds (module docstring): a process killed after some periods, or a fault its
#: master causes; their position in the tables is "robot"
ROBOT_KINDS: dict[str, str] = {
    "robot-kill-drive": "{drive}",
    "robot-kill-plant": "plant",
    "robot-kill-hub": "hub",
    **{f"robot-master-{name}": name for name in SCENARIOS},
}


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, max(0, round(q / 100 * (len(v) - 1))))]


def draw(rng: random.Random, kind: str, iterations: int, n_ticks: int) -> tuple[str, str, int]:
    """A spec for ``kind`` at a random position: (spec, where drawn, the trials the summary holds
    at the earliest moment it can act)."""
    template, positions = KINDS[kind]
    where = rng.choice(positions)
    trial = rng.randrange(iterations)
    if where == "before":
        when, kept = "before", 0
    elif where == "tick":
        when, kept = f"{trial}:{rng.randrange(n_ticks)}", trial
    elif where == "end":
        trial = rng.randrange(max(iterations - 1, 1))  # between trial T and T + 1
        when, kept = f"{trial}:end", trial
    else:
        when, kept = "after", iterations - 1
    drive = rng.randint(1, 4)
    spec = template.format(when=when, drive=f"drive{drive}", seed=rng.randrange(1000), sdo_id=hex(0x580 + drive))
    return spec, where, kept


def expected_kept(o: Outcome, spec: str, kept_min: int) -> int:
    """The trials that were complete when the fault was injected: the injection record's ``kept``
    (the launcher's and the host's records say it), else the drawn lower bound."""
    for rec in read_injections(o.out):
        if rec.get("spec") == spec and isinstance(rec.get("kept"), int):
            return int(rec["kept"])
    return kept_min


def recording_trials(rrd: Path) -> list[int] | None:
    """The trials of ``recording.rrd`` as rerun's RrdReader reads them; None: it cannot."""
    from rerun.chunk import RrdReader

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ents = {c.entity_path for c in RrdReader(rrd).stream() if not c.is_static}
    except Exception:  # noqa: BLE001 - the check is whether it opens
        return None
    return sorted(int(e.rsplit("iter", 1)[1]) for e in ents if e.startswith("/joint1/error/iter"))


def files_left(o: Outcome) -> list[str]:
    """What a run must not leave: processes, the hub's folder, temporary or reserve files, trial
    arrays the summary does not hold."""
    left = [f"pid {p}" for p in o.left]
    if o.hub_dir and os.path.exists(o.hub_dir):
        left.append(o.hub_dir)
    left += [p.name for p in o.out.rglob("*") if p.name.endswith(".tmp") or "reserve" in p.name]
    kept = o.kept
    left += [p.name for p in (o.out / "trials").glob("trial-*.npz") if int(p.stem.split("-")[1]) >= kept]
    return left


def judge(o: Outcome, kind: str, spec: str, kept_min: int, tick: int | None, trial: int | None) -> dict[str, Any]:
    """One run's results (see the module docstring)."""
    f = o.fault or {}
    detected = o.code == 3 and bool(f) and len(o.lines) == 1 and o.lines[0].startswith("ilcrig: fault:")
    want = expected_kept(o, spec, kept_min)
    kept_ok = o.summary is not None and o.summary.get("trace_sha256") == sim_digest(o.kept)
    lost = max(0, want - o.kept) + (0 if kept_ok else o.kept)
    nulls = [k for k in FIELDS if f.get(k) is None]
    if (f.get("tick") is None) == (f.get("position") == "in_trial"):
        nulls.append("tick")
    drives = [e for e in (o.summary or {}).get("safe_state", []) if str(e.get("node", "")).startswith("drive")]
    unsafe = [e.get("node") for e in drives if e.get("torque") != "off"] + (["drives missing"] if len(drives) != 4 else [])
    rec = recording_trials(o.out / "recording.rrd")
    readable = rec is not None and rec == list(range(o.kept))
    tick_latency = (
        (f.get("tick") - tick)
        if (kind in FRAME_KINDS and isinstance(f.get("tick"), int) and tick is not None and f.get("trial") == trial)
        else None
    )
    return {
        "kind": kind,
        "spec": spec,
        "code": o.code,
        "detected": detected,
        "fault_kind": f.get("kind"),
        "position": f.get("position"),
        "detected_by": f.get("detected_by"),
        "latency_ms": f.get("latency_ms"),
        "tick_latency": tick_latency,
        "kept": o.kept,
        "expected_kept": want,
        "lost": lost,
        "nulls": nulls,
        "unsafe": unsafe,
        "recording_ok": readable,
        "left": files_left(o),
        "wall_s": round(o.wall_s, 1),
        "line": o.lines[0] if o.lines else "",
    }


def table(results: list[dict[str, Any]], key: str, order: list[str]) -> list[str]:
    rows = [
        f"| {key} | runs | detected | trials lost | null fields | drives not safe | unreadable recordings | files left | "
        "latency p50 ms | latency p99 ms | tick latency p50/max |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in [*order, "all"]:
        rs = [r for r in results if name == "all" or r[key] == name]
        if not rs:
            continue
        lats = [float(r["latency_ms"]) for r in rs if isinstance(r["latency_ms"], int | float)]
        ticks = [int(r["tick_latency"]) for r in rs if r["tick_latency"] is not None]
        tl = f"{statistics.median(ticks):.0f}/{max(ticks)}" if ticks else "-"
        rows.append(
            f"| {name} | {len(rs)} | {sum(r['detected'] for r in rs)} | {sum(r['lost'] for r in rs)} | "
            f"{sum(len(r['nulls']) for r in rs)} | {sum(len(r['unsafe']) for r in rs)} | "
            f"{sum(not r['recording_ok'] for r in rs)} | {sum(len(r['left']) for r in rs)} | "
            f"{pct(lats, 50):.0f} | {pct(lats, 99):.0f} | {tl} |"
        )
    return rows


def _robot_row(
    i: int,
    kind: str,
    spec: str,
    code: int | None,
    detected: bool,
    fault_kind: str,
    detected_by: str,
    latency_ms: float | None,
    tick_latency: int | None,
    *,
    unsafe: list[str],
    left: list[str],
    t0: float,
    line: str,
) -> dict[str, Any]:
    """The row of one run on the robot (no trials, no recording to judge); ``t0``: its start (``time.monotonic()``)."""
    return {
        "i": i,
        "kind": kind,
        "spec": spec,
        "code": code,
        "detected": detected,
        "fault_kind": fault_kind,
        "detected_by": detected_by,
        "latency_ms": latency_ms,
        "tick_latency": tick_latency,
        "position": "robot",
        "drawn": "robot",
        "kept": 0,
        "expected_kept": 0,
        "lost": 0,
        "nulls": [],
        "unsafe": unsafe,
        "recording_ok": True,
        "left": left,
        "wall_s": round(time.monotonic() - t0, 1),
        "line": line,
    }


def robot_run(i: int, kind: str, victim: str, out: Path, periods_before: int) -> dict[str, Any]:
    """One ``robot-kill-*`` run (module docstring); its row."""
    t0 = time.monotonic()
    o = robot_fault_run(out, victim, periods_before=periods_before)
    detected = o["code"] == 3 and len(o["stderr"]) == 1 and o["stderr"][0].startswith(f"ilcrig: fault: {victim} (pid ")
    r = _robot_row(
        i,
        kind,
        f"kill:{victim} after {periods_before} periods",
        o["code"],
        detected,
        "process_died",
        "launcher",
        o["latency_ms"],
        None,
        unsafe=[],
        left=[f"pid {p}" for p in o["left"]],
        t0=t0,
        line=o["stderr"][0] if o["stderr"] else "",
    )
    print(
        f"{i:3d} {r['spec']:34s} exit {o['code']} {'detected' if detected else 'MISSED':8s} by launcher "
        f"{o['latency_ms']:7.0f} ms (exit after {o['exit_ms']:.0f} ms) left {len(o['left'])} ({r['wall_s']:.0f} s)",
        flush=True,
    )
    return r


def robot_master_run(i: int, kind: str, scenario: str, out: Path) -> dict[str, Any]:
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
    r = _robot_row(
        i,
        kind,
        f"master: {scenario}",
        code,
        detected,
        scenario,
        "plant" if res.robot_emcy else "drives",
        res.latency_ms if res.latency_ms else None,
        res.periods or None,
        unsafe=[] if safe else ["robot"],
        left=[],
        t0=t0,
        line="",
    )
    lat = f"{res.latency_ms:7.0f} ms" if res.latency_ms else "      - ms"
    print(
        f"{i:3d} {r['spec']:34s} exit {code} {'detected' if detected else 'MISSED':8s} by {r['detected_by']:8s} "
        f"{lat} periods {res.periods} brakes 0x{res.brakes:X} ({r['wall_s']:.0f} s)",
        flush=True,
    )
    return r


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--seed", type=int, default=9)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--cycle", type=float, default=0.15)
    p.add_argument(
        "--kinds", default="*", help="comma-separated glob patterns of the kinds to draw from (default: all, e.g. 'robot-*')"
    )
    p.add_argument("--out", default=None, help="keep the run folders here (default: a temp folder)")
    p.add_argument("--json", default=None, help="write every run's result to this file")
    args = p.parse_args(argv)
    EXPERIMENT[:] = ["--cycle", repr(args.cycle)]
    n_ticks = round(2 * args.cycle / 0.001) + 1
    rng = random.Random(args.seed)
    patterns = [p.strip() for p in args.kinds.split(",") if p.strip()]
    kinds = [k for k in (*KINDS, *ROBOT_KINDS) if any(fnmatch.fnmatchcase(k, p) for p in patterns)]
    if not kinds:
        p.error(f"--kinds {args.kinds}: no kind matches (kinds: {', '.join((*KINDS, *ROBOT_KINDS))})")
    plan: list[tuple[str, str, str, int]] = []
    for i in range(args.runs):
        kind = kinds[i % len(kinds)] if i < len(kinds) else rng.choice(kinds)  # every kind at least once
        if kind in ROBOT_KINDS:
            victim = ROBOT_KINDS[kind].format(drive=f"drive{rng.randint(1, 4)}")
            plan.append((kind, victim, "robot", rng.randrange(n_ticks) + 1))  # the periods before the kill
        else:
            plan.append((kind, *draw(rng, kind, args.iterations, n_ticks)))
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ilcrig-faultmatrix-"))
    results = []
    t_start = time.monotonic()
    print(
        f"{args.runs} injections over the whole run, {args.iterations} trials of N = {n_ticks} ticks; heartbeat "
        f"{HOST_HEARTBEAT_MS} ms; load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    for i, (kind, spec, where, kept_min) in enumerate(plan):
        out = base / f"run{i:03d}"
        if kind.startswith("robot-master-"):
            results.append(robot_master_run(i, kind, spec, out))
            continue
        if kind.startswith("robot-"):
            results.append(robot_run(i, kind, spec, out, periods_before=kept_min))
            continue
        o = run_rig(out, "--inject", spec, iterations=args.iterations, timeout_s=600)
        kill_session(o)
        at = spec.split("@", 1)[1].split(",", 1)[0]
        trial_s, _, tick_s = at.partition(":")
        tick = int(tick_s) if tick_s.isdigit() else None
        r = judge(o, kind, spec, kept_min, tick, int(trial_s) if trial_s.isdigit() else None) | {"i": i, "drawn": where}
        results.append(r)
        lat = f"{r['latency_ms']:.0f} ms" if isinstance(r["latency_ms"], int | float) else "-"
        bad = [
            w
            for w, cond in (
                ("MISSED", not r["detected"]),
                ("LOST", r["lost"]),
                ("NULL", r["nulls"]),
                ("UNSAFE", r["unsafe"]),
                ("RRD", not r["recording_ok"]),
                ("LEFT", r["left"]),
            )
            if cond
        ]
        print(
            f"{i:3d} {spec:48s} exit {o.code} {str(r['fault_kind']):14s} {str(r['position']):18s} by "
            f"{str(r['detected_by']):8s} {lat:>7s} kept {o.kept}/{r['expected_kept']} ({o.wall_s:.0f} s) {' '.join(bad) or 'ok'}",
            flush=True,
        )
        if bad:
            print(f"    {r['line']}  {r['nulls']} {r['unsafe']} {r['left']}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    print(f"\n{len(results)} runs in {(time.monotonic() - t_start) / 60:.1f} min; load average {os.getloadavg()}\n")
    print("\n".join(table(results, "kind", [*KINDS, *ROBOT_KINDS])))
    print()
    print("\n".join(table(results, "position", [*POSITIONS, "robot"])))
    failed = sum(
        (not r["detected"]) + bool(r["lost"]) + bool(r["nulls"]) + bool(r["unsafe"]) + (not r["recording_ok"]) + bool(r["left"])
        for r in results
    )
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
