"""Benchmark: peak memory and wall time of ``ilcrig sim`` against the trial length N, per law.

For each law and N (a cycle of (N − 1)/2 ms at Ts = 1 ms) and number of trials, runs
``python -m host.cli sim --law L --cycle C --iterations K --out DIR`` in a child process with the
preflight's memory check out of the way (``ILCRIG_AVAILABLE_MEMORY=1T``) and prints the child's
peak resident memory (``ru_maxrss`` of ``wait4``: that child alone), its peak virtual size
(``VmPeak``, sampled from /proc while it runs: what an address-space limit must allow) and its
wall time, next to the preflight's estimate (:func:`host.experiment.plan.run_memory_bytes`).
Then, per law, the least-squares line peak RSS = a + b·N over the runs with the smallest number
of trials, and the growth per trial and sample over the runs with more trials.

    python benchmarks/run_memory.py [--laws no-ilc-id,pd-ilc] [--sizes 1001,20001] [--iterations 2,20]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from host.experiment.plan import MEMORY_ENV, run_memory_bytes

LAWS = ("no-ilc-id", "no-ilc", "pd-ilc", "q-ilc", "pd-ilc-q")
SIZES = (1001, 5001, 10001, 20001, 40001)
MB = 1e6


def _vm_peak_kb(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmPeak:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def _tree_rss_kb(root: int) -> int:
    """The resident memory of ``root`` and all its descendants, kB."""
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    parent[int(entry)] = int(fh.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    tree, frontier = {root}, [root]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parent.items() if pp == p and c not in tree]
        tree.update(kids)
        frontier.extend(kids)
    total = 0
    for pid in tree:
        try:
            with open(f"/proc/{pid}/status") as fh:
                total += next((int(x.split()[1]) for x in fh if x.startswith("VmRSS:")), 0)
        except OSError:
            continue
    return total


def measure(law: str, n: int, iterations: int, out: Path, command: str = "sim") -> tuple[float, float, float, int]:
    """(peak RSS MB, peak virtual MB, wall s, exit code) of one ``ilcrig sim``; of ``ilcrig run``
    the peak of the summed resident memory of all its processes (sampled) and the launcher's
    peak virtual size."""
    cycle = (n - 1) // 2 * 0.001
    argv = [sys.executable, "-m", "host.cli", command, "--law", law, "--cycle", f"{cycle:g}", "--iterations", str(iterations)]
    env = dict(os.environ, **{MEMORY_ENV: "1T"})
    t0 = time.monotonic()
    proc = subprocess.Popen([*argv, "--out", str(out)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    vm_kb = tree_kb = 0
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        vm_kb = max(vm_kb, _vm_peak_kb(proc.pid))
        if command == "run":
            tree_kb = max(tree_kb, _tree_rss_kb(proc.pid))
        time.sleep(0.05)
    wall = time.monotonic() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    rss_mb = tree_kb * 1024 / MB if command == "run" else usage.ru_maxrss * 1024 / MB
    return rss_mb, vm_kb * 1024 / MB, wall, proc.returncode


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--laws", default=",".join(LAWS))
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--iterations", default="2", help="numbers of trials (comma-separated)")
    ap.add_argument("--command", choices=("sim", "run"), default="sim", help="ilcrig sim or the rig, ilcrig run")
    args = ap.parse_args(argv)
    laws = args.laws.split(",")
    sizes = [int(x) for x in args.sizes.split(",")]
    iters = [int(x) for x in args.iterations.split(",")]
    rows: list[tuple[str, int, int, float, float, float, float]] = []
    print(f"{'law':<10} {'N':>6} {'trials':>6} {'peak RSS MB':>11} {'VmPeak MB':>9} {'wall s':>7} {'estimate MB':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        for law in laws:
            for n in sizes:
                for k in iters:
                    rss, vm, wall, code = measure(law, n, k, Path(tmp) / f"{law}-{n}-{k}", args.command)
                    est = run_memory_bytes(n, k, law, rig=args.command == "run") / MB
                    flag = "" if code == 0 else f"  exit {code}"
                    print(f"{law:<10} {n:>6} {k:>6} {rss:>11.0f} {vm:>9.0f} {wall:>7.1f} {est:>11.0f}{flag}", flush=True)
                    rows.append((law, n, k, rss, vm, wall, est))
    print()
    k0 = min(iters)
    for law in laws:
        pts = [(n, rss) for (lw, n, k, rss, *_) in rows if lw == law and k == k0]
        if len(pts) >= 2:
            x, y = np.array(pts, dtype=float).T
            b, a = np.polyfit(x, y, 1)
            print(f"{law:<10} {k0} trials: peak RSS ≈ {a:.0f} MB + {b * MB / 1e3:.2f} kB × N")
        # the growth with the trials: Δpeak = c + d·N·ΔK over all N (the runs with the fewest trials as base)
        deltas = [
            (n * (k - k0), rss - r0)
            for (lw, n, k, rss, *_) in rows
            if lw == law and k != k0
            for (lw0, n0, kk0, r0, *_) in rows
            if lw0 == law and n0 == n and kk0 == k0
        ]
        if len(deltas) >= 2:
            x, y = np.array(deltas, dtype=float).T
            d, _ = np.polyfit(x, y, 1)
            print(f"{law:<10} {d * MB:.0f} bytes more per trial and sample (fitted over N)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
