"""CiA 301 PDO and SYNC object indices, COB-ID bits, transmission types and mapping entries.

This module owns the numbers of the PDO service that the slave side
(:mod:`bus.cia301.pdo`) and the rig's cyclic layout (:mod:`bus.cyclic`) must agree on
(CiA 301 §7.5.2.35–7.5.2.38, docs/canopen-objects.md §6).
"""

from __future__ import annotations

import logging

logger = logging.getLogger(__name__)

#: object index bases of the four PDO parameter ranges
RPDO_COMM_BASE = 0x1400
RPDO_MAP_BASE = 0x1600
TPDO_COMM_BASE = 0x1800
TPDO_MAP_BASE = 0x1A00
#: COB-ID SYNC object (U32; bits 0–10 the identifier, bit 30 = 1 this node produces SYNC)
COB_ID_SYNC_INDEX = 0x1005
#: bit 30 of 0x1005: the node generates SYNC
SYNC_PRODUCER = 1 << 30
#: communication cycle period (U32 µs; 0 = none): a SYNC consumer expects a SYNC this often
COMM_CYCLE_PERIOD_INDEX = 0x1006
#: synchronous counter overflow value (U8; 0 = SYNC without counter, 2..240 = SYNC with a counter
#: byte counting 1..value)
SYNC_COUNTER_OVERFLOW_INDEX = 0x1019
SYNC_COUNTER_MIN = 2
SYNC_COUNTER_MAX = 240
#: default SYNC COB-ID of the predefined connection set
SYNC_COB_ID_DEFAULT = 0x080

#: COB-ID bits of a PDO communication parameter
PDO_NOT_VALID = 1 << 31
PDO_NO_RTR = 1 << 30
PDO_EXTENDED = 1 << 29
COB_ID_MASK_11 = 0x7FF

#: communication parameter sub-indices
COMM_COB_ID = 1
COMM_TRANSMISSION_TYPE = 2
COMM_INHIBIT_TIME = 3  #: TPDO: U16, 100 µs
COMM_EVENT_TIMER = 5  #: TPDO: U16 ms, period of an event-driven TPDO; RPDO: U16 ms, deadline
COMM_SYNC_START = 6  #: TPDO: U8, the SYNC counter value of the first transmission
#: transmission types
TT_SYNC_ACYCLIC = 0
TT_SYNC_MAX = 240
TT_EVENT_MANUFACTURER = 254
TT_EVENT_PROFILE = 255
#: most objects one PDO can map, and its payload limit
MAX_MAPPED = 8
MAX_PDO_BITS = 64

#: CiA 301 restricted CAN identifiers (Table 3), as inclusive ranges
RESTRICTED_CAN_IDS: tuple[tuple[int, int], ...] = (
    (0x000, 0x000),
    (0x001, 0x07F),
    (0x101, 0x180),
    (0x581, 0x5FF),
    (0x601, 0x67F),
    (0x6E0, 0x6FF),
    (0x701, 0x77F),
    (0x780, 0x7FF),
)


def is_restricted_can_id(can_id: int) -> bool:
    """True when ``can_id`` is one of CiA 301's restricted identifiers."""
    return any(lo <= can_id <= hi for lo, hi in RESTRICTED_CAN_IDS)


def mapping_entry(index: int, sub: int, bits: int) -> int:
    """A mapping entry ``index << 16 | sub << 8 | bits``."""
    return (int(index) << 16) | (int(sub) << 8) | int(bits)


def split_entry(entry: int) -> tuple[int, int, int]:
    """(index, sub, bits) of a mapping entry."""
    return (entry >> 16) & 0xFFFF, (entry >> 8) & 0xFF, entry & 0xFF
