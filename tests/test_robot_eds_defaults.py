"""The EDS DefaultValues are what a master reads after boot: every object of bus/plant.eds
and bus/drive.eds with a DefaultValue, read as python canopen's ``import_od`` reads the EDS, is
uploaded over SDO from the booted robot (``ilcrig robot``'s nodes in process:
:class:`robot_util.VirtualRobot`, the plant in SYNC-stepped robot mode, drives of a SYNC-stepped
plant) and compared with it.  The only values a node boots with that differ from its EDS are the
documented role defaults: a drive of the robot has :data:`firmware_model.drive.ROBOT_MODE_DEFAULTS`
(the servo drive's cascade), a plant without the robot mode (``ilcrig plant``, ``ilcrig run``)
:data:`bus.plant_objects.ROBOT_OFF_BOOT_VALUES`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODVariable, import_od
from canopen.objectdictionary import datatypes as dt
from robot_util import PLANT_ID, LockstepMaster, VirtualRobot, new_channels

from bus.objects import DRIVE_EDS_PATH
from bus.plant_objects import PLANT_EDS_PATH, ROBOT_OFF_BOOT_VALUES, RobotMode
from firmware_model.drive import ROBOT_MODE_DEFAULTS

DRIVE = 2


def defaults(eds: Path, node_id: int) -> list[ODVariable]:
    """The readable entries with a DefaultValue, as import_od gives them."""
    od = import_od(str(eds), node_id)
    out = []
    for obj in od.values():
        for var in obj.values() if hasattr(obj, "values") else [obj]:
            if var.default is not None and var.access_type != "wo" and var.data_type != dt.DOMAIN:
                out.append(var)
    return sorted(out, key=lambda v: (v.index, v.subindex))


def read_back(node: canopen.RemoteNode, entries: list[ODVariable]) -> dict[tuple[int, int], Any]:
    """Each entry uploaded over SDO, decoded as its EDS type."""
    return {(v.index, v.subindex): v.decode_raw(node.sdo.upload(v.index, v.subindex)) for v in entries}


def differences(entries: list[ODVariable], got: dict[tuple[int, int], Any]) -> dict[tuple[int, int], tuple[Any, Any]]:
    return {
        (v.index, v.subindex): (v.default, got[(v.index, v.subindex)]) for v in entries if got[(v.index, v.subindex)] != v.default
    }


def booted(mode: RobotMode) -> tuple[dict[tuple[int, int], tuple[Any, Any]], dict[tuple[int, int], tuple[Any, Any]]]:
    """(plant, drive) differences between EDS default and SDO upload right after boot."""
    channels = new_channels()
    master = LockstepMaster(channels[0])  # on the bus before the nodes boot
    robot = VirtualRobot(mode, channels=channels)
    try:
        master.wait_booted()
        plant_entries, drive_entries = defaults(PLANT_EDS_PATH, PLANT_ID), defaults(DRIVE_EDS_PATH, DRIVE)
        assert len(plant_entries) > 50 and len(drive_entries) > 200
        plant = differences(plant_entries, read_back(master.plant, plant_entries))
        drive = differences(drive_entries, read_back(master.drives[DRIVE], drive_entries))
    finally:
        master.close()
        robot.close()
    return plant, drive


def test_what_the_robot_boots_with_is_its_eds() -> None:
    plant, drive = booted(RobotMode.SYNC)
    assert plant == {}
    assert drive == {key: (drive_default(key), value) for key, value in ROBOT_MODE_DEFAULTS.items()}


def test_a_plant_without_the_robot_mode_differs_only_by_its_documented_boot_values() -> None:
    plant, _ = booted(RobotMode.OFF)
    assert {key: got for key, (_, got) in plant.items()} == ROBOT_OFF_BOOT_VALUES


def drive_default(key: tuple[int, int]) -> Any:
    od = import_od(str(DRIVE_EDS_PATH), DRIVE)
    return od[key[0]][key[1]].default
