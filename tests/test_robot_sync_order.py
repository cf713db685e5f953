"""A stall of the SYNC-stepped robot under a streaming master, and that a master faster than the robot is served
late, never dropped.

The cause of the stall: the first period with one drive enabled (some joints braked, the others
free) was the first call of the locked-joint dynamics (``plant._kernels.plant_step_locked``), which
numba compiled then — seconds on a loaded machine, while the master's SYNCs (every 2–5 ms) piled
up and all but one were counted as overruns, dropped, with the robot's state still ``ready``.  Now
the robot compiles every kernel of a period before its boot-up (:func:`plant.mechanics.warm_up_robot`),
every SYNC waits in order for its period (served late: periods stepped = SYNCs sent), and in
SYNC-stepped mode the SYNC that finds :data:`bus.cyclic.SYNC_BACKLOG_MAX` waiting is a robot fault
(EMCY 0x8110 from node 32, the robot's state ``fault``, torque-free) and is served all the same; in
real time it stays a counted overrun.

The fast tests drive :class:`plant.plant_node_robot.RobotLoop` by its hooks (no threads); the slow one
runs a streaming python-canopen master (tests/streaming_master.py) against ``ilcrig robot``.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from robot_util import RobotProcess, new_channels, plant_factory

from bus.cyclic import SYNC_BACKLOG_MAX
from bus.plant_objects import ROBOT_EMCY_FLAG, ROBOT_FAULT_EMCY, RobotFault, RobotMode, RobotState
from plant import _kernels as K
from plant.disturbance import disturbance_torque
from plant.mechanics import MechanicalLimits, warm_up_robot
from plant.plant_node import PlantNode

REPO = Path(__file__).resolve().parents[1]
MASTER = Path(__file__).resolve().parent / "streaming_master.py"


@pytest.fixture
def node() -> Iterator[tuple[PlantNode, can.BusABC]]:
    """A plant node in robot mode on virtual buses (not serving: the test calls its hooks), and a
    listener on its fieldbus."""
    fb_ch, io_ch = new_channels()
    fb, io, listener = (can.Bus(interface="virtual", channel=c) for c in (fb_ch, io_ch, fb_ch))
    plant = PlantNode(fb, io, plant_factory=plant_factory, disturbance_fn=disturbance_torque, robot_mode=RobotMode.SYNC)
    plant.robot.set_mode(RobotMode.SYNC)
    try:
        yield plant, listener
    finally:
        plant.robot.close()
        for bus in (fb, io, listener):
            bus.shutdown()


def test_the_robot_compiles_the_locked_joint_dynamics_before_it_boots() -> None:
    warm_up_robot(plant_factory(1e-3, 4), MechanicalLimits())
    assert K.plant_step_locked.signatures  # compiled (or loaded from the cache) here, not in a period


def test_frames_the_plants_receiver_lost_are_a_robot_fault_with_its_emcy(node: tuple[PlantNode, can.BusABC]) -> None:
    """The plant's fieldbus receiver overflowed (udp_multicast reports a datagram the kernel dropped
    as SocketCAN's receive-overflow error frame): a SYNC may be among the frames lost, so the
    periods would no longer be the SYNCs on the bus without anybody knowing -- a robot fault
    (FRAMES_LOST, EMCY 0x8110 of node 32), torque-free until reset, and the next SYNC still a period."""
    from bus.can_errors import overflow_error_frame

    plant, listener = node
    robot = plant.robot
    robot.on_sync(0.0)
    plant._on_fieldbus(overflow_error_frame(1.0, "fieldbus"))  # as the select loop hands it over
    assert robot.state == RobotState.FAULT and robot.fault == RobotFault.FRAMES_LOST
    assert "a SYNC may be among them" in robot.info()["fault"]["message"]
    emcy = [m for m in iter(lambda: listener.recv(timeout=0.5), None) if m.arbitration_id == 0x080 + plant.node_id]
    code, register = ROBOT_FAULT_EMCY[RobotFault.FRAMES_LOST]
    assert (code, register) == (0x8110, 0x11)
    assert [bytes(m.data) for m in emcy] == [struct.pack("<HBBBHx", code, register, ROBOT_EMCY_FLAG | 8, 0, 0)]
    syncs = robot.syncs
    robot.on_sync(2.0)
    assert robot.syncs == syncs + 1


def test_io_frames_the_plants_receiver_lost_are_a_robot_fault_of_their_own(node: tuple[PlantNode, can.BusABC]) -> None:
    """The plant's io receiver overflowed while a period waited for its torques: a torque frame
    never comes -- the robot fault IO_FRAMES_LOST at once (EMCY 0x8110 of node 32, fault 9), named
    as such by ``ilcrig robot``'s console, not a damaged frame nor a period timeout a second later."""
    from bus.can_errors import overflow_error_frame
    from host.rig.robot_watch import EmcySeen, robot_fault_of

    plant, listener = node
    robot = plant.robot
    robot.on_sync(0.0)
    assert robot.expecting_io
    plant.on_io(overflow_error_frame(1.0, "io"))
    assert robot.state == RobotState.FAULT and robot.fault == RobotFault.IO_FRAMES_LOST
    assert "io frames lost in the plant's receiver" in robot.info()["fault"]["message"]
    emcy = [m for m in iter(lambda: listener.recv(timeout=0.5), None) if m.arbitration_id == 0x080 + plant.node_id]
    code, register = ROBOT_FAULT_EMCY[RobotFault.IO_FRAMES_LOST]
    assert [bytes(m.data) for m in emcy] == [struct.pack("<HBBBHx", code, register, ROBOT_EMCY_FLAG | 9, 0, 0)]
    seen = EmcySeen(plant.node_id, code, register, bytes(emcy[0].data[3:]), 0.0)
    assert robot_fault_of(seen) == "robot fault IO_FRAMES_LOST (EMCY 0x8110) in period 0 (mod 2^16)"


def _accounted(info: dict[str, int]) -> int:
    """The SYNCs a robot summary accounts for (docs/robot.md, What a session leaves)."""
    keys = ("periods", "periods_dropped", "period_in_progress", "syncs_waiting", "syncs_unstepped")
    return sum(int(info[k]) for k in keys)


def test_every_sync_the_plant_saw_is_accounted_for(node: tuple[PlantNode, can.BusABC]) -> None:
    from bus.can_errors import overflow_error_frame

    plant, _ = node
    robot = plant.robot
    for k in range(3):  # one period in progress (no drive answers here), two waiting
        robot.on_sync(float(k))
    info = robot.info()
    assert (info["syncs"], info["period_in_progress"], info["syncs_waiting"]) == (3, 1, 2) and _accounted(info) == 3
    plant.on_io(overflow_error_frame(1.0, "io"))  # the period in progress is dropped, the next one starts
    info = robot.info()
    assert (info["periods_dropped"], info["period_in_progress"], info["syncs_waiting"]) == (1, 1, 1) and _accounted(info) == 3
    robot.set_mode(RobotMode.OFF)  # the period in progress is dropped, the waiting SYNC never stepped
    robot.on_sync(5.0)  # seen while the robot is off
    info = robot.info()
    assert (info["periods_dropped"], info["period_in_progress"], info["syncs_waiting"], info["syncs_unstepped"]) == (2, 0, 0, 2)
    assert info["syncs"] == 4 == _accounted(info)


def test_a_sync_beyond_the_bound_is_a_robot_fault_with_its_emcy_and_still_served(node: tuple[PlantNode, can.BusABC]) -> None:
    plant, listener = node
    robot = plant.robot
    for k in range(1 + SYNC_BACKLOG_MAX):  # one period in progress (no drive answers here), the rest waiting
        robot.on_sync(float(k))
    assert robot.state == RobotState.READY and robot.overruns == 0
    robot.on_sync(9e9)
    assert robot.overruns == 1 and robot.state == RobotState.FAULT and robot.fault == RobotFault.SYNC_OVERRUN
    info = robot.info()
    assert info["fault"]["fault"] == "SYNC_OVERRUN" and info["fault"]["period"] == 0 and "served late" in info["fault"]["message"]
    assert info["syncs_waiting"] == SYNC_BACKLOG_MAX + 1  # kept: every SYNC is a period
    emcy = [m for m in iter(lambda: listener.recv(timeout=0.5), None) if m.arbitration_id == 0x080 + plant.node_id]
    code, register = ROBOT_FAULT_EMCY[RobotFault.SYNC_OVERRUN]
    assert [bytes(m.data) for m in emcy] == [struct.pack("<HBBBHx", code, register, ROBOT_EMCY_FLAG | 7, 0, 0)]
    robot.on_sync(9e9)  # more overruns in that episode: counted, one fault, one EMCY
    assert robot.overruns == 2 and robot.faults_total == 1


def test_in_real_time_an_overrun_stays_a_counted_miss(node: tuple[PlantNode, can.BusABC]) -> None:
    plant, _ = node
    robot = plant.robot
    robot.set_mode(RobotMode.REALTIME)
    for k in range(SYNC_BACKLOG_MAX + 3):
        robot.on_sync(plant._clock() + k * 1e-3)
    assert robot.overruns >= 1 and robot.state == RobotState.READY


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_streaming_master_never_meets_a_silent_robot(tmp_path: Path) -> None:
    """Map, start, 30 SYNCs 10 ms apart, enable the drives by SDO one SYNC per step, then RPDO1 +
    SYNC every 2–5 ms: every SYNC is a period, or the robot says it faulted (EMCY, state, summary,
    one console line) — never a stall with the state ``ready``; served late, every SYNC is a period."""
    robot = RobotProcess(tmp_path / "run")
    try:
        ready = robot.ready()
        done = subprocess.run(
            [sys.executable, str(MASTER), ready["interface"], ready["channel"]],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr
        syncs, periods, seen, overruns, state = (int(v) for v in done.stdout.split()[-5:])
        assert syncs == seen == periods == 565
        assert overruns == 0 and state == RobotState.READY
    finally:
        code = robot.stop()
        robot.kill()
    assert code == 143
    assert "robot kernels ready" in (tmp_path / "run" / "logs" / "plant.log").read_text()
    assert np.isfinite(periods)


def test_a_sync_whose_encoder_frames_cannot_be_sent_is_still_accounted_for() -> None:
    """The hub gone as the session ends (the launcher killed): the SYNC that reached the plant starts
    a period whose encoder frames cannot be sent; the period counts as in progress (it was a SYNC
    counted by no field of the session: 409 SYNCs, 408 periods and nothing else)."""
    fb_ch, io_ch = new_channels()
    fb, io = (can.Bus(interface="virtual", channel=c) for c in (fb_ch, io_ch))
    plant = PlantNode(fb, io, plant_factory=plant_factory, disturbance_fn=disturbance_torque, robot_mode=RobotMode.SYNC)
    plant.robot.set_mode(RobotMode.SYNC)
    try:
        io.shutdown()  # every send on io fails from here
        with pytest.raises(can.CanError):
            plant.robot.on_sync(0.0)
        info = plant.robot.info()
        assert (info["syncs"], info["period_in_progress"], info["periods"]) == (1, 1, 0) and _accounted(info) == 1
    finally:
        plant.robot.close()
        fb.shutdown()
