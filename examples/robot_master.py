"""Drive the ilcrig robot from your own CANopen master: python canopen's ``BaseNode402`` powers the
four drives, homes them, moves the robot point to point in profile position, then along a
pick-and-place it plans itself in cyclic synchronous position, and stops it with quick stop.

Start the robot first; it prints the python-can interface and channel of its fieldbus::

    ilcrig robot
    python examples/robot_master.py --interface ilcrig_hub --channel 'unix:/tmp/ilcrig-hub-…/hub.sock#fieldbus'
    python examples/robot_master.py --interface socketcan --channel vcan0      # the same over SocketCAN

What the script does, with python canopen's own API only (docs/robot.md):

1. PDOs, in NMT PRE-OPERATIONAL (``node.tpdo.read()``, ``add_variable``, ``save()``): TPDO1 =
   position actual + position demand on every SYNC (the master's period clock), RPDO1 =
   controlword on change (BaseNode402 sends it whenever it sets the controlword), RPDO2 = target
   position, synchronous (the CSP set-point of the next SYNC); ``setup_402_state_machine(
   read_pdos=False)``.  The statusword and the mode display are read by SDO (BaseNode402's
   fallback when no TPDO maps them): BaseNode402 waits for a periodic statusword TPDO at every
   state change, and in the SYNC-stepped robot a periodic TPDO comes only with a SYNC -- by SDO
   the state machine, ``op_mode`` and homing take no control period, so every period is one the
   master chose.
2. NMT OPERATIONAL and one control period (:meth:`Master.step`: the RPDOs, one SYNC
   (``network.sync.transmit``), the four TPDO1 back — the robot steps one period per SYNC), so the
   drives know where the robot stands.
3. Homing on the current position (method 37, or 35: ``--homing-method``) with the home offset
   0x607C = the counts of the robot's home pose, where the robot stands: ``node.homing()`` (it
   selects the mode, enables the drive, starts it by the controlword and waits for "homing
   attained").
4. Profile position (``node.op_mode = "PROFILED POSITION"``) to the first waypoint, all joints
   arriving together (0x6081/0x6083/0x6084 scaled per joint): 0x607A by SDO, then the set-point
   handshake on the controlword (bit 4 up, statusword bit 12 acknowledges, bit 4 down), then
   control periods until every drive's position demand is on its goal and its statusword says
   "target reached" (bit 10).
5. Cyclic synchronous position (``node.op_mode = "CYCLIC SYNCHRONOUS POSITION"``): the
   pick-and-place — task-space waypoints (x, y, z, θ), each move a jerk-limited Ruckig profile
   sampled at the control period, joint targets by the robot model's inverse kinematics
   (``plant.kinematics``, as a user imports the model of their robot) — one RPDO2 per drive and
   one SYNC per period.
6. Quick stop (``node.state = "QUICK STOP ACTIVE"`` with 0x605A = 6: the quick-stop ramp, then
   holding) and control periods until every drive reports standstill, then
   ``node.state = "SWITCH ON DISABLED"``: torque-free, the brakes hold the robot.

Every SYNC is sent by :meth:`Master.step` and waits for the four TPDOs, and nothing else waits on
time, so this master gets the same robot trace every time.  It prints one JSON object: homing
(the drives' positions after it beside the robot's), the profile-position move (goal, reached,
periods), per waypoint the planned joint targets [counts] and the positions the drives reported,
the robot's joint positions and TCP pose read from the plant node (node 32, 0x2451 / 0x2452) and
the state after the quick stop.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import threading
import time
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
#: the profile-position move: to the first waypoint of the pick-and-place
PP_GOAL = (-0.10, 0.00, -0.63, 0.0)
#: profile velocity [counts/s], acceleration and deceleration [counts/s²] of the joint that moves furthest
PP_VELOCITY, PP_ACCELERATION = 1_048_576, 10_485_760
#: the pick-and-place from PP_GOAL: (name, pose (x, y, z [m], θ [rad]), dwell [periods]); back home at the end
WAYPOINTS: tuple[tuple[str, tuple[float, float, float, float], int], ...] = (
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
#: statusword bits: target reached, set-point acknowledge; the state patterns
SW_TARGET_REACHED, SW_SETPOINT_ACK = 0x0400, 0x1000
#: controlword: enable operation, + new set-point
CW_ENABLE, CW_NEW_SETPOINT = 0x000F, 0x0010


def default_eds() -> str:
    """The drives' EDS shipped with ilcrig (``ilcrig robot`` prints its path)."""
    import bus

    return str(Path(bus.__file__).resolve().parent / "drive.eds")


def counts(q_rad: np.ndarray) -> list[int]:
    """Joint angles [rad] as encoder counts."""
    return [int(c) for c in np.rint(np.asarray(q_rad) * COUNTS_PER_RAD)]


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
    q = inverse_kinematics(np.concatenate(poses))  # the robot model's IK, (n, 4) rad
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
        self.periods = 0
        self._tpdo1_seen = 0
        self._cond = threading.Condition()

    def _on_tpdo1(self, _map: Any) -> None:
        with self._cond:
            self._tpdo1_seen += 1
            self._cond.notify_all()

    def configure_pdos(self) -> None:
        """Step 1 of the module docstring (NMT PRE-OPERATIONAL)."""
        self.network.nmt.state = "PRE-OPERATIONAL"
        for node in self.drives:
            node.tpdo.read()
            node.rpdo.read()
            for pdo in (*node.tpdo.values(), *node.rpdo.values()):
                pdo.enabled = False
            layout = (
                (node.tpdo[1], ("Position actual value", "Position demand value"), 1),
                (node.rpdo[1], ("Controlword",), 255),
                (node.rpdo[2], ("Target position",), 1),
            )
            for pdo, names, trans_type in layout:
                pdo.clear()
                for name in names:
                    pdo.add_variable(name)
                pdo.trans_type = trans_type
                pdo.enabled = True
            node.tpdo.save()
            node.rpdo.save()
            node.setup_402_state_machine(read_pdos=False)
            node.tpdo[1].add_callback(self._on_tpdo1)

    def step(self, targets: Sequence[int] | None = None) -> tuple[list[int], list[int]]:
        """One control period: RPDO2 (target position [counts]) per drive if ``targets`` are
        given, one SYNC, the four TPDO1 back.  Returns the positions actual and demanded [counts]."""
        if targets is not None:
            for node, target in zip(self.drives, targets):
                node.rpdo[2]["Target position"].raw = int(target)
                node.rpdo[2].transmit()
        with self._cond:
            seen = self._tpdo1_seen
        self.network.sync.transmit()
        with self._cond:
            if not self._cond.wait_for(lambda: self._tpdo1_seen >= seen + len(self.drives), timeout=2 * self.timeout_s):
                raise RuntimeError(f"period {self.periods}: the TPDOs did not come")
        self.periods += 1
        return (
            [int(node.tpdo[1]["Position actual value"].raw) for node in self.drives],
            [int(node.tpdo[1]["Position demand value"].raw) for node in self.drives],
        )

    def start(self) -> list[int]:
        """Step 2: NMT OPERATIONAL, one control period; the drives' positions [counts]."""
        self.network.nmt.state = "OPERATIONAL"
        return self.step()[0]

    def home(self, offsets: Sequence[int], method: int = 37) -> dict[str, Any]:
        """Step 3: homing on the current position (``method`` 35 or 37) with the home offsets
        [counts]."""
        ok = []
        for node, offset in zip(self.drives, offsets):
            node.sdo["Homing method"].raw = method
            node.sdo["Home offset"].raw = int(offset)
            ok.append(bool(node.homing(timeout=self.timeout_s)))
        return {
            "homed": ok,
            "offsets_counts": [int(o) for o in offsets],
            "position_counts": [int(node.sdo["Position actual value"].raw) for node in self.drives],
            "robot_counts": self.robot_pose()["q_counts"],
        }

    def move_pp(self, goal: Sequence[int], max_periods: int = 5000) -> dict[str, Any]:
        """Step 4: profile position to ``goal`` [counts], every joint on the same time scale."""
        here, _ = self.step()
        span = [abs(int(g) - h) for g, h in zip(goal, here)]
        longest = max(max(span), 1)
        for node, target, d in zip(self.drives, goal, span):
            node.op_mode = "PROFILED POSITION"
            node.sdo["Profile velocity"].raw = max(1, PP_VELOCITY * d // longest)
            node.sdo["Profile acceleration"].raw = max(1, PP_ACCELERATION * d // longest)
            node.sdo["Profile deceleration"].raw = max(1, PP_ACCELERATION * d // longest)
            node.sdo["Target position"].raw = int(target)
        for node in self.drives:  # the set-point handshake (the controlword's RPDO comes before the SDO read)
            node.controlword = CW_ENABLE | CW_NEW_SETPOINT
            if not node.check_statusword() & SW_SETPOINT_ACK:
                raise RuntimeError(f"drive {node.id}: the set-point was not acknowledged")
            node.controlword = CW_ENABLE
        start = self.periods
        goal = [int(g) for g in goal]
        for _ in range(max_periods):
            actual, demand = self.step()
            if demand == goal and all(node.check_statusword() & SW_TARGET_REACHED for node in self.drives):
                return {"goal_counts": goal, "actual_counts": actual, "periods": self.periods - start}
        raise RuntimeError(f"profile position: target not reached within {max_periods} periods")

    def stream(self, targets: np.ndarray) -> np.ndarray:
        """Step 5: CSP, one period per row of ``targets`` [counts]; the position actual values
        [counts] of every period (n, 4)."""
        for node in self.drives:
            node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
        actual = np.zeros_like(targets)
        for k, row in enumerate(targets):
            actual[k] = self.step(row.tolist())[0]
        return actual

    def quick_stop(self, max_periods: int = 5000) -> dict[str, Any]:
        """Step 6: quick stop with 0x605A = 6 (the quick-stop ramp, then holding in Quick stop
        active), control periods until every drive is at standstill (statusword bit 10), then
        Disable voltage: torque-free, the brakes hold the robot."""
        for node in self.drives:
            node.sdo["Quick stop option code"].raw = 6
            node.state = "QUICK STOP ACTIVE"
        start = self.periods
        for _ in range(max_periods):
            self.step()
            if all(node.check_statusword() & SW_TARGET_REACHED for node in self.drives):
                break
        else:
            raise RuntimeError(f"quick stop: no standstill within {max_periods} periods")
        stopped = [node.state for node in self.drives]
        for node in self.drives:
            node.state = "SWITCH ON DISABLED"
        self.step()  # a period with every drive torque-free: the brakes close
        return {"states": stopped, "then": [node.state for node in self.drives], "periods": self.periods - start}

    def robot_pose(self) -> dict[str, Any]:
        """The robot as the plant node reports it: joint positions [counts], TCP (x, y, z [m], θ
        [rad]), brakes (bit j-1: joint j held), periods stepped — after the plant has ended every
        period this master stepped: the drives send their TPDOs before the plant has their torques
        and integrates the period, so the plant's period count (0x2450:4) is waited for first."""
        sdo = self.plant.sdo

        def i32(index: int, sub: int) -> int:
            return int.from_bytes(sdo.upload(index, sub), "little", signed=True)

        deadline = time.monotonic() + self.timeout_s
        while (periods := i32(0x2450, 4)) < self.periods:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the robot ended {periods} of {self.periods} periods within {self.timeout_s} s")
        return {
            "q_counts": [i32(0x2451, j) for j in range(1, 5)],
            "tcp": [i32(0x2452, j) * 1e-6 for j in range(1, 5)],
            "brakes": sdo.upload(0x2450, 12)[0],
            "periods": periods,
        }

    def close(self) -> None:
        self.network.disconnect()


def run(interface: str, channel: str, eds: str, timeout_s: float = 5.0, homing_method: int = 37) -> dict[str, Any]:
    """The whole session (module docstring); the results as a dict."""
    master = Master(interface, channel, eds, timeout_s)
    try:
        master.configure_pdos()
        start = master.start()
        homing = master.home(counts(inverse_kinematics(np.array(HOME))), homing_method)
        pp = master.move_pp(counts(inverse_kinematics(np.array(PP_GOAL))))
        targets, marks = plan_pick_and_place(PP_GOAL)
        actual = master.stream(targets)
        reached = [
            {"waypoint": name, "period": k, "target_counts": targets[k].tolist(), "actual_counts": actual[k].tolist()}
            for name, k in marks
        ]
        pose = master.robot_pose()
        stop = master.quick_stop()
        return {
            "start_counts": start,
            "homing": homing,
            "profile_position": pp,
            "periods": len(targets),
            "waypoints": reached,
            "robot": pose,
            "after_quick_stop": stop["states"],
            "after_disable": stop["then"],
            "quick_stop_periods": stop["periods"],
            "robot_after_quick_stop": master.robot_pose(),
            "periods_total": master.periods,
        }
    finally:
        master.close()


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interface", default="ilcrig_hub", help="python-can interface (ilcrig_hub, socketcan, …)")
    ap.add_argument("--channel", required=True, help="the fieldbus channel `ilcrig robot` printed (e.g. vcan0)")
    ap.add_argument("--eds", default=default_eds(), help="the drives' EDS (default: the one ilcrig ships)")
    ap.add_argument("--timeout", type=float, default=5.0, help="longest wait for the drives' answers, s")
    ap.add_argument("--homing-method", type=int, choices=(35, 37), default=37, help="homing on the current position")
    args = ap.parse_args(argv)
    # BaseNode402 warns at every statusword it reads by SDO; here that is the choice (step 1)
    logging.getLogger("canopen.profiles.p402").setLevel(logging.ERROR)
    print(json.dumps(run(args.interface, args.channel, args.eds, args.timeout, args.homing_method), indent=1))


if __name__ == "__main__":
    main()
