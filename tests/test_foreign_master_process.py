"""The real ``ilcrig drive`` process over the hub, driven by python canopen's ``BaseNode402``: boot-up,
the CiA 402 state machine on SYNC-driven TPDOs, a profile-position move in lockstep with the echo
plant on the hub's io bus (positions exactly the integer profile's), and the loss of the master's
heartbeat (EMCY bytes, torque-free drive), and 0x1010 saving into the role's ``--param-dir``.  The
process is stopped with SIGTERM and must exit 0.
"""

from __future__ import annotations

import signal
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from drive402_util import K_ECHO, reference_profile
from foreign_master import WAIT_S, MasterRig
from hub_util import serving

from bus import fixedpoint as fp
from bus.transports.hub.server import HubServer

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
NODE = 1
TPDO1 = 0x180 + NODE


def test_base_node_402_drives_an_ilcrig_drive_process_over_the_hub(tmp_path: Path) -> None:
    server = HubServer([f"unix:{tmp_path}/hub.sock"])
    with serving(server):
        address = str(server.addresses[0])
        rig = MasterRig(
            {"interface": "ilcrig_hub", "channel": f"{address}#fieldbus"},
            {"interface": "ilcrig_hub", "channel": f"{address}#io"},
            NODE,
        )
        drive = subprocess.Popen(
            [sys.executable, "-m", "host.cli", "drive", "--node", str(NODE), "--bus", "hub", "--hub", address]
            + ["--param-dir", str(tmp_path / "params")],
            cwd=REPO,
            start_new_session=True,
        )
        try:
            assert rig.wait_frame(0x700 + NODE) == b"\x00"  # boot-up
            node = rig.node
            assert node.op_mode == "PROFILED POSITION"
            node.sdo["Gains"]["Kp"].raw = K_ECHO << fp.KP_Q
            node.sdo["Gains"]["Kd"].raw = 0
            node.sdo["Profile velocity"].raw = 100_000
            node.sdo["Profile acceleration"].raw = 5_000_000
            node.sdo["Profile deceleration"].raw = 5_000_000
            rig.count = -500
            rig.plant_tick()
            rig.enable_position_pdos()
            node.rpdo[1]["Target position"].raw = 2_500
            node.controlword = 0x1F
            assert struct.unpack("<Hi", rig.sync_cycle(TPDO1)) == (0x1237, -500)
            node.controlword = 0x0F
            expected = reference_profile(-500, 2_500, 6_553_600, 327_680, 327_680)  # 0x6081/3/4 per 1 ms in Q16
            seen = [struct.unpack("<Hi", rig.sync_cycle(TPDO1)) for _ in range(len(expected) + 1)]
            assert [p for _, p in seen] == [-500, *expected] and seen[-1] == (0x0637, 2_500)
            # the master's heartbeat: consumed, then lost
            node.sdo[0x1016][1].raw = (127 << 16) | round(500 * WAIT_S / 20)
            rig.network.send_message(0x77F, b"\x05")
            rig.sdo_probe()
            assert rig.wait_emcy() == bytes.fromhex("30 81 11 03 7F 00 00 00")
            torque = rig.plant_tick()
            assert torque.torque_units == 0 and torque.status & 0x02  # torque-free, Fault
            assert node.sdo[0x1003][1].raw == 0x8130 and node.sdo["Statusword"].raw & 0x4F == 0x08
            node.sdo[0x1010][1].raw = 0x65766173  # "save": into the folder the role was given
            assert (tmp_path / "params" / f"node{NODE}.json").exists()
        finally:
            rig.close()
            drive.send_signal(signal.SIGTERM)
            try:
                drive.wait(WAIT_S)
            except subprocess.TimeoutExpired:
                drive.kill()
                drive.wait()
        assert drive.returncode == 0
