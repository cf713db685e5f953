"""The rig's cyclic exchange over SYNC and PDOs (``--ff-transport pdo``): what each drive's PDOs
carry, their COB-IDs and byte layout, the CiA 301 configuration writes, and whether one control
period of these frames fits the fieldbus.

This module owns the one definition both sides use — the host (:mod:`host.rig.bring_up` and
:mod:`host.rig.pdo_stream` with the canopen library's PDO API, :mod:`host.sim.inprocess` with
the same bytes in one process),
the DBC files (:mod:`bus.dbc`) and the tests:

* per control period: one SYNC (COB-ID 0x080, no data), per drive one RPDO (RPDO1,
  0x200 + node id) and one TPDO (TPDO1, 0x180 + node id), both synchronous (transmission type 1);
* RPDO1 in cyclic synchronous position (CSP, the pdo mode's mode): 0x607A target position,
  INTEGER32 counts, then 0x60B2 torque offset, INTEGER16 per thousand of the rated torque 0x6076
  (the learned feed-forward; 1 ‰ = 88.2 mN·m here) — 6 bytes;
  in cyclic synchronous torque (CST): 0x6071 target torque, then 0x60B2, both INTEGER16 ‰;
* TPDO1: 0x6064 position actual, INTEGER32 counts, then 0x6077 torque actual, INTEGER16 ‰ —
  6 bytes.  Little endian, as every CANopen value.

Bus fit (:func:`cyclic_bus_fit`): the frames of one period in classic-CAN bits
(:mod:`bus.busload`, without and with worst-case stuffing) against the bits the bus carries in
one period; the exchange *fits* when the worst case takes at most 100 % of the period.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from bus.busload import DEFAULT_BITRATE_BPS, frame_bits, frame_bits_worst_case
from bus.objects import RATED_TORQUE_MNM, ModeOfOperation, Obj
from bus.pdo_objects import (
    COMM_COB_ID,
    COMM_TRANSMISSION_TYPE,
    PDO_NOT_VALID,
    RPDO_COMM_BASE,
    RPDO_MAP_BASE,
    SYNC_COB_ID_DEFAULT,
    TPDO_COMM_BASE,
    TPDO_MAP_BASE,
    mapping_entry,
)

logger = logging.getLogger(__name__)

#: the feed-forward transports of an experiment: SDO tables before the trial, or PDOs each tick
FF_TRANSPORTS: Final[tuple[str, ...]] = ("table", "pdo")
#: SYNC COB-ID (no data bytes: no SYNC counter)
SYNC_COB_ID: Final[int] = SYNC_COB_ID_DEFAULT
SYNC_BYTES: Final[int] = 0
#: the drive mode of the pdo transport
PDO_MODE: Final[ModeOfOperation] = ModeOfOperation.CSP
#: SYNCs a drive keeps as credits for io ticks not yet run (firmware_model.cyclic_pdo): the next SYNC
#: of a lockstep trial may come before the io tick of the last one.  A drive of a SYNC-stepped robot
#: never has more than one: its frames after a SYNC wait until that SYNC's io tick ran
#: (:data:`SYNC_BACKLOG_MAX`)
SYNC_CREDITS_MAX: Final[int] = 2
#: a SYNC-stepped robot (``ilcrig robot``, docs/robot.md "Time"): the SYNCs that may wait behind the
#: period in progress.  A master faster than the robot is served late: every SYNC is one period, taken
#: in order, the drives' fieldbus frames waiting behind the SYNC whose period is in progress
#: (firmware_model.drive_node); the SYNC that finds this many waiting is a SYNC overrun, a robot fault
#: (EMCY 0x8110 of the plant node) -- and is served all the same, late, like every SYNC before it
SYNC_BACKLOG_MAX: Final[int] = 1024
#: a drive of a SYNC-stepped robot: the fieldbus frames (SYNCs aside) that may wait behind the SYNC
#: whose period is in progress; one more is lost as in a CAN controller's full receive queue (EMCY
#: 0x8110 CAN overrun of the drive).  SYNCs are never lost: a drive steps every SYNC the robot steps
FRAME_BACKLOG_MAX: Final[int] = 16 * SYNC_BACKLOG_MAX
#: PDO number (1-based) used for the cyclic set-points and actuals
RPDO_NUMBER: Final[int] = 1
TPDO_NUMBER: Final[int] = 1
#: transmission type: synchronous, every SYNC
TRANSMISSION_TYPE: Final[int] = 1
#: (index, sub, bits) mapped, in order
CSP_RPDO_MAP: Final[tuple[tuple[int, int, int], ...]] = ((Obj.TARGET_POSITION, 0, 32), (Obj.TORQUE_OFFSET, 0, 16))
CST_RPDO_MAP: Final[tuple[tuple[int, int, int], ...]] = ((Obj.TARGET_TORQUE, 0, 16), (Obj.TORQUE_OFFSET, 0, 16))
TPDO_MAP: Final[tuple[tuple[int, int, int], ...]] = ((Obj.POSITION_ACTUAL, 0, 32), (Obj.TORQUE_ACTUAL, 0, 16))

_CSP_RPDO = struct.Struct("<ih")
_CST_RPDO = struct.Struct("<hh")
_TPDO = struct.Struct("<ih")
INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1


def rpdo_cob_id(node_id: int) -> int:
    """COB-ID of a drive's cyclic RPDO (RPDO1 of the predefined connection set)."""
    return 0x200 + int(node_id)


def tpdo_cob_id(node_id: int) -> int:
    """COB-ID of a drive's cyclic TPDO (TPDO1 of the predefined connection set)."""
    return 0x180 + int(node_id)


def map_bytes(mapping: tuple[tuple[int, int, int], ...]) -> int:
    """Payload bytes of a mapping."""
    return sum(bits for _, _, bits in mapping) // 8


RPDO_BYTES: Final[int] = map_bytes(CSP_RPDO_MAP)
TPDO_BYTES: Final[int] = map_bytes(TPDO_MAP)


def encode_csp_rpdo(target_counts: int, torque_offset_permille: int) -> bytes:
    """RPDO1 payload in CSP: target position [counts], torque offset [‰]."""
    return _CSP_RPDO.pack(int(target_counts), int(torque_offset_permille))


def encode_cst_rpdo(target_torque_permille: int, torque_offset_permille: int) -> bytes:
    """RPDO1 payload in CST: target torque [‰], torque offset [‰]."""
    return _CST_RPDO.pack(int(target_torque_permille), int(torque_offset_permille))


def decode_tpdo(data: bytes) -> tuple[int, int]:
    """TPDO1 payload → (position actual [counts], torque actual [‰])."""
    pos, torque = _TPDO.unpack(bytes(data[: _TPDO.size]))
    return int(pos), int(torque)


def nm_to_permille_array(tau_nm: npt.ArrayLike, rated_torque_mnm: int = RATED_TORQUE_MNM) -> npt.NDArray[np.int16]:
    """Torques [N·m] → INTEGER16 per thousand of the rated torque, nearest (half to even), saturated."""
    x = np.rint(np.asarray(tau_nm, dtype=np.float64) * (1e6 / rated_torque_mnm))
    return np.clip(x, INT16_MIN, INT16_MAX).astype(np.int16)


def permille_to_nm_array(permille: npt.ArrayLike, rated_torque_mnm: int = RATED_TORQUE_MNM) -> npt.NDArray[np.float64]:
    """Per thousand of the rated torque → N·m (exact: 1 ‰ = rated mN·m in µN·m)."""
    return (np.asarray(permille, dtype=np.int64) * rated_torque_mnm * 1e-6).astype(np.float64)


def pdo_config_writes(node_id: int, mode: ModeOfOperation = PDO_MODE) -> list[tuple[int, int, int, int]]:
    """The CiA 301 re-mapping sequence that gives drive ``node_id`` the rig's cyclic PDOs, as
    (index, sub, value, size in bytes) writes in order; to be written in NMT PRE-OPERATIONAL
    (what the canopen library's ``PdoMap.save()`` writes for the same maps)."""
    rmap = CSP_RPDO_MAP if mode == ModeOfOperation.CSP else CST_RPDO_MAP
    out: list[tuple[int, int, int, int]] = []
    for comm, mapping_index, cob, mapping in (
        (RPDO_COMM_BASE + RPDO_NUMBER - 1, RPDO_MAP_BASE + RPDO_NUMBER - 1, rpdo_cob_id(node_id), rmap),
        (TPDO_COMM_BASE + TPDO_NUMBER - 1, TPDO_MAP_BASE + TPDO_NUMBER - 1, tpdo_cob_id(node_id), TPDO_MAP),
    ):
        out.append((comm, COMM_COB_ID, cob | PDO_NOT_VALID, 4))
        out.append((comm, COMM_TRANSMISSION_TYPE, TRANSMISSION_TYPE, 1))
        out.append((mapping_index, 0, 0, 1))
        for sub, (index, isub, bits) in enumerate(mapping, start=1):
            out.append((mapping_index, sub, mapping_entry(index, isub, bits), 4))
        out.append((mapping_index, 0, len(mapping), 1))
        out.append((comm, COMM_COB_ID, cob, 4))
    return out


# ---------------------------------------------------------------------------------------
# bus fit
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BusFit:
    """One control period of SYNC + n_drives RPDOs + n_drives TPDOs on a classic CAN bus.

    :ivar rate_hz: control rate (1/Ts), Hz
    :ivar bitrate_bps: fieldbus bit rate, bit/s
    :ivar frames_per_cycle: frames per period
    :ivar bits_nominal: bits per period without stuffing; ``bits_worst_case`` with worst-case stuffing
    :ivar load_percent_worst_case: worst-case bits / bits available per period × 100
    :ivar fits: worst case ≤ 100 % of the period
    :ivar margin_percent: 100 − worst-case load (negative: missing)
    :ivar max_rate_hz: highest control rate that fits at this bit rate (worst case)
    :ivar min_bitrate_bps: lowest bit rate that fits at this control rate (worst case)
    """

    rate_hz: float
    bitrate_bps: int
    n_drives: int
    rpdo_bytes: int
    tpdo_bytes: int
    frames_per_cycle: int
    bits_nominal: int
    bits_worst_case: int
    load_percent_nominal: float
    load_percent_worst_case: float
    fits: bool
    margin_percent: float
    max_rate_hz: float
    min_bitrate_bps: int

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)

    def message(self) -> str:
        """One line: the figures and the verdict."""
        verdict = (
            f"fits with {self.margin_percent:.1f} % margin" if self.fits else f"does NOT fit ({-self.margin_percent:.1f} % over)"
        )
        return (
            f"SYNC + {self.n_drives} RPDO ({self.rpdo_bytes} B) + {self.n_drives} TPDO ({self.tpdo_bytes} B) "
            f"= {self.bits_nominal}–{self.bits_worst_case} bits per period: at {self.rate_hz:g} Hz and "
            f"{self.bitrate_bps / 1e6:g} Mbit/s {self.load_percent_nominal:.1f}–{self.load_percent_worst_case:.1f} % "
            f"of the bus, {verdict}; worst case fits up to {self.max_rate_hz:.0f} Hz at this bit rate, "
            f"or from {self.min_bitrate_bps / 1e6:.3f} Mbit/s at this rate"
        )


def cyclic_bus_fit(
    period_s: float,
    bitrate_bps: int = DEFAULT_BITRATE_BPS,
    *,
    n_drives: int = 4,
    rpdo_bytes: int = RPDO_BYTES,
    tpdo_bytes: int = TPDO_BYTES,
    sync_bytes: int = SYNC_BYTES,
) -> BusFit:
    """Whether one period of the cyclic exchange fits the bus (11-bit identifiers).

    :raises ValueError: non-positive period or bit rate
    """
    if not period_s > 0 or not bitrate_bps > 0:
        raise ValueError(f"period and bit rate must be > 0, got {period_s} s, {bitrate_bps} bit/s")
    nominal = frame_bits(sync_bytes) + n_drives * (frame_bits(rpdo_bytes) + frame_bits(tpdo_bytes))
    worst = frame_bits_worst_case(sync_bytes) + n_drives * (frame_bits_worst_case(rpdo_bytes) + frame_bits_worst_case(tpdo_bytes))
    budget = bitrate_bps * period_s
    load_worst = 100.0 * worst / budget
    return BusFit(
        rate_hz=1.0 / period_s,
        bitrate_bps=int(bitrate_bps),
        n_drives=n_drives,
        rpdo_bytes=rpdo_bytes,
        tpdo_bytes=tpdo_bytes,
        frames_per_cycle=1 + 2 * n_drives,
        bits_nominal=nominal,
        bits_worst_case=worst,
        load_percent_nominal=100.0 * nominal / budget,
        load_percent_worst_case=load_worst,
        fits=worst <= budget + 1e-9,
        margin_percent=100.0 - load_worst,
        max_rate_hz=bitrate_bps / worst,
        min_bitrate_bps=int(math.ceil(worst / period_s - 1e-9)),
    )
