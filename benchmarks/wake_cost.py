"""Benchmark: what sleeping between periods costs the code of one period — the drive's, in one process.

A robot period costs a drive process ~120 µs of CPU in the rig (``benchmarks/robot_speed.py``), but
the same Python code costs ~27 µs in a loop that never sleeps. This measures the difference without
sockets or other processes: one :class:`firmware_model.drive_node.DriveNode` (CSP, enabled,
OPERATIONAL, lockstep, RPDO1 = controlword + target, TPDO1 = statusword + position actual, both
synchronous) on two in-memory buses, and per period what the rig gives it — RPDO1 + SYNC on the
fieldbus, the encoder frame on io — and what it answers (torque frame, TPDO1). Timed is the
period's code alone (``time.perf_counter`` around it); before each period the process

* does nothing (the floor: the code hot in the CPU's caches, the CPU awake), or
* sleeps ``--sleeps`` µs, as a process of the rig does between its wake-ups,

each with and without a PM QoS CPU latency request of 0 µs (:mod:`host.rig.cpu_latency`: idle CPUs
poll instead of halting; root only, else that row is left out). Printed: the median µs per period and
its ratio to the floor of the same run.

    python benchmarks/wake_cost.py [--periods 3000] [--sleeps 0 100 500 2000]
"""

from __future__ import annotations

import argparse
import os
import statistics
import struct
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
sys.path.insert(0, str(HERE.parent))

import can  # noqa: E402
from robot_util import map_pdo  # noqa: E402

from bus import io_frames  # noqa: E402
from bus.fastmsg import new_message  # noqa: E402
from firmware_model.drive import Drive  # noqa: E402
from firmware_model.drive_node import DriveNode  # noqa: E402
from host.rig.cpu_latency import CpuLatencyRequest  # noqa: E402

NODE = 1


class MemoryBus(can.BusABC):
    """A bus in memory: frames put in :attr:`incoming` are received, sent frames are counted (the
    last one kept)."""

    def __init__(self) -> None:
        self.incoming: deque[can.Message] = deque()
        self.sent = 0
        self.last: can.Message | None = None
        super().__init__(channel="memory")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent += 1
        self.last = msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.incoming.popleft() if self.incoming else None), False

    def recv_batch(self) -> list[can.Message]:
        msgs = list(self.incoming)
        self.incoming.clear()
        return msgs

    def frames_pending(self) -> bool:
        return bool(self.incoming)

    def fileno(self) -> int:
        raise NotImplementedError  # the node polls

    def _apply_filters(self, filters: Any) -> None:
        pass


class DrivePeriods:
    """One drive node in CSP, enabled, stepped by :meth:`period`."""

    def __init__(self) -> None:
        self.fieldbus, self.io = MemoryBus(), MemoryBus()
        self.drive = Drive(NODE)
        self.node = DriveNode(self.drive, self.fieldbus, self.io, lockstep=True)
        self.node.start()
        self.wire = 0
        # TPDO1 = statusword + position actual, RPDO1 = controlword + target, both synchronous; CSP
        map_pdo(self, 0x1800, [0x60410010, 0x60640020], 1, 0x180 + NODE)
        map_pdo(self, 0x1400, [0x60400010, 0x607A0020], 1, 0x200 + NODE)
        self.download(0x6060, 0, b"\x08")
        self.fieldbus.incoming.append(new_message(0x000, bytearray([0x01, NODE])))  # NMT start
        self.node.step(0.0)
        for controlword in (0x06, 0x07, 0x0F):
            for _ in range(3):
                self.period(controlword)
        if self.drive.statusword & 0x006F != 0x0027:
            raise RuntimeError(f"the drive is not in Operation enabled: statusword 0x{self.drive.statusword:04X}")

    def download(self, index: int, sub: int, data: bytes) -> None:
        """An expedited SDO download (CiA 301 §7.2.4.3.3) of 1, 2 or 4 bytes, served at once (the
        ``sdo`` of :func:`robot_util.map_pdo`)."""
        command = {1: 0x2F, 2: 0x2B, 4: 0x23}[len(data)]
        request = bytes([command]) + struct.pack("<HB", index, sub) + data.ljust(4, b"\0")
        self.fieldbus.incoming.append(new_message(0x600 + NODE, bytearray(request)))
        self.node.step(0.0)
        answer = self.fieldbus.last
        if answer is None or answer.arbitration_id != 0x580 + NODE or answer.data[0] != 0x60:
            got = "nothing" if answer is None else bytes(answer.data).hex()
            raise RuntimeError(f"SDO download of 0x{index:04X}:{sub} not confirmed: {got}")

    def close(self) -> None:
        self.fieldbus.shutdown()
        self.io.shutdown()

    def period(self, controlword: int = 0x0F) -> None:
        """RPDO1 + SYNC, then the encoder frame: the drive answers with its torque frame and TPDO1."""
        self.fieldbus.incoming.append(new_message(0x200 + NODE, bytearray(struct.pack("<Hi", controlword, 0))))
        self.fieldbus.incoming.append(new_message(0x080, bytearray()))
        self.node.step(0.0)
        self.io.incoming.append(io_frames.encode_encoder(NODE - 1, self.wire & io_frames.TICK_MASK, 0))
        self.wire += 1
        self.node.step(0.0)


def measure(periods: int, sleep_us: float, rig: DrivePeriods) -> float:
    """Median µs of one period's code, with ``sleep_us`` of sleep before each."""
    times = []
    sleep_s = sleep_us * 1e-6
    for _ in range(periods):
        if sleep_s:
            time.sleep(sleep_s)
        t0 = time.perf_counter()
        rig.period()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=int, default=3000)
    ap.add_argument("--sleeps", type=float, nargs="+", default=[0.0, 100.0, 500.0, 2000.0], help="µs before each period")
    args = ap.parse_args()
    rig = DrivePeriods()
    measure(args.periods, 0.0, rig)  # warm up
    print(f"drive period's code, in-process: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    try:
        request: CpuLatencyRequest | None = CpuLatencyRequest(0)
    except OSError as err:
        request = None
        print(f"  (no PM QoS request: {err}; the rows with it are left out)")
    variants = [("idle CPUs polling (PM QoS 0 µs)", True)] if request is not None else []
    if request is not None:
        request.release()
    variants.append(("idle CPUs may halt", False))
    try:
        for name, poll in variants:
            run_variant(name, poll, args, rig)
    finally:
        rig.close()


def run_variant(name: str, poll: bool, args: argparse.Namespace, rig: DrivePeriods) -> None:
    """One row: the floor, then each sleep, with the PM QoS request held (``poll``) or not."""
    held = CpuLatencyRequest(0) if poll else None
    try:
        floor = measure(args.periods, 0.0, rig)
        row = [f"floor (no sleep) {floor:.1f} us"]
        for sleep_us in args.sleeps:
            if sleep_us:
                us = measure(args.periods, sleep_us, rig)
                row.append(f"after {sleep_us:g} us asleep {us:.1f} us ({us / floor:.2f} x floor)")
    finally:
        if held is not None:
            held.release()
    print(f"  {name}: " + "; ".join(row), flush=True)


if __name__ == "__main__":
    main()
