"""A random foreign master against ``ilcrig robot`` (python canopen over the hub): a hypothesis
``RuleBasedStateMachine`` that writes valid and invalid SDOs, sends NMT commands, controlword
sequences and mode switches by SDO, steps the robot SYNC by SYNC (waiting for the TPDOs), sends
SYNC bursts as fast as it can (the robot serves them late, every SYNC a period, the drives' frames
waiting behind them in order) and pauses.  After every step, the invariants:

* periods stepped = SYNCs sent (0x2450:4 of the plant node, within a bound: no stall), no overrun,
  the robot ``ready``;
* torque only where CiA 402 allows it: after a lockstep SYNC, a joint is free of its brake
  (0x2450:12) only if its drive is in Operation enabled (its TPDO when OPERATIONAL, its statusword
  by SDO when PRE-OPERATIONAL: NMT does not switch a power stage off);
* the TPDO of period k carries period k: after a lockstep SYNC, each drive's TPDO1 position actual is
  the joint count the plant had at the start of that period (0x2451, read before the SYNC).

Bounded for CI (``max_examples`` 10, 15 steps, one robot for the module); a replay of one fixed
master sequence against two fresh in-process robots gives the same trace digest.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import canopen
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule
from robot_util import DRIVES, PLANT_ID, LockstepMaster, RobotProcess, VirtualRobot, new_channels

from bus.objects import DRIVE_EDS_PATH
from bus.plant_objects import PLANT_EDS_PATH, PlantObj, RobotState, RobotSub
from plant.trace import read_trace, trace_digest

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

#: longest wait for the robot to have stepped every SYNC sent (no stall), s
STALL_S = 20.0
_OP_ENABLED = 0x27


class Master:
    """python canopen on the robot's fieldbus: SDO clients of the drives and the plant, TPDO1 seen."""

    def __init__(self, interface: str, channel: str) -> None:
        self.net = canopen.Network()
        self.net.connect(interface=interface, channel=channel)
        self.drives = {n: self.net.add_node(n, str(DRIVE_EDS_PATH)) for n in DRIVES}
        self.plant = self.net.add_node(PLANT_ID, str(PLANT_EDS_PATH))
        for node in (*self.drives.values(), self.plant):
            node.sdo.RESPONSE_TIMEOUT = 10.0
        self.cond = threading.Condition()
        self.tpdo: dict[int, tuple[int, int]] = {}
        self.tpdos = 0
        for n in DRIVES:
            self.net.subscribe(0x180 + n, self._on_tpdo)
        self.nmt = dict.fromkeys(DRIVES, "PRE-OPERATIONAL")
        for n, node in self.drives.items():  # TPDO1 = statusword + position actual, RPDO1 = controlword + target, type 1
            node.nmt.state = "PRE-OPERATIONAL"
            sdo = node.sdo
            sdo.download(0x1800, 1, struct.pack("<I", 0xC0000180 + n))
            sdo.download(0x1A00, 0, b"\x00")
            sdo.download(0x1A00, 1, struct.pack("<I", 0x60410010))
            sdo.download(0x1A00, 2, struct.pack("<I", 0x60640020))
            sdo.download(0x1A00, 0, b"\x02")
            sdo.download(0x1800, 2, b"\x01")
            sdo.download(0x1800, 1, struct.pack("<I", 0x40000180 + n))
            for k in (2, 3, 4):
                sdo.download(0x1800 + k - 1, 1, struct.pack("<I", 0xC0000180 + 0x100 * (k - 1) + n))

    def _on_tpdo(self, cob: int, data: bytearray, _t: float) -> None:
        with self.cond:
            self.tpdo[cob - 0x180] = struct.unpack_from("<Hi", bytes(data))
            self.tpdos += 1
            self.cond.notify_all()

    def u32(self, sub: int) -> int:
        return int.from_bytes(self.plant.sdo.upload(PlantObj.ROBOT, sub), "little")

    def joint_counts(self) -> dict[int, int]:
        return {n: int.from_bytes(self.plant.sdo.upload(PlantObj.JOINT_POSITION, n), "little", signed=True) for n in DRIVES}

    def close(self) -> None:
        self.net.disconnect()


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Master]:
    proc = RobotProcess(tmp_path_factory.mktemp("fsm") / "run")
    try:
        ready = proc.ready()
        master = Master(ready["interface"], ready["channel"])
        try:
            yield master
        finally:
            master.close()
    finally:
        proc.stop()
        proc.kill()


class RandomMaster(RuleBasedStateMachine):
    m: Master
    #: lockstep periods checked over every example (the test sees that the machine ran)
    lockstep_periods = 0

    @initialize()
    def begin(self) -> None:
        """Every example starts from the same robot (the robot lives for the module): each drive
        PRE-OPERATIONAL with its power stage off, applied by one SYNC — so what a rule does never
        depends on the examples before it."""
        self.syncs0 = self.m.u32(RobotSub.SYNCS)
        self.periods0 = self.m.u32(RobotSub.PERIODS)
        self.sent = 0
        for n, node in self.m.drives.items():
            node.nmt.state = "PRE-OPERATIONAL"
            self.m.nmt[n] = "PRE-OPERATIONAL"
            node.sdo.download(0x6040, 0, struct.pack("<H", 0x00))  # disable voltage (after the NMT command)
        self._sync()

    # ------------------------------------------------------------------ rules

    def _sync(self, count: int = 1) -> None:
        """``count`` SYNCs back to back once the robot has stepped the ones before."""
        self._wait_stepped()
        for _ in range(count):
            self.m.net.sync.transmit()
        self.sent += count

    @rule(node=st.sampled_from(DRIVES), value=st.integers(1, 2_000_000))
    def sdo_valid(self, node: int, value: int) -> None:
        sdo = self.m.drives[node].sdo
        if self.m.nmt[node] == "STOPPED":
            return
        sdo.download(0x6081, 0, struct.pack("<I", value))  # profile velocity
        assert struct.unpack("<I", sdo.upload(0x6081, 0))[0] == value

    @rule(node=st.sampled_from(DRIVES), index=st.sampled_from([(0x6041, 0), (0x6064, 0), (0x1000, 0), (0x5FFF, 0), (0x6040, 9)]))
    def sdo_invalid(self, node: int, index: tuple[int, int]) -> None:
        if self.m.nmt[node] == "STOPPED":
            return
        with pytest.raises(canopen.SdoAbortedError):
            self.m.drives[node].sdo.download(*index, b"\x00\x00")

    @rule(node=st.sampled_from(DRIVES), state=st.sampled_from(["OPERATIONAL", "PRE-OPERATIONAL", "STOPPED"]))
    def nmt(self, node: int, state: str) -> None:
        self.m.drives[node].nmt.state = state
        self.m.nmt[node] = state
        if state != "STOPPED":
            self.m.drives[node].sdo.upload(0x1000, 0)  # handled after the NMT command
        else:
            time.sleep(0.05)

    @rule(
        node=st.sampled_from(DRIVES), cws=st.lists(st.sampled_from([0x00, 0x06, 0x07, 0x0F, 0x80, 0x02]), min_size=1, max_size=4)
    )
    def controlwords(self, node: int, cws: list[int]) -> None:
        if self.m.nmt[node] == "STOPPED":
            return
        sdo = self.m.drives[node].sdo
        sdo.download(0x607A, 0, sdo.upload(0x6064, 0))  # enabling holds where the joint is
        for cw in cws:
            sdo.download(0x6040, 0, struct.pack("<H", cw))
            self._sync()

    @rule(node=st.sampled_from(DRIVES), mode=st.sampled_from([1, 8, 9]))
    def mode_switch(self, node: int, mode: int) -> None:
        if self.m.nmt[node] == "STOPPED":
            return
        sdo = self.m.drives[node].sdo
        sdo.download(0x607A, 0, sdo.upload(0x6064, 0))
        sdo.download(0x60FF, 0, b"\x00\x00\x00\x00")
        sdo.download(0x6071, 0, b"\x00\x00")
        try:
            sdo.download(0x6060, 0, struct.pack("<b", mode))
        except canopen.SdoAbortedError:
            pass  # a mode the drive does not support is refused

    @rule()
    def lockstep_sync(self) -> None:
        """One SYNC, the TPDOs of the OPERATIONAL drives: each carries this period's joint count."""
        self._wait_stepped()  # the periods of a burst before it are done: the joints stand where they start
        counts = self.m.joint_counts()
        live = [n for n in DRIVES if self.m.nmt[n] == "OPERATIONAL"]
        with self.m.cond:
            self.m.tpdo.clear()
        self._sync()
        RandomMaster.lockstep_periods += 1
        with self.m.cond:
            assert self.m.cond.wait_for(lambda: all(n in self.m.tpdo for n in live), STALL_S), self.m.tpdo
            got = dict(self.m.tpdo)
        for n in live:
            assert got[n][1] == counts[n], (n, got[n], counts)
        self._wait_stepped()
        brakes = self.m.u32(RobotSub.BRAKES)
        for n in DRIVES:  # torque only where CiA 402 allows it: a free joint's drive is in Operation enabled
            if brakes >> (n - 1) & 1:
                continue
            if n in live:  # its TPDO of this period
                status = got[n][0]
            elif self.m.nmt[n] == "PRE-OPERATIONAL":  # no PDOs (NMT does not switch a power stage off): by SDO
                status = struct.unpack("<H", self.m.drives[n].sdo.upload(0x6041, 0))[0]
            else:
                continue  # STOPPED: nothing but NMT and heartbeats reach the drive, nothing to read
            assert status & 0x6F == _OP_ENABLED, (n, brakes, status, self.m.nmt)

    @rule(count=st.integers(1, 40))
    def sync_burst(self, count: int) -> None:
        """SYNCs back to back, without waiting for the robot: served late, every SYNC one period
        (the rules after it find the drives' frames handled in order behind them)."""
        for _ in range(count):
            self.m.net.sync.transmit()
        self.sent += count

    @rule(ms=st.integers(0, 30))
    def pause(self, ms: int) -> None:
        time.sleep(ms / 1000)

    # ------------------------------------------------------------------ invariants

    def _wait_stepped(self) -> None:
        deadline = time.monotonic() + STALL_S
        while self.m.u32(RobotSub.PERIODS) - self.periods0 < self.sent and time.monotonic() < deadline:
            time.sleep(0.002)

    @invariant()
    def every_sync_is_one_period_and_no_stall(self) -> None:
        if not hasattr(self, "sent"):
            return
        self._wait_stepped()
        assert self.m.u32(RobotSub.SYNCS) - self.syncs0 == self.sent
        assert self.m.u32(RobotSub.PERIODS) - self.periods0 == self.sent
        assert self.m.u32(RobotSub.SYNC_OVERRUNS) == 0
        assert self.m.u32(RobotSub.STATE) == RobotState.READY


def test_a_random_foreign_master_finds_nothing(robot: Master) -> None:
    RandomMaster.m = robot
    RandomMaster.TestCase.settings = settings(
        max_examples=10, stateful_step_count=15, deadline=None, suppress_health_check=list(HealthCheck)
    )
    RandomMaster.TestCase().runTest()
    assert RandomMaster.lockstep_periods > 0
    assert robot.u32(RobotSub.SYNC_OVERRUNS) == 0 and robot.u32(RobotSub.STATE) == RobotState.READY


def _replay(tmp: Path) -> str:
    """One fixed master sequence (configure, start, enable in CSP, a short move) on a fresh
    in-process robot: its trace digest."""
    ch = new_channels()
    tmp.mkdir(parents=True)
    trace = tmp / "trace.bin"
    master = LockstepMaster(ch[0])
    robot = VirtualRobot(trace_path=str(trace), channels=ch)
    try:
        master.wait_booted()
        master.configure()
        master.start()
        counts: dict[int, Any] = {}
        for _ in range(3):
            counts = master.cycle(dict.fromkeys(DRIVES, (0x00, 0)))
        home = {n: counts[n][1] for n in DRIVES}
        master.enable(home)
        for k in range(60):
            master.cycle({n: (0x0F, home[n] + 40 * k) for n in DRIVES})
    finally:
        master.close()
        robot.close()
    return trace_digest(read_trace(trace).records)


def test_the_replay_of_one_master_sequence_gives_the_same_digest_twice(tmp_path: Path) -> None:
    assert _replay(tmp_path / "a") == _replay(tmp_path / "b")
