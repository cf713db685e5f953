"""The robot mode of the plant node (plant/plant_node_robot.py, plant/mechanics.py, plant/trace.py)
with the real plant and four real drive nodes as threads on python-can ``virtual`` buses, stepped
by a lockstep master (tests/robot_util.py: RPDOs + SYNC, then the four TPDOs, every period):
the robot stands braked at its home pose; one period per SYNC with the positions the drives report
equal to the plant's; the same master script gives the same trace; driving into a joint end stop
is one EMCY from the plant node, the robot held at the stop, until the fault reset; a trial of the
ILC host takes precedence over the SYNCs.  Plus the mechanics alone (brakes, limits) and the trace
file.  Everything waits for frames, never for time.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from clock_util import wait_for
from robot_util import DRIVES, PLANT_ID, LockstepMaster, VirtualRobot, counts_of, new_channels, plant_factory

from bus import units
from bus.plant_objects import ROBOT_EMCY_FLAG, LimitSub, PlantObj, RobotFault, RobotMode, RobotState, RobotSub
from plant.kinematics import inverse_kinematics
from plant.mechanics import HOME_POSE, MechanicalLimits, Mechanics
from plant.plant_node import PlantNode
from plant.trace import TraceWriter, read_trace, trace_digest

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def _no_leaked_virtual_channels() -> Iterator[None]:
    from can.interfaces import virtual

    yield
    assert not virtual.channels, f"virtual channels left open: {list(virtual.channels)}"


class Robot:
    """A virtual robot and its master, booted."""

    def __init__(self, tmp: Path, mode: RobotMode = RobotMode.SYNC) -> None:
        ch = new_channels()
        tmp.mkdir(parents=True, exist_ok=True)
        self.trace_path = tmp / "trace.bin"
        self.master = LockstepMaster(ch[0])
        try:
            self.robot = VirtualRobot(mode, trace_path=str(self.trace_path), channels=ch)
        except BaseException:
            self.master.close()
            raise
        try:
            self.master.wait_booted()
        except BaseException:
            self.close()
            raise

    @property
    def plant(self) -> PlantNode:
        return self.robot.plant

    def settle(self, periods: int) -> None:
        """Until the plant has integrated ``periods`` periods (its TPDOs come before that)."""
        assert wait_for(lambda: self.plant.robot.periods >= periods)

    def stop(self) -> None:
        """Stop the nodes (the trace is complete afterwards)."""
        self.robot.close()

    def sdo_u32(self, index: int, sub: int) -> int:
        return int.from_bytes(self.master.plant.sdo.upload(index, sub), "little", signed=index in (0x2451, 0x2452, 0x2453))

    def close(self) -> None:
        self.master.close()
        self.robot.close()


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Robot]:
    r = Robot(tmp_path)
    try:
        yield r
    finally:
        r.close()


HOME_Q = inverse_kinematics(np.array(HOME_POSE))


def test_robot_stands_braked_at_home_and_steps_one_period_per_sync(robot: Robot) -> None:
    m = robot.master
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.MODE) == RobotMode.SYNC
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.STATE) == RobotState.READY
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.BRAKES) == 0xF
    home = counts_of(HOME_Q)
    assert [robot.sdo_u32(PlantObj.JOINT_POSITION, j) for j in DRIVES] == [home[n] for n in DRIVES]
    tcp = [robot.sdo_u32(PlantObj.TCP_POSE, j) for j in (1, 2, 3, 4)]
    assert tcp == [round(v * 1e6) for v in HOME_POSE]
    assert robot.sdo_u32(PlantObj.MECHANICAL_LIMITS, LimitSub.JOINT_HIGH_COUNTS) == round(np.radians(80) / units.RAD_PER_COUNT)
    m.configure()
    m.start()
    for _ in range(40):  # drives in Switch on disabled: no torque, every joint held by its brake
        tp = m.cycle({n: (0x00, home[n]) for n in DRIVES})
    assert {n: tp[n][1] for n in DRIVES} == home
    assert all(tp[n][0] & 0x4F == 0x40 for n in DRIVES)  # Switch on disabled
    robot.settle(40)
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.PERIODS) == 40 == robot.sdo_u32(PlantObj.ROBOT, RobotSub.SYNCS)
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.SYNC_OVERRUNS) == 0
    np.testing.assert_array_equal(robot.plant.robot.mechanics.plant.q, HOME_Q)  # not a bit moved


def ramp(m: LockstepMaster, start: dict[int, int], targets: np.ndarray) -> list[dict[int, tuple[int, int]]]:
    """CSP: one period per row of joint targets [rad] (controlword Enable operation)."""
    out = []
    for row in targets:
        out.append(m.cycle({n: (0x0F, round(float(row[n - 1]) / units.RAD_PER_COUNT)) for n in DRIVES}))
    return out


def test_csp_moves_the_robot_and_the_tpdos_carry_the_plants_positions(robot: Robot) -> None:
    m = robot.master
    home = enabled_at_home(m)
    assert robot.plant.robot.brakes == 0  # torque on, brakes open
    x = np.linspace(HOME_POSE, (0.05, -0.03, -0.70, 0.3), 300)
    q_ref = inverse_kinematics(np.concatenate([x, np.repeat(x[-1:], 100, axis=0)]))
    robot.settle(4)  # the four periods of enable(): their TPDOs come before the plant integrates
    n0 = robot.plant.robot.periods
    assert n0 == 4
    tpdos = ramp(m, home, q_ref)
    robot.settle(n0 + len(tpdos))
    robot.stop()
    rec = read_trace(robot.trace_path).records
    assert len(rec) == n0 + len(tpdos)
    # the TPDO of a period carries the encoder count the plant sent for it: q at the end of the one before
    for k in range(1, len(tpdos)):
        period = n0 + k
        expected = np.rint(rec["q_rad"][period - 1] / units.RAD_PER_COUNT).astype(np.int64)
        assert [tpdos[k][n][1] for n in DRIVES] == expected.tolist()
    final = robot.plant.robot.mechanics.plant.task_pose()
    # after the dwell within 1 mm; the tool angle within 30 mrad (θ is the screw: 0.1 mm of gap is 16 mrad)
    np.testing.assert_allclose(final[:3], x[-1][:3], atol=1e-3)
    assert abs(final[3] - x[-1][3]) < 0.03
    assert all(rec["held"][n0 + 1 :] == 0)


def enabled_at_home(m: LockstepMaster) -> dict[int, int]:
    """PDOs configured, NMT START, every drive enabled holding the home pose; its counts per node."""
    m.configure()
    m.start()
    home = counts_of(HOME_Q)
    m.enable(home)
    return home


def script(m: LockstepMaster, n: int) -> None:
    home = enabled_at_home(m)
    x = np.linspace(HOME_POSE, (-0.04, 0.02, -0.68, -0.2), n)
    ramp(m, home, inverse_kinematics(x))


def test_the_same_master_script_gives_the_same_trace(tmp_path: Path) -> None:
    digests = []
    for run in range(2):
        r = Robot(tmp_path / f"run{run}")
        try:
            script(r.master, 150)
            r.settle(154)
            r.stop()
            assert r.plant.robot.periods == 154
            digests.append(trace_digest(read_trace(r.trace_path).records))
        finally:
            r.close()
    assert digests[0] == digests[1]


def test_driving_into_an_end_stop_is_one_emcy_and_the_robot_held_there(robot: Robot) -> None:
    m = robot.master
    enabled_at_home(m)
    # straight down until the lower sub-platform's arms (joints 2, 4) pass 80 deg
    z = np.linspace(HOME_POSE[2], -0.87, 460)
    q_ref = inverse_kinematics(np.stack([np.zeros_like(z), np.zeros_like(z), z, np.zeros_like(z)], axis=1))
    for row in q_ref:
        m.cycle({n: (0x0F, round(float(row[n - 1]) / units.RAD_PER_COUNT)) for n in DRIVES})
        if robot.plant.robot.fault != RobotFault.NONE:
            break
    cob, data = m.wait_emcy(lambda cob, data: cob == 0x080 + PLANT_ID)
    code, register = struct.unpack_from("<HB", data)
    assert (code, register) == (0xFF10, 0x81)
    assert data[3] == ROBOT_EMCY_FLAG | RobotFault.END_STOP and data[4] in (2, 4)
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.STATE) == RobotState.FAULT
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.FAULT_CODE) == RobotFault.END_STOP
    q_stop = robot.plant.robot.mechanics.plant.q
    assert q_stop[data[4] - 1] == MechanicalLimits().q_max_rad and np.all(np.isfinite(q_stop))
    for _ in range(5):  # held: the drives' torques are not applied, nothing moves
        m.cycle({n: (0x0F, round(float(q_ref[-1][n - 1]) / units.RAD_PER_COUNT)) for n in DRIVES})
    np.testing.assert_array_equal(robot.plant.robot.mechanics.plant.q, q_stop)
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.BRAKES) == 0xF
    n_emcy = len(m.emcy)
    m.plant.sdo.download(PlantObj.ROBOT, RobotSub.COMMAND, b"\x01")  # fault reset
    cob, data = m.wait_emcy(lambda cob, data: cob == 0x080 + PLANT_ID and data[:2] == b"\x00\x00")
    assert len([e for e in m.emcy[n_emcy:] if e[0] == 0x080 + PLANT_ID]) == 1
    assert robot.sdo_u32(PlantObj.ROBOT, RobotSub.STATE) == RobotState.READY


# -- the mechanics and the trace alone ----------------------------------------------------------


def test_a_braked_joint_does_not_move_while_the_others_fall() -> None:
    mech = Mechanics(plant_factory(1e-3, 4))
    mech.home()
    q0 = mech.plant.q
    held = np.array([True, False, True, True])
    for _ in range(50):
        assert mech.step(np.zeros(4, dtype=np.int64), held) is None
    q = mech.plant.q
    assert q[0] == q0[0] and q[2] == q0[2] and q[3] == q0[3]
    assert q[1] > q0[1]  # joint 2 has no torque and no brake: it falls (positive = down)


def test_the_screw_stop_keeps_the_robot_at_its_last_pose() -> None:
    mech = Mechanics(plant_factory(1e-3, 4), MechanicalLimits(gap_min_m=0.049, gap_max_m=0.051))
    mech.home()
    held = np.array([False, True, True, True])
    hit = None
    for _ in range(400):  # joint 1 alone falls: the upper sub-platform moves against the lower one
        q_before = mech.plant.q
        hit = mech.step(np.zeros(4, dtype=np.int64), held)
        if hit is not None:
            break
    assert hit is not None and hit.kind == "screw_stop" and hit.joint == 0
    np.testing.assert_array_equal(mech.plant.q, q_before)
    assert not mech.plant.qd.any()


def test_trace_file_round_trip_and_a_partial_record(tmp_path: Path) -> None:
    path = tmp_path / "t.bin"
    w = TraceWriter(path, 1e-3, 4)
    for k in range(300):
        w.add(k, np.full(4, k * 0.5), np.arange(4) + k, k % 16, 1 if k == 7 else 0)
    w.close()
    t = read_trace(path)
    assert (t.ts_s, t.substeps, len(t.records)) == (1e-3, 4, 300)
    assert t.records["period"].tolist() == list(range(300)) and t.records["flags"][7] == 1
    np.testing.assert_array_equal(t.q_rad[299], np.full(4, 149.5))
    with open(path, "ab") as f:
        f.write(b"\x01\x02\x03")  # a killed writer's half record
    assert len(read_trace(path).records) == 300
    assert trace_digest(read_trace(path).records) == trace_digest(t.records)


def test_a_trial_of_the_ilc_host_takes_precedence_and_the_robot_goes_on_from_its_end(robot: Robot) -> None:
    """And the robot's periods ask the io transport for their four torque frames in one write (the
    hub's gather record): at the first period, again after the trial (whose end sets 0), and 0 when
    the robot goes off."""
    from host.nodes.plant_client import PlantClient
    from host.nodes.sdo_access import SdoAccess

    gathers: list[int] = []
    robot.plant.robot._gather = gathers.append  # the virtual bus does not gather: record the requests
    m = robot.master
    m.configure()
    m.start()
    home = counts_of(HOME_Q)
    for _ in range(5):
        m.cycle({n: (0x00, home[n]) for n in DRIVES})
    robot.settle(5)
    assert gathers == [4]
    # drives in PRE-OPERATIONAL answer the trial's ticks without SYNC, as the ILC host's table mode
    m.network.nmt.state = "PRE-OPERATIONAL"
    client = PlantClient(SdoAccess(m.plant))
    q0 = HOME_Q + np.array([0.0, 0.02, 0.0, 0.0])
    client.start_trial(0, 80, q0, np.zeros(4))
    m.network.send_message(0x080, b"")  # a SYNC during the trial: counted, not stepped
    state = client.wait_trial(timeout_s=30.0)
    assert state.status.name == "DONE" and state.ticks_done == 80
    assert robot.plant.robot.periods == 5 and robot.plant.robot.syncs == 6
    q_end = robot.plant.robot.mechanics.plant.q  # the trial moved the robot (no brakes in a trial)
    assert q_end[1] != HOME_Q[1] + 0.02
    m.start()
    tp = m.cycle({n: (0x00, home[n]) for n in DRIVES})  # the robot goes on where the trial left it
    assert [tp[n][1] for n in DRIVES] == np.rint(q_end / units.RAD_PER_COUNT).astype(int).tolist()
    robot.settle(6)
    assert gathers == [4, 4]
    m.plant.sdo.download(PlantObj.ROBOT, RobotSub.MODE, struct.pack("<B", RobotMode.OFF))
    assert gathers == [4, 4, 0]
