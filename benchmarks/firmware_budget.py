"""Benchmark: the drive firmware's budget on an emulated Cortex-M4 (processor in the loop), and the
rig's speed with each firmware.

1. **Instructions per control period** of ``ilc_control_tick`` on QEMU's ``mps2-an386``
   (Cortex-M4F, image built with -O2 by firmware_model/pil_build.py), measured by SysTick under
   ``-icount shift=0`` (1 ns of virtual time per instruction; SysTick at 25 MHz: a resolution of
   40 instructions).  **An instruction count, not silicon cycles**: QEMU models no pipeline, wait
   states or caches.  Per loop structure:

   * ``pd``: the PD loop of the ILC experiments -- the periods of the drives of the rig run below
     (``ilcrig run --firmware pil``, the default experiment), from the drives' logs;
   * ``cascade (robot session)``: the four drives of a robot session -- examples/robot_master.py's
     CSP pick-and-place against the SYNC-stepped robot in this process (tests/robot_util.py), the
     drives booted as robot mode does, with the servo drive's cascade (0x2110:4 = 1) --, whose
     result and period trace are checked equal to the Python firmware's;
   * ``pd (replay)`` / ``cascade (replay)``: one drive's kernel replaying a 1,001-period move
     (a smooth 100,000-count reference with its velocity and a feed-forward, the encoder 0..±64
     counts off it) with the EDS parameters: the PD loop of the ILC experiments, and the servo
     drive's cascade that robot mode boots with (0x2110:4 = 1).

   Beside each: the share of a 1 ms control period at a drive MCU clock (``--clock-mhz``, default
   168 MHz, an STM32F4) **as an instruction-count estimate** (one instruction per cycle).

2. **The rig's speed** with ``--firmware python``, ``c`` (where the extension is built) and
   ``pil``: ``ilcrig run --iterations N --cycle 0.5`` (1001-tick trials) on the hub, lockstep
   ticks/s as the plant measures them in the trials, the host's figure, the digest (the same for
   every firmware); and the floor of the same machine minutes: the bare 5-process io lockstep on
   the hub (benchmarks/transport_speed.py).

    python benchmarks/firmware_budget.py [--iterations 2] [--clock-mhz 168] [--skip-rig] [--skip-robot]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from firmware_model import control_law as cl  # noqa: E402

_LOG_LINE = re.compile(r"PIL target: (.*)$")
_LOOP_FIGURES = re.compile(r"(\w+): (\d+) periods, mean (\d+), max (\d+) instructions")


def replay(loop: int, n: int = 1001) -> tuple[float, float, int]:
    """(mean, max instructions, periods) of one drive's PIL kernel replaying a move with the EDS
    parameters and loop structure ``loop``."""
    from firmware_model.drive import Drive
    from firmware_model.pil import pil_control_tick

    drive = Drive(1)  # the Python model: its parameter objects give st[] the EDS values
    st = drive._st.copy()  # noqa: SLF001 - the benchmark reads the drive's parameter vector
    st[cl.P_LOOP] = loop
    t = np.linspace(0.0, 1.0, n)
    s = 10 * t**3 - 15 * t**4 + 6 * t**5  # quintic 0 -> 1
    ds = (30 * t**2 - 60 * t**3 + 30 * t**4) / 1.0
    tables = cl.new_tables(n)
    tables[0, :n] = np.round(100_000 * s).astype(np.int32)
    tables[1, :n] = np.round(100_000 * ds).astype(np.int32)
    tables[2, :n] = np.round(200_000 * np.sin(2 * np.pi * t)).astype(np.int32)
    rec = cl.new_recorder(n)
    rng = np.random.default_rng(1)
    counts = tables[0, :n].astype(np.int64) + rng.integers(-64, 65, n)
    kernel = pil_control_tick(1)
    try:
        for k in range(n):
            kernel(int(counts[k]), k, k, st, tables, rec)
        stats = next(iter(kernel.stats.values()))
        return stats.mean, stats.largest, stats.periods
    finally:
        kernel.close()


def robot_session() -> tuple[dict[str, tuple[int, float, float]], bool]:
    """The robot session with the Python firmware, then with PIL: per loop structure (periods, mean,
    max instructions) over the four drives, and whether result and period trace were equal."""
    import functools
    import logging

    import robot_util

    import firmware_model.pil as pil
    from firmware_model.drive import Drive

    logging.getLogger("canopen").setLevel(logging.ERROR)  # the example master's notes on SDO fallbacks

    outcome = {}
    figures: dict[str, tuple[int, float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for fw in ("python", "pil"):
            robot_util.Drive = functools.partial(Drive, firmware=fw)  # type: ignore[attr-defined]
            outcome[fw] = robot_util.run_example_in_process(Path(tmp) / fw)
            if fw == "pil":
                for kernel in list(pil._KERNELS):  # noqa: SLF001 - the four drives' kernels
                    for name, st in kernel.stats.items():
                        periods, total, largest = figures.get(name, (0, 0.0, 0.0))
                        figures[name] = (periods + st.periods, total + st.total, max(largest, st.largest))
                    kernel.close()
                pil._KERNELS.clear()  # noqa: SLF001
    return {k: (p, t / p, m) for k, (p, t, m) in figures.items()}, outcome["python"] == outcome["pil"]


def rig(firmware: str, iterations: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "host.cli", "run", "--iterations", str(iterations), "--cycle", "0.5"]
        cmd += ["--bus", "hub", "--firmware", firmware, "--out", str(out)]
        t0 = time.perf_counter()
        res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=1800)
        total = time.perf_counter() - t0
        if res.returncode != 0:
            return {"error": (res.stderr or res.stdout).strip().splitlines()[-1:]}
        s = json.loads((out / "summary.json").read_text())
        loops: dict[str, list[tuple[int, int, int]]] = {}
        for log in sorted((out / "logs").glob("drive*.log")):
            for line in log.read_text().splitlines():
                m = _LOG_LINE.search(line)
                if m:
                    for name, periods, mean, largest in _LOOP_FIGURES.findall(m.group(1)):
                        loops.setdefault(name, []).append((int(periods), int(mean), int(largest)))
        return {
            "ticks": s["ticks"],
            "host_ticks_per_s": s["ticks_per_s"],
            "lockstep_ticks_per_s": s["bench"].get("timing", {}).get("achieved_ticks_per_s", 0.0),
            "digest": s["trace_sha256"],
            "total_s": total,
            "loops": loops,
        }


def floor() -> float | None:
    import transport_speed as bt

    ns = argparse.Namespace(seconds=1.0, pings=200, only=["hub-unix"], modes=["io"])
    try:
        res = bt.run_transport("hub-unix", ns)
    except Exception as exc:  # report, do not hide
        print(f"floor failed: {exc}")
        return None
    return (res.get("io") or {}).get("ticks_per_s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=2, help="trials per rig run")
    ap.add_argument("--clock-mhz", type=float, default=168.0, help="drive MCU clock for the share of 1 ms")
    ap.add_argument("--skip-rig", action="store_true", help="no rig runs (the replay and the robot session only)")
    ap.add_argument("--skip-robot", action="store_true", help="no robot session")
    args = ap.parse_args()
    from firmware_model.firmware_select import c_available
    from firmware_model.pil_build import require_tools

    require_tools()
    per_ms = args.clock_mhz * 1e3  # instructions in 1 ms at one instruction per cycle
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    print(
        f"firmware budget on QEMU mps2-an386 (Cortex-M4F, -O2, -icount shift=0: instruction counts at a "
        f"40-instruction resolution, not cycles); commit {commit}; {os.cpu_count()} CPUs; "
        f"load avg {os.getloadavg()[0]:.1f}"
    )
    print(f"{'loop':<20}{'periods':>9}{'mean instr':>12}{'max instr':>11}{f'share of 1 ms @ {args.clock_mhz:g} MHz':>30}")

    def row(name: str, periods: int, mean: float, largest: float) -> None:
        share = f"{100 * mean / per_ms:.3f} % (max {100 * largest / per_ms:.3f} %)"
        print(f"{name:<20}{periods:>9}{mean:>12.0f}{largest:>11.0f}{share:>30}")

    for loop, name in ((cl.LOOP_PD, "pd (replay)"), (cl.LOOP_CASCADE, "cascade (replay)")):
        mean, largest, periods = replay(loop)
        row(name, periods, mean, largest)
    if not args.skip_robot:
        loops, same = robot_session()
        for name, (periods, mean, largest) in sorted(loops.items()):
            row(f"{name} (robot session)", periods, mean, largest)
        print(f"{'':<20}robot session with pil: result and period trace equal to python's: {same}")
    if args.skip_rig:
        return
    firmwares = ["python", *(["c"] if c_available() else []), "pil"]
    runs = {fw: rig(fw, args.iterations) for fw in firmwares}
    pil = runs.get("pil", {})
    for name, figures in sorted(pil.get("loops", {}).items()):
        periods = sum(p for p, _, _ in figures)
        mean = sum(p * m for p, m, _ in figures) / periods
        row(f"{name} (rig, 4 drives)", periods, mean, max(x for _, _, x in figures))
    bare = floor()
    print(
        f"\nrig: ilcrig run --iterations {args.iterations} --cycle 0.5 (1001-tick trials) on the hub; "
        f"floor (bare 5-process io lockstep on the hub): {f'{bare:,.0f}' if bare else 'n/a'} ticks/s"
    )
    print(f"{'firmware':<10}{'lockstep ticks/s':>18}{'host ticks/s':>14}{'x real time':>13}{'/ floor':>9}{'wall s':>9}  digest")
    for fw, r in runs.items():
        if "error" in r:
            print(f"{fw:<10} failed: {r['error']}")
            continue
        lock = r["lockstep_ticks_per_s"]
        ratio = f"{lock / bare:.3f}" if bare else "n/a"
        print(
            f"{fw:<10}{lock:>18,.0f}{r['host_ticks_per_s']:>14,.0f}{lock / 1000:>13.3f}{ratio:>9}"
            f"{r['total_s']:>9.0f}  {r['digest'][:16]}"
        )
    digests = {r["digest"] for r in runs.values() if "digest" in r}
    print(f"digests equal: {len(digests) == 1}; load avg now {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
