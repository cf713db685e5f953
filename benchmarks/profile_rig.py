"""Profile of the distributed rig: CPU time per tick of every role process (hub, plant, drives, host).

Starts ``ilcrig run`` on the hub transport, reads the process ids from the launcher's status line,
and samples every ``--every`` seconds the CPU time (user + system, ``/proc/<pid>/stat``) of each
role and the io frame count of the hub (:func:`bus.transports.hub.stats.query_hub_stats`; one
lockstep tick = 8 io frames). Only the sampling intervals in which ticks ran at no less than half
the best rate seen are counted (so the start-up, the SDO exchange between trials and the
shutdown are left out), and the figures are CPU µs per tick for each role, their sum, and the
load average.

    python benchmarks/profile_rig.py [--iterations 3] [--cycle 0.5] [--every 0.25]

A wall-clock measurement: run it beside ``benchmarks/rig_speed.py`` and read the figures as
shares of the total, not as absolute numbers on a shared machine.

``--phases``: where a whole run's time goes, start-up and end included. At each of the run's
console marks (the launcher's status line, the host's first line, the trials' header, the last
trial's row, the closing line, the launcher's exit) the wall time since the start and the CPU
seconds each process has used so far; then the CPU of each phase per process.

    python benchmarks/profile_rig.py --phases [--iterations 2] [--cycle 0.15] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

from bus.transports.hub.stats import query_hub_stats  # noqa: E402
from bus.transports.hub.wire import HubError  # noqa: E402

_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> tuple[float, float] | None:
    """(user, system) CPU seconds of process ``pid`` (all its threads), None if gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[11]) / _TICKS, int(fields[12]) / _TICKS


def ctx_switches(pid: int) -> tuple[int, int] | None:
    """(voluntary, involuntary) context switches of process ``pid`` (all its threads), None if gone."""
    vol = invol = 0
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            for line in (task / "status").read_text().splitlines():
                if line.startswith("voluntary_ctxt_switches:"):
                    vol += int(line.split()[1])
                elif line.startswith("nonvoluntary_ctxt_switches:"):
                    invol += int(line.split()[1])
    except (OSError, ValueError):
        return None
    return vol, invol


def children_of(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(d.name))
    return out


#: the console marks a line's start says: the launcher's status line, the host's first line, the
#: trials' header; a trial's row and the closing line are matched by :func:`_mark_of`
_STARTS = {"status": "ilcrig run: transport", "host": "ilcrig host:", "header": "iter "}
_ROW = re.compile(r"^\s*\d+\s+\d")


def _mark_of(line: str) -> str | None:
    """Which console mark ``line`` is (None: none)."""
    if _ROW.match(line):
        return "row"
    if "trace_sha256" in line and "ticks/s in trials" in line:
        return "closing"
    return next((name for name, start in _STARTS.items() if line.startswith(start)), None)


def phases(iterations: int, cycle: float, extra: list[str]) -> list[tuple[str, float, dict[str, float]]]:
    """One ``ilcrig run``: at each console mark (the last row only), (mark, wall s since the start,
    CPU s of each process so far); "exit" last, with the launcher's own and its reaped children's CPU."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-u", "-m", "host.cli", "run", "--iterations", str(iterations), "--cycle", str(cycle)]
        cmd += ["--bus", "hub", "--out", str(Path(tmp) / "run"), *extra]
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, text=True, start_new_session=True)
        assert proc.stdout is not None
        roles: dict[str, int] = {"launcher": proc.pid}
        last: dict[str, float] = {}
        marks: list[tuple[str, float, dict[str, float]]] = []
        for line in proc.stdout:
            mark = _mark_of(line)
            if mark is None:
                continue
            now = time.monotonic() - t0
            if mark == "status":
                m = re.search(r"processes: (.*); role logs", line)
                if m:
                    roles |= {name: int(pid) for name, pid in (p.split() for p in m.group(1).split(", "))}
            if "host" not in roles and mark != "status":
                host = [p for p in children_of(proc.pid) if p not in roles.values()]
                if host:
                    roles["host"] = host[0]
            for name, pid in roles.items():
                c = cpu_s(pid)
                if c is not None:
                    last[name] = sum(c)
            if mark == "row" and marks and marks[-1][0] == "row":
                marks.pop()  # the last row only
            marks.append((mark, now, dict(last)))
        proc.wait()
        marks.append(("exit", time.monotonic() - t0, dict(last)))
    return marks


def main_phases(args: argparse.Namespace) -> None:
    """``--phases``: the marks of ``--repeat`` runs, then the CPU of each phase per process."""
    print(f"load average {os.getloadavg()[0]:.2f}; ilcrig run --iterations {args.iterations} --cycle {args.cycle} --bus hub")
    for r in range(args.repeat):
        marks = phases(args.iterations, args.cycle, args.extra)
        names = sorted({n for _, _, cpu in marks for n in cpu}, key=lambda n: (n != "launcher", n))
        print(f"run {r + 1}: " + ", ".join(f"{m} {t:.2f} s" for m, t, _ in marks))
        print(f"  {'phase':<18}{'wall s':>8}" + "".join(f"{n:>9}" for n in names) + f"{'all':>9}   (CPU s)")
        prev_t, prev_cpu = 0.0, dict.fromkeys(names, 0.0)
        for mark, t, cpu in marks:
            used = [cpu.get(n, prev_cpu[n]) - prev_cpu[n] for n in names]
            print(f"  {'to ' + mark:<18}{t - prev_t:8.2f}" + "".join(f"{u:9.2f}" for u in used) + f"{sum(used):9.2f}")
            prev_t, prev_cpu = t, {n: cpu.get(n, prev_cpu[n]) for n in names}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--cycle", type=float, default=0.5)
    ap.add_argument("--every", type=float, default=0.25, help="sampling period, s")
    ap.add_argument("--phases", action="store_true", help="where a whole run's time goes (module docstring)")
    ap.add_argument("--repeat", type=int, default=3, help="runs, with --phases")
    ap.add_argument("extra", nargs="*", help="more `ilcrig run` options")
    args = ap.parse_args()
    if args.phases:
        main_phases(args)
        return
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-u",
            "-m",
            "host.cli",
            "run",
            "--iterations",
            str(args.iterations),
            "--cycle",
            str(args.cycle),
            "--bus",
            "hub",
            "--out",
            str(Path(tmp) / "run"),
            *args.extra,
        ]
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, text=True, start_new_session=True)
        assert proc.stdout is not None
        roles: dict[str, int] = {}
        hub = ""
        for line in proc.stdout:
            m = re.search(r"transport hub \((\S+)\); processes: (.*); role logs", line)
            if m:
                hub = m.group(1)
                roles = {name: int(pid) for name, pid in (p.split() for p in m.group(2).split(", "))}
                break
        time.sleep(0.5)
        host = [p for p in children_of(proc.pid) if p not in roles.values()]
        if host:
            roles["host"] = host[0]
        samples: list[tuple[float, int, dict[str, tuple[float, float, int, int]]]] = []
        while proc.poll() is None:
            try:
                frames = query_hub_stats(hub)["io"].frames if hub else 0
            except (HubError, KeyError, OSError):
                frames = 0
            cpu = {name: cpu_s(pid) for name, pid in roles.items()}
            ctx = {name: ctx_switches(pid) for name, pid in roles.items()}
            samples.append((time.monotonic(), frames, {k: (*v, *(ctx[k] or (0, 0))) for k, v in cpu.items() if v is not None}))
            time.sleep(args.every)
        tail = proc.stdout.read()
    rates = [(b[1] - a[1]) / 8 / (b[0] - a[0]) for a, b in zip(samples, samples[1:])]
    best = max(rates, default=0.0)
    ticks = 0.0
    wall = 0.0
    cpu_tot: dict[str, list[float]] = {}
    for (a, b), rate in zip(zip(samples, samples[1:]), rates):
        if best <= 0 or rate < 0.5 * best:
            continue
        ticks += (b[1] - a[1]) / 8
        wall += b[0] - a[0]
        for name in a[2]:
            if name in b[2]:
                tot = cpu_tot.setdefault(name, [0.0, 0.0, 0.0, 0.0])
                for i in range(4):
                    tot[i] += b[2][name][i] - a[2][name][i]
    print(
        f"load average {os.getloadavg()[0]:.2f}; {ticks:.0f} ticks counted in {wall:.2f} s "
        f"({ticks / wall if wall else 0:.0f} ticks/s); CPU µs per tick:"
    )
    print(f"  {'role':<8}{'total':>8}{'user':>8}{'system':>8}   context switches/tick: voluntary, involuntary")
    sums = [0.0, 0.0, 0.0, 0.0]
    for name in sorted(cpu_tot):
        user, system = (1e6 * v / ticks if ticks else 0.0 for v in cpu_tot[name][:2])
        vol, invol = (v / ticks if ticks else 0.0 for v in cpu_tot[name][2:])
        for i, v in enumerate((user, system, vol, invol)):
            sums[i] += v
        print(f"  {name:<8}{user + system:8.0f}{user:8.0f}{system:8.0f}{vol:10.2f}{invol:8.2f}")
    print(f"  {'sum':<8}{sums[0] + sums[1]:8.0f}{sums[0]:8.0f}{sums[1]:8.0f}{sums[2]:10.2f}{sums[3]:8.2f}")
    last = [ln for ln in tail.splitlines() if "ticks" in ln]
    if last:
        print(last[-1])


if __name__ == "__main__":
    main()
