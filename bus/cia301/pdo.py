"""CiA 301 process data objects (PDO) and SYNC consumption of a slave, on its object store.

This module owns the slave side of the PDO service: the communication parameters
(RPDO 0x1400+k, TPDO 0x1800+k) and mapping parameters (RPDO 0x1600+k, TPDO 0x1A00+k) as
CiA 301 §7.5.2.35–7.5.2.38 defines them, their validation when written by SDO, packing and
unpacking of PDO payloads by the mapping, and the SYNC consumer (COB-ID object 0x1005).
It knows nothing about CAN frames or the application: :class:`PdoEngine` is given received
PDO payloads and SYNC events and hands back the TPDO payloads due; the node runtime
(``firmware_model.drive_node``) moves the frames, the application (``firmware_model.cyclic_pdo``)
decides when a cycle's TPDOs are due.

Objects (described by the node's EDS; k = 0..3 → PDO 1..4)

* communication parameter, sub 1 COB-ID (U32): bit 31 = 1 PDO *not valid*, bit 30 = 1 no RTR
  (TPDO; ignored for RPDO), bit 29 = 1 extended frame (not supported: refused), bits 0–10
  the CAN identifier; sub 2 transmission type (U8): 0 synchronous acyclic, 1–240 synchronous
  (a TPDO every n-th SYNC), 254/255 event driven; 241–253 (reserved, RTR-only) are refused.
  TPDO sub 3 inhibit time (100 µs), sub 5 event timer (ms) and sub 6 SYNC start value are
  stored but not applied.
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

Run time (only in NMT OPERATIONAL, as CiA 301 requires)

* a received synchronous RPDO (type 0..240) is buffered and written to its objects at the
  next SYNC; an event-driven RPDO (254/255) is written at once.  A payload shorter than the
  mapping is not processed (CiA 301: EMCY 0x8210; counted in :attr:`PdoEngine.length_errors`).
* the writes go through the object store with its usual checks and hooks, so an RPDO has
  exactly the effect of the same SDO downloads;
* :meth:`PdoEngine.collect_tpdos` is called by the application when a cycle's sample exists:
  synchronous TPDOs of type n are due once per n SYNCs, type 0 when the mapped data changed
  since the last transmission; event-driven TPDOs (254/255) whenever the data changed.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass

from canopen.objectdictionary import ODVariable

from bus.cia301.nmt import NmtState
from bus.cia301.object_store import ObjectStore
from bus.errors import AbortCode, SdoAbort
from bus.pdo_objects import (  # noqa: F401 - re-exported
    COB_ID_MASK_11,
    COB_ID_SYNC_INDEX,
    COMM_COB_ID,
    COMM_TRANSMISSION_TYPE,
    MAX_MAPPED,
    MAX_PDO_BITS,
    PDO_EXTENDED,
    PDO_NO_RTR,
    PDO_NOT_VALID,
    RESTRICTED_CAN_IDS,
    RPDO_COMM_BASE,
    RPDO_MAP_BASE,
    SYNC_COB_ID_DEFAULT,
    TPDO_COMM_BASE,
    TPDO_MAP_BASE,
    TT_EVENT_MANUFACTURER,
    TT_EVENT_PROFILE,
    TT_SYNC_ACYCLIC,
    TT_SYNC_MAX,
    is_restricted_can_id,
    mapping_entry,
    split_entry,
)

logger = logging.getLogger(__name__)

_INT_STRUCTS = {1: "B", 2: "H", 4: "I", 8: "Q"}


@dataclass
class _Pdo:
    """One PDO of the node (receive or transmit)."""

    number: int  # 1-based
    comm: int  # communication parameter index
    mapping: int  # mapping parameter index
    receive: bool
    pending: bytes | None = None  # RPDO: synchronous payload waiting for the next SYNC
    last_sent: bytes | None = None  # TPDO: payload of the last transmission


class PdoEngine:
    """The PDOs and the SYNC consumer of one node (see the module docstring).

    :param store: the node's :class:`bus.cia301.object_store.ObjectStore` (values, hooks, metadata).
    :param nmt_state: returns the node's NMT state (:class:`bus.cia301.nmt.NmtState` value).
    """

    def __init__(self, store: ObjectStore, nmt_state: Callable[[], int]) -> None:
        self.store = store
        self._nmt_state = nmt_state
        self.rpdos: list[_Pdo] = []
        self.tpdos: list[_Pdo] = []
        for k in range(512):
            for comm_base, map_base, receive, out in (
                (RPDO_COMM_BASE, RPDO_MAP_BASE, True, self.rpdos),
                (TPDO_COMM_BASE, TPDO_MAP_BASE, False, self.tpdos),
            ):
                if (comm_base + k, COMM_COB_ID) in store.vars and (map_base + k, 0) in store.vars:
                    out.append(_Pdo(k + 1, comm_base + k, map_base + k, receive))
        self.sync_count = 0  #: SYNCs received since the last reset (NMT operational)
        self._sync_tx_due = False
        self.length_errors = 0  #: RPDOs too short for their mapping (not processed)
        self._rx_by_cob: dict[int, _Pdo] | None = None
        self._tx_valid: list[_Pdo] | None = None  # the valid TPDOs, in order (None: to be computed)
        self._install_hooks()

    # ------------------------------------------------------------------ configuration

    def _install_hooks(self) -> None:
        w = self.store.write_hooks
        for pdo in (*self.rpdos, *self.tpdos):
            w[(pdo.comm, COMM_COB_ID)] = lambda v, p=pdo: self._write_cob_id(p, int(v))  # type: ignore[misc]
            if (pdo.comm, COMM_TRANSMISSION_TYPE) in self.store.vars:
                w[(pdo.comm, COMM_TRANSMISSION_TYPE)] = lambda v, p=pdo: self._write_transmission_type(p, int(v))  # type: ignore[misc]
            w[(pdo.mapping, 0)] = lambda v, p=pdo: self._write_map_count(p, int(v))  # type: ignore[misc]
            for sub in range(1, MAX_MAPPED + 1):
                if (pdo.mapping, sub) in self.store.vars:
                    w[(pdo.mapping, sub)] = lambda v, p=pdo, s=sub: self._write_map_entry(p, s, int(v))  # type: ignore[misc]

    def _value(self, index: int, sub: int) -> int:
        return int(self.store.values[(index, sub)])

    def cob_id(self, pdo: _Pdo) -> int:
        """The raw COB-ID value (U32) of ``pdo``."""
        return self._value(pdo.comm, COMM_COB_ID)

    def valid(self, pdo: _Pdo) -> bool:
        return not self.cob_id(pdo) & PDO_NOT_VALID

    def transmission_type(self, pdo: _Pdo) -> int:
        key = (pdo.comm, COMM_TRANSMISSION_TYPE)
        return self._value(*key) if key in self.store.vars else TT_EVENT_PROFILE

    def mapping(self, pdo: _Pdo) -> list[tuple[int, int, int]]:
        """The active mapping (index, sub, bits) of ``pdo`` (entries 1..sub 0)."""
        n = self._value(pdo.mapping, 0)
        return [split_entry(self._value(pdo.mapping, s)) for s in range(1, n + 1)]

    def _write_cob_id(self, pdo: _Pdo, value: int) -> None:
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
                    AbortCode.VALUE_RANGE, f"{self._name(pdo)} is valid: invalidate it (bit 31) before changing its COB-ID"
                )
        pdo.pending = None
        pdo.last_sent = None
        self._rx_by_cob = None
        self._tx_valid = None
        logger.debug("%s COB-ID 0x%08X", self._name(pdo), value)

    def _write_transmission_type(self, pdo: _Pdo, value: int) -> None:
        if not (value <= TT_SYNC_MAX or value in (TT_EVENT_MANUFACTURER, TT_EVENT_PROFILE)):
            raise SdoAbort(AbortCode.VALUE_RANGE, f"transmission type {value} not supported (0..240, 254, 255)")
        pdo.pending = None

    def _check_mapping_writable(self, pdo: _Pdo) -> None:
        if int(self._nmt_state()) != NmtState.PRE_OPERATIONAL:
            raise SdoAbort(AbortCode.DEVICE_STATE, "PDO mapping can be changed only in NMT PRE-OPERATIONAL")
        if self.valid(pdo):
            raise SdoAbort(
                AbortCode.UNSUPPORTED_ACCESS, f"{self._name(pdo)} is valid: set bit 31 of its COB-ID before changing the mapping"
            )

    def _write_map_count(self, pdo: _Pdo, n: int) -> None:
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
        pdo.pending = None
        pdo.last_sent = None

    def _write_map_entry(self, pdo: _Pdo, sub: int, entry: int) -> None:
        self._check_mapping_writable(pdo)
        if self._value(pdo.mapping, 0) != 0:
            raise SdoAbort(
                AbortCode.UNSUPPORTED_ACCESS, f"{self._name(pdo)} mapping: set sub-index 0 to 0 before writing entries"
            )
        if entry != 0:
            self._check_entry(pdo, entry)

    def _check_entry(self, pdo: _Pdo, entry: int) -> None:
        index, sub, bits = split_entry(entry)
        var = self.store.lookup(index, sub)  # 0x06020000 / 0x06090011
        size_bits = 8 * _size_bytes(var)
        if not var.pdo_mappable or size_bits == 0 or bits != size_bits:
            raise SdoAbort(AbortCode.NOT_MAPPABLE, f"0x{index:04X}:{sub} ({bits} bits) cannot be mapped")
        if pdo.receive and var.access_type not in ("rw", "wo", "rww"):
            raise SdoAbort(AbortCode.NOT_MAPPABLE, f"0x{index:04X}:{sub} is not writable: not RPDO-mappable")
        if not pdo.receive and var.access_type == "wo":
            raise SdoAbort(AbortCode.NOT_MAPPABLE, f"0x{index:04X}:{sub} is write-only: not TPDO-mappable")

    @staticmethod
    def _name(pdo: _Pdo) -> str:
        return f"{'RPDO' if pdo.receive else 'TPDO'}{pdo.number}"

    # ------------------------------------------------------------------ run time

    def reset(self) -> None:
        """Forget buffered data and counters (NMT reset communication / node)."""
        for pdo in (*self.rpdos, *self.tpdos):
            pdo.pending = None
            pdo.last_sent = None
        self.sync_count = 0
        self._sync_tx_due = False
        self._rx_by_cob = None
        self._tx_valid = None

    @property
    def active(self) -> bool:
        """PDOs are processed only in NMT OPERATIONAL."""
        return int(self._nmt_state()) == NmtState.OPERATIONAL

    def sync_cob_id(self) -> int:
        """The SYNC identifier this node consumes (0x1005 bits 0–10)."""
        if (COB_ID_SYNC_INDEX, 0) not in self.store.vars:
            return SYNC_COB_ID_DEFAULT
        return self._value(COB_ID_SYNC_INDEX, 0) & COB_ID_MASK_11

    def rpdo_cob_ids(self) -> dict[int, _Pdo]:
        """CAN identifier → valid RPDO."""
        if self._rx_by_cob is None:
            self._rx_by_cob = {self.cob_id(p) & COB_ID_MASK_11: p for p in self.rpdos if self.valid(p)}
        return self._rx_by_cob

    def tpdo_cob_ids(self) -> set[int]:
        """CAN identifiers of the valid TPDOs (the node's own transmit IDs)."""
        return {self.cob_id(p) & COB_ID_MASK_11 for p in self.tpdos if self.valid(p)}

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A frame with identifier ``can_id``: True when it is one of the valid RPDOs (handled)."""
        pdo = self.rpdo_cob_ids().get(can_id)
        if pdo is None:
            return False
        if not self.active:
            return True
        need = sum(bits for _, _, bits in self.mapping(pdo)) // 8
        if len(data) < need:
            self.length_errors += 1
            logger.warning("%s: %d bytes, mapping needs %d: not processed", self._name(pdo), len(data), need)
            return True
        if self.transmission_type(pdo) <= TT_SYNC_MAX:
            pdo.pending = bytes(data[:need])
        else:
            self._apply(pdo, bytes(data[:need]))
        return True

    def on_sync(self) -> None:
        """A SYNC: write the buffered synchronous RPDOs (in PDO order); TPDOs become due."""
        if not self.active:
            return
        self.sync_count += 1
        self._sync_tx_due = True
        for pdo in self.rpdos:
            if pdo.pending is not None:
                data, pdo.pending = pdo.pending, None
                self._apply(pdo, data)

    def _apply(self, pdo: _Pdo, data: bytes) -> None:
        offset = 0
        for index, sub, bits in self.mapping(pdo):
            n = bits // 8
            try:
                self.store.write_object(index, sub, data[offset : offset + n])
            except SdoAbort as err:  # the value is refused like an SDO download would be
                logger.warning("%s: 0x%04X:%d not written: %s", self._name(pdo), index, sub, err)
            offset += n

    def pack(self, pdo: _Pdo) -> bytes:
        """The current payload of ``pdo`` (its mapped objects, read now)."""
        return b"".join(self.store.read_object(index, sub) for index, sub, _ in self.mapping(pdo))

    def collect_tpdos(self) -> list[tuple[int, bytes]]:
        """(CAN identifier, payload) of every TPDO due now (see the module docstring); call it
        once the cycle's sample exists (after the control tick)."""
        valid = self._tx_valid
        if valid is None:  # recomputed after a COB-ID write or a reset (the hot path: every io tick)
            valid = self._tx_valid = [p for p in self.tpdos if self.valid(p)]
        if not valid or not self.active:
            self._sync_tx_due = False
            return []
        out: list[tuple[int, bytes]] = []
        sync_due, self._sync_tx_due = self._sync_tx_due, False
        for pdo in valid:
            tt = self.transmission_type(pdo)
            if 1 <= tt <= TT_SYNC_MAX:
                if not (sync_due and self.sync_count % tt == 0):
                    continue
                data = self.pack(pdo)
            else:
                if tt == TT_SYNC_ACYCLIC and not sync_due:
                    continue
                data = self.pack(pdo)
                if data == pdo.last_sent:
                    continue
            pdo.last_sent = data
            out.append((self.cob_id(pdo) & COB_ID_MASK_11, data))
        return out


def _size_bytes(var: ODVariable) -> int:
    """Size of a numeric object in bytes (0 for DOMAIN / strings)."""
    if var.data_type not in ODVariable.STRUCT_TYPES:
        return 0
    return len(var) // 8


def unpack_fields(data: bytes, sizes_signed: list[tuple[int, bool]]) -> list[int]:
    """Little-endian integers of the given (bytes, signed) sizes, back to back."""
    out = []
    offset = 0
    for n, signed in sizes_signed:
        fmt = "<" + (_INT_STRUCTS[n].lower() if signed else _INT_STRUCTS[n])
        out.append(struct.unpack_from(fmt, data, offset)[0])
        offset += n
    return out
