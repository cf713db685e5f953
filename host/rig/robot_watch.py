"""What ``ilcrig robot`` sees on its two channels: boot-ups, SYNCs, EMCYs, the master's RPDO
mappings and set-points, and the robot's periods on the io channel.

This module owns :class:`RobotBusWatch`, the classifier of the launcher's passive channel monitors
(:class:`host.rig.monitor.ChannelMonitor`; frames one by one or as arrays of
:data:`bus.bus_features.FRAME_DTYPE`):

* fieldbus — the nodes' boot-up frames (the robot is announced once all five booted), the SYNC
  frames (COB-ID 0x080), every EMCY (kept with its node, code and time for the session summary),
  and, for the live view, the target position 0x607A a master sends each drive by RPDO: the RPDO
  COB-IDs and mappings start as the drive EDS's defaults and follow the master's expedited SDO
  downloads to 0x1400..0x1403 sub 1 and 0x1600..0x1603 (what ``pdo.save()`` of a CANopen library
  writes);
* io — every period's encoder counts (the robot's joint angles) and torque frames (the drives'
  torques), handed to a listener (the live view, :class:`host.analysis.live_view.RobotLiveView`)
  one period at a time.

It never sends anything.  Counters are read under :attr:`RobotBusWatch.lock`.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from bus import io_frames, units
from bus.bus_features import FRAME_ERR, FRAME_EXT, FRAME_RTR
from bus.objects import DRIVE_EDS_PATH, DRIVE_NODE_IDS
from bus.pdo_objects import PDO_NOT_VALID, RPDO_COMM_BASE, RPDO_MAP_BASE, SYNC_COB_ID_DEFAULT
from bus.plant_objects import DEFAULT_PLANT_NODE_ID, ROBOT_EMCY_FLAG, ROBOT_FAULT_EMCY, RobotFault

logger = logging.getLogger(__name__)

__all__ = ["EmcySeen", "PeriodSample", "RobotBusWatch"]

_TARGET_POSITION = 0x607A
_N = io_frames.N_JOINTS
_ENC_LO = io_frames.ENCODER_COB_BASE
_TRQ_LO = io_frames.TORQUE_COB_BASE
#: the nodes of the robot
ROBOT_NODES: tuple[int, ...] = (*DRIVE_NODE_IDS, DEFAULT_PLANT_NODE_ID)


@dataclass(frozen=True)
class EmcySeen:
    """One EMCY frame on the fieldbus.

    :ivar t_s: when the monitor saw it, s (wall clock, ``time.time()``)
    """

    node: int
    code: int
    register: int
    data: bytes
    t_s: float


def robot_fault_of(emcy: EmcySeen) -> str | None:
    """The robot fault an EMCY of the plant node reports, in words (None: not a robot fault; the
    bytes are :func:`bus.plant_objects.robot_fault_emcy_data`'s: u8 0x80 | fault, u8 joint, u16 period)."""
    if emcy.node != DEFAULT_PLANT_NODE_ID or len(emcy.data) < 4 or not emcy.data[0] & ROBOT_EMCY_FLAG:
        return None
    code = emcy.data[0] & ~ROBOT_EMCY_FLAG
    try:
        fault = RobotFault(code)
    except ValueError:
        return None
    if fault not in ROBOT_FAULT_EMCY:
        return None
    joint, period = emcy.data[1], int.from_bytes(emcy.data[2:4], "little")
    where = f", joint/drive {joint}" if joint else ""
    return f"robot fault {fault.name} (EMCY 0x{emcy.code:04X}){where} in period {period} (mod 2^16)"


@dataclass(frozen=True)
class PeriodSample:
    """One period of the robot on the io channel.

    :ivar period: the period's index as the watch counted them (0 = the first it saw)
    :ivar q_rad: (4,) joint angles the plant sent, rad
    :ivar torque_nm: (4,) the drives' torques for it, N·m
    """

    period: int
    q_rad: np.ndarray
    torque_nm: np.ndarray


class _RpdoMaps:
    """The drives' RPDO COB-IDs and mappings as the master configured them (module docstring)."""

    def __init__(self) -> None:
        import canopen

        self.cob: dict[tuple[int, int], int] = {}
        self.maps: dict[tuple[int, int], list[int]] = {}
        for node in DRIVE_NODE_IDS:
            od = canopen.import_od(str(DRIVE_EDS_PATH), node)
            for k in range(4):
                comm: Any = od[RPDO_COMM_BASE + k]
                mapping: Any = od[RPDO_MAP_BASE + k]
                self.cob[(node, k)] = int(comm[1].default) if isinstance(comm[1].default, int) else PDO_NOT_VALID
                n = int(mapping[0].default or 0)
                self.maps[(node, k)] = [int(mapping[s].default or 0) for s in range(1, n + 1)]
        self.by_cob: dict[int, tuple[int, int, int]] = {}
        self._rebuild()

    def _rebuild(self) -> None:
        """COB-ID → (node, byte offset, byte size) of 0x607A in a valid RPDO."""
        self.by_cob = {}
        for (node, k), cob in self.cob.items():
            if cob & PDO_NOT_VALID:
                continue
            offset = 0
            for entry in self.maps[(node, k)]:
                index, bits = entry >> 16, entry & 0xFF
                if index == _TARGET_POSITION and bits == 32:
                    self.by_cob[cob & 0x7FF] = (node, offset, 4)
                offset += bits // 8

    def on_sdo_download(self, node: int, data: bytes) -> None:
        """An SDO request to ``node``: an expedited download to an RPDO object updates the tables."""
        if len(data) < 8 or data[0] & 0xE3 != 0x23:  # ccs 1 (initiate download), expedited, size given
            return
        index, sub = struct.unpack_from("<HB", data, 1)
        size = 4 - ((data[0] >> 2) & 0x3)
        value = int.from_bytes(data[4 : 4 + size], "little")
        k = index - RPDO_COMM_BASE if RPDO_COMM_BASE <= index < RPDO_COMM_BASE + 4 else index - RPDO_MAP_BASE
        if not 0 <= k < 4 or (node, k) not in self.cob:
            return
        if index < RPDO_MAP_BASE and sub == 1:
            self.cob[(node, k)] = value
        elif index >= RPDO_MAP_BASE:
            entries = self.maps[(node, k)]
            if sub == 0:
                del entries[value:]
            else:
                entries.extend([0] * (sub - len(entries)))
                entries[sub - 1] = value
        else:
            return
        self._rebuild()


class RobotBusWatch:
    """The launcher's view of the robot's channels (see the module docstring).

    :param on_period: called with every :class:`PeriodSample` (in the io monitor's thread), or None.
    :ivar on_targets: called at every SYNC with its index (0 = the first the watch saw: the period it
        starts, when no SYNC overran) and the target positions the drives got by RPDO so far, rad
        (NaN: none yet), in the fieldbus monitor's thread; set by :meth:`follow_targets`
    """

    def __init__(self, on_period: Callable[[PeriodSample], None] | None = None) -> None:
        self.lock = threading.Lock()
        self.booted: set[int] = set()
        self.syncs = 0
        self.emcys: list[EmcySeen] = []
        self.periods = 0
        self.on_period = on_period
        self._booted_event = threading.Event()
        self._rpdo: _RpdoMaps | None = None
        self.on_targets: Callable[[int, np.ndarray], None] | None = None
        self._target = np.full(_N, np.nan)
        self._q_counts = np.zeros(_N, dtype=np.int64)
        self._torque = np.zeros(_N, dtype=np.int64)
        self._have_q = 0
        self._have_tau = 0

    def follow_targets(self, on_targets: Callable[[int, np.ndarray], None]) -> None:
        """Follow the master's RPDO mappings and target positions (:attr:`on_targets`)."""
        self._rpdo = _RpdoMaps()
        self.on_targets = on_targets

    # ------------------------------------------------------------------ waiting

    def wait_booted(self, timeout_s: float) -> bool:
        """True once every node of the robot sent its boot-up frame (False after ``timeout_s``)."""
        return self._booted_event.wait(timeout_s)

    # ------------------------------------------------------------------ fieldbus

    def fieldbus_frame(self, msg: can.Message) -> None:
        """One fieldbus frame (the monitor's per-frame classifier)."""
        if msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
            return
        self._fieldbus(msg.arbitration_id, bytes(msg.data), msg.timestamp or time.time())

    def fieldbus_frames(self, frames: np.ndarray) -> None:
        """Many fieldbus frames (:data:`bus.bus_features.FRAME_DTYPE`, in order)."""
        ids = frames["arbitration_id"]
        flags = frames["flags"]
        ok = (flags & (FRAME_ERR | FRAME_EXT | FRAME_RTR)) == 0
        if self._rpdo is None:  # SYNCs counted at once; the rest one by one
            syncs = int(np.count_nonzero(ok & (ids == SYNC_COB_ID_DEFAULT)))
            if syncs:
                with self.lock:
                    self.syncs += syncs
            rest = np.flatnonzero(ok & (ids != SYNC_COB_ID_DEFAULT))
        else:  # in order: a target belongs to the SYNC after it
            rest = np.flatnonzero(ok)
        for i in rest.tolist():
            row = frames[i]
            self._fieldbus(int(row["arbitration_id"]), bytes(row["data"][: int(row["length"])]), float(row["timestamp"]))

    def _fieldbus(self, cob: int, data: bytes, t_s: float) -> None:
        if cob == SYNC_COB_ID_DEFAULT:
            with self.lock:
                index = self.syncs
                self.syncs += 1
            if self.on_targets is not None and not np.isnan(self._target).all():
                self.on_targets(index, self._target.copy())
            return
        node = cob & 0x7F
        func = cob & 0x780
        if func == 0x700 and node in ROBOT_NODES and data[:1] == b"\x00":
            with self.lock:
                self.booted.add(node)
                if self.booted >= set(ROBOT_NODES):
                    self._booted_event.set()
        elif func == 0x080 and node in ROBOT_NODES and len(data) >= 3:
            code, register = struct.unpack_from("<HB", data)
            with self.lock:
                self.emcys.append(EmcySeen(node, code, register, data[3:8], t_s))
        elif self._rpdo is not None:
            if func == 0x600 and node in DRIVE_NODE_IDS:
                self._rpdo.on_sdo_download(node, data)
            else:
                hit = self._rpdo.by_cob.get(cob)
                if hit is not None:
                    node_id, offset, size = hit
                    if len(data) >= offset + size:
                        (value,) = struct.unpack_from("<i", data, offset)
                        self._target[node_id - 1] = value * units.RAD_PER_COUNT

    # ------------------------------------------------------------------ io

    def io_frame(self, msg: can.Message) -> None:
        """One io frame (the monitor's per-frame classifier)."""
        if msg.is_error_frame:
            return
        self._io(msg.arbitration_id, bytes(msg.data))

    def io_frames(self, frames: np.ndarray) -> None:
        """Many io frames (:data:`bus.bus_features.FRAME_DTYPE`, in order)."""
        if self.on_period is None:
            with self.lock:
                ids = frames["arbitration_id"]
                self.periods += int(np.count_nonzero((ids == _ENC_LO) & ((frames["flags"] & FRAME_ERR) == 0)))
            return
        for row in frames.tolist():
            _, cob, flags, _, length, data = row
            if not flags & FRAME_ERR:
                self._io(cob, bytes(data[:length]))

    def _io(self, cob: int, data: bytes) -> None:
        j = cob - _ENC_LO
        if 0 <= j < _N and len(data) >= 4:
            if j == 0:
                self._emit()
            (self._q_counts[j],) = struct.unpack_from("<i", data)
            self._have_q |= 1 << j
            return
        j = cob - _TRQ_LO
        if 0 <= j < _N and len(data) >= 4:
            (self._torque[j],) = struct.unpack_from("<i", data)
            self._have_tau |= 1 << j
            if self._have_tau == 0xF and self._have_q == 0xF:
                self._emit()

    def _emit(self) -> None:
        """The period whose encoder and torque frames were seen is complete."""
        if self._have_q != 0xF or self._have_tau != 0xF:
            self._have_q = self._have_tau = 0
            return
        self._have_q = self._have_tau = 0
        with self.lock:
            period = self.periods
            self.periods += 1
        if self.on_period is not None:
            sample = PeriodSample(period, self._q_counts * units.RAD_PER_COUNT, self._torque * units.TORQUE_LSB_NM)
            try:
                self.on_period(sample)
            except Exception:  # noqa: BLE001 - the view must never stop the watch
                logger.exception("the live view failed; it stops")
                self.on_period = None

    def info(self) -> dict[str, Any]:
        """What the watch saw, for the session summary."""
        with self.lock:
            return {
                "syncs_on_bus": self.syncs,
                "periods_on_io": self.periods,
                "emcy": [
                    {"node": e.node, "code": f"0x{e.code:04X}", "register": e.register, "data": e.data.hex(), "t": e.t_s}
                    for e in self.emcys
                ],
            }
