"""CiA 301 process data objects (PDO) and SYNC consumption of a slave, on its object store.

This module owns the slave side of the PDO service: the communication parameters
(RPDO 0x1400+k, TPDO 0x1800+k) and mapping parameters (RPDO 0x1600+k, TPDO 0x1A00+k) as
CiA 301 §7.5.2.35–7.5.2.38 defines them, their validation when written by SDO, packing and
unpacking of PDO payloads by the mapping, and the SYNC consumer (COB-ID object 0x1005).
It knows nothing about CAN frames or the application: :class:`PdoEngine` is given received
PDO payloads, SYNC events and remote requests and hands back the TPDO payloads due; the node
runtime (``firmware_model.drive_node``) moves the frames, the application
(``firmware_model.cyclic_pdo``) decides when a SYNC's TPDOs are sampled.

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

Run time (only in NMT OPERATIONAL, as CiA 301 requires; :meth:`PdoEngine.start` when the node
enters it: every counter and timer starts afresh)

* a received synchronous RPDO (type 0..240) is buffered and written to its objects at the
  next SYNC; an event-driven RPDO (254/255) is written at once.  A payload shorter than the
  mapping is not processed (CiA 301: EMCY 0x8210, reported through ``report``).  The writes go
  through the object store with its usual checks and hooks, so an RPDO has the effect of the
  same SDO downloads, in this order: first the objects without a write hook (set-points such as
  0x607A), then those with one (commands such as the controlword), each group in mapping order;
  a controlword therefore acts on the set-points of its own RPDO, whatever the mapping order.
  An RPDO with an event timer must come again within it: from its first reception on,
  :meth:`PdoEngine.expired_rpdos` reports it once when it does not (CiA 301: EMCY 0x8250), and the
  next reception arms it again.
* SYNC (:meth:`PdoEngine.on_sync`, with its counter byte when the producer sends one): the
  synchronous TPDOs due at it are returned; the application samples them
  (:meth:`PdoEngine.sample`) when the values of its control cycle exist.  Type n (1–240) is due
  every n-th SYNC counted from the start (the first at the n-th SYNC); with a SYNC start value
  s > 0 (sub 6) and SYNCs carrying a counter (0x1019 > 0) the first transmission is at the SYNC
  whose counter is s, then every n-th.  Type 0 is due at every SYNC, and sent only when its data
  changed since its last transmission.
* event-driven TPDOs (254/255, :meth:`PdoEngine.poll`): sent when their data changed since the
  last transmission (the first poll after the start sends them) and when their event timer
  (sub 5 > 0) expires, in both cases not before the inhibit time (sub 3) since their last
  transmission has passed -- a change within it is sent when it ends, with the data of that
  moment.  Every transmission restarts the event timer.
* RTR (:meth:`PdoEngine.on_rtr`): a remote frame with the identifier of a valid TPDO whose bit 30
  is 0 is answered with the TPDO's data of that moment (any transmission type).

What the run time reads of the PDO objects -- validity, identifiers, transmission types, inhibit
times, event timers, SYNC start values, the mappings (as the struct that packs or unpacks them,
the mapped objects' read hooks, the write order) -- is read from the object store once and kept
(:class:`_Plan`) until one of those objects is written (their write hooks, installed here, drop it)
or the engine is reset (NMT reset communication, entering OPERATIONAL): the objects are written
only through :meth:`ObjectStore.write_object` or by a reset of the store, which the node follows with
:meth:`PdoEngine.reset`.  The object store's hooks are installed before the node runs.

Time: ``clock`` [s] (the node's clock: the monotonic clock, or the lockstep time of the
application); no wall clock is read here.
"""

from __future__ import annotations

import functools
import logging
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from canopen.objectdictionary import ODVariable

from bus.cia301.emcy import EmcyCode
from bus.cia301.nmt import NmtState
from bus.cia301.object_store import ObjectStore, struct_of
from bus.errors import AbortCode, SdoAbort
from bus.pdo_objects import (  # noqa: F401 - re-exported
    COB_ID_MASK_11,
    COB_ID_SYNC_INDEX,
    COMM_COB_ID,
    COMM_EVENT_TIMER,
    COMM_INHIBIT_TIME,
    COMM_SYNC_START,
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
#: inhibit time unit [s]
INHIBIT_UNIT_S = 100e-6
_EVENT = (TT_EVENT_MANUFACTURER, TT_EVENT_PROFILE)
#: a timer is due this close to its time [s]: time sums of whole µs carry float rounding
_EPS_S = 1e-9
_OPERATIONAL = int(NmtState.OPERATIONAL)
_SYNC_KEY = (COB_ID_SYNC_INDEX, 0)

Frame = tuple[int, bytes]


@dataclass(frozen=True)
class _Config:
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
class _Plan:
    """The PDO objects as the run time needs them, read once (dropped by a write of any of them or a
    reset; rebuilt at the next use)."""

    rx_by_cob: dict[int, _Pdo] = field(default_factory=dict)  # CAN identifier -> valid RPDO
    tx_valid: list[_Pdo] = field(default_factory=list)  # the valid TPDOs, in order
    tx_sync: list[_Pdo] = field(default_factory=list)  # the valid synchronous TPDOs (0..240)
    tx_event: list[_Pdo] = field(default_factory=list)  # the valid event-driven TPDOs (254/255)


@dataclass
class _Pdo:
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
    cfg: _Config | None = None  # its parameters as the run time reads them (set with the plan)

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


class PdoEngine:
    """The PDOs and the SYNC consumer of one node (see the module docstring).

    :param store: the node's :class:`bus.cia301.object_store.ObjectStore` (values, hooks, metadata).
    :param nmt_state: returns the node's NMT state (:class:`bus.cia301.nmt.NmtState` value).
    :param clock: the node's time [s] (inhibit times, event timers, RPDO deadlines).
    :param report: called with (EMCY error code, PDO number) for an RPDO too short for its mapping.
    """

    def __init__(
        self,
        store: ObjectStore,
        nmt_state: Callable[[], int],
        clock: Callable[[], float] = time.monotonic,
        report: Callable[[int, int], None] | None = None,
    ) -> None:
        self.store = store
        self._nmt_state = nmt_state
        self.clock = clock
        self._report = report
        self.rpdos: list[_Pdo] = []
        self.tpdos: list[_Pdo] = []
        for k in range(512):
            for comm_base, map_base, receive, out in (
                (RPDO_COMM_BASE, RPDO_MAP_BASE, True, self.rpdos),
                (TPDO_COMM_BASE, TPDO_MAP_BASE, False, self.tpdos),
            ):
                if (comm_base + k, COMM_COB_ID) in store.vars and (map_base + k, 0) in store.vars:
                    out.append(_Pdo(k + 1, comm_base + k, map_base + k, receive))
        self.sync_count = 0  #: SYNCs received since the start (NMT operational)
        self.length_errors = 0  #: RPDOs too short for their mapping (not processed)
        self._plan: _Plan | None = None  # the PDO objects as the run time reads them (None: to be read)
        self._install_hooks()

    # ------------------------------------------------------------------ configuration

    def _install_hooks(self) -> None:
        """The write hooks of every PDO parameter: the write is checked (an :class:`SdoAbort`
        refuses it), then the plan is dropped (the store keeps the value right after)."""
        w = self.store.write_hooks

        def put(key: tuple[int, int], check: Callable[[int], None]) -> None:
            def hook(value: object) -> None:
                check(int(value))  # type: ignore[call-overload]
                self._plan = None

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

    def _sub(self, pdo: _Pdo, sub: int, default: int = 0) -> int:
        key = (pdo.comm, sub)
        return int(self.store.values[key]) if key in self.store.vars else default

    def cob_id(self, pdo: _Pdo) -> int:
        """The raw COB-ID value (U32) of ``pdo``."""
        return self._value(pdo.comm, COMM_COB_ID)

    def valid(self, pdo: _Pdo) -> bool:
        return not self.cob_id(pdo) & PDO_NOT_VALID

    def transmission_type(self, pdo: _Pdo) -> int:
        return self._sub(pdo, COMM_TRANSMISSION_TYPE, TT_EVENT_PROFILE)

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
        pdo.forget()
        logger.debug("%s COB-ID 0x%08X", self._name(pdo), value)

    def _write_transmission_type(self, pdo: _Pdo, value: int) -> None:
        if not (value <= TT_SYNC_MAX or value in _EVENT):
            raise SdoAbort(AbortCode.VALUE_RANGE, f"transmission type {value} not supported (0..240, 254, 255)")
        pdo.forget()

    def _write_event_timer(self, pdo: _Pdo) -> None:
        pdo.deadline_s = None  # RPDO: armed again by the next reception
        pdo.event_due_s = None  # TPDO: restarted by the next transmission

    def _write_while_invalid(self, pdo: _Pdo, what: str) -> None:
        if self.valid(pdo):
            raise SdoAbort(
                AbortCode.VALUE_RANGE, f"{self._name(pdo)} is valid: set bit 31 of its COB-ID before changing its {what}"
            )

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
        pdo.forget()

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

    # ------------------------------------------------------------------ the plan

    def _read_plan(self) -> _Plan:
        """Read the PDO objects as the run time needs them (:class:`_Plan`, :class:`_Config`)."""
        plan = _Plan()
        for pdo in (*self.rpdos, *self.tpdos):
            cfg = pdo.cfg = self._read_config(pdo)
            if not cfg.valid:
                continue
            if pdo.receive:
                plan.rx_by_cob[cfg.can_id] = pdo
                continue
            plan.tx_valid.append(pdo)
            if cfg.transmission_type <= TT_SYNC_MAX:
                plan.tx_sync.append(pdo)
            elif cfg.transmission_type in _EVENT:
                plan.tx_event.append(pdo)
        self._plan = plan
        return plan

    def _read_config(self, pdo: _Pdo) -> _Config:
        """The :class:`_Config` of ``pdo`` from the object store now."""
        cob = self.cob_id(pdo)
        entries = self.mapping(pdo)
        writes = []
        pack = None
        if pdo.receive:
            offsets = [0]
            for _, _, bits in entries:
                offsets.append(offsets[-1] + bits // 8)
            # first the objects without a write hook (set-points), then those with one (commands)
            hooks = self.store.write_hooks
            for k in sorted(range(len(entries)), key=lambda k: (entries[k][0], entries[k][1]) in hooks):
                index, sub, _ = entries[k]
                writes.append((index, sub, offsets[k], offsets[k + 1], self._writer(index, sub)))
        else:
            pack = self._packer(entries)
        return _Config(
            valid=not cob & PDO_NOT_VALID,
            can_id=cob & COB_ID_MASK_11,
            rtr=not cob & PDO_NOT_VALID and not cob & PDO_NO_RTR,
            transmission_type=self.transmission_type(pdo),
            inhibit_s=self._sub(pdo, COMM_INHIBIT_TIME) * INHIBIT_UNIT_S,
            event_ms=self._sub(pdo, COMM_EVENT_TIMER),
            sync_start=self._sub(pdo, COMM_SYNC_START),
            nbytes=sum(bits for _, _, bits in entries) // 8,
            writes=tuple(writes),
            pack=pack,
        )

    def _writer(self, index: int, sub: int) -> Callable[[bytes], None] | None:
        try:
            return self.store.writer(index, sub)
        except SdoAbort:
            return None  # not in the dictionary: refused at every write, by write_object

    def _packer(self, entries: list[tuple[int, int, int]]) -> Callable[[], bytes] | None:
        """The payload of the mapped objects ``entries`` (index, sub, bits), read when called, as
        :meth:`ObjectStore.read_object` of each would give it; None when one of them cannot be
        read that way (not in the dictionary, write-only, not a number of its mapped size)."""
        store = self.store
        getters: list[Callable[[], object]] = []
        fmt = "<"
        for index, sub, bits in entries:
            var = store.vars.get((index, sub))
            code = None if var is None else _struct_code(var)
            if var is None or var.access_type == "wo" or code is None or struct.calcsize("<" + code) * 8 != bits:
                return None
            key = (index, sub)
            hook = store.read_hooks.get(key)
            getters.append(hook if hook is not None else functools.partial(store.values.__getitem__, key))
            fmt += code
        packer = struct.Struct(fmt).pack
        if not getters:
            return lambda: b""
        if len(getters) == 1:
            (one,) = getters
            return lambda: packer(one())
        if len(getters) == 2:
            first, second = getters
            return lambda: packer(first(), second())
        return lambda: packer(*[get() for get in getters])

    def _config(self, pdo: _Pdo) -> _Config:
        """The current :class:`_Config` of ``pdo``."""
        if self._plan is None:
            self._read_plan()
        assert pdo.cfg is not None
        return pdo.cfg

    def _current_plan(self) -> _Plan:
        plan = self._plan
        return plan if plan is not None else self._read_plan()

    # ------------------------------------------------------------------ run time

    def reset(self) -> None:
        """Forget buffered data, counters and timers (NMT reset communication / node); the PDO
        objects are read afresh (the store may have been reset)."""
        for pdo in (*self.rpdos, *self.tpdos):
            pdo.forget()
        self.sync_count = 0
        self._plan = None

    def start(self) -> None:
        """The node entered NMT OPERATIONAL: every counter and timer starts afresh."""
        self.reset()

    @property
    def active(self) -> bool:
        """PDOs are processed only in NMT OPERATIONAL."""
        return int(self._nmt_state()) == _OPERATIONAL

    def sync_cob_id(self) -> int:
        """The SYNC identifier this node consumes (0x1005 bits 0–10)."""
        value = self.store.values.get(_SYNC_KEY)
        return SYNC_COB_ID_DEFAULT if value is None else int(value) & COB_ID_MASK_11

    def rpdo_cob_ids(self) -> dict[int, _Pdo]:
        """CAN identifier → valid RPDO."""
        return self._current_plan().rx_by_cob

    def tpdo_cob_ids(self) -> set[int]:
        """CAN identifiers of the valid TPDOs (the node's own transmit IDs)."""
        return {self._config(p).can_id for p in self._current_plan().tx_valid}

    def tpdo_rtr_ids(self) -> set[int]:
        """CAN identifiers of the valid TPDOs that answer a remote frame (bit 30 = 0)."""
        return {self._config(p).can_id for p in self._current_plan().tx_valid if self._config(p).rtr}

    def _valid_tpdos(self) -> list[_Pdo]:
        return self._current_plan().tx_valid

    # ------------------------------------------------------------------ receive

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A frame with identifier ``can_id``: True when it is one of the valid RPDOs (handled)."""
        plan = self._plan if self._plan is not None else self._read_plan()
        pdo = plan.rx_by_cob.get(can_id)
        if pdo is None:
            return False
        if int(self._nmt_state()) != _OPERATIONAL:
            return True
        cfg = pdo.cfg
        assert cfg is not None
        need = cfg.nbytes
        if len(data) < need:
            self.length_errors += 1
            logger.warning("%s: %d bytes, mapping needs %d: not processed", self._name(pdo), len(data), need)
            if self._report is not None:
                self._report(EmcyCode.PDO_LENGTH, pdo.number)
            return True
        timeout_ms = cfg.event_ms
        pdo.deadline_s = self.clock() + timeout_ms / 1000.0 if timeout_ms else None
        if cfg.transmission_type <= TT_SYNC_MAX:
            pdo.pending = bytes(data[:need])
        else:
            self._apply(pdo, bytes(data[:need]))
        return True

    def expired_rpdos(self, now: float) -> list[int]:
        """Numbers of the RPDOs whose deadline passed at ``now`` [s] (each once per loss)."""
        late = [pdo for pdo in self.rpdos if pdo.deadline_s is not None and now >= pdo.deadline_s - _EPS_S]
        if not late or int(self._nmt_state()) != _OPERATIONAL:
            return []
        for pdo in late:
            pdo.deadline_s = None
        return [pdo.number for pdo in late]

    def on_sync(self, counter: int | None = None) -> list[_Pdo]:
        """A SYNC (``counter``: its counter byte, None without): write the buffered synchronous
        RPDOs (in PDO order); returns the synchronous TPDOs due at it (to :meth:`sample`)."""
        if int(self._nmt_state()) != _OPERATIONAL:
            return []
        self.sync_count += 1
        for pdo in self.rpdos:
            if pdo.pending is not None:
                data, pdo.pending = pdo.pending, None
                self._apply(pdo, data)
        due = []
        plan = self._plan if self._plan is not None else self._read_plan()  # the RPDOs may have changed it
        for pdo in plan.tx_sync:
            tt = pdo.cfg.transmission_type  # type: ignore[union-attr]
            if tt == TT_SYNC_ACYCLIC:
                due.append(pdo)
            elif self._sync_due(pdo, tt, counter):
                due.append(pdo)
        return due

    def _sync_due(self, pdo: _Pdo, tt: int, counter: int | None) -> bool:
        """Count one SYNC for TPDO ``pdo`` of type ``tt`` (1..240): True when it is due."""
        if pdo.countdown == 0 and not pdo.waiting_start:  # first SYNC since the start
            start = self._config(pdo).sync_start
            pdo.waiting_start = start > 0 and counter is not None
            pdo.countdown = tt
        if pdo.waiting_start:
            if counter != self._config(pdo).sync_start:
                return False
            pdo.waiting_start = False
            pdo.countdown = tt
            return True
        pdo.countdown -= 1
        if pdo.countdown > 0:
            return False
        pdo.countdown = tt
        return True

    def _apply(self, pdo: _Pdo, data: bytes) -> None:
        """Write an RPDO's payload: first the objects without a write hook (set-points), then those
        with one (commands such as a controlword), each group in mapping order -- so a command
        sees the set-points that came in the same RPDO."""
        for index, sub, start, end, write in self._config(pdo).writes:
            try:
                if write is None:
                    self.store.write_object(index, sub, data[start:end])
                else:
                    write(data[start:end])
            except SdoAbort as err:  # the value is refused like an SDO download would be
                logger.warning("%s: 0x%04X:%d not written: %s", self._name(pdo), index, sub, err)

    # ------------------------------------------------------------------ transmit

    def pack(self, pdo: _Pdo) -> bytes:
        """The current payload of ``pdo`` (its mapped objects, read now)."""
        packer = self._config(pdo).pack
        if packer is not None:
            return packer()
        return b"".join(self.store.read_object(index, sub) for index, sub, _ in self.mapping(pdo))

    def _sent(self, pdo: _Pdo, data: bytes, now: float) -> Frame:
        cfg = self._config(pdo)
        pdo.last_sent = data
        pdo.last_tx_s = now
        pdo.held = False
        event_ms = cfg.event_ms
        pdo.event_due_s = now + event_ms / 1000.0 if event_ms and cfg.transmission_type in _EVENT else None
        return cfg.can_id, data

    def sample(self, pdos: list[_Pdo]) -> list[Frame]:
        """(CAN identifier, payload) of the synchronous TPDOs ``pdos`` (from :meth:`on_sync`), their
        data read now; a type-0 TPDO only if its data changed since its last transmission."""
        if not pdos or int(self._nmt_state()) != _OPERATIONAL:
            return []
        now = self.clock()
        out = []
        for pdo in pdos:
            cfg = self._config(pdo)
            if not cfg.valid:
                continue
            data = cfg.pack() if cfg.pack is not None else self.pack(pdo)
            if cfg.transmission_type == TT_SYNC_ACYCLIC and data == pdo.last_sent:
                continue
            out.append(self._sent(pdo, data, now))
        return out

    def poll(self, now: float) -> list[Frame]:
        """The event-driven TPDOs due at ``now`` [s] (see the module docstring)."""
        plan = self._plan if self._plan is not None else self._read_plan()
        if not plan.tx_event or int(self._nmt_state()) != _OPERATIONAL:
            return []
        out = []
        for pdo in plan.tx_event:
            data = self.pack(pdo)
            changed = data != pdo.last_sent
            timer = pdo.event_due_s is not None and now >= pdo.event_due_s - _EPS_S
            if not (changed or timer):
                continue
            inhibit_s = self._config(pdo).inhibit_s
            if pdo.last_tx_s is not None and now < pdo.last_tx_s + inhibit_s - _EPS_S:
                pdo.held = True  # sent when the inhibit time ends
                continue
            out.append(self._sent(pdo, data, now))
        return out

    def on_rtr(self, can_id: int) -> Frame | None:
        """A remote frame with identifier ``can_id``: the TPDO it asks for, sampled now (None when
        no valid TPDO with RTR allowed has this identifier, or not OPERATIONAL)."""
        if not self.active:
            return None
        for pdo in self._valid_tpdos():
            cfg = self._config(pdo)
            if cfg.can_id == can_id and cfg.rtr:
                return self._sent(pdo, self.pack(pdo), self.clock())
        return None

    def next_deadline(self) -> float | None:
        """The earliest time [s] at which :meth:`poll` or :meth:`expired_rpdos` has work (None:
        none)."""
        if not self.active:
            return None
        times = [p.deadline_s for p in self.rpdos if p.deadline_s is not None]
        for pdo in self._valid_tpdos():
            if pdo.event_due_s is not None:
                times.append(pdo.event_due_s)
            if pdo.held and pdo.last_tx_s is not None:
                times.append(pdo.last_tx_s + self._config(pdo).inhibit_s)
        return min(times) if times else None


def _struct_code(var: ODVariable) -> str | None:
    """The struct code of a numeric object (None for DOMAIN, strings, a missing data type), as
    :meth:`ObjectStore.encode` packs it."""
    s = struct_of(var)
    return None if s is None else s.format.lstrip("<")


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
