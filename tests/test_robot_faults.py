"""Faults a foreign master causes on ``ilcrig robot`` (tests/robot_faults.py, one robot for all):
the master's heartbeat lost, NMT STOP mid-motion, its RPDOs stopping, its SYNCs stopping, a
mechanical limit.  Each gives the reaction the drives' 0x6007 / 0x605A / 0x1029 say (every
scenario chooses another), an EMCY with the cause (none in NMT STOPPED, CiA 301: the error is in
0x1003 afterwards), and a torque-free robot: every brake closed, the joints still.  The robot's own
processes dying: tests/test_fault_matrix.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from robot_faults import RPDO_DEADLINE_MS, SCENARIOS, FaultMaster, FaultResult
from robot_util import DRIVES, RobotProcess

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

SOD, FAULT = 0x40, 0x08  # statusword & 0x4F: Switch on disabled, Fault


@pytest.fixture(scope="module")
def master(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FaultMaster]:
    robot = RobotProcess(Path(tmp_path_factory.mktemp("robot")) / "run", env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    try:
        where = robot.ready()
        m = FaultMaster(interface=where["interface"], channel=where["channel"])
        try:
            yield m
        finally:
            m.close()
        assert robot.stop() == 143
    finally:
        robot.kill()


def torque_free(r: FaultResult) -> None:
    assert r.brakes == 0xF and r.still


def test_master_heartbeat_lost_quick_stops_the_robot(master: FaultMaster) -> None:
    r = SCENARIOS["heartbeat-lost"](master)
    assert r.emcy == {n: [bytes.fromhex("30 81 11 03 7F 00 00 00")] for n in DRIVES}  # 0x8130, cause 3, node 127
    assert all(sw & 0x4F == SOD for sw in r.states.values())  # 0x6007 = 3: quick stop, 0x605A = 2: then disabled
    assert r.nmt == {n: "OPERATIONAL" for n in DRIVES}  # 0x1029:1 = 1
    assert all(err[0] == 0x8130 for err in r.objects.values())
    torque_free(r)


def test_nmt_stop_mid_motion_faults_every_drive_without_an_emcy(master: FaultMaster) -> None:
    r = SCENARIOS["nmt-stop"](master)
    assert r.nmt == {n: "STOPPED" for n in DRIVES}
    torque_free(r)
    assert r.emcy == {}  # no EMCY in STOPPED
    assert r.extra["nmt_after"] == {n: "PRE-OPERATIONAL" for n in DRIVES}
    assert all(sw & 0x4F == FAULT for sw in r.states.values())  # 0x6007 = 1
    assert r.objects == {n: (0x8100, 0x8100) for n in DRIVES}


def test_rpdos_stopping_fault_every_drive_after_the_deadline_in_periods(master: FaultMaster) -> None:
    r = SCENARIOS["rpdo-stop"](master)
    assert r.emcy == {n: [bytes.fromhex("50 82 11 05 01 00 00 00")] for n in DRIVES}  # 0x8250, cause 5, RPDO1
    # the deadline counts control periods: 50 after the last RPDO (its own period and 49 without)
    # the drive faults, so the 50th period without an RPDO is the first the robot stands braked
    assert r.periods == RPDO_DEADLINE_MS
    torque_free(r)
    assert r.nmt == {n: "PRE-OPERATIONAL" for n in DRIVES}  # 0x1029:1 = 0
    assert all(sw & 0x4F == FAULT for sw in r.states.values())
    assert r.objects == {n: (0x8250, 0x8250) for n in DRIVES}


def test_sync_stopping_disables_every_drive(master: FaultMaster) -> None:
    r = SCENARIOS["sync-stop"](master)
    assert r.emcy == {n: [bytes.fromhex("00 81 11 06 00 00 00 00")] for n in DRIVES}  # 0x8100, cause 6
    assert all(sw & 0x4F == SOD for sw in r.states.values())  # 0x6007 = 2: Disable voltage
    assert all(sw & 0x4F == SOD for sw in r.extra["tpdo_states"].values())  # still OPERATIONAL: TPDOs
    assert r.nmt == {n: "OPERATIONAL" for n in DRIVES}
    torque_free(r)
    assert all(err[0] == 0x8100 for err in r.objects.values())


def test_an_end_stop_is_a_robot_fault_then_following_errors(master: FaultMaster) -> None:
    r = SCENARIOS["end-stop"](master)
    assert len(r.robot_emcy) == 1 and r.robot_emcy[0][:3] == bytes.fromhex("10 FF 81")  # 0xFF10, register 0x81
    assert r.extra["fault"]["code"] == 1 and r.extra["fault"]["joint"] in (2, 4)
    torque_free(r)
    assert r.emcy and all(data[:2] == bytes.fromhex("11 86") for e in r.emcy.values() for data in e)
    assert all(r.states[n] & 0x4F == FAULT for n in r.emcy)
    assert all(err == (0x8611, 0x8611) for err in r.objects.values())
