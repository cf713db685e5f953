"""Benchmark: the lockstep tick rate of the plant node over the hub with real processes, next
to a bare lockstep floor on the same transport.

Speed is measured and printed here, never asserted in the test suite.  Set-up: one hub (Unix socket), four drive processes
(``ilcrig drive --node N --bus hub``), the plant process (``ilcrig plant --bus hub``), the host in
this process (canopen over the hub).  The drives are enabled but not armed (their PD holds the
start pose); per trial of ``--ticks`` ticks:

* node ticks/s: ticks / the trial time the plant node measured itself (0x2430 last_trial_us);
* host ticks/s: ticks / wall time from the start request to the observed completion (SDO start,
  the lockstep ticks, completion polled every ``--poll`` s, so it includes up to one poll);

floor, measured in this run on the same transport (benchmarks/transport_speed.py): lockstep[io]
(one plant process, four drive processes exchanging the real io frames, no firmware and no
plant model) and the 2-process ping-pong round trip.  ``node/floor`` is the share of the bare
transport's tick rate the rig keeps; ``x real time`` is node ticks/s at 1 kHz.

    python benchmarks/plant_node_speed.py [--ticks 3000] [--trials 2] [--floor-seconds 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO / "tests"))

from short_move import TS_S, configure_drives, short_reference  # noqa: E402

PLANT_ID = 32


def floor(seconds: float, pings: int) -> dict[str, Any]:
    """transport_speed on the hub over a Unix socket: ping-pong RTT and lockstep[io]."""
    ns = argparse.Namespace(seconds=seconds, pings=pings, modes=["io"])
    try:
        import transport_speed as bt

        return bt.run_transport("hub-unix", ns)
    except Exception as exc:  # report, do not hide
        return {"error": f"{type(exc).__name__}: {exc}"}


def wait_until(predicate: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def rig(ticks: int, trials: int, poll_s: float) -> list[dict[str, float]]:
    """Hub + 4 drive processes + the plant process; returns per-trial rates."""
    import canopen

    from bus.plant_objects import PLANT_EDS_PATH
    from bus.transports.hub.process import start_hub
    from host.nodes.drive_client import DriveClient
    from host.nodes.plant_client import PlantClient
    from host.nodes.sdo_access import SdoAccess
    from host.rig.role_commands import child_argv

    drive_eds = REPO / "bus" / "drive.eds"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: list[subprocess.Popen[bytes]] = []
    out: list[dict[str, float]] = []
    with start_hub() as hub:
        addr = hub.address
        try:
            # the roles as ilcrig run starts them (the one home of a role's command line)
            bus_args = ["--bus", "hub", "--hub", addr]
            for node_id in (1, 2, 3, 4):
                procs.append(subprocess.Popen(child_argv("drive", bus_args, node=node_id), env=env, cwd=REPO))
            procs.append(subprocess.Popen(child_argv("plant", bus_args), env=env, cwd=REPO))
            network = canopen.Network()
            network.connect(interface="ilcrig_hub", channel=f"{addr}#fieldbus")
            try:
                booted: set[int] = set()
                for node_id in (1, 2, 3, 4, PLANT_ID):
                    network.subscribe(0x700 + node_id, lambda cob, _data, _t: booted.add(cob - 0x700))
                wait_until(lambda: len(booted) == 5, 120.0, "the boot-up of 4 drives and the plant")
                network.nmt.send_command(0x01)
                nodes = {
                    i: canopen.RemoteNode(i, str(drive_eds if i != PLANT_ID else PLANT_EDS_PATH)) for i in (1, 2, 3, 4, PLANT_ID)
                }
                for node in nodes.values():
                    network.add_node(node)
                drives = [DriveClient(SdoAccess(nodes[i]), i) for i in (1, 2, 3, 4)]
                bench = PlantClient(SdoAccess(nodes[PLANT_ID]))
                q, qd, _, _ = short_reference(60)
                configure_drives(drives, q, qd)  # enabled, not armed: PD holds the start pose
                bench.configure(TS_S, 4, "none", 0)
                for trial in range(trials):
                    t0 = time.perf_counter()
                    bench.start_trial(trial, ticks, q[0].copy(), qd[0].copy())
                    state = bench.wait_trial(600.0, poll_s=poll_s)
                    wall = time.perf_counter() - t0
                    if state.ticks_done != ticks:
                        raise RuntimeError(f"trial {trial}: {state.ticks_done} of {ticks} ticks")
                    node_s = bench.counters()["last_trial_us"] / 1e6
                    out.append(
                        {"node_ticks_per_s": ticks / node_s, "host_ticks_per_s": ticks / wall, "node_s": node_s, "host_s": wall}
                    )
            finally:
                network.disconnect()
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--ticks",
        type=int,
        default=int(os.environ.get("ILCRIG_PLANT_NODE_TICKS", "3000")),
        help="ticks per trial (default 3000, or $ILCRIG_PLANT_NODE_TICKS)",
    )
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--poll", type=float, default=0.05, help="host completion poll period, s")
    ap.add_argument("--floor-seconds", type=float, default=2.0, help="bare lockstep duration, s")
    ap.add_argument("--pings", type=int, default=1000)
    args = ap.parse_args()

    print(
        f"ilcrig bench-node benchmark: hub (unix socket), 4 drive processes + plant process, host here; "
        f"{args.ticks}-tick trials, {args.trials} trials, {os.cpu_count()} CPUs"
    )
    f = floor(args.floor_seconds, args.pings)
    rtt = (f.get("ping") or {}).get("median_us")
    bare = (f.get("io") or {}).get("ticks_per_s")
    if "error" in f:
        print(f"floor failed: {f['error']}")
    else:
        print(f"floor (this run): ping-pong RTT median {rtt:.0f} us, lockstep io (bare) {bare:,.0f} ticks/s")
    rates = rig(args.ticks, args.trials, args.poll)
    print(f"{'trial':<7}{'node ticks/s':>14}{'host ticks/s':>14}{'node/floor':>12}{'host/floor':>12}{'x real time':>13}")
    for k, r in enumerate(rates):
        nf = f"{r['node_ticks_per_s'] / bare:.2f}" if bare else "n/a"
        hf = f"{r['host_ticks_per_s'] / bare:.2f}" if bare else "n/a"
        print(
            f"{k:<7}{r['node_ticks_per_s']:>14,.0f}{r['host_ticks_per_s']:>14,.0f}{nf:>12}{hf:>12}"
            f"{r['node_ticks_per_s'] / 1000:>13.2f}"
        )
    if len(rates) > 1:
        med = statistics.median(r["node_ticks_per_s"] for r in rates)
        print(f"median node ticks/s {med:,.0f}" + (f" = {med / bare:.2f} x the bare lockstep floor" if bare else ""))


if __name__ == "__main__":
    main()
