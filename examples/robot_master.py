"""Drive the ilcrig robot from your own CANopen master: python canopen's ``BaseNode402`` powers the
four drives, moves the robot along a pick-and-place it plans itself and stops it with quick stop.

Start the robot first; it prints the python-can interface and channel of its fieldbus::

    ilcrig robot
    python examples/robot_master.py --interface ilcrig_hub --channel 'unix:/tmp/ilcrig-hub-…/hub.sock#fieldbus'
    python examples/robot_master.py --interface socketcan --channel vcan0      # the same over SocketCAN

What the script does, with python canopen's own API only (docs/robot.md):

1. PDOs, in NMT PRE-OPERATIONAL: ``node.tpdo.read()`` / ``node.rpdo.read()``, then TPDO1 =
   statusword + position actual, TPDO2 = mode of operation display + torque actual, RPDO1 =
   controlword + target position, all synchronous (a frame every SYNC), ``save()``;
   ``setup_402_state_machine(read_pdos=False)``.
2. NMT OPERATIONAL, the SYNC producer (``network.sync.start``) and the RPDOs running, then
   ``node.op_mode = "CYCLIC SYNCHRONOUS POSITION"`` with the target at the actual position and
   ``node.state = "OPERATION ENABLED"`` (the brakes open).
3. The pick-and-place, planned here: task-space waypoints (x, y, z, θ), each move a jerk-limited
   Ruckig profile sampled at the control period, joint targets by the robot model's inverse
   kinematics (``plant.kinematics``, as a user imports the model of their robot).  Streamed in
   cyclic synchronous position: per control period the four RPDOs, one SYNC, and the four TPDOs
   back before the next (``network.sync.transmit``, ``tpdo.add_callback``) — the robot steps one
   period per SYNC, so this master gets the same trace every time.
4. Quick stop (``node.state = "QUICK STOP ACTIVE"``): the drives remove torque, the brakes hold
   the robot where it stands.

It prints one JSON object: per waypoint the planned joint targets [counts] and the positions the
drives reported by TPDO at the end of the dwell there, the robot's joint positions and TCP pose
read from the plant node (node 32, 0x2451 / 0x2452) and the state after the quick stop.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import canopen
import numpy as np
from canopen.profiles.p402 import BaseNode402
from ruckig import InputParameter, Result, Ruckig, Trajectory

from plant.kinematics import inverse_kinematics

DRIVES = (1, 2, 3, 4)
PLANT = 32
#: the control period of the robot (the plant's 0x2400:1 and the drives' loop), s
TS_S = 1e-3
#: encoder counts per joint revolution (bus/units.py: 10·2²⁰)
COUNTS_PER_RAD = 10 * 2**20 / (2 * math.pi)
HOME = (0.0, 0.0, -0.65, 0.0)
#: the pick-and-place: (name, pose (x, y, z [m], θ [rad]), dwell [periods]); back home at the end
WAYPOINTS: tuple[tuple[str, tuple[float, float, float, float], int], ...] = (
    ("above pick", (-0.10, 0.00, -0.63, 0.0), 0),
    ("pick", (-0.10, 0.00, -0.68, 0.0), 150),
    ("above pick", (-0.10, 0.00, -0.63, 0.0), 0),
    ("above place", (0.10, 0.05, -0.63, math.pi / 2), 0),
    ("place", (0.10, 0.05, -0.68, math.pi / 2), 150),
    ("above place", (0.10, 0.05, -0.63, math.pi / 2), 0),
    ("home", HOME, 150),
)
#: Ruckig limits per task axis (x, y, z [m], θ [rad]): velocity, acceleration, jerk
V_MAX = (1.0, 1.0, 1.0, 8.0)
A_MAX = (8.0, 8.0, 8.0, 60.0)
J_MAX = (150.0, 150.0, 150.0, 1200.0)


def default_eds() -> str:
    """The drives' EDS shipped with ilcrig (``ilcrig robot`` prints its path)."""
    import bus

    return str(Path(bus.__file__).resolve().parent / "drive.eds")


# -- planning ----------------------------------------------------------------------------------


def plan_move(start: Sequence[float], goal: Sequence[float]) -> np.ndarray:
    """Rest-to-rest jerk-limited move in task space, sampled every control period: (n, 4)."""
    otg = Ruckig(4, TS_S)
    inp = InputParameter(4)
    inp.current_position = list(start)
    inp.target_position = list(goal)
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = list(V_MAX), list(A_MAX), list(J_MAX)
    traj = Trajectory(4)
    if otg.calculate(inp, traj) not in (Result.Working, Result.Finished):
        raise RuntimeError(f"ruckig cannot plan {start} -> {goal}")
    n = max(1, math.ceil(traj.duration / TS_S))
    return np.array([traj.at_time(min(k * TS_S, traj.duration))[0] for k in range(1, n + 1)])


def plan_pick_and_place(start: Sequence[float]) -> tuple[np.ndarray, list[tuple[str, int]]]:
    """Joint targets [counts] per period (n, 4) and (waypoint, index of its last period)."""
    poses: list[np.ndarray] = []
    marks: list[tuple[str, int]] = []
    here = tuple(start)
    for name, pose, dwell in WAYPOINTS:
        move = plan_move(here, pose)
        poses.append(move)
        poses.append(np.repeat(move[-1:], dwell, axis=0))
        here = pose
        marks.append((name, sum(len(p) for p in poses) - 1))
    x = np.concatenate(poses)
    q = inverse_kinematics(x)  # the robot model's IK, (n, 4) rad
    return np.rint(q * COUNTS_PER_RAD).astype(np.int64), marks


# -- the master --------------------------------------------------------------------------------


class Master:
    """The four drives as python canopen ``BaseNode402`` nodes and the robot's plant node."""

    def __init__(self, interface: str, channel: str, eds: str, timeout_s: float = 5.0) -> None:
        self.network = canopen.Network()
        self.network.connect(interface=interface, channel=channel)
        self.timeout_s = timeout_s
        self.drives: list[BaseNode402] = []
        for node_id in DRIVES:
            node = BaseNode402(node_id, eds)
            # a loaded machine answers slower than canopen's defaults assume
            node.TIMEOUT_SWITCH_STATE_FINAL = node.TIMEOUT_SWITCH_STATE_SINGLE = timeout_s
            node.TIMEOUT_SWITCH_OP_MODE = node.TIMEOUT_CHECK_TPDO = timeout_s
            node.sdo.RESPONSE_TIMEOUT = max(node.sdo.RESPONSE_TIMEOUT, timeout_s / 5)
            self.network.add_node(node)
            self.drives.append(node)
        self.plant = self.network.add_node(PLANT, canopen.ObjectDictionary())
        self._tpdo_seen = 0
        self._cond = threading.Condition()

    def _on_tpdo1(self, _map: Any) -> None:
        with self._cond:
            self._tpdo_seen += 1
            self._cond.notify_all()

    def configure_pdos(self) -> None:
        """Step 1 of the module docstring (NMT PRE-OPERATIONAL)."""
        self.network.nmt.state = "PRE-OPERATIONAL"
        for node in self.drives:
            node.tpdo.read()
            node.rpdo.read()
            for pdo in (*node.tpdo.values(), *node.rpdo.values()):
                pdo.enabled = False
            t1, t2, r1 = node.tpdo[1], node.tpdo[2], node.rpdo[1]
            t1.clear()
            t1.add_variable("Statusword")
            t1.add_variable("Position actual value")
            t2.clear()
            t2.add_variable("Modes of operation display")
            t2.add_variable("Torque actual value")
            r1.clear()
            r1.add_variable("Controlword")
            r1.add_variable("Target position")
            for pdo in (t1, t2, r1):
                pdo.trans_type = 1
                pdo.enabled = True
            node.tpdo.save()
            node.rpdo.save()
            node.setup_402_state_machine(read_pdos=False)
            t1.add_callback(self._on_tpdo1)

    def power_on(self, period_s: float) -> None:
        """Step 2: NMT OPERATIONAL, SYNC and RPDOs running, CSP at the actual position, enabled."""
        self.network.nmt.state = "OPERATIONAL"
        self.network.sync.start(period_s)
        for node in self.drives:
            node.tpdo[1].wait_for_reception(timeout=self.timeout_s)
            node.rpdo[1]["Target position"].raw = node.tpdo[1]["Position actual value"].raw
            node.rpdo[1].start(period_s)
        for node in self.drives:
            node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
            node.state = "OPERATION ENABLED"

    def stream(self, targets: np.ndarray) -> np.ndarray:
        """Step 3: one period per row of ``targets`` [counts]: RPDOs, SYNC, the four TPDOs back.
        Returns the position actual values [counts] of every period (n, 4)."""
        self.network.sync.stop()
        for node in self.drives:
            node.rpdo[1].stop()
        actual = np.zeros_like(targets)
        for k, row in enumerate(targets):
            for node, target in zip(self.drives, row):
                node.rpdo[1]["Controlword"].raw = 0x000F
                node.rpdo[1]["Target position"].raw = int(target)
                node.rpdo[1].transmit()
            with self._cond:
                seen = self._tpdo_seen
            self.network.sync.transmit()
            with self._cond:
                if not self._cond.wait_for(lambda s=seen: self._tpdo_seen >= s + len(self.drives), timeout=2 * self.timeout_s):
                    raise RuntimeError(f"period {k}: the TPDOs did not come")
            actual[k] = [node.tpdo[1]["Position actual value"].raw for node in self.drives]
        return actual

    def quick_stop(self, period_s: float) -> list[str]:
        """Step 4: quick stop, with SYNC running again (the statusword comes by TPDO)."""
        self.network.sync.start(period_s)
        for node in self.drives:
            node.rpdo[1].start(period_s)
        for node in self.drives:
            node.state = "QUICK STOP ACTIVE"
        return [node.state for node in self.drives]

    def robot_pose(self) -> dict[str, Any]:
        """The robot as the plant node reports it: joint positions [counts], TCP (x, y, z [m], θ [rad])."""
        sdo = self.plant.sdo

        def i32(index: int, sub: int) -> int:
            return int.from_bytes(sdo.upload(index, sub), "little", signed=True)

        return {
            "q_counts": [i32(0x2451, j) for j in range(1, 5)],
            "tcp": [i32(0x2452, 1) * 1e-6, i32(0x2452, 2) * 1e-6, i32(0x2452, 3) * 1e-6, i32(0x2452, 4) * 1e-6],
        }

    def close(self) -> None:
        self.network.sync.stop()
        for node in self.drives:
            for pdo in node.rpdo.values():
                pdo.stop()
        self.network.disconnect()


def run(interface: str, channel: str, eds: str, period_s: float = 0.002, timeout_s: float = 5.0) -> dict[str, Any]:
    """The whole session (module docstring); the results as a dict."""
    master = Master(interface, channel, eds, timeout_s)
    try:
        master.configure_pdos()
        master.power_on(period_s)
        start = [int(node.tpdo[1]["Position actual value"].raw) for node in master.drives]
        targets, marks = plan_pick_and_place(HOME)
        actual = master.stream(targets)
        reached = [
            {"waypoint": name, "period": k, "target_counts": targets[k].tolist(), "actual_counts": actual[k].tolist()}
            for name, k in marks
        ]
        pose = master.robot_pose()
        states = master.quick_stop(period_s)
        return {"start_counts": start, "periods": len(targets), "waypoints": reached, "robot": pose, "after_quick_stop": states}
    finally:
        master.close()


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interface", default="ilcrig_hub", help="python-can interface (ilcrig_hub, socketcan, …)")
    ap.add_argument("--channel", required=True, help="the fieldbus channel `ilcrig robot` printed (e.g. vcan0)")
    ap.add_argument("--eds", default=default_eds(), help="the drives' EDS (default: the one ilcrig ships)")
    ap.add_argument("--sync-period", type=float, default=0.002, help="SYNC period while powering and stopping, s")
    ap.add_argument("--timeout", type=float, default=5.0, help="longest wait for the drives' answers, s")
    args = ap.parse_args(argv)
    print(json.dumps(run(args.interface, args.channel, args.eds, args.sync_period, args.timeout), indent=1))


if __name__ == "__main__":
    main()
