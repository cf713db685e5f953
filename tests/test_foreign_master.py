"""A master nobody here wrote -- python canopen's ``BaseNode402`` -- drives the real drive firmware
(``DriveNode`` in a thread) over python-can virtual buses, with the echo plant on the io channel
(tests/foreign_master.py).  Checked: bytes on the bus, TPDO contents after N SYNCs, EMCY bytes,
the statusword after each step, positions after profile-position moves computed exactly from the
integer profile, homing, and the faults a master causes (heartbeat lost, RPDOs stopping, SYNC
stopping, NMT STOP mid-motion).
"""

from __future__ import annotations

import struct
import threading
from typing import Any

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402, State402
from drive402_util import K_ECHO, reference_profile
from foreign_master import WAIT_S, MasterRig, configure_pdos, in_process_drive, wait_until
from robot_util import DRIVES, PLANT_ID, VirtualRobot, new_channels

from bus import fixedpoint as fp
from bus.objects import DRIVE_EDS_PATH
from bus.plant_objects import RobotMode
from bus.units import timeout_scale

NODE = 1
TPDO1, TPDO2 = 0x180 + NODE, 0x280 + NODE
#: the slowest foreign master timer used here [ms], × ILCRIG_TIMEOUT_SCALE
SLOW_MS = round(400 * timeout_scale())


def echo_gains(rig: MasterRig) -> None:
    rig.node.sdo["Gains"]["Kp"].raw = K_ECHO << fp.KP_Q
    rig.node.sdo["Gains"]["Kd"].raw = 0


def test_base_node_402_walks_the_state_machine_and_the_modes_on_sync_tpdos() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        assert node.op_mode == "PROFILED POSITION"  # the mode the drive boots in (SDO)
        assert node.sdo["Supported drive modes"].raw == 0x000103A1
        rig.configure_pdos(
            {1: (["Statusword", "Modes of operation display", "Position actual value"], 1)},
            {1: (["Controlword", "Target position"], 255)},
        )
        node.sdo["Quick stop option code"].raw = 6  # stay in Quick stop active
        node.nmt.state = "OPERATIONAL"
        rig.network.sync.start(0.01)  # the TPDO with the statusword comes on every SYNC
        node.state = "OPERATION ENABLED"
        assert node.statusword & 0x6F == 0x27 and node.is_faulted() is False
        for mode in ("CYCLIC SYNCHRONOUS POSITION", "CYCLIC SYNCHRONOUS VELOCITY", "CYCLIC SYNCHRONOUS TORQUE", "HOMING"):
            node.op_mode = mode
            assert node.op_mode == mode  # from the TPDO (0x6061 mapped)
        node.op_mode = "PROFILED POSITION"
        with pytest.raises(TypeError, match="not suppported"):
            node.op_mode = "PROFILED VELOCITY"  # not in 0x6502
        node.state = "QUICK STOP ACTIVE"
        assert node.statusword & 0x6F == 0x07
        node.state = "OPERATION ENABLED"  # transition 16, allowed by 0x605A = 6
        node.state = "SWITCH ON DISABLED"
        assert node.statusword & 0x4F == 0x40
        rig.network.sync.stop()


def test_tpdos_after_n_syncs_without_a_plant() -> None:
    """30 SYNCs: TPDO1 (type 1) after every one, TPDO2 (type 4) after every 4th, each with the
    values of the moment; nothing else."""
    with in_process_drive(NODE) as rig:
        rig.count = 4242
        rig.plant_tick()  # torque off: the drive reads its encoder once
        rig.configure_pdos({1: (["Statusword", "Position actual value"], 1), 2: (["Statusword"], 4)}, {})
        rig.node.nmt.state = "OPERATIONAL"
        rig.sdo_probe()
        rig.frames()
        seen: list[tuple[int, bytes]] = []
        for _ in range(30):
            rig.network.sync.transmit()
            rig.wait_frame(TPDO1, seen)
        rig.sdo_probe()  # every TPDO of the 30 SYNCs is on the bus before its answer
        seen.extend(rig.frames())
        tpdos = [(cob, data) for cob, data in seen if cob in (TPDO1, TPDO2)]
        tpdo1, tpdo2 = (TPDO1, struct.pack("<Hi", 0x0240, 4242)), (TPDO2, struct.pack("<H", 0x0240))
        assert tpdos == [f for n in range(1, 31) for f in [tpdo1, *([tpdo2] if n % 4 == 0 else [])]]
        assert len(tpdos) == 30 + 7


def test_profile_position_moves_exactly_along_the_integer_profile() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        echo_gains(rig)
        node.sdo["Profile velocity"].raw = 200_000
        node.sdo["Profile acceleration"].raw = 4_000_000
        node.sdo["Profile deceleration"].raw = 2_000_000
        rig.count = 1000
        rig.plant_tick()
        rig.enable_position_pdos()
        node.rpdo[1]["Target position"].raw = 31_000
        node.controlword = 0x1F  # new set-point (RPDO1: controlword and target position)
        first = rig.sync_cycle(TPDO1)
        assert struct.unpack("<Hi", first) == (0x1237, 1000)  # set-point acknowledged, not reached
        node.controlword = 0x0F
        expected = reference_profile(1000, 31_000, 13_107_200, 262_144, 131_072)  # 0x6081/3/4 per 1 ms in Q16
        seen = [struct.unpack("<Hi", rig.sync_cycle(TPDO1)) for _ in range(len(expected) + 1)]
        # each SYNC's TPDO: the latest completed cycle's position, the demand of the cycle before it
        assert [p for _, p in seen] == [1000, *expected]
        assert seen[0][0] & 0x1400 == 0  # acknowledge back to 0, moving
        assert seen[-1] == (0x0637, 31_000)  # target reached
        assert rig.plant_tick().torque_units == 0 and rig.count == 31_000


def test_base_node_402_homing_on_the_current_position() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        echo_gains(rig)
        rig.count = 777
        rig.plant_tick()
        node.sdo["Homing method"].raw = 37
        node.sdo["Home offset"].raw = 1234
        rig.configure_pdos({1: (["Statusword"], 1)}, {1: (["Controlword"], 255)})
        node.nmt.state = "OPERATIONAL"
        rig.network.sync.start(0.01)
        assert node.homing(timeout=60) is True
        rig.network.sync.stop()
        assert node.sdo["Position actual value"].raw == 1234
        assert rig.plant_tick().torque_units == 0  # the drive holds where it is: encoder 777 is 1234 now
        assert node.sdo["Position actual value"].raw == 1234


def enabled_over_sdo(rig: MasterRig) -> None:
    """NMT OPERATIONAL and Operation enabled (the statusword over SDO: no TPDO mapped)."""
    echo_gains(rig)
    rig.plant_tick()
    rig.node.nmt.state = "OPERATIONAL"
    rig.node.state = "OPERATION ENABLED"
    assert rig.plant_tick().status & 0x01  # ENABLED: torque applied


def torque_free(rig: MasterRig, code: int) -> None:
    """After the fault: torque off on the io channel, the error in 0x1003:1 and 0x603F, the
    statusword Fault (the drive is PRE-OPERATIONAL again by 0x1029:1 = 0 or by the test)."""
    torque = rig.plant_tick()
    assert torque.torque_units == 0 and not torque.status & 0x01 and torque.status & 0x02
    node = rig.node
    assert node.sdo[0x1003][1].raw == code and node.sdo["Error code"].raw == code
    assert node.statusword & 0x4F == 0x08  # Fault (statusword by SDO)


def test_heartbeat_of_the_master_lost() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        node.sdo[0x1016][1].raw = (127 << 16) | SLOW_MS
        rig.network.send_message(0x77F, b"\x05")  # arms the consumer...
        rig.sdo_probe()  # ...before this answer
        task = rig.network.send_periodic(0x77F, b"\x05", 0.02)
        enabled_over_sdo(rig)
        task.stop()
        rig.forget_emcy()
        assert rig.wait_emcy() == bytes.fromhex("30 81 11 03 7F 00 00 00")  # 0x8130, cause 3, node 127
        torque_free(rig, 0x8130)


def test_rpdos_stopping() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        rig.configure_pdos({}, {1: (["Controlword"], 255)})
        node.sdo[0x1400][5].raw = SLOW_MS  # the RPDO's deadline
        echo_gains(rig)
        rig.plant_tick()
        node.nmt.state = "OPERATIONAL"
        rpdo = node.rpdo[1]
        for cw in (0x06, 0x07, 0x0F):
            rpdo["Controlword"].raw = cw
            rpdo.transmit()
        rpdo.start(0.02)  # the master keeps sending it
        assert wait_until(lambda: node.sdo["Statusword"].raw & 0x6F == 0x27)
        rpdo.stop()
        rig.forget_emcy()
        assert rig.wait_emcy() == bytes.fromhex("50 82 11 05 01 00 00 00")  # 0x8250, cause 5, RPDO1
        torque_free(rig, 0x8250)


def test_sync_stopping() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        node.sdo["Communication cycle period"].raw = SLOW_MS * 1000  # µs: lost after 1.5 periods
        enabled_over_sdo(rig)
        rig.network.sync.start(0.01)
        rig.network.sync.transmit()
        rig.sdo_probe()
        rig.network.sync.stop()
        rig.forget_emcy()
        assert rig.wait_emcy() == bytes.fromhex("00 81 11 06 00 00 00 00")  # 0x8100, cause 6
        torque_free(rig, 0x8100)


def test_nmt_stop_mid_motion_then_start_brings_no_torque_back() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        node.sdo["Producer heartbeat time"].raw = 20
        enabled_over_sdo(rig)
        node.sdo["Target position"].raw = 50_000
        node.controlword = 0x1F
        for _ in range(20):
            assert rig.plant_tick().status & 0x01  # moving
        node.nmt.state = "STOPPED"
        assert wait_until(lambda: rig.plant_tick().torque_units == 0)  # at the next tick after the STOP
        node.nmt.wait_for_heartbeat(timeout=WAIT_S)
        assert wait_until(lambda: node.nmt.state == "STOPPED")
        assert rig.emcy.empty()  # no EMCY in STOPPED
        node.nmt.state = "PRE-OPERATIONAL"
        torque_free(rig, 0x8100)
        node.nmt.state = "OPERATIONAL"
        rig.sdo_probe()
        assert rig.plant_tick().torque_units == 0 and node.statusword & 0x4F == 0x08


def test_rtr_and_event_tpdo() -> None:
    with in_process_drive(NODE) as rig:
        node = rig.node
        rig.configure_pdos({2: (["Statusword"], 255)}, {})
        node.tpdo[2].event_timer = 0
        node.nmt.state = "OPERATIONAL"
        assert rig.wait_frame(TPDO2) == struct.pack("<H", 0x0240)  # sent when OPERATIONAL starts
        node.sdo["Controlword"].raw = 0x06
        assert rig.wait_frame(TPDO2) == struct.pack("<H", 0x0231)  # on change
        node.tpdo[2].remote_request()
        assert node.tpdo[2].wait_for_reception(timeout=20) is not None
        assert node.tpdo[2]["Statusword"].raw == 0x0231


# ------------------------------------------------------------------ quick stop seen by BaseNode402


def _quick_stop_master(channel: str) -> tuple[canopen.Network, BaseNode402]:
    """BaseNode402 for drive 1 of a robot on ``channel``."""
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    node = BaseNode402(NODE, str(DRIVE_EDS_PATH))
    node.sdo.RESPONSE_TIMEOUT = 5.0 * timeout_scale()
    node.TIMEOUT_SWITCH_STATE_FINAL = WAIT_S
    node.TIMEOUT_SWITCH_STATE_SINGLE = node.TIMEOUT_SWITCH_OP_MODE = node.TIMEOUT_CHECK_TPDO = WAIT_S / 4
    network.add_node(node)
    return network, node


class _Tpdos:
    """(state, position actual) of every TPDO1 (statusword, position actual) of a BaseNode402, in order."""

    def __init__(self, node: BaseNode402) -> None:
        self.seen: list[tuple[str, int]] = []
        self._cond = threading.Condition()
        node.tpdo[1].add_callback(self._on_tpdo)

    def _on_tpdo(self, pdo: Any) -> None:
        statusword, position = int(pdo["Statusword"].raw), int(pdo["Position actual value"].raw)
        state = next((name for name, (mask, bits) in State402.SW_MASK.items() if statusword & mask == bits), "UNKNOWN")
        with self._cond:
            self.seen.append((state, position))
            self._cond.notify_all()

    def until(self, state: str, since: int) -> list[tuple[str, int]]:
        """The TPDOs from number ``since`` on, up to the first in ``state`` (included)."""

        def found() -> int | None:
            return next((k for k in range(since, len(self.seen)) if self.seen[k][0] == state), None)

        with self._cond:
            assert self._cond.wait_for(lambda: found() is not None, WAIT_S), self.seen[since:][-20:]
            end = found()
            assert end is not None
            return self.seen[since : end + 1]

    def __len__(self) -> int:
        with self._cond:
            return len(self.seen)


class _SteppedSync(threading.Thread):
    """The master's SYNC producer in lockstep with the robot: a SYNC, then the TPDO it brings, then
    the next SYNC (the robot never falls behind the producer, however busy the machine is)."""

    def __init__(self, network: canopen.Network, tpdos: _Tpdos) -> None:
        super().__init__(name="stepped-sync", daemon=True)
        self._network, self._tpdos = network, tpdos
        self._halt = threading.Event()
        self.error: str | None = None

    def run(self) -> None:
        tp = self._tpdos
        while not self._halt.is_set():
            with tp._cond:
                n = len(tp.seen)
            self._network.send_message(0x80, b"")
            with tp._cond:
                if not tp._cond.wait_for(lambda n=n: len(tp.seen) > n or self._halt.is_set(), WAIT_S):
                    self.error = f"no TPDO within {WAIT_S} s of SYNC {n + 1}"
                    return

    def stop(self) -> None:
        self._halt.set()
        with self._tpdos._cond:
            self._tpdos._cond.notify_all()
        self.join(WAIT_S)
        assert not self.is_alive()


def test_base_node_402_sees_quick_stop_active_on_the_sync_stepped_robot_at_standstill_and_moving() -> None:
    """``node.state = "QUICK STOP ACTIVE"`` with 0x605A = 2 on a drive of the SYNC-stepped robot (a
    TPDO carries the control cycle of its SYNC; the master's SYNC producer runs): the state is
    entered and seen, and the quick stop ends in Switch on disabled by itself; from standstill the
    ramp takes one control cycle, moving the drive goes on during the ramp."""
    fb_channel, io_channel = new_channels()
    network, node = _quick_stop_master(fb_channel)
    booted: set[int] = set()
    cond = threading.Condition()

    def boot_up(cob: int, data: bytearray, _t: float) -> None:
        if data[:1] == b"\x00":
            with cond:
                booted.add(cob - 0x700)
                cond.notify_all()

    for node_id in (*DRIVES, PLANT_ID):
        network.subscribe(0x700 + node_id, boot_up)
    try:
        robot = VirtualRobot(RobotMode.SYNC, channels=(fb_channel, io_channel))
        stepper: _SteppedSync | None = None
        try:
            with cond:  # the plant boots once its model is ready to step
                assert cond.wait_for(lambda: booted >= {*DRIVES, PLANT_ID}, WAIT_S), booted
            configure_pdos(node, {1: (["Statusword", "Position actual value"], 1)}, {1: (["Controlword"], 255)})
            tpdos = _Tpdos(node)
            node.sdo["Quick stop option code"].raw = 2
            node.sdo["Profile velocity"].raw = 400_000  # counts/s
            node.sdo["Profile acceleration"].raw = 4_000_000  # counts/s²
            node.sdo["Quick stop deceleration"].raw = 2_000_000  # counts/s²: 200 ms from 400 000 counts/s
            node.nmt.state = "OPERATIONAL"
            stepper = _SteppedSync(network, tpdos)  # each SYNC is one control period of the robot
            stepper.start()

            # at standstill
            node.state = "OPERATION ENABLED"
            since = len(tpdos)
            node.state = "QUICK STOP ACTIVE"  # returns once a TPDO says so
            states = [state for state, _ in tpdos.until("SWITCH ON DISABLED", since)]
            first = states.index("QUICK STOP ACTIVE")
            assert set(states[:first]) <= {"OPERATION ENABLED"}
            # the ramp's control cycle; the controlword's RPDO comes between two SYNCs, and one that
            # reaches the drive after the next SYNC's period began acts one period later
            assert states[first:-1] in (["QUICK STOP ACTIVE"], ["QUICK STOP ACTIVE"] * 2), stepper.error

            # moving: a profile-position move, stopped on the way
            node.state = "OPERATION ENABLED"
            start = tpdos.until("OPERATION ENABLED", len(tpdos))[-1][1]
            node.sdo["Target position"].raw = start + 1_000_000
            node.controlword = 0x1F  # new set-point
            assert wait_until(lambda: bool(node.check_statusword() & 0x1000))  # set-point acknowledged
            node.controlword = 0x0F
            assert wait_until(lambda: tpdos.seen[-1][1] > start + 20_000)
            since = len(tpdos)
            node.state = "QUICK STOP ACTIVE"
            seen = tpdos.until("SWITCH ON DISABLED", since - 1)  # from the last TPDO before the command
            first = [state for state, _ in seen].index("QUICK STOP ACTIVE")
            assert first >= 1 and {state for state, _ in seen[:first]} == {"OPERATION ENABLED"}
            ramp = seen[first:-1]
            assert {state for state, _ in ramp} == {"QUICK STOP ACTIVE"} and len(ramp) >= 20  # about 200 cycles
            positions = [position for _, position in seen[first - 1 : -1]]  # the command's period, the ramp
            steps = [b - a for a, b in zip(positions, positions[1:])]
            assert steps[0] > 100 and positions[-1] - positions[0] > 5_000  # it went on while decelerating
            assert abs(steps[-1]) < steps[0] // 10 and positions[-1] < start + 1_000_000  # stopped short of the target
            assert stepper.error is None, stepper.error
        finally:
            if stepper is not None:
                stepper.stop()
            robot.close()
    finally:
        network.disconnect()
