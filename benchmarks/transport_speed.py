"""Transport benchmark: round-trip floor and lockstep tick rate per python-can transport.

Per transport (hub over a Unix socket, hub over loopback TCP, udp_multicast inside a private
network namespace, python-can ``virtual`` between threads as a reference):

* ping-pong: 2 processes (threads for ``virtual``), one frame each way; median and p99
  round trip in µs;
* lockstep: 1 "plant" process and 4 "drive" processes (threads for ``virtual``); per tick
  the plant sends a tick frame and waits for the 4 answers; ticks/s over ``--seconds``.
  Mode ``broadcast``: one 2-byte tick frame per tick (1 + 4 frames). Mode ``io``: the real
  io channel, 4 encoder frames + 4 torque frames (bus.io_frames codecs, TickTracker checks).

Usage::

    python benchmarks/transport_speed.py [--seconds 3] [--pings 2000]
        [--only hub-unix hub-tcp udp_multicast virtual] [--modes broadcast io]

udp_multicast re-runs this script under ``unshare -rn`` (loopback up, multicast route);
it is skipped with a note when that is unavailable.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import os
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from bus.io_frames import (
    N_JOINTS,
    TickTracker,
    TorqueStatus,
    decode_encoder,
    decode_torque,
    encode_encoder,
    encode_torque,
    encoder_cob_id,
    torque_cob_id,
)
from bus.transports.config import ChannelConfig, open_bus, udp_multicast_transport
from bus.transports.hub.process import start_hub

CTX = mp.get_context("fork")
PING_ID, PONG_ID = 0x100, 0x101
TICK_ID, STOP_ID = 0x010, 0x011
ANSWER_BASE = 0x181
_U16 = struct.Struct("<H")
NETNS_SETUP = "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo"

Opener = Callable[[list[dict[str, Any]] | None], can.BusABC]


def _filters(*ids: int) -> list[dict[str, Any]]:
    return [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids]


# -- ping-pong ------------------------------------------------------------------------------


def _pong(opener: Opener, ready: Any, n: int) -> None:
    bus = opener(_filters(PING_ID))
    try:
        ready.wait(20)
        answer = can.Message(arbitration_id=PONG_ID, is_extended_id=False, data=b"\x00" * 8)
        done = 0
        while done < n:
            m = bus.recv(10.0)
            if m is None:
                return
            if m.arbitration_id == PING_ID:
                bus.send(answer)
                done += 1
    finally:
        bus.shutdown()


def ping_pong(opener: Opener, n: int, threads: bool) -> dict[str, float]:
    warm = 200
    ready = threading.Barrier(2) if threads else CTX.Barrier(2)
    worker = (threading.Thread if threads else CTX.Process)(target=_pong, args=(opener, ready, n + warm))
    worker.start()
    bus = opener(_filters(PONG_ID))
    rtts: list[int] = []
    try:
        ready.wait(20)
        ping = can.Message(arbitration_id=PING_ID, is_extended_id=False, data=b"\x01" * 8)
        for i in range(n + warm):
            t0 = time.perf_counter_ns()
            bus.send(ping)
            while True:
                m = bus.recv(5.0)
                if m is None:
                    raise RuntimeError("ping-pong: no answer")
                if m.arbitration_id == PONG_ID:
                    break
            if i >= warm:
                rtts.append(time.perf_counter_ns() - t0)
    finally:
        bus.shutdown()
        _join(worker)
    rtts.sort()
    return {"median_us": statistics.median(rtts) / 1e3, "p99_us": rtts[int(0.99 * (len(rtts) - 1))] / 1e3}


# -- lockstep -------------------------------------------------------------------------------


def _drive(opener: Opener, joint: int, mode: str, ready: Any) -> None:
    listen = TICK_ID if mode == "broadcast" else encoder_cob_id(joint)
    bus = opener(_filters(listen, STOP_ID))
    try:
        ready.wait(20)
        if mode == "broadcast":
            answer_id = ANSWER_BASE + joint
            while True:
                m = bus.recv(10.0)
                if m is None or m.arbitration_id == STOP_ID:
                    return
                if m.arbitration_id == TICK_ID:
                    bus.send(can.Message(arbitration_id=answer_id, is_extended_id=False, data=m.data, check=False))
        else:
            tracker = TickTracker(0, f"encoder joint {joint}")
            while True:
                m = bus.recv(10.0)
                if m is None or m.arbitration_id == STOP_ID:
                    return
                if m.arbitration_id == listen:
                    enc = decode_encoder(m)
                    tick = tracker.accept(enc.tick)
                    bus.send(encode_torque(joint, tick, -enc.count, TorqueStatus.ENABLED))
    finally:
        bus.shutdown()


def lockstep(opener: Opener, seconds: float, mode: str, threads: bool) -> dict[str, float]:
    ready = threading.Barrier(N_JOINTS + 1) if threads else CTX.Barrier(N_JOINTS + 1)
    make = threading.Thread if threads else CTX.Process
    workers = [make(target=_drive, args=(opener, j, mode, ready)) for j in range(N_JOINTS)]
    for w in workers:
        w.start()
    answer_ids = (
        [ANSWER_BASE + j for j in range(N_JOINTS)] if mode == "broadcast" else [torque_cob_id(j) for j in range(N_JOINTS)]
    )
    bus = opener(_filters(*answer_ids))
    trackers = [TickTracker(0, f"torque joint {j}") for j in range(N_JOINTS)]
    tick_ns: list[int] = []
    ticks = 0
    try:
        ready.wait(20)
        t_start = time.perf_counter()
        t_end = t_start + seconds
        while True:
            t0 = time.perf_counter_ns()
            if mode == "broadcast":
                bus.send(can.Message(arbitration_id=TICK_ID, is_extended_id=False, data=_U16.pack(ticks & 0xFFFF), check=False))
            else:
                for j in range(N_JOINTS):
                    bus.send(encode_encoder(j, ticks, 1000 * j + ticks))
            pending = N_JOINTS
            while pending:
                m = bus.recv(5.0)
                if m is None:
                    raise RuntimeError(f"lockstep: tick {ticks} timed out")
                j = m.arbitration_id - (ANSWER_BASE if mode == "broadcast" else torque_cob_id(0))
                if not 0 <= j < N_JOINTS:
                    continue  # e.g. own frames looped back (udp_multicast)
                if mode == "broadcast":
                    if _U16.unpack(m.data)[0] != ticks & 0xFFFF:
                        raise RuntimeError("lockstep: wrong tick in answer")
                else:
                    trackers[j].accept(decode_torque(m).tick)
                pending -= 1
            tick_ns.append(time.perf_counter_ns() - t0)
            ticks += 1
            if time.perf_counter() >= t_end:
                break
        elapsed = time.perf_counter() - t_start
        bus.send(can.Message(arbitration_id=STOP_ID, is_extended_id=False, data=b""))
    finally:
        bus.shutdown()
        for w in workers:
            _join(w)
    tick_ns.sort()
    return {
        "ticks_per_s": ticks / elapsed,
        "ticks": ticks,
        "tick_median_us": statistics.median(tick_ns) / 1e3,
        "tick_p99_us": tick_ns[int(0.99 * (len(tick_ns) - 1))] / 1e3,
    }


def _join(worker: Any) -> None:
    worker.join(10)
    if isinstance(worker, mp.process.BaseProcess) and worker.is_alive():
        worker.kill()
        worker.join()


# -- transports -----------------------------------------------------------------------------


def _opener(cfg: ChannelConfig) -> Opener:
    def open_(filters: list[dict[str, Any]] | None) -> can.BusABC:
        return open_bus(dataclasses.replace(cfg, kwargs={**cfg.kwargs, "can_filters": filters}))

    return open_


def run_transport(name: str, args: argparse.Namespace) -> dict[str, Any]:
    result: dict[str, Any] = {"transport": name}
    if name in ("hub-unix", "hub-tcp"):
        with start_hub(None if name == "hub-unix" else "tcp:127.0.0.1:0") as hub:
            opener = _opener(ChannelConfig("ilcrig_hub", hub.channel("bench")))
            result["ping"] = ping_pong(opener, args.pings, threads=False)
            for mode in args.modes:
                result[mode] = lockstep(opener, args.seconds, mode, threads=False)
    elif name == "udp_multicast":
        opener = _opener(udp_multicast_transport().io)
        result["ping"] = ping_pong(opener, args.pings, threads=False)
        for mode in args.modes:
            result[mode] = lockstep(opener, args.seconds, mode, threads=False)
    elif name == "virtual":
        opener = _opener(ChannelConfig("virtual", f"bench-{os.getpid()}"))
        result["ping"] = ping_pong(opener, args.pings, threads=True)
        for mode in args.modes:
            result[mode] = lockstep(opener, args.seconds, mode, threads=True)
    else:
        raise ValueError(f"unknown transport {name!r}")
    return result


def run_udp_in_netns(args: argparse.Namespace) -> dict[str, Any]:
    if not shutil.which("unshare"):
        return {"transport": "udp_multicast", "skipped": "unshare not installed"}
    cmd = [
        "unshare", "-rn", "sh", "-c", f'{NETNS_SETUP} && exec "$0" "$@"', sys.executable, os.path.abspath(__file__),
        "--json", "--only", "udp_multicast", "--seconds", str(args.seconds), "--pings", str(args.pings),
        "--modes", *args.modes,
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=60 + 3 * args.seconds)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return {"transport": "udp_multicast", "skipped": "timed out in the netns"}
    if proc.returncode != 0:
        return {"transport": "udp_multicast", "skipped": f"netns run failed: {err.strip()[-300:]}"}
    return json.loads(out.strip().splitlines()[-1])


def _print(res: dict[str, Any], modes: list[str]) -> None:
    name = res["transport"]
    if "skipped" in res:
        print(f"{name:<14} skipped: {res['skipped']}")
        return
    p = res["ping"]
    line = f"{name:<14} ping-pong RTT median {p['median_us']:7.1f} µs  p99 {p['p99_us']:7.1f} µs"
    for mode in modes:
        ls = res[mode]
        line += (
            f" | lockstep[{mode}] {ls['ticks_per_s']:7.0f} ticks/s"
            f" (tick median {ls['tick_median_us']:6.1f} µs, p99 {ls['tick_p99_us']:6.1f} µs)"
        )
    print(line, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="lockstep duration per run, s")
    parser.add_argument("--pings", type=int, default=2000, help="measured ping-pong round trips")
    parser.add_argument("--only", nargs="+", default=["hub-unix", "hub-tcp", "udp_multicast", "virtual"])
    parser.add_argument("--modes", nargs="+", default=["broadcast", "io"], choices=["broadcast", "io"])
    parser.add_argument("--json", action="store_true", help="print one JSON line per transport (internal)")
    args = parser.parse_args(argv)
    if not args.json:
        print(f"python-can {can.__version__}, {os.cpu_count()} CPUs, lockstep {args.seconds} s, {args.pings} pings")
    for name in args.only:
        if name == "udp_multicast" and not args.json:
            res = run_udp_in_netns(args)
        else:
            res = run_transport(name, args)
        if args.json:
            print(json.dumps(res), flush=True)
        else:
            _print(res, args.modes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
