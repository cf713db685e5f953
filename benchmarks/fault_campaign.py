"""The seeded fault campaign: our own signals and ``--inject`` specs at every moment of real
``ilcrig run`` rigs, each run checked against the invariants of the fault path.

``python benchmarks/fault_campaign.py [--runs 300] [--seed 33] [--iterations 2] [--cycle 0.15]
[--jobs 1] [--only I,J,…] [--out DIR] [--json FILE]``; ``--table FILE``: the table of the runs in
a ``--json`` file so far

Each run (seeded draw, short: 2 trials of 0.3 s) is one of

* a **signal** of ours: SIGKILL, or SIGSTOP for 3 s (longer than the 500 ms consumer time) then
  SIGCONT, of one process of the run — the hub, the plant, a drive, the host or the launcher
  (``ilcrig run`` itself) — at a **moment** taken from the run's stdout: ``bring_up`` (0–150 ms
  after the host's header line), ``after_row`` (0–50 ms after a printed trial row),
  ``between_trials`` (50–300 ms after a row that is not the last), ``in_trial`` (0.45–0.9 s after
  a row that is not the last: the next trial's set-up or the trial itself), ``after_last``
  (0–400 ms after the last row) or ``shutdown`` (0–100 ms after the host's last line);
* an **injection** ``--inject SPEC`` at ``before``, ``T:N``, ``T:end`` or ``after``: every kind of
  benchmarks/fault_matrix.py plus those the protocol absorbs (``duplicate`` / ``delay`` / ``drop``
  of fieldbus frames, a stall shorter than the consumer time).

After each run, the invariants (a violation is a bug to fix at its cause):

* ``summary`` — ``summary.json`` exists (a SIGKILL of the launcher aside: it takes the host
  with it; docs/faults.md);
* ``lost`` — every trial whose row was printed is kept (rows printed ⊆ trials kept);
* ``silent`` — a signal of ours to a process of the run while the host ran ends in a fault (exit
  3) naming that process, or, once the results were safe, a ``liveness_incidents`` entry; every
  ``--inject`` spec has an ``injections`` entry (``fault``, ``tolerated``, or ``not_injected``
  only when the run had ended before its moment);
* ``wrong`` — the fault record says what was done: its ``node`` the process signalled or the
  injection's target, its ``kind`` one the cause can give, its ``position``, ``trial`` and ``tick``
  those of the injection's moment (``@T:N``: trial T, tick ≥ N; ``@T:end``: after trial T;
  ``@before``; ``@after``) and consistent with the trials kept;
* ``null_times`` — every fault record has both ``t_detected_mono`` and ``t_detected_wall``;
* ``left`` — no process, hub folder, temporary file or stray trial array left
  (benchmarks/fault_matrix.py :func:`files_left`).

Counted apart (``unprovoked``, not a violation of the fault path): a fault that came before the
signal, or in a run whose injection is accounted as not its cause — a process starved longer than
its consumer time on a loaded machine; its record and accounting are still checked. On a shared,
loaded machine run it with ``ILCRIG_TIMEOUT_SCALE=2`` (every consumer time and timeout doubled:
the 3 s stalls stay longer than the 1 s consumer time).

Prints one row per run, then the table per family and moment (the one in docs/benchmarks.md).
The fast subset (``--runs 5``) is ``tests/test_fault_campaign.py`` (full tier).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from fault_harness import EXPERIMENT, Outcome, host_pid, kill_session, printed_rows, run_rig, status_pids  # noqa: E402
from fault_matrix import KINDS, files_left  # noqa: E402

#: the processes our signals hit
VICTIMS = ("hub", "plant", "drive1", "drive2", "drive3", "drive4", "host", "launcher")
#: the moments of our signals (module docstring), each with its stdout trigger and delay range, s
MOMENTS: dict[str, tuple[str, float, float]] = {
    "bring_up": ("header", 0.0, 0.15),
    "after_row": ("row", 0.0, 0.05),
    "between_trials": ("row_not_last", 0.05, 0.3),
    "in_trial": ("row_not_last", 0.45, 0.9),
    "after_last": ("last_row", 0.0, 0.4),
    "shutdown": ("final", 0.0, 0.1),
}
#: SIGSTOP lasts this long, s (longer than the consumer time)
STALL_S = 3.0
#: injections the protocol absorbs (a tolerated one is recorded as such; a fault is fine too)
TOLERABLE: dict[str, tuple[str, tuple[str, ...]]] = {
    "duplicate-fieldbus": ("duplicate:fieldbus@{when},seed={seed}", ("before", "tick", "end", "after")),
    "delay-fieldbus": ("delay:fieldbus@{when},seed={seed}", ("before", "tick", "end", "after")),
    "drop-heartbeat": ("drop:fieldbus@{when},id={hb_id}", ("before", "tick", "end", "after")),
    "short-stall": ("stall:{drive}@{when},for=0.1", ("before", "tick", "end", "after")),
}
#: what a fault of each target may be recorded as
KINDS_OF: dict[str, set[str]] = {
    "hub": {"bus_lost", "bus_silent", "process_died"},
    "host": {"process_died", "host_lost"},
    "plant": {"node_lost", "process_died", "plant_error"},
    **{f"drive{n}": {"node_lost", "process_died", "emcy"} for n in range(1, 5)},
}


@dataclass
class Plan:
    """One run of the campaign."""

    i: int
    family: str  # "signal" or "inject"
    moment: str  # a key of MOMENTS, or before / tick / end / after
    spec: str  # "SIGKILL drive2", "SIGSTOP host", or an --inject spec
    victim: str | None = None
    sig: str | None = None
    delay_s: float = 0.0
    row: int = 0  # the row that triggers (row moments)
    extra: dict[str, Any] = field(default_factory=dict)


def draw(rng: random.Random, i: int, iterations: int, n_ticks: int) -> Plan:
    """The i-th run of the campaign (half signals, half injections)."""
    if i % 2 == 0:
        moment = list(MOMENTS)[(i // 2) % len(MOMENTS)]
        victim = rng.choice(VICTIMS)
        sig = rng.choice(("SIGKILL", "SIGSTOP"))
        trigger, lo, hi = MOMENTS[moment]
        row = iterations - 1 if trigger == "last_row" else rng.randrange(max(iterations - 1, 1))
        return Plan(i, "signal", moment, f"{sig} {victim}", victim, sig, rng.uniform(lo, hi), row)
    kinds = {**KINDS, **TOLERABLE}
    kind = rng.choice(sorted(kinds))
    template, positions = kinds[kind]
    where = rng.choice(positions)
    trial = rng.randrange(iterations)
    if where == "before":
        when = "before"
    elif where == "tick":
        when = f"{trial}:{rng.randrange(n_ticks)}"
    elif where == "end":
        when = f"{rng.randrange(max(iterations - 1, 1))}:end"
    else:
        when = "after"
    drive = rng.randint(1, 4)
    spec = template.format(
        when=when,
        drive=f"drive{drive}",
        seed=rng.randrange(1000),
        sdo_id=hex(0x580 + drive),
        hb_id=hex(0x700 + rng.choice((1, 2, 3, 4, 32, 127))),
    )
    return Plan(i, "inject", where, spec, extra={"kind": kind})


class Signaller:
    """Sends a plan's signal at its moment, from the launcher's stdout lines (``on_line``)."""

    def __init__(self, plan: Plan, out: Path, iterations: int) -> None:
        self.plan = plan
        self.out = out
        self.iterations = iterations
        self.pids: dict[str, int] = {}
        self.sent: dict[str, Any] = {}
        self.rows = 0
        self.timers: list[threading.Timer] = []

    def on_line(self, line: str, proc: Any) -> None:
        self.pids.update(status_pids(line))
        self.pids["launcher"] = proc.pid
        trigger = MOMENTS[self.plan.moment][0]
        fire = False
        if line.startswith("ilcrig host:"):
            pid = host_pid(self.out)
            if pid is not None:
                self.pids["host"] = pid
            fire = trigger == "header"
        elif printed_rows(line):
            k = printed_rows(line)[0]
            self.rows = k + 1
            last = k == self.iterations - 1
            fire = (
                (trigger == "row" and k == self.plan.row)
                or (trigger == "row_not_last" and k == self.plan.row and not last)
                or (trigger == "last_row" and last)
            )
        elif "trace_sha256" in line:
            fire = trigger == "final"
        if fire and not self.sent:
            self.sent = {"armed_after_rows": self.rows}
            t = threading.Timer(self.plan.delay_s, self._fire)
            t.daemon = True
            self.timers.append(t)
            t.start()

    def _fire(self) -> None:
        plan = self.plan
        pid = self.pids.get(plan.victim or "")
        host = self.pids.get("host")
        self.sent |= {"pid": pid, "t_mono": time.monotonic(), "host_running": _running(host) if host else None}
        if pid is None or not _running(pid):
            self.sent["missed"] = "not running"
            return
        with contextlib.suppress(ProcessLookupError):
            if plan.sig == "SIGKILL":
                os.kill(pid, signal.SIGKILL)
            else:
                os.kill(pid, signal.SIGSTOP)
                t = threading.Timer(STALL_S, _cont, (pid,))
                t.daemon = True
                self.timers.append(t)
                t.start()

    def finish(self) -> None:
        """Every stalled process resumed (the run has ended)."""
        for t in self.timers:
            t.join(timeout=STALL_S + 1)


def _cont(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGCONT)


def _running(pid: int) -> bool:
    """The process exists and has not ended (a zombie has)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")


def expected_place(spec: str, iterations: int) -> tuple[set[str], int | None, int | None]:
    """(positions, trial, least tick) a fault of the injection ``spec`` must be recorded at."""
    at = spec.split("@", 1)[1].split(",", 1)[0]
    if at == "before":
        return {"before_first_trial"}, 0, None
    if at == "after":
        return {"after_last_trial"}, iterations - 1, None
    t, _, n = at.partition(":")
    if n == "end":
        if int(t) == iterations - 1:
            return {"after_last_trial"}, int(t), None
        return {"between_trials"}, int(t) + 1, None
    return {"in_trial"}, int(t), int(n)


def target_of(spec: str) -> str | None:
    """The process an injection names (None: a channel or the disk)."""
    head = spec.split("@", 1)[0]
    action, _, target = head.partition(":")
    return target if action in ("kill", "stall", "emcy") else None


def check(plan: Plan, o: Outcome, sent: dict[str, Any], iterations: int) -> dict[str, list[str]]:
    """The invariants of one run (module docstring): violation name → what."""
    bad: dict[str, list[str]] = {}
    s = o.summary
    launcher_killed = plan.victim == "launcher" and plan.sig == "SIGKILL" and not sent.get("missed")
    if s is None and not launcher_killed:
        bad.setdefault("summary", []).append(f"no summary.json (exit {o.code})")
    rows = printed_rows(o.stdout)
    if s is not None and any(r >= o.kept for r in rows):
        bad.setdefault("lost", []).append(f"rows {rows} printed, {o.kept} kept")
    faults = (s or {}).get("faults") or []
    for f in faults:
        if f.get("t_detected_mono") is None or f.get("t_detected_wall") is None:
            bad.setdefault("null_times", []).append(f"{f.get('kind')} of {f.get('node')}")
    f = faults[0] if faults else None
    if f is not None:
        n_ticks = int((s or {}).get("config", {}).get("n_ticks") or 1 << 30)
        _check_consistent(f, o.kept, iterations, n_ticks, bad)
    if plan.family == "signal":
        _check_signal(plan, o, sent, f, bad)
    else:
        _check_inject(plan, o, f, iterations, bad)
    left = files_left(o)
    if left:
        bad["left"] = left
    return bad


#: what the launcher's own watch records (a silence or a stop it noticed): placed where the run was
#: then, whatever the host kept after it (docs/faults.md "Stalls at the edges")
LAUNCHER_SILENCES = {"node_lost", "host_lost", "bus_silent"}


def _check_consistent(f: dict[str, Any], kept: int, iterations: int, n_ticks: int, bad: dict[str, list[str]]) -> None:
    """A record's place agrees with the trials kept (a silence the launcher noticed: with those
    kept when it noticed it, at most those kept in the end)."""
    pos, trial, tick = f.get("position"), f.get("trial"), f.get("tick")
    if f.get("detected_by") == "launcher" and f.get("kind") in LAUNCHER_SILENCES and isinstance(trial, int):
        noticed = {"before_first_trial": 0, "in_trial": trial, "between_trials": trial, "after_last_trial": iterations}
        kept = min(kept, noticed.get(str(pos), kept))
    want = {
        "before_first_trial": (0, kept == 0),
        "in_trial": (kept, tick is not None),
        "between_trials": (kept, tick is None),
        "after_last_trial": (iterations - 1, kept == iterations and tick is None),
    }.get(str(pos))
    if want is None or trial != want[0] or not want[1]:
        bad.setdefault("wrong", []).append(f"{pos} trial {trial} tick {tick} with {kept} kept")
    elif isinstance(tick, int) and not 0 <= tick < n_ticks:
        bad.setdefault("wrong", []).append(f"tick {tick} outside a trial of {n_ticks} ticks")


def _check_signal(plan: Plan, o: Outcome, sent: dict[str, Any], f: dict[str, Any] | None, bad: dict[str, list[str]]) -> None:
    if sent.get("missed") or not sent or plan.victim == "launcher":
        return  # the process had ended already; the launcher's own signal: summary and rows only
    if f is not None and f.get("t_detected_mono") is not None and float(f["t_detected_mono"]) < sent.get("t_mono", 0.0):
        bad.setdefault("unprovoked", []).append(f"{f.get('kind')} of {f.get('node')} before the signal")
        return
    host_running = sent.get("host_running")
    if plan.victim != "host" and not host_running:
        return  # the results were safe: a liveness incident at most (the launcher ends the rest)
    if f is None:
        incidents = (o.summary or {}).get("liveness_incidents") or []
        if not any(inc.get("node") == plan.victim for inc in incidents) and o.code != 143:
            bad.setdefault("silent", []).append(f"{plan.spec}: exit {o.code}, no fault, no incident")
        return
    kinds = KINDS_OF.get(str(plan.victim), set())
    if f.get("node") != plan.victim or f.get("kind") not in kinds:
        bad.setdefault("wrong", []).append(f"{plan.spec} recorded as {f.get('kind')} of {f.get('node')}")


def _check_inject(plan: Plan, o: Outcome, f: dict[str, Any] | None, iterations: int, bad: dict[str, list[str]]) -> None:
    entries = {e.get("spec"): e for e in (o.summary or {}).get("injections") or []}
    entry = entries.get(plan.spec)
    if o.summary is not None and (entry is None or (entry.get("effect") == "not_injected" and o.code == 0)):
        bad.setdefault("silent", []).append(f"{plan.spec}: {entry}")
    if entry is None or entry.get("effect") != "fault":
        if o.code == 3 and entry is not None:  # a fault nobody injected (accounted as such): the machine's
            bad.setdefault("unprovoked", []).append(f"{entry.get('effect')}: {entry.get('what')}")
        return
    if f is None:
        bad.setdefault("wrong", []).append(f"{plan.spec} a fault without a record")
        return
    positions, trial, tick = expected_place(plan.spec, iterations)
    target = target_of(plan.spec)
    if target is not None:
        kinds = KINDS_OF.get(target, set()) | ({"emcy"} if plan.spec.startswith("emcy") else set())
        if plan.spec.startswith("stall:host"):
            kinds = {"host_lost", "process_died"}
        if f.get("node") != target or f.get("kind") not in kinds:
            bad.setdefault("wrong", []).append(f"{plan.spec} recorded as {f.get('kind')} of {f.get('node')}")
    if f.get("position") not in positions or f.get("trial") != trial:
        bad.setdefault("wrong", []).append(f"{plan.spec} recorded at {f.get('position')} trial {f.get('trial')}")
    elif tick is not None and (f.get("tick") is None or int(f["tick"]) < tick):
        bad.setdefault("wrong", []).append(f"{plan.spec} recorded at tick {f.get('tick')}")


def run_one(plan: Plan, base: Path, iterations: int) -> dict[str, Any]:
    """Run one plan and check it; its row."""
    out = base / f"run{plan.i:03d}"
    t0 = time.monotonic()
    if plan.family == "signal":
        sig = Signaller(plan, out, iterations)
        o = run_rig(out, iterations=iterations, timeout_s=600, on_line=sig.on_line)
        sig.finish()
        sent = sig.sent
    else:
        o = run_rig(out, "--inject", plan.spec, iterations=iterations, timeout_s=600)
        sent = {}
    kill_session(o)
    bad = check(plan, o, sent, iterations)
    f = o.fault or {}
    inj: dict[str, Any] = next((e for e in (o.summary or {}).get("injections") or [] if e.get("spec") == plan.spec), {})
    return {
        "i": plan.i,
        "family": plan.family,
        "moment": plan.moment,
        "spec": plan.spec,
        "delay_ms": round(plan.delay_s * 1000),
        "missed": sent.get("missed"),
        "code": o.code,
        "summary": o.summary is not None,
        "written_by": (o.summary or {}).get("written_by", "host") if o.summary else None,
        "kept": o.kept,
        "rows": printed_rows(o.stdout),
        "fault": f"{f.get('kind')} of {f.get('node')} at {f.get('position')} trial {f.get('trial')} tick {f.get('tick')}"
        if f
        else None,
        "effect": inj.get("effect"),
        "bad": bad,
        "wall_s": round(time.monotonic() - t0, 1),
        "line": o.lines[-1] if o.lines else "",
    }


INVARIANTS = ("summary", "lost", "silent", "wrong", "null_times", "left")
#: not a violation of the fault path, counted apart: a fault that came before (or without) what the
#: run did — a process starved longer than its consumer time on a loaded machine
APART = ("unprovoked",)


def table(results: list[dict[str, Any]]) -> list[str]:
    """The campaign's table: per family and moment, runs and violations of each invariant."""
    rows = [
        "| family | moment | runs | exit 0 / 3 / other | faults | tolerated | no summary (launcher SIGKILL) | "
        + " | ".join((*INVARIANTS, *APART))
        + " |",
        "|---|---|---|---|---|---|---|" + "---|" * (len(INVARIANTS) + len(APART)),
    ]
    keys = sorted({(r["family"], r["moment"]) for r in results})
    for fam, mom in [*keys, ("all", "all")]:
        rs = [r for r in results if fam == "all" or (r["family"], r["moment"]) == (fam, mom)]
        codes = (
            f"{sum(r['code'] == 0 for r in rs)} / {sum(r['code'] == 3 for r in rs)} / {sum(r['code'] not in (0, 3) for r in rs)}"
        )
        nosum = sum(not r["summary"] for r in rs)
        rows.append(
            f"| {fam} | {mom} | {len(rs)} | {codes} | {sum(r['fault'] is not None for r in rs)} | "
            f"{sum(r['effect'] == 'tolerated' for r in rs)} | {nosum} | "
            + " | ".join(str(sum(k in r["bad"] for r in rs)) for k in (*INVARIANTS, *APART))
            + " |"
        )
    return rows


def plans(runs: int, seed: int, iterations: int, n_ticks: int) -> list[Plan]:
    """The campaign's runs, seeded."""
    rng = random.Random(seed)
    return [draw(rng, i, iterations, n_ticks) for i in range(runs)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=300)
    p.add_argument("--seed", type=int, default=33)
    p.add_argument("--iterations", type=int, default=2)
    p.add_argument("--cycle", type=float, default=0.15)
    p.add_argument("--jobs", type=int, default=1, help="runs at the same time (default 1)")
    p.add_argument("--only", default=None, help="comma-separated run numbers to run (a rerun of failures)")
    p.add_argument("--out", default=None, help="keep the run folders here (default: a temp folder)")
    p.add_argument("--json", default=None, help="write every run's result to this file (JSON lines, as they end)")
    p.add_argument("--table", default=None, help="only print the table of the runs in this --json file (so far)")
    args = p.parse_args(argv)
    if args.table:
        done = [json.loads(ln) for ln in Path(args.table).read_text(encoding="utf-8").splitlines() if ln.strip()]
        print(f"{len(done)} runs\n")
        print("\n".join(table(sorted(done, key=lambda r: r["i"]))))
        return 0
    EXPERIMENT[:] = ["--cycle", repr(args.cycle)]
    n_ticks = round(2 * args.cycle / 0.001) + 1
    todo = plans(args.runs, args.seed, args.iterations, n_ticks)
    if args.only:
        keep = {int(x) for x in args.only.split(",")}
        todo = [pl for pl in todo if pl.i in keep]
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ilcrig-faultcampaign-"))
    base.mkdir(parents=True, exist_ok=True)
    print(
        f"{len(todo)} runs (seed {args.seed}), {args.iterations} trials of N = {n_ticks} ticks, {args.jobs} at a time; "
        f"load average {os.getloadavg()[0]:.2f}; folders in {base}",
        flush=True,
    )
    results: list[dict[str, Any]] = []
    lock = threading.Lock()
    t_start = time.monotonic()

    def one(plan: Plan) -> None:
        r = run_one(plan, base, args.iterations)
        with lock:
            results.append(r)
            if args.json:
                with open(args.json, "a", encoding="utf-8") as fh:
                    fh.write(json.dumps(r) + "\n")
            verdict = " ".join(f"{k.upper()}: {'; '.join(v)}" for k, v in r["bad"].items()) or "ok"
            print(
                f"{r['i']:3d} {r['family']:6s} {r['moment']:14s} {r['spec']:44s} +{r['delay_ms']:3d}ms exit {r['code']:3d} "
                f"kept {r['kept']} rows {len(r['rows'])} {r['effect'] or r['missed'] or '':12s} {r['fault'] or '-'} "
                f"({r['wall_s']:.0f} s) {verdict}",
                flush=True,
            )

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        list(pool.map(one, todo))
    results.sort(key=lambda r: r["i"])
    print(f"\n{len(results)} runs in {(time.monotonic() - t_start) / 60:.1f} min; load average {os.getloadavg()}\n")
    print("\n".join(table(results)))
    failed = [r["i"] for r in results if set(r["bad"]) - set(APART)]
    if failed:
        print(f"\nruns with a violation: {','.join(map(str, failed))}")
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
