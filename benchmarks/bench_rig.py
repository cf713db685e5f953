"""Benchmark: the distributed rig's lockstep speed per transport, next to a bare round-trip floor.

Per transport (the zero-privilege hub over a Unix socket; udp_multicast inside a private network
namespace; socketcan when vcan0/vcan1 exist):

* floor: a 2-process python-can ping-pong on the same transport (benchmarks/bench_transport.py),
  median round trip in µs, measured in this run;
* rig: ``ilcrig run`` (4 drive + plant + host processes, plus the hub) on a 1001-tick trial
  (cycle 0.5 s), 3 trials; ticks/s = ticks / wall time of the trials as the host measures them
  (trial start over SDO, lockstep ticks, completion poll), and the real-time factor at 1 kHz.

    python benchmarks/bench_rig.py [--iterations 3]

Target (issue 3): >= 1,000 ticks/s (1x real time at 1 kHz) on the default transport, 2 cores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(HERE))


def rig(bus: str, iterations: int, netns: bool = False) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "host.cli", "run", "--iterations", str(iterations), "--cycle", "0.5",
               "--bus", bus, "--out", str(out)]
        if netns:
            from netns_util import NETNS_SETUP

            cmd = ["unshare", "-rn", "sh", "-c", f"{NETNS_SETUP} && ILCRIG_PRIVATE_NETNS=1 exec " + " ".join(cmd)]
        t0 = time.perf_counter()
        res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
        total = time.perf_counter() - t0
        if res.returncode != 0:
            return {"error": (res.stderr or res.stdout).strip().splitlines()[-1:]}
        s = json.loads((out / "summary.json").read_text())
        fb = s["bench"]["channels"]["fieldbus"]
        return {"ticks": s["ticks"], "ticks_per_s": s["ticks_per_s"], "total_s": total,
                "fieldbus_frames": fb["frames"], "fieldbus_load_pct": fb["load_percent_worst_case"]}


def floor(name: str) -> dict:
    import bench_transport as bt

    ns = argparse.Namespace(seconds=1.0, pings=1000, only=[name], modes=["io"])
    try:
        res = bt.run_udp_in_netns(ns) if name == "udp_multicast" else bt.run_transport(name, ns)
    except Exception as exc:  # report, do not hide
        return {"error": str(exc)}
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=3)
    args = ap.parse_args()
    from netns_util import netns_unavailable_reason

    from bus.transports.config import vcan_available

    plan = [("hub", "hub-unix", False)]
    if netns_unavailable_reason() is None:
        plan.append(("udp_multicast", "udp_multicast", True))
    if vcan_available():
        plan.append(("socketcan", None, False))
    print("ilcrig rig benchmark: 4 drive + plant + host processes, 1001-tick trials, "
          f"{args.iterations} trials per transport")
    print(f"{'transport':<15}{'RTT floor median':>18}{'lockstep io (bare)':>20}{'rig ticks/s':>13}{'x real time':>13}"
          f"{'run wall s':>12}{'fieldbus %':>12}")
    for bus, floor_name, netns in plan:
        f = floor(floor_name) if floor_name else {}
        r = rig(bus, args.iterations, netns)
        rtt = (f.get("ping") or {}).get("median_us")
        bare = (f.get("io") or {}).get("ticks_per_s")
        if "error" in r:
            print(f"{bus:<15} rig failed: {r['error']}")
            continue
        print(f"{bus:<15}{(f'{rtt:.0f} us' if rtt else 'n/a'):>18}{(f'{bare:,.0f}' if bare else 'n/a'):>20}"
              f"{r['ticks_per_s']:>13,.0f}{r['ticks_per_s'] / 1000:>13.2f}{r['total_s']:>12.1f}"
              f"{r['fieldbus_load_pct']:>12.1f}")
        if f and (rtt is None or bare is None):
            print(f"   floor raw: {json.dumps(f)[:300]}")


if __name__ == "__main__":
    main()
