"""A streaming master sequence, python canopen over any python-can bus, against a running
``ilcrig robot`` (``python tests/streaming_master.py INTERFACE CHANNEL [SEED]``): per drive 1–4 in
PRE-OPERATIONAL TPDO1 = 0x6041 + 0x6064 and RPDO1 = 0x6040 + 0x607A (type 1); NMT start; 30 SYNCs
10 ms apart; per drive 0x6060 = 8, 0x607A = 0x6064, controlword 0x80, 0x06, 0x07, 0x0F by SDO with
one SYNC after each step; then RPDO1 + SYNC every 2–5 ms (a seeded draw) up to 565 SYNCs.  Prints
``SYNCs-sent periods SYNCs-seen overruns state`` as the plant node (0x2450:4, 5, 8, 3) has them
once it has stepped every SYNC (served late, never dropped; tests/test_robot_sync_order.py).
"""

from __future__ import annotations

import random
import struct
import sys
import time

import canopen

from bus.objects import DRIVE_EDS_PATH
from bus.plant_objects import PLANT_EDS_PATH, PlantObj, RobotSub

DRIVES = (1, 2, 3, 4)
SYNCS = 565


def main(interface: str, channel: str, seed: int = 1) -> None:
    rng = random.Random(seed)
    net = canopen.Network()
    net.connect(interface=interface, channel=channel)
    nodes = {n: net.add_node(canopen.BaseNode402(n, str(DRIVE_EDS_PATH))) for n in DRIVES}
    plant = net.add_node(32, str(PLANT_EDS_PATH))
    plant.sdo.RESPONSE_TIMEOUT = 10.0
    sent = 0

    def sync() -> None:
        nonlocal sent
        net.sync.transmit()
        sent += 1

    try:
        for node in nodes.values():
            node.sdo.RESPONSE_TIMEOUT = 10.0
            node.nmt.state = "PRE-OPERATIONAL"
            node.tpdo.read()
            node.rpdo.read()
            for maps, names in (
                (node.tpdo, ("Statusword", "Position actual value")),
                (node.rpdo, ("Controlword", "Target position")),
            ):
                pdo = maps[1]
                pdo.clear()
                for name in names:
                    pdo.add_variable(name)
                pdo.trans_type = 1
                pdo.enabled = True
                pdo.save()
        for node in nodes.values():
            node.nmt.state = "OPERATIONAL"
        for _ in range(30):
            sync()
            time.sleep(0.01)
        for node in nodes.values():
            node.sdo[0x6060].raw = 8
            sync()
            node.sdo[0x607A].raw = node.sdo[0x6064].raw
            sync()
            for cw in (0x80, 0x06, 0x07, 0x0F):
                node.sdo[0x6040].raw = cw
                sync()
        pos = {n: int(node.sdo[0x6064].raw) for n, node in nodes.items()}
        while sent < SYNCS:
            for n in DRIVES:
                net.send_message(0x200 + n, struct.pack("<Hi", 0x0F, pos[n]))
            sync()
            time.sleep(rng.uniform(0.002, 0.005))

        def u32(sub: int) -> int:
            return int.from_bytes(plant.sdo.upload(PlantObj.ROBOT, sub), "little")

        deadline = time.monotonic() + 60.0
        while u32(RobotSub.SYNCS) < sent or u32(RobotSub.PERIODS) < sent:
            if time.monotonic() > deadline:
                break
            time.sleep(0.05)
        figures = (u32(RobotSub.PERIODS), u32(RobotSub.SYNCS), u32(RobotSub.SYNC_OVERRUNS), u32(RobotSub.STATE))
        print(sent, *figures)
    finally:
        net.disconnect()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], *(int(a) for a in sys.argv[3:4]))
