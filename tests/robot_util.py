"""Test helpers of the robot: the plant node in robot mode and four real drive nodes as threads on
python-can ``virtual`` buses (:class:`VirtualRobot`), and a lockstep master on the fieldbus
(:class:`LockstepMaster`: SDO through the canopen library, RPDOs and SYNC as raw frames, every
period waits for the four TPDOs, so the periods are deterministic).

Everything waits for events (frames counted under a condition), never for time.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from cli_util import pid_alive
from clock_util import SDO_RESPONSE_S

from bus import units
from bus.objects import DRIVE_EDS_PATH
from bus.plant_objects import PLANT_EDS_PATH, RobotMode
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode
from plant.disturbance import disturbance_torque
from plant.params import default_true_plant
from plant.plant_node import PlantNode
from plant.simulator import Plant

_counter = itertools.count()
PLANT_ID = 32
DRIVES = (1, 2, 3, 4)

#: RPDO1 of the lockstep master: controlword (U16), target position (I32)
RPDO_LAYOUT = struct.Struct("<Hi")
#: TPDO1: statusword (U16), position actual (I32)
TPDO_LAYOUT = struct.Struct("<Hi")


def new_channels() -> tuple[str, str]:
    """Fresh names of a virtual fieldbus and io channel."""
    k = next(_counter)
    return f"robot-fb-{k}", f"robot-io-{k}"


class NodeThread:
    """A node (a SlaveNode subclass) serving in a thread on its own buses until :meth:`close`."""

    def __init__(self, node: Any, buses: list[can.BusABC]) -> None:
        self.node = node
        self.buses = buses
        self.stop = threading.Event()
        self.thread = threading.Thread(target=node.run, args=(self.stop,), daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5.0)
        assert not self.thread.is_alive()
        for bus in self.buses:
            bus.shutdown()


def plant_factory(ts_s: float, substeps: int) -> Plant:
    return Plant(default_true_plant(), ts_s, substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)


class VirtualRobot:
    """The robot's nodes as threads: the plant node (robot mode ``mode``) and drives 1..4 (drives of
    a SYNC-stepped plant, as ``ilcrig robot`` starts them: ``DriveNode(lockstep=True)``).

    :param trace_path: the plant's period trace (None: none).
    :param tick_timeout_s: the plant's longest wait for a period's torques, s.
    """

    def __init__(
        self,
        mode: RobotMode = RobotMode.SYNC,
        trace_path: str | None = None,
        tick_timeout_s: float = 5.0,
        channels: tuple[str, str] | None = None,
    ) -> None:
        self.fb_channel, self.io_channel = channels if channels is not None else new_channels()
        self.threads: list[NodeThread] = []
        try:
            fb = can.Bus(interface="virtual", channel=self.fb_channel)
            io = can.Bus(interface="virtual", channel=self.io_channel)
            self.plant = PlantNode(
                fb,
                io,
                plant_factory=plant_factory,
                disturbance_fn=disturbance_torque,
                robot_mode=mode,
                trace_path=trace_path,
                tick_timeout_s=tick_timeout_s,
            )
            self.threads.append(NodeThread(self.plant, [fb, io]))
            self.drives: list[Drive] = []
            for node_id in DRIVES:
                drive = Drive(node_id)
                fb_d = can.Bus(interface="virtual", channel=self.fb_channel)
                io_d = can.Bus(interface="virtual", channel=self.io_channel)
                self.drives.append(drive)
                self.threads.append(NodeThread(DriveNode(drive, fb_d, io_d, lockstep=True), [fb_d, io_d]))
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop the nodes and close the plant's trace (idempotent)."""
        for t in self.threads:
            t.close()
        self.threads = []
        if hasattr(self, "plant"):
            self.plant.robot.close()


def map_pdo(sdo: Any, comm: int, entries: Sequence[int], kind: int, cob_id: int) -> None:
    """The CiA 301 mapping procedure by SDO for the PDO of communication object ``comm`` (0x1400+k,
    0x1800+k; its mapping object is ``comm`` + 0x200): invalid while mapped, sub 0 = 0, the
    ``entries`` (mapping words: index << 16 | sub-index << 8 | bits), sub 0 = their count,
    transmission type ``kind``, then COB-ID ``cob_id`` (valid)."""
    mapping = comm + 0x200
    sdo.download(comm, 1, struct.pack("<I", 0x80000000 | cob_id))
    sdo.download(mapping, 0, b"\x00")
    for sub, entry in enumerate(entries, start=1):
        sdo.download(mapping, sub, struct.pack("<I", entry))
    sdo.download(mapping, 0, bytes([len(entries)]))
    sdo.download(comm, 2, bytes([kind]))
    sdo.download(comm, 1, struct.pack("<I", cob_id))


class LockstepMaster:
    """A CANopen master on the robot's fieldbus that steps it one period at a time.

    SDO through canopen ``RemoteNode``s; per period :meth:`cycle` sends each drive's RPDO1
    (controlword, target position [counts]) and one SYNC, then waits for the four TPDO1s
    (statusword, position actual), which it returns.

    :param virtual_channel: the virtual fieldbus channel (or pass ``bus_kwargs`` of python-can's
        ``Bus`` for another interface).
    """

    def __init__(self, virtual_channel: str | None = None, **bus_kwargs: Any) -> None:
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.02
        if virtual_channel is not None:
            bus_kwargs = {"interface": "virtual", "channel": virtual_channel}
        self.network.connect(**bus_kwargs)
        self.drives = {n: self.network.add_node(n, str(DRIVE_EDS_PATH)) for n in DRIVES}
        self.plant = self.network.add_node(PLANT_ID, str(PLANT_EDS_PATH))
        for node in (*self.drives.values(), self.plant):
            node.sdo.RESPONSE_TIMEOUT = SDO_RESPONSE_S
        self.emcy: list[tuple[int, bytes]] = []
        self.booted: set[int] = set()
        self._tpdo: dict[int, tuple[int, int]] = {}
        self._tpdo_count = 0
        self._cond = threading.Condition()
        for node in (*DRIVES, PLANT_ID):
            self.network.subscribe(0x080 + node, self._on_emcy)
        for node in DRIVES:
            self.network.subscribe(0x180 + node, self._on_tpdo)
        for node in (*DRIVES, PLANT_ID):
            self.network.subscribe(0x700 + node, self._on_heartbeat)

    def _on_heartbeat(self, cob: int, data: bytearray, _t: float) -> None:
        if data[:1] == b"\x00":
            with self._cond:
                self.booted.add(cob - 0x700)
                self._cond.notify_all()

    def wait_booted(self, timeout_s: float = 60.0) -> None:
        """Until every node has sent its boot-up frame."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.booted >= {*DRIVES, PLANT_ID}, timeout_s):
                raise TimeoutError(f"booted: {sorted(self.booted)}")

    def _on_emcy(self, cob: int, data: bytearray, _t: float) -> None:
        with self._cond:
            self.emcy.append((cob, bytes(data)))
            self._cond.notify_all()

    def _on_tpdo(self, cob: int, data: bytearray, _t: float) -> None:
        with self._cond:
            self._tpdo[cob - 0x180] = TPDO_LAYOUT.unpack(bytes(data[: TPDO_LAYOUT.size]))
            self._tpdo_count += 1
            self._cond.notify_all()

    def configure(self, mode: int = 8) -> None:
        """In PRE-OPERATIONAL: RPDO1 = controlword + target position, TPDO1 = statusword + position
        actual (both synchronous, every SYNC), mode of operation ``mode`` (8 = CSP)."""
        for node in self.drives.values():
            sdo = node.sdo
            map_pdo(sdo, 0x1400, (0x60400010, 0x607A0020), 1, 0x200 + node.id)  # RPDO1, every SYNC
            map_pdo(sdo, 0x1800, (0x60410010, 0x60640020), 1, 0x40000180 + node.id)  # TPDO1, no RTR
            sdo.download(0x6060, 0, struct.pack("<b", mode))

    def start(self) -> None:
        """NMT start of every node (broadcast), confirmed by an SDO answer of every drive (handled
        after the NMT command: python-can's virtual bus may hold a node's frames back for a while
        behind one its filters drop, never reorder them)."""
        self.network.nmt.state = "OPERATIONAL"
        for node in self.drives.values():
            node.sdo.upload(0x6041, 0)

    def cycle(self, targets: dict[int, tuple[int, int]], timeout_s: float = 10.0) -> dict[int, tuple[int, int]]:
        """One period: RPDO1 (controlword, target) per drive, SYNC, the four TPDO1s back.

        :returns: per drive (statusword, position actual [counts]).
        :raises TimeoutError: the TPDOs did not all come.
        """
        with self._cond:
            count0 = self._tpdo_count
        for node_id, (cw, target) in targets.items():
            self.network.send_message(0x200 + node_id, RPDO_LAYOUT.pack(cw, target))
        self.network.send_message(0x080, b"")
        with self._cond:
            if not self._cond.wait_for(lambda: self._tpdo_count >= count0 + len(DRIVES), timeout_s):
                raise TimeoutError(f"TPDOs of the period: {self._tpdo_count - count0} of {len(DRIVES)} came")
            return dict(self._tpdo)

    def wait_emcy(self, predicate: Callable[[int, bytes], bool], timeout_s: float = 10.0) -> tuple[int, bytes]:
        """The first EMCY (COB-ID, data) matching ``predicate``."""
        with self._cond:
            found: list[tuple[int, bytes]] = []

            def match() -> bool:
                found[:] = [e for e in self.emcy if predicate(*e)]
                return bool(found)

            if not self._cond.wait_for(match, timeout_s):
                raise TimeoutError(f"no matching EMCY; got {self.emcy}")
            return found[0]

    def enable(self, positions: dict[int, int]) -> dict[int, tuple[int, int]]:
        """CiA 402 to Operation enabled with the target at ``positions``; returns the last TPDOs."""
        tp: dict[int, tuple[int, int]] = {}
        for cw in (0x06, 0x07, 0x0F):
            tp = self.cycle({n: (cw, positions[n]) for n in DRIVES})
        tp = self.cycle({n: (0x0F, positions[n]) for n in DRIVES})
        return tp

    def close(self) -> None:
        """Disconnect (the robot, and its hub, may be gone already)."""
        try:
            self.network.disconnect()
        except (can.CanError, OSError) as err:
            logging.getLogger(__name__).debug("master: %s", err)


def counts_of(q_rad: np.ndarray) -> dict[int, int]:
    """Joint angles [rad] as encoder counts per drive node."""
    return {n: round(float(q_rad[n - 1]) / units.RAD_PER_COUNT) for n in DRIVES}


def iter_cycles(master: LockstepMaster, targets: Iterator[dict[int, tuple[int, int]]]) -> list[dict[int, tuple[int, int]]]:
    """Run one :meth:`LockstepMaster.cycle` per item; the TPDOs of each."""
    return [master.cycle(t) for t in targets]


class RobotProcess:
    """``ilcrig robot`` as a child process: its output lines as they come, the announcement parsed.

    :param out: the run folder.
    :param args: more options (``--realtime``, ``--view``, ``--bus``…).
    :param env: environment changes.
    """

    def __init__(self, out: Path, *args: str, env: dict[str, str] | None = None) -> None:
        import queue

        self.out = out
        self.lines: queue.Queue[tuple[str, str]] = queue.Queue()
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "host.cli", "robot", "--out", str(out), *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **(env or {})},
        )
        self._readers = [
            threading.Thread(target=self._read, args=(name, stream), daemon=True)
            for name, stream in (("out", self.proc.stdout), ("err", self.proc.stderr))
        ]
        for t in self._readers:
            t.start()

    def wait(self, timeout_s: float = 120.0) -> int:
        """Its exit code, once it ended and its output is read to the end."""
        code = self.proc.wait(timeout=timeout_s)
        for t in self._readers:
            t.join(timeout=10)
        return code

    def _read(self, name: str, stream: Any) -> None:
        for line in stream:
            (self.stdout if name == "out" else self.stderr).append(line.rstrip("\n"))
            self.lines.put((name, line.rstrip("\n")))

    def wait_line(self, pattern: str, timeout_s: float = 180.0) -> re.Match[str]:
        """The first output line matching ``pattern`` (seen before or arriving now)."""
        import queue

        rx = re.compile(pattern)
        for line in self.stdout + self.stderr:
            m = rx.search(line)
            if m:
                return m
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None and self.lines.empty():
                raise TimeoutError(f"no line matching {pattern!r}; out {self.stdout}, err {self.stderr}")
            try:
                _, line = self.lines.get(timeout=min(left, 1.0))
            except queue.Empty:
                continue
            m = rx.search(line)
            if m:
                return m

    def ready(self, timeout_s: float = 180.0) -> dict[str, Any]:
        """Wait for the announcement; the fieldbus's python-can interface and channel, the pids."""
        self.wait_line(r"Ctrl-C to stop", timeout_s)
        text = "\n".join(self.stdout)
        m = re.search(r"connect: python-can interface=(\S+) channel=(\S+)", text)
        assert m, text
        pids = {name: int(pid) for name, pid in re.findall(r"(hub|plant|drive\d) (\d+)", text)}
        return {"interface": m.group(1), "channel": m.group(2), "pids": pids}

    def stop(self, signum: int = signal.SIGTERM, timeout_s: float = 60.0) -> int:
        """Signal it and wait for its exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signum)
        return self.wait(timeout_s)

    def kill(self) -> None:
        """Make sure it is gone (the test's cleanup)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)


def robot_fault_run(out: Path, victim: str, *, periods_before: int = 100) -> dict[str, Any]:
    """``ilcrig robot`` with a lockstep master holding the enabled robot in CSP; after
    ``periods_before`` periods ``victim`` (``drive1`` … ``drive4``, ``plant``, ``hub``) is killed
    (SIGKILL).  Returns the exit code, the stderr lines, the time from the kill to the fault line
    (``latency_ms``) and to the launcher's exit (``exit_ms``, every process stopped), the processes
    left alive and the session summary."""
    robot = RobotProcess(out)
    stop = threading.Event()
    cycled = threading.Semaphore(0)
    errors: list[BaseException] = []
    try:
        where = robot.ready()
        master = LockstepMaster(interface=where["interface"], channel=where["channel"])

        def hold() -> None:
            try:
                master.configure()
                master.start()
                home = {n: int.from_bytes(master.plant.sdo.upload(0x2451, n), "little", signed=True) for n in DRIVES}
                master.enable(home)
                while not stop.is_set():
                    master.cycle({n: (0x0F, home[n]) for n in DRIVES}, timeout_s=2.0)
                    cycled.release()
            except BaseException as exc:  # noqa: BLE001 - the robot is being killed under it
                errors.append(exc)
                cycled.release()

        thread = threading.Thread(target=hold, daemon=True)
        thread.start()
        for _ in range(periods_before):
            if not cycled.acquire(timeout=120) or errors:
                raise RuntimeError(f"the master did not get going: {errors}")
        pids = where["pids"]
        t_kill = time.monotonic()
        os.kill(pids[victim], signal.SIGKILL)
        robot.wait_line(r"^ilcrig: fault:", timeout_s=120)
        latency_ms = (time.monotonic() - t_kill) * 1e3
        code = robot.proc.wait(timeout=120)
        exit_ms = (time.monotonic() - t_kill) * 1e3
        robot.wait()
        stop.set()
        thread.join(timeout=30)
        master.close()
        summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else None
        return {
            "code": code,
            "stderr": list(robot.stderr),
            "latency_ms": latency_ms,
            "exit_ms": exit_ms,
            "left": [name for name, pid in pids.items() if pid_alive(pid)],
            "pids": pids,
            "summary": summary,
        }
    finally:
        stop.set()
        robot.kill()


#: encoder counts per radian at the joint (bus/units.py)
COUNTS_PER_RAD = 10 * 2**20 / (2 * np.pi)
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "robot_master.py"


def run_example(
    interface: str, channel: str, cwd: Path, timeout_s: float = 600.0, wait_s: float = 5.0, homing_method: int = 37
) -> dict[str, Any]:
    """examples/robot_master.py as a user runs it, against a running robot (``wait_s``: its
    ``--timeout``); its JSON."""
    done = subprocess.run(
        [
            sys.executable,
            str(EXAMPLE),
            "--interface",
            interface,
            "--channel",
            channel,
            "--timeout",
            repr(wait_s),
            "--homing-method",
            str(homing_method),
        ],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=cwd,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def run_example_in_process(tmp: Path, homing_method: int = 37) -> tuple[dict[str, Any], str]:
    """examples/robot_master.py's session against a :class:`VirtualRobot` in this process: its
    result and the digest of the robot's period trace."""
    import importlib.util

    from plant.trace import read_trace, trace_digest

    spec = importlib.util.spec_from_file_location("robot_master_example", EXAMPLE)
    assert spec is not None and spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    tmp.mkdir(parents=True, exist_ok=True)
    trace = tmp / "trace.bin"
    channels = new_channels()
    waiter = LockstepMaster(channels[0])  # on the bus before the nodes boot
    try:
        robot = VirtualRobot(RobotMode.SYNC, trace_path=str(trace), channels=channels)
        try:
            waiter.wait_booted()
            res = example.run("virtual", channels[0], str(DRIVE_EDS_PATH), homing_method=homing_method)
        finally:
            robot.close()
    finally:
        waiter.close()
    return res, trace_digest(read_trace(trace).records)


def check_pick_and_place(res: dict[str, Any]) -> None:
    """What the example's session must show: homing made every drive's position its home offset,
    the robot's own joint counts (it stood at its home pose); the profile-position move and every
    waypoint reached by the drives' TPDOs within 0.005 rad (the gravity sag of the PD position
    loop); the plant's joints equal to the drives' last report and its TCP home; every drive in
    Quick stop active, then Switch on disabled with every brake closed and the robot where it
    stopped; every SYNC the master sent was one period of the robot."""
    from plant.kinematics import inverse_kinematics

    q_home = np.rint(inverse_kinematics(np.array([0.0, 0.0, -0.65, 0.0])) * COUNTS_PER_RAD).astype(int).tolist()
    homing = res["homing"]
    assert homing["homed"] == [True] * 4
    assert homing["offsets_counts"] == q_home == homing["position_counts"]
    assert np.abs(np.array(homing["robot_counts"]) - np.array(q_home)).max() <= 1
    assert res["start_counts"] == homing["robot_counts"]  # the drives saw the robot before homing
    pp = res["profile_position"]
    assert pp["periods"] > 100
    assert (np.abs(np.array(pp["actual_counts"]) - np.array(pp["goal_counts"])) / COUNTS_PER_RAD).max() < 0.005, pp
    for wp in res["waypoints"]:
        err = np.abs(np.array(wp["actual_counts"]) - np.array(wp["target_counts"])) / COUNTS_PER_RAD
        assert err.max() < 0.005, wp
    home = res["waypoints"][-1]
    assert home["waypoint"] == "home" and home["target_counts"] == q_home
    assert np.abs(np.array(res["robot"]["q_counts"]) - np.array(home["actual_counts"])).max() <= 200
    np.testing.assert_allclose(res["robot"]["tcp"][:3], (0.0, 0.0, -0.65), atol=1e-3)
    assert res["robot"]["brakes"] == 0  # torque on: brakes open
    assert res["after_quick_stop"] == ["QUICK STOP ACTIVE"] * 4
    assert res["after_disable"] == ["SWITCH ON DISABLED"] * 4
    stopped = res["robot_after_quick_stop"]
    assert stopped["brakes"] == 0xF
    assert np.abs(np.array(stopped["q_counts"]) - np.array(res["robot"]["q_counts"])).max() <= 200
    assert stopped["periods"] == res["periods_total"]  # one robot period per SYNC of the master
