"""CiA 301 process data objects (PDO) and SYNC consumption of a slave, on its object store.

This module owns the slave side of the PDO service: the communication parameters
(RPDO 0x1400+k, TPDO 0x1800+k) and mapping parameters (RPDO 0x1600+k, TPDO 0x1A00+k) as
CiA 301 §7.5.2.35–7.5.2.38 defines them, their validation when written by SDO, packing and
unpacking of PDO payloads by the mapping, and the SYNC consumer (COB-ID object 0x1005).
It knows nothing about CAN frames or the application: :class:`PdoEngine` is given received
PDO payloads, SYNC events and remote requests and hands back the TPDO payloads due; the node
runtime (``firmware_model.drive_node``) moves the frames, the application
(``firmware_model.cyclic_pdo``) decides when a SYNC's TPDOs are sampled.

The objects and the rules for writing them are :mod:`bus.cia301.pdo_parameters`'s.

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
(:class:`_Plan`) until one of those objects is written (their write hooks, installed by
:class:`bus.cia301.pdo_parameters.PdoParameters`, drop it)
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
from bus.cia301.pdo_parameters import Pdo, PdoConfig, PdoParameters
from bus.errors import SdoAbort
from bus.pdo_objects import (
    COB_ID_MASK_11,
    COB_ID_SYNC_INDEX,
    COMM_EVENT_TIMER,
    COMM_INHIBIT_TIME,
    COMM_SYNC_START,
    PDO_NO_RTR,
    PDO_NOT_VALID,
    SYNC_COB_ID_DEFAULT,
    TT_EVENT_MANUFACTURER,
    TT_EVENT_PROFILE,
    TT_SYNC_ACYCLIC,
    TT_SYNC_MAX,
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


@dataclass
class _Plan:
    """The PDO objects as the run time needs them, read once (dropped by a write of any of them or a
    reset; rebuilt at the next use)."""

    rx_by_cob: dict[int, Pdo] = field(default_factory=dict)  # CAN identifier -> valid RPDO
    tx_valid: list[Pdo] = field(default_factory=list)  # the valid TPDOs, in order
    tx_sync: list[Pdo] = field(default_factory=list)  # the valid synchronous TPDOs (0..240)
    tx_event: list[Pdo] = field(default_factory=list)  # the valid event-driven TPDOs (254/255)


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
        #: the PDO objects and the rules of writing them; a write drops the plan
        self.params = PdoParameters(store, nmt_state, self._drop_plan)
        self.rpdos: list[Pdo] = self.params.rpdos
        self.tpdos: list[Pdo] = self.params.tpdos
        self.sync_count = 0  #: SYNCs received since the start (NMT operational)
        self.length_errors = 0  #: RPDOs too short for their mapping (not processed)
        self._plan: _Plan | None = None  # the PDO objects as the run time reads them (None: to be read)

    def _drop_plan(self) -> None:
        self._plan = None

    def cob_id(self, pdo: Pdo) -> int:
        """The raw COB-ID value (U32) of ``pdo``."""
        return self.params.cob_id(pdo)

    def valid(self, pdo: Pdo) -> bool:
        return self.params.valid(pdo)

    def transmission_type(self, pdo: Pdo) -> int:
        return self.params.transmission_type(pdo)

    def mapping(self, pdo: Pdo) -> list[tuple[int, int, int]]:
        """The active mapping (index, sub, bits) of ``pdo`` (entries 1..sub 0)."""
        return self.params.mapping(pdo)

    # ------------------------------------------------------------------ the plan

    def _read_plan(self) -> _Plan:
        """Read the PDO objects as the run time needs them (:class:`_Plan`, :class:`PdoConfig`)."""
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

    def _read_config(self, pdo: Pdo) -> PdoConfig:
        """The :class:`PdoConfig` of ``pdo`` from the object store now."""
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
        return PdoConfig(
            valid=not cob & PDO_NOT_VALID,
            can_id=cob & COB_ID_MASK_11,
            rtr=not cob & PDO_NOT_VALID and not cob & PDO_NO_RTR,
            transmission_type=self.transmission_type(pdo),
            inhibit_s=self.params.sub(pdo, COMM_INHIBIT_TIME) * INHIBIT_UNIT_S,
            event_ms=self.params.sub(pdo, COMM_EVENT_TIMER),
            sync_start=self.params.sub(pdo, COMM_SYNC_START),
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

    def _config(self, pdo: Pdo) -> PdoConfig:
        """The current :class:`PdoConfig` of ``pdo``."""
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

    def rpdo_cob_ids(self) -> dict[int, Pdo]:
        """CAN identifier → valid RPDO."""
        return self._current_plan().rx_by_cob

    def tpdo_cob_ids(self) -> set[int]:
        """CAN identifiers of the valid TPDOs (the node's own transmit IDs)."""
        return {self._config(p).can_id for p in self._current_plan().tx_valid}

    def tpdo_rtr_ids(self) -> set[int]:
        """CAN identifiers of the valid TPDOs that answer a remote frame (bit 30 = 0)."""
        return {self._config(p).can_id for p in self._current_plan().tx_valid if self._config(p).rtr}

    def _valid_tpdos(self) -> list[Pdo]:
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
            logger.warning("%s: %d bytes, mapping needs %d: not processed", self.params.name(pdo), len(data), need)
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

    def on_sync(self, counter: int | None = None) -> list[Pdo]:
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

    def _sync_due(self, pdo: Pdo, tt: int, counter: int | None) -> bool:
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

    def _apply(self, pdo: Pdo, data: bytes) -> None:
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
                logger.warning("%s: 0x%04X:%d not written: %s", self.params.name(pdo), index, sub, err)

    # ------------------------------------------------------------------ transmit

    def pack(self, pdo: Pdo) -> bytes:
        """The current payload of ``pdo`` (its mapped objects, read now)."""
        packer = self._config(pdo).pack
        if packer is not None:
            return packer()
        return b"".join(self.store.read_object(index, sub) for index, sub, _ in self.mapping(pdo))

    def _sent(self, pdo: Pdo, data: bytes, now: float) -> Frame:
        cfg = self._config(pdo)
        pdo.last_sent = data
        pdo.last_tx_s = now
        pdo.held = False
        event_ms = cfg.event_ms
        pdo.event_due_s = now + event_ms / 1000.0 if event_ms and cfg.transmission_type in _EVENT else None
        return cfg.can_id, data

    def sample(self, pdos: list[Pdo]) -> list[Frame]:
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

    def timers_idle(self) -> bool:
        """True when no PDO timer can fall due: no event-driven TPDO in the valid set (their event
        timer, inhibit time and change of state) and no RPDO deadline armed. A node may then leave
        out :meth:`poll` and :meth:`expired_rpdos` until a frame or a clock deadline comes."""
        plan = self._plan if self._plan is not None else self._read_plan()
        if plan.tx_event:
            return False
        for pdo in self.rpdos:
            if pdo.deadline_s is not None:
                return False
        return True

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


def unpack_fields(data: bytes, sizes_signed: list[tuple[int, bool]]) -> list[int]:
    """Little-endian integers of the given (bytes, signed) sizes, back to back."""
    out = []
    offset = 0
    for n, signed in sizes_signed:
        fmt = "<" + (_INT_STRUCTS[n].lower() if signed else _INT_STRUCTS[n])
        out.append(struct.unpack_from(fmt, data, offset)[0])
        offset += n
    return out
