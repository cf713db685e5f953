"""CiA 301 PDO communication and mapping parameters of a slave: the objects and the rules of writing them.

This module owns the PDOs of a node as objects of its dictionary (:class:`Pdo`: one RPDO or TPDO
with its run-time state) and :class:`PdoParameters`: the write hooks that check every SDO write
to a PDO parameter against CiA 301 (an :class:`bus.errors.SdoAbort` refuses it) and tell the
run time (:class:`bus.cia301.pdo.PdoEngine`) that its plan is stale.

Objects (described by the node's EDS; k = 0..3 → PDO 1..4)

* communication parameter, sub 1 COB-ID (U32): bit 31 = 1 PDO *not valid*, bit 30 = 1 no RTR
  (TPDO; ignored for RPDO), bit 29 = 1 extended frame (not supported: refused), bits 0–10
  the CAN identifier; sub 2 transmission type (U8): 0 synchronous acyclic, 1–240 synchronous
  (a TPDO every n-th SYNC), 254/255 event driven; 241–253 (reserved, RTR-only) are refused.
  TPDO sub 3 inhibit time (U16, 100 µs) and sub 6 SYNC start value (U8) can change only while
  the PDO is not valid (else 0x06090030); TPDO sub 5 event timer (U16 ms); RPDO sub 5 event
  timer (U16 ms): the RPDO's deadline (CiA 301 §7.5.2.35: deadline monitoring).
* mapping parameter, sub 0 number of mapped objects (0..8), subs 1..8 entries
  ``index << 16 | sub << 8 | bit length``; whole objects only (the bit length must equal the
  object's size), at most 64 bits in total.

Rules (CiA 301 re-mapping procedure; abort codes as CANopenNode answers them)

* the COB-ID of a valid PDO cannot change to another valid COB-ID (invalidate it first) →
  0x06090030; a restricted CAN-ID (CiA 301 Table 3: 0x000, 0x001–0x07F, 0x101–0x180,
  0x581–0x5FF, 0x601–0x67F, 0x6E0–0x6FF, 0x701–0x77F, 0x780–0x7FF) or an extended frame →
  0x06090030;
* the mapping can be written only in NMT PRE-OPERATIONAL (this drive does not support
  re-mapping while operational) → else 0x08000022, only while the PDO is not valid → else
  0x06010000, and an entry (sub 1..8) only while sub 0 is 0 → else 0x06010000;
* an entry naming an object that does not exist → 0x06020000 / 0x06090011; an object that is
  not PDO-mappable in this direction (an RPDO needs a writable object, a TPDO a readable one),
  or a bit length other than the object's size → 0x06040041; sub 0 larger than 8 or the
  entries 1..sub 0 longer than 64 bits → 0x06040042.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from canopen.objectdictionary import ODVariable

from bus.cia301.nmt import NmtState
from bus.cia301.object_store import ObjectStore
from bus.errors import AbortCode, SdoAbort
from bus.pdo_objects import (
    COB_ID_MASK_11,
    COMM_COB_ID,
    COMM_EVENT_TIMER,
    COMM_INHIBIT_TIME,
    COMM_SYNC_START,
    COMM_TRANSMISSION_TYPE,
    MAX_MAPPED,
    MAX_PDO_BITS,
    PDO_EXTENDED,
    PDO_NOT_VALID,
    RPDO_COMM_BASE,
    RPDO_MAP_BASE,
    TPDO_COMM_BASE,
    TPDO_MAP_BASE,
    TT_EVENT_MANUFACTURER,
    TT_EVENT_PROFILE,
    TT_SYNC_MAX,
    is_restricted_can_id,
    split_entry,
)

logger = logging.getLogger(__name__)

__all__ = ["Pdo", "PdoConfig", "PdoParameters", "size_bytes"]

_EVENT = (TT_EVENT_MANUFACTURER, TT_EVENT_PROFILE)


@dataclass(frozen=True)
class PdoConfig:
    """What the communication and mapping parameters of one PDO say now (see :class:`_Plan`)."""

    valid: bool
    can_id: int  # bits 0-10 of the COB-ID
    rtr: bool  # TPDO: a valid TPDO that answers a remote frame (bit 30 = 0)
    transmission_type: int
    inhibit_s: float  # TPDO: sub 3 [s]
    event_ms: int  # sub 5 [ms]
    sync_start: int  # TPDO: sub 6
    nbytes: int  # the mapped bytes
    #: RPDO: (index, sub, first byte, end byte, writer) of each mapped object, in the order they are
    #: written (writer: :meth:`ObjectStore.writer`, None for an object not in the dictionary)
    writes: tuple[tuple[int, int, int, int, Callable[[bytes], None] | None], ...]
    #: TPDO: the payload now (None: the mapping names an object that cannot be read; read each time)
    pack: Callable[[], bytes] | None


@dataclass
class Pdo:
    """One PDO of the node (receive or transmit) and its run-time state."""

    number: int  # 1-based
    comm: int  # communication parameter index
    mapping: int  # mapping parameter index
    receive: bool
    pending: bytes | None = None  # RPDO: synchronous payload waiting for the next SYNC
    deadline_s: float | None = None  # RPDO: when the next one must have come (event timer)
    last_sent: bytes | None = None  # TPDO: payload of the last transmission
    last_tx_s: float | None = None  # TPDO: time of the last transmission
    countdown: int = 0  # TPDO 1..240: SYNCs until it is due (0: load the transmission type)
    waiting_start: bool = False  # TPDO: waits for the SYNC whose counter is its start value
    event_due_s: float | None = None  # TPDO 254/255: when the event timer expires
    held: bool = False  # TPDO 254/255: a change waits for the end of the inhibit time
    cfg: PdoConfig | None = None  # its parameters as the run time reads them (set with the plan)

    def forget(self) -> None:
        """Drop the run-time state (a new start, a new configuration)."""
        self.pending = None
        self.deadline_s = None
        self.last_sent = None
        self.last_tx_s = None
        self.countdown = 0
        self.waiting_start = False
        self.event_due_s = None
        self.held = False


class PdoParameters:
    """The PDO parameters of one node and the checks of their writes (see the module docstring).

    :param store: the node's :class:`bus.cia301.object_store.ObjectStore`; the PDOs are those whose
        communication and mapping parameters it has; the write hooks are installed on it here.
    :param nmt_state: returns the node's NMT state (:class:`bus.cia301.nmt.NmtState` value).
    :param changed: called after every accepted write of a PDO parameter (before the store keeps it).
    """

    def __init__(self, store: ObjectStore, nmt_state: Callable[[], int], changed: Callable[[], None]) -> None:
        self.store = store
        self._nmt_state = nmt_state
        self._changed = changed
        self.rpdos: list[Pdo] = []
        self.tpdos: list[Pdo] = []
        for k in range(512):
            for comm_base, map_base, receive, out in (
                (RPDO_COMM_BASE, RPDO_MAP_BASE, True, self.rpdos),
                (TPDO_COMM_BASE, TPDO_MAP_BASE, False, self.tpdos),
            ):
                if (comm_base + k, COMM_COB_ID) in store.vars and (map_base + k, 0) in store.vars:
                    out.append(Pdo(k + 1, comm_base + k, map_base + k, receive))
        self._install_hooks()

    def _install_hooks(self) -> None:
        """The write hooks of every PDO parameter: the write is checked (an :class:`SdoAbort`
        refuses it), then the plan is dropped (the store keeps the value right after)."""
        w = self.store.write_hooks

        def put(key: tuple[int, int], check: Callable[[int], None]) -> None:
            def hook(value: object) -> None:
                check(int(value))  # type: ignore[call-overload]
                self._changed()

            w[key] = hook

        for pdo in (*self.rpdos, *self.tpdos):
            put((pdo.comm, COMM_COB_ID), lambda v, p=pdo: self._write_cob_id(p, v))  # type: ignore[misc]
            if (pdo.comm, COMM_TRANSMISSION_TYPE) in self.store.vars:
                put((pdo.comm, COMM_TRANSMISSION_TYPE), lambda v, p=pdo: self._write_transmission_type(p, v))  # type: ignore[misc]
            if (pdo.comm, COMM_EVENT_TIMER) in self.store.vars:
                put((pdo.comm, COMM_EVENT_TIMER), lambda v, p=pdo: self._write_event_timer(p))  # type: ignore[misc]
            if not pdo.receive:
                for sub, what in ((COMM_INHIBIT_TIME, "inhibit time"), (COMM_SYNC_START, "SYNC start value")):
                    if (pdo.comm, sub) in self.store.vars:
                        put((pdo.comm, sub), lambda v, p=pdo, t=what: self._write_while_invalid(p, t))  # type: ignore[misc]
            put((pdo.mapping, 0), lambda v, p=pdo: self._write_map_count(p, v))  # type: ignore[misc]
            for sub in range(1, MAX_MAPPED + 1):
                if (pdo.mapping, sub) in self.store.vars:
                    put((pdo.mapping, sub), lambda v, p=pdo, s=sub: self._write_map_entry(p, s, v))  # type: ignore[misc]

    def _value(self, index: int, sub: int) -> int:
        return int(self.store.values[(index, sub)])

    def sub(self, pdo: Pdo, sub: int, default: int = 0) -> int:
        key = (pdo.comm, sub)
        return int(self.store.values[key]) if key in self.store.vars else default

    def cob_id(self, pdo: Pdo) -> int:
        """The raw COB-ID value (U32) of ``pdo``."""
        return self._value(pdo.comm, COMM_COB_ID)

    def valid(self, pdo: Pdo) -> bool:
        return not self.cob_id(pdo) & PDO_NOT_VALID

    def transmission_type(self, pdo: Pdo) -> int:
        return self.sub(pdo, COMM_TRANSMISSION_TYPE, TT_EVENT_PROFILE)

    def mapping(self, pdo: Pdo) -> list[tuple[int, int, int]]:
        """The active mapping (index, sub, bits) of ``pdo`` (entries 1..sub 0)."""
        n = self._value(pdo.mapping, 0)
        return [split_entry(self._value(pdo.mapping, s)) for s in range(1, n + 1)]

    def _write_cob_id(self, pdo: Pdo, value: int) -> None:
        new_valid = not value & PDO_NOT_VALID
        if new_valid:
            if value & PDO_EXTENDED:
                raise SdoAbort(AbortCode.VALUE_RANGE, "29-bit PDO identifiers are not supported")
            can_id = value & COB_ID_MASK_11
            if value & 0x1FFFF800:
                raise SdoAbort(AbortCode.VALUE_RANGE, f"COB-ID 0x{value:08X} has bits above the 11-bit identifier")
            if is_restricted_can_id(can_id):
                raise SdoAbort(AbortCode.VALUE_RANGE, f"CAN-ID 0x{can_id:03X} is restricted (CiA 301 Table 3)")
            if self.valid(pdo) and can_id != self.cob_id(pdo) & COB_ID_MASK_11:
                raise SdoAbort(
                    AbortCode.VALUE_RANGE, f"{self.name(pdo)} is valid: invalidate it (bit 31) before changing its COB-ID"
                )
        pdo.forget()
        logger.debug("%s COB-ID 0x%08X", self.name(pdo), value)

    def _write_transmission_type(self, pdo: Pdo, value: int) -> None:
        if not (value <= TT_SYNC_MAX or value in _EVENT):
            raise SdoAbort(AbortCode.VALUE_RANGE, f"transmission type {value} not supported (0..240, 254, 255)")
        pdo.forget()

    def _write_event_timer(self, pdo: Pdo) -> None:
        pdo.deadline_s = None  # RPDO: armed again by the next reception
        pdo.event_due_s = None  # TPDO: restarted by the next transmission

    def _write_while_invalid(self, pdo: Pdo, what: str) -> None:
        if self.valid(pdo):
            raise SdoAbort(
                AbortCode.VALUE_RANGE, f"{self.name(pdo)} is valid: set bit 31 of its COB-ID before changing its {what}"
            )

    def _check_mapping_writable(self, pdo: Pdo) -> None:
        if int(self._nmt_state()) != NmtState.PRE_OPERATIONAL:
            raise SdoAbort(AbortCode.DEVICE_STATE, "PDO mapping can be changed only in NMT PRE-OPERATIONAL")
        if self.valid(pdo):
            raise SdoAbort(
                AbortCode.UNSUPPORTED_ACCESS, f"{self.name(pdo)} is valid: set bit 31 of its COB-ID before changing the mapping"
            )

    def _write_map_count(self, pdo: Pdo, n: int) -> None:
        self._check_mapping_writable(pdo)
        if n > MAX_MAPPED:
            raise SdoAbort(AbortCode.PDO_LENGTH, f"at most {MAX_MAPPED} objects per PDO, got {n}")
        bits = 0
        for sub in range(1, n + 1):
            entry = self._value(pdo.mapping, sub)
            self._check_entry(pdo, entry)
            bits += entry & 0xFF
        if bits > MAX_PDO_BITS:
            raise SdoAbort(AbortCode.PDO_LENGTH, f"mapping of {bits} bits exceeds {MAX_PDO_BITS}")
        pdo.forget()

    def _write_map_entry(self, pdo: Pdo, sub: int, entry: int) -> None:
        self._check_mapping_writable(pdo)
        if self._value(pdo.mapping, 0) != 0:
            raise SdoAbort(AbortCode.UNSUPPORTED_ACCESS, f"{self.name(pdo)} mapping: set sub-index 0 to 0 before writing entries")
        if entry != 0:
            self._check_entry(pdo, entry)

    def _check_entry(self, pdo: Pdo, entry: int) -> None:
        index, sub, bits = split_entry(entry)
        var = self.store.lookup(index, sub)  # 0x06020000 / 0x06090011
        size_bits = 8 * size_bytes(var)
        if not var.pdo_mappable or size_bits == 0 or bits != size_bits:
            raise SdoAbort(AbortCode.NOT_MAPPABLE, f"0x{index:04X}:{sub} ({bits} bits) cannot be mapped")
        if pdo.receive and var.access_type not in ("rw", "wo", "rww"):
            raise SdoAbort(AbortCode.NOT_MAPPABLE, f"0x{index:04X}:{sub} is not writable: not RPDO-mappable")
        if not pdo.receive and var.access_type == "wo":
            raise SdoAbort(AbortCode.NOT_MAPPABLE, f"0x{index:04X}:{sub} is write-only: not TPDO-mappable")

    @staticmethod
    def name(pdo: Pdo) -> str:
        return f"{'RPDO' if pdo.receive else 'TPDO'}{pdo.number}"


def size_bytes(var: ODVariable) -> int:
    """Size of a numeric object in bytes (0 for DOMAIN / strings)."""
    if var.data_type not in ODVariable.STRUCT_TYPES:
        return 0
    return len(var) // 8
