"""Test harness: a drive driven by a CANopen master nobody here wrote -- python canopen's
``BaseNode402`` on a canopen ``Network`` -- with a stand-in plant on the io channel.

* :class:`MasterRig` connects the master (``network``, ``node``: a ``BaseNode402`` from
  ``bus/drive.eds``), an observer that records every fieldbus frame in arrival order, and the
  echo plant of tests/drive402_util.py on the io channel (:meth:`MasterRig.plant_tick`: encoder
  frame out, torque frame back, the count moves by τ // K).  The buses are python-can buses of any
  interface (``virtual`` in process, ``ilcrig_hub`` to a drive process).
* :func:`configure_pdos` maps the PDOs of any ``BaseNode402`` with the library's PDO API.
* :func:`in_process_drive` serves a real :class:`firmware_model.drive.Drive` on virtual buses in a
  thread of the test (:class:`firmware_model.drive_node.DriveNode`).

Only the canopen library's own API talks to the drive (``node.sdo``, ``node.tpdo``/``node.rpdo``
read/configure/save, ``node.state``, ``node.op_mode``, ``node.homing()``, ``node.controlword``,
``network.sync``, ``node.nmt``).  Waits are for frames and answers; a timeout only bounds a
failure.  BaseNode402's own timeouts are raised (they are wall-clock bounds of its polling loops,
not behaviour) so a busy machine does not fail the tests.
"""

from __future__ import annotations

import contextlib
import itertools
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import canopen
from canopen.profiles.p402 import BaseNode402
from clock_util import SDO_RESPONSE_S, wait_for
from drive402_util import K_ECHO

from bus import io_frames
from bus.objects import DRIVE_EDS_PATH
from bus.units import timeout_scale
from firmware_model.drive import Drive
from firmware_model.drive_node import DriveNode

#: bounds of a failure [s] (× ILCRIG_TIMEOUT_SCALE)
WAIT_S = 20.0 * timeout_scale()
_counter = itertools.count()


def configure_pdos(node: BaseNode402, tpdos: dict[int, tuple[list[str], int]], rpdos: dict[int, tuple[list[str], int]]) -> None:
    """Map PDOs of ``node`` with the library's PDO API in PRE-OPERATIONAL: number → (object names,
    transmission type); the others are left as they are."""
    node.nmt.state = "PRE-OPERATIONAL"
    node.tpdo.read()
    node.rpdo.read()
    for maps, config in ((node.tpdo, tpdos), (node.rpdo, rpdos)):
        for number, (names, tt) in config.items():
            pdo = maps[number]
            pdo.clear()
            for name in names:
                pdo.add_variable(name)
            pdo.trans_type = tt
            pdo.enabled = True
            pdo.save()
    node.setup_402_state_machine(read_pdos=False)


class MasterRig:
    """The master, the observer and the stand-in plant (see the module docstring).

    :param fieldbus: keyword arguments of ``can.Bus`` for the fieldbus.
    :param io: keyword arguments of ``can.Bus`` for the io channel.
    :param node_id: the drive's node id (joint node_id − 1).
    """

    def __init__(self, fieldbus: dict[str, Any], io: dict[str, Any], node_id: int = 1) -> None:
        self.node_id = node_id
        self.joint = node_id - 1
        self.observer = can.Bus(**fieldbus)
        self.plant = can.Bus(**io)
        self.plant.set_filters([{"can_id": io_frames.torque_cob_id(self.joint), "can_mask": 0x7FF, "extended": False}])
        self.network = canopen.Network()
        self.network.connect(**fieldbus)
        self.node = BaseNode402(node_id, str(DRIVE_EDS_PATH))
        self.network.add_node(self.node)
        node = self.node
        node.sdo.RESPONSE_TIMEOUT = SDO_RESPONSE_S
        node.TIMEOUT_SWITCH_STATE_FINAL = WAIT_S
        node.TIMEOUT_SWITCH_STATE_SINGLE = WAIT_S / 4
        node.TIMEOUT_SWITCH_OP_MODE = WAIT_S / 4
        node.TIMEOUT_CHECK_TPDO = WAIT_S / 4
        self.emcy: queue.Queue[bytes] = queue.Queue()
        self.network.subscribe(0x80 + node_id, lambda _cob, data, _t: self.emcy.put(bytes(data)))
        self.count = 0
        self.tick = 0

    def close(self) -> None:
        self.network.sync.stop()
        self.network.disconnect()
        self.observer.shutdown()
        self.plant.shutdown()

    # ------------------------------------------------------------------ the bus

    def frames(self) -> list[tuple[int, bytes]]:
        """Every fieldbus frame the observer has now (identifier, data), in order."""
        out = []
        while (msg := self.observer.recv(timeout=0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out

    def wait_frame(self, cob_id: int, seen: list[tuple[int, bytes]] | None = None) -> bytes:
        """The next fieldbus frame with ``cob_id``; the frames up to it go to ``seen`` (if given)."""
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            msg = self.observer.recv(timeout=0.5)
            if msg is None or msg.is_remote_frame:
                continue
            if seen is not None:
                seen.append((msg.arbitration_id, bytes(msg.data)))
            if msg.arbitration_id == cob_id:
                return bytes(msg.data)
        raise AssertionError(f"no frame 0x{cob_id:03X} within {WAIT_S:g} s")

    def wait_emcy(self) -> bytes:
        return self.emcy.get(timeout=WAIT_S)

    def forget_emcy(self) -> None:
        """Drop the EMCY frames received so far (e.g. of a watchdog a stalled sender tripped
        early), so :meth:`wait_emcy` gets the next one."""
        while not self.emcy.empty():
            self.emcy.get_nowait()

    def sync_cycle(self, tpdo_cob: int, plant: bool = True) -> bytes:
        """One control cycle in lockstep: SYNC, the TPDO it makes due (sampled at the SYNC: the
        latest completed cycle), then the plant's io tick."""
        self.network.sync.transmit()
        data = self.wait_frame(tpdo_cob)
        if plant:
            self.plant_tick()
        return data

    # ------------------------------------------------------------------ the plant

    def plant_tick(self) -> io_frames.TorqueFrame:
        """One io tick of the echo plant: the encoder frame, the drive's torque frame; the count
        moves by τ // K."""
        self.plant.send(io_frames.encode_encoder(self.joint, self.tick & io_frames.TICK_MASK, self.count))
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            msg = self.plant.recv(timeout=0.5)
            if msg is not None and msg.arbitration_id == io_frames.torque_cob_id(self.joint):
                torque = io_frames.decode_torque(msg)
                self.tick += 1
                self.count += torque.torque_units // K_ECHO
                return torque
        raise AssertionError(f"no torque frame for io tick {self.tick}")

    # ------------------------------------------------------------------ helpers on the master's API

    def configure_pdos(self, tpdos: dict[int, tuple[list[str], int]], rpdos: dict[int, tuple[list[str], int]]) -> None:
        """Map the drive's PDOs (:func:`configure_pdos`)."""
        configure_pdos(self.node, tpdos, rpdos)

    def enable_position_pdos(self) -> None:
        """TPDO1 (statusword, position actual value) on every SYNC, RPDO1 (controlword, target
        position) event driven; OPERATIONAL, OPERATION ENABLED under a 10 ms SYNC, then the SYNC
        stopped and every frame so far forgotten (:meth:`quiesce`)."""
        node = self.node
        self.configure_pdos({1: (["Statusword", "Position actual value"], 1)}, {1: (["Controlword", "Target position"], 255)})
        node.nmt.state = "OPERATIONAL"
        self.network.sync.start(0.01)
        node.state = "OPERATION ENABLED"
        self.network.sync.stop()
        self.quiesce()

    def sdo_probe(self) -> None:
        """An SDO round trip: every frame the master sent before it has been handled by the drive."""
        self.node.sdo.upload(0x1000, 0)

    def quiesce(self) -> None:
        """An SDO round trip, then forget every fieldbus frame so far: the drive's frames sent
        before its answer are all in, so the next frame read is a new one."""
        self.sdo_probe()
        self.frames()


def wait_until(predicate: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    """:func:`clock_util.wait_for`, by default for :data:`WAIT_S`."""
    return wait_for(predicate, timeout_s)


@contextlib.contextmanager
def in_process_drive(node_id: int = 1, **drive_kwargs: Any) -> Iterator[MasterRig]:
    """A real Drive served by a DriveNode in a thread on virtual buses, and the MasterRig on the
    same buses; everything is shut down on the way out."""
    k = next(_counter)
    fb_channel, io_channel = f"fm-fb-{k}", f"fm-io-{k}"
    fb = can.Bus(interface="virtual", channel=fb_channel)
    io = can.Bus(interface="virtual", channel=io_channel)
    drive = Drive(node_id, **drive_kwargs)
    runtime = DriveNode(drive, fb, io)
    stop = threading.Event()
    thread = threading.Thread(target=runtime.run, args=(stop,), daemon=True)
    thread.start()
    rig = MasterRig({"interface": "virtual", "channel": fb_channel}, {"interface": "virtual", "channel": io_channel}, node_id)
    try:
        yield rig
    finally:
        rig.close()
        stop.set()
        thread.join(10)
        fb.shutdown()
        io.shutdown()
    assert not thread.is_alive()
