"""udp_multicast loss benchmark: datagrams lost under SDO block uploads on a busy machine.

Inside a private network namespace (the script re-runs itself under ``unshare -rn``), per bus
configuration:

* a "host" process asks a "drive" process for ``--blocks`` SDO-style block uploads: one request
  frame, the drive answers with a block of 127 segments back to back, the host acknowledges after
  the last segment (or after 0.5 s when segments were lost: a stalled block);
* ``--listeners`` more processes (the other drives, the plant, the monitors) read every datagram
  too, as every member of a udp_multicast group does;
* every receiver spends ``--work-us`` µs per frame (a node's handling of a frame) and ``--busy``
  processes spin on the CPUs meanwhile (the machine busy).

Every process counts the datagrams its socket delivered (its own looped back included) and the
kernel's drop count of its socket (``SO_MEMINFO``); lost = sent − received.  The configurations:
``python-can`` (python-can's UdpMulticastBus as it opens it: the receive buffer is
``net.core.rmem_default``) and ``ilcrig`` (:class:`bus.transports.udp_multicast.CheckedUdpMulticastBus`,
the bus ``ilcrig run --bus udp_multicast`` opens; its losses reported as bus error frames).

Usage::

    python benchmarks/udp_multicast_loss.py [--blocks 200] [--listeners 5] [--busy 3] [--work-us 30]
        [--only python-can ilcrig] [--rcvbuf BYTES]

Prints one line per configuration and a JSON line with every count.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import socket
import struct
import subprocess
import sys
import time
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus

from bus.transports.udp_multicast import SO_MEMINFO, UDP_RCVBUF_BYTES, CheckedUdpMulticastBus

CTX = mp.get_context("fork")
NETNS_SETUP = "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo"
GROUP, PORT = "239.74.163.77", 43177
REQUEST_ID, SEGMENT_ID, STOP_ID = 0x604, 0x584, 0x7FF
BLOCK = 127
IDLE_END_S = 3.0
STALL_S = 0.5


def _open(kind: str, rcvbuf: int) -> can.BusABC:
    if kind == "python-can":
        return UdpMulticastBus(GROUP, port=PORT, hop_limit=1)
    return CheckedUdpMulticastBus(GROUP, port=PORT, hop_limit=1, receive_buffer_bytes=rcvbuf)


def _socket_of(bus: can.BusABC) -> socket.socket:
    return bus._multicast._socket  # type: ignore[attr-defined, no-any-return]


def _kernel_drops(bus: can.BusABC) -> int:
    raw = _socket_of(bus).getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 36)
    return int(struct.unpack_from("=9I", raw)[8])


def _work(us: float) -> None:
    end = time.perf_counter() + us * 1e-6
    while time.perf_counter() < end:
        pass


class _Counter:
    """Counts what one process's socket delivered."""

    def __init__(self, bus: can.BusABC, work_us: float) -> None:
        self.bus = bus
        self.work_us = work_us
        self.datagrams = 0
        self.error_frames = 0
        self.stopped = False

    def recv(self, timeout: float) -> can.Message | None:
        while True:
            msg = self.bus.recv(timeout)
            if msg is None:
                return None
            if msg.is_error_frame:
                self.error_frames += 1
                continue
            self.datagrams += 1
            self.stopped = self.stopped or msg.arbitration_id == STOP_ID
            _work(self.work_us)
            return msg

    def report(self, name: str, sent: int) -> dict[str, Any]:
        return {
            "name": name,
            "sent": sent,
            "received": self.datagrams,
            "kernel_drops": _kernel_drops(self.bus),
            "error_frames": self.error_frames,
            "frames_lost": getattr(self.bus, "frames_lost", None),
            "rcvbuf": _socket_of(self.bus).getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF),
        }

    def drain(self) -> None:
        """Read until the stop frame came and nothing more arrives."""
        idle_since = time.monotonic()
        while time.monotonic() - idle_since < (0.3 if self.stopped else IDLE_END_S):
            if self.recv(0.1) is not None:
                idle_since = time.monotonic()


def _listener(kind: str, rcvbuf: int, work_us: float, ready: Any, out: Any, name: str) -> None:
    c = _Counter(_open(kind, rcvbuf), work_us)
    ready.release()
    c.drain()
    out.put(c.report(name, 0))
    c.bus.shutdown()


def _drive(kind: str, rcvbuf: int, work_us: float, ready: Any, out: Any) -> None:
    c = _Counter(_open(kind, rcvbuf), work_us)
    ready.release()
    sent = 0
    idle_since = time.monotonic()
    while not c.stopped and time.monotonic() - idle_since < IDLE_END_S:
        msg = c.recv(0.1)
        if msg is None or msg.arbitration_id != REQUEST_ID or msg.data[0] != ord("R"):
            continue
        idle_since = time.monotonic()
        for seq in range(1, BLOCK + 1):
            c.bus.send(can.Message(arbitration_id=SEGMENT_ID, is_extended_id=False, data=bytes([seq]) + bytes(7)))
            sent += 1
    c.drain()
    out.put(c.report("drive", sent))
    c.bus.shutdown()


def _host(kind: str, rcvbuf: int, work_us: float, blocks: int, out: Any) -> None:
    c = _Counter(_open(kind, rcvbuf), work_us)
    sent = 0
    stalled = 0
    for _ in range(blocks):
        c.bus.send(can.Message(arbitration_id=REQUEST_ID, is_extended_id=False, data=b"R" + bytes(7)))
        sent += 1
        deadline = time.monotonic() + STALL_S
        while True:
            msg = c.recv(max(0.0, deadline - time.monotonic()))
            if msg is None:
                stalled += 1  # the last segment (or the request) was lost
                break
            if msg.arbitration_id == SEGMENT_ID and msg.data[0] == BLOCK:
                break
        c.bus.send(can.Message(arbitration_id=REQUEST_ID, is_extended_id=False, data=b"A" + bytes(7)))
        sent += 1
    c.bus.send(can.Message(arbitration_id=STOP_ID, is_extended_id=False, data=b""))
    sent += 1
    c.drain()
    report = c.report("host", sent)
    report["stalled_blocks"] = stalled
    out.put(report)
    c.bus.shutdown()


def _spin() -> None:
    while True:
        pass


def measure(kind: str, blocks: int, listeners: int, busy: int, work_us: float, rcvbuf: int) -> dict[str, Any]:
    """One configuration: the per-process counts, the totals and the wall time."""
    out = CTX.Queue()
    ready = CTX.Semaphore(0)
    spinners = [CTX.Process(target=_spin, daemon=True) for _ in range(busy)]
    for p in spinners:
        p.start()
    procs = [CTX.Process(target=_listener, args=(kind, rcvbuf, work_us, ready, out, f"listener{i}")) for i in range(listeners)]
    procs.append(CTX.Process(target=_drive, args=(kind, rcvbuf, work_us, ready, out)))
    t0 = time.monotonic()
    try:
        for p in procs:
            p.start()
        for _ in procs:
            ready.acquire(timeout=30)
        host = CTX.Process(target=_host, args=(kind, rcvbuf, work_us, blocks, out))
        host.start()
        procs.append(host)
        reports = [out.get(timeout=600) for _ in procs]
    finally:
        for p in [*procs, *spinners]:
            if p.is_alive() and p in spinners:
                p.kill()
            p.join(30)
            if p.is_alive():
                p.kill()
                p.join()
    total_sent = sum(r["sent"] for r in reports)
    for r in reports:
        r["lost"] = total_sent - r["received"]
    return {
        "kind": kind,
        "wall_s": round(time.monotonic() - t0, 2),
        "datagrams_sent": total_sent,
        "receivers": len(reports),
        "lost": sum(r["lost"] for r in reports),
        "kernel_drops": sum(r["kernel_drops"] for r in reports),
        "error_frames": sum(r["error_frames"] for r in reports),
        "stalled_blocks": next(r["stalled_blocks"] for r in reports if r["name"] == "host"),
        "processes": sorted(reports, key=lambda r: r["name"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--blocks", type=int, default=200, help="block uploads of 127 segments")
    parser.add_argument("--listeners", type=int, default=5, help="further receivers of every datagram")
    parser.add_argument("--busy", type=int, default=3, help="processes spinning on the CPUs meanwhile")
    parser.add_argument("--work-us", type=float, default=30.0, help="work per received frame, µs")
    parser.add_argument("--rcvbuf", type=int, default=UDP_RCVBUF_BYTES, help="receive buffer of the ilcrig bus, bytes")
    parser.add_argument("--only", nargs="+", default=["python-can", "ilcrig"], choices=["python-can", "ilcrig"])
    parser.add_argument("--in-netns", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if not args.in_netns:
        if shutil.which("unshare") is None:
            sys.exit("udp_multicast_loss: needs unshare(1) for a private network namespace")
        cmd = ["unshare", "-rn", "sh", "-c", f'{NETNS_SETUP} && exec "$0" "$@"', sys.executable, *sys.argv, "--in-netns"]
        sys.exit(subprocess.call(cmd, env=dict(os.environ)))
    results = []
    for kind in args.only:
        res = measure(kind, args.blocks, args.listeners, args.busy, args.work_us, args.rcvbuf)
        results.append(res)
        per = res["datagrams_sent"] * res["receivers"]
        print(
            f"{kind:10s} rcvbuf {res['processes'][0]['rcvbuf']:>8d} B: {res['lost']:5d} of {per} datagrams lost "
            f"({res['kernel_drops']} kernel drops, {res['error_frames']} bus error frames reported, "
            f"{res['stalled_blocks']} of {args.blocks} blocks stalled) in {res['wall_s']} s",
            flush=True,
        )
    print(json.dumps({"config": vars(args), "results": results}))


if __name__ == "__main__":
    main()
