"""A master faster than the robot is served late, never dropped (docs/robot.md "Time").

A python canopen master bursts RPDO1 + SYNC period after period without waiting for anything
(:func:`burst`), against the SYNC-stepped robot in process (:class:`robot_util.VirtualRobot`: the
plant node and four drive nodes as threads on virtual buses).  Every SYNC is one period: periods
stepped = SYNCs sent, no overrun, the robot ``ready``; the TPDO of period k carries period k (its
position actual is the joint's encoder count at the start of period k in the robot's period trace);
and the periods are those of a lockstep master that waits for the TPDOs after every SYNC — the same
TPDOs, the same trace digest.

The unit tests drive :class:`firmware_model.sync_backlog.SyncBacklog` by its hooks
(tests/test_robot_sync_order.py has the plant's side: the bound, the fault past it).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest
from robot_util import DRIVES, RPDO_LAYOUT, TPDO_LAYOUT, LockstepMaster, VirtualRobot, counts_of, new_channels

from bus.plant_objects import RobotMode, RobotState, RobotSub
from firmware_model.sync_backlog import SyncBacklog
from plant.trace import read_trace, trace_digest

#: periods the master bursts
BURST = 120


class TpdoLog:
    """Every TPDO1 of the drives, in the order each drive sent them."""

    def __init__(self, master: LockstepMaster) -> None:
        self.cond = threading.Condition()
        self.by_node: dict[int, list[tuple[int, int]]] = {n: [] for n in DRIVES}
        for n in DRIVES:
            master.network.subscribe(0x180 + n, self._on_tpdo)

    def _on_tpdo(self, cob: int, data: bytearray, _t: float) -> None:
        with self.cond:
            self.by_node[cob - 0x180].append(TPDO_LAYOUT.unpack(bytes(data[: TPDO_LAYOUT.size])))
            self.cond.notify_all()

    def count(self) -> int:
        with self.cond:
            return min(len(v) for v in self.by_node.values())

    def wait(self, n: int, timeout_s: float = 120.0) -> None:
        with self.cond:
            assert self.cond.wait_for(lambda: min(len(v) for v in self.by_node.values()) >= n, timeout_s), {
                k: len(v) for k, v in self.by_node.items()
            }


def _u32(master: LockstepMaster, sub: int) -> int:
    return int.from_bytes(master.plant.sdo.upload(0x2450, sub), "little")


def session(tmp: Path, *, lockstep: bool) -> tuple[dict[int, list[tuple[int, int]]], str, dict[str, int], int]:
    """Configure, start and enable the robot in CSP step by step, then :data:`BURST` periods of a
    small move on every joint: each RPDO1 + SYNC sent at once after the last (``lockstep=False``)
    or after the TPDOs of the last came (``lockstep=True``).  Returns the TPDOs of every period,
    the trace digest, the plant's counters and the most frames that waited in a drive."""
    tmp.mkdir(parents=True)
    trace = tmp / "trace.bin"
    channels = new_channels()
    master = LockstepMaster(channels[0])
    robot = VirtualRobot(RobotMode.SYNC, trace_path=str(trace), channels=channels)
    try:
        master.wait_booted()
        for node in (*master.drives.values(), master.plant):
            node.sdo.RESPONSE_TIMEOUT = 30.0
        log = TpdoLog(master)
        master.configure()
        master.start()
        first = master.cycle(dict.fromkeys(DRIVES, (0x00, 0)))
        home = {n: first[n][1] for n in DRIVES}
        master.enable(home)
        before = log.count()
        for k in range(BURST):
            targets = {n: (0x0F, home[n] + 60 * k * (1 if n % 2 else -1)) for n in DRIVES}
            if lockstep:
                master.cycle(targets, timeout_s=60.0)
                continue
            for n, (cw, target) in targets.items():
                master.network.send_message(0x200 + n, RPDO_LAYOUT.pack(cw, target))
            master.network.send_message(0x080, b"")
        log.wait(before + BURST)
        deadline = time.monotonic() + 60.0
        while _u32(master, RobotSub.PERIODS) < 5 + BURST and time.monotonic() < deadline:
            time.sleep(0.01)
        figures = {
            name: _u32(master, sub)
            for name, sub in (
                ("periods", RobotSub.PERIODS),
                ("syncs", RobotSub.SYNCS),
                ("overruns", RobotSub.SYNC_OVERRUNS),
                ("state", RobotSub.STATE),
            )
        }
        with log.cond:
            tpdos = {n: list(v) for n, v in log.by_node.items()}
        waited = max(t.node.backlog.most for t in robot.threads[1:])
    finally:
        master.close()
        robot.close()
    return tpdos, trace_digest(read_trace(trace).records), figures, waited


@pytest.mark.slow
def test_a_bursting_master_is_served_late_every_sync_a_period_carried_by_its_tpdos(tmp_path: Path) -> None:
    tpdos, digest, figures, waited = session(tmp_path / "burst", lockstep=False)
    assert waited > 10  # the master was faster than the robot: frames waited in the drives
    syncs = 5 + BURST  # one to read the home pose, four to enable, the burst
    assert figures == {"periods": syncs, "syncs": syncs, "overruns": 0, "state": int(RobotState.READY)}
    records = read_trace(tmp_path / "burst" / "trace.bin").records
    assert len(records) == syncs and records["period"].tolist() == list(range(syncs))
    for n in DRIVES:
        assert len(tpdos[n]) == syncs
        for k in range(1, syncs):  # TPDO of period k: the count at its start = the end of period k - 1
            status, position = tpdos[n][k]
            assert abs(position - counts_of(records["q_rad"][k - 1])[n]) <= 1, (n, k, position)
        assert tpdos[n][-1][0] & 0x6F == 0x27  # Operation enabled throughout the burst
    moved = np.array([tpdos[n][-1][1] - tpdos[n][5][1] for n in DRIVES])
    assert np.all(np.abs(moved) > 1000), moved  # the burst's set-points were taken, period by period
    lock_tpdos, lock_digest, lock_figures, _ = session(tmp_path / "lockstep", lockstep=True)
    assert lock_figures == figures
    assert lock_tpdos == tpdos
    assert lock_digest == digest


# ---------------------------------------------------------------------------- the parts


def _frame(cob: int, data: bytes = b"", **kw: bool) -> can.Message:
    return can.Message(arbitration_id=cob, data=data, is_extended_id=False, **kw)


def test_the_frames_after_a_sync_wait_in_order_until_its_tick_ran() -> None:
    handled: list[int] = []
    lost: list[int] = []

    def handle(msg: can.Message) -> None:  # the node runtime: a SYNC handled waits for its tick
        handled.append(msg.arbitration_id)
        if msg.arbitration_id == 0x080 and not msg.is_remote_frame:
            backlog.sync_handled(0.0)

    backlog = SyncBacklog(1, handle, lambda: 0x080, lambda: lost.append(1), 5.0, max_frames=5)
    assert not backlog.offer(_frame(0x201))  # nothing waits: handled at once
    backlog.sync_handled(0.0)
    for cob in (0x201, 0x601, 0x080, 0x201, 0x000):
        assert backlog.offer(_frame(cob))
    assert not backlog.offer(_frame(0x77F, b"\x05"))  # a heartbeat never waits
    assert not backlog.offer(_frame(0x080, is_error_frame=True))
    assert backlog.offer(_frame(0x181, is_remote_frame=True))
    assert len(backlog) == 6 and not lost
    assert backlog.offer(_frame(0x602)) and lost == [1] and backlog.lost_frames == 1  # a 6th frame: lost
    assert backlog.offer(_frame(0x080)) and lost == [1]  # a SYNC is never lost
    handled.clear()
    backlog.tick_ran()
    assert handled == [0x201, 0x601, 0x080]  # up to the next SYNC, which waits for its own tick
    handled.clear()
    backlog.tick_ran()
    assert handled == [0x201, 0x000, 0x181, 0x080]
    handled.clear()
    backlog.tick_ran()
    assert handled == [] and len(backlog) == 0 and not backlog.sync_waiting


def test_a_sync_whose_tick_never_comes_lets_the_frames_go() -> None:
    handled: list[int] = []
    backlog = SyncBacklog(1, lambda m: handled.append(m.arbitration_id), lambda: 0x080, lambda: None, 5.0)
    backlog.sync_handled(10.0)
    assert backlog.offer(_frame(0x601)) and backlog.deadline() == 15.0
    backlog.expire(14.0)
    assert not handled
    backlog.expire(15.0)
    assert handled == [0x601] and not backlog.offer(_frame(0x602))  # unheld until the next tick
    backlog.tick_ran()
    backlog.sync_handled(20.0)
    assert backlog.offer(_frame(0x603))
