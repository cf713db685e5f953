"""The cyclic PDO exchange of one drive: SYNC, RPDOs, TPDOs, their timers, and the SYNC pacing of
io ticks.

Owns the drive's use of the CiA 301 PDO service (:class:`bus.cia301.pdo.PdoEngine`: the PDO
communication and mapping objects 0x1400/0x1600/0x1800/0x1A00, the SYNC COB-ID 0x1005), the SYNC
consumer's objects 0x1006 (communication cycle period) and 0x1019 (synchronous counter overflow),
and the SYNC credit (docs/canopen-objects.md §10, docs/timing.md §7).  The PDOs work only in NMT
OPERATIONAL and start afresh when the drive enters it.

* a SYNC (:meth:`CyclicPdo.on_sync`, with its counter byte if it has one) grants one io tick --
  in PRE-OPERATIONAL too, where CiA 301 consumes SYNC as well, so a drive started between a SYNC
  and its io tick runs that tick at once; the credits are the SYNCs whose io tick has not run yet,
  at most :data:`bus.cyclic.SYNC_CREDITS_MAX` (a lockstep trial's next SYNC may come before the
  io tick of the last one).  A drive of a SYNC-stepped plant (:attr:`CyclicPdo.sync_stepped`,
  ``ilcrig robot``) counts every SYNC, in every NMT state and over NMT resets: the plant's periods
  go on whatever the drive's state; its node runtime hands it the next SYNC only after the io tick
  of the last one (:class:`firmware_model.sync_backlog.SyncBacklog`: a faster master is served
  late), so it has one credit at most, and the RPDOs of SYNC k are those that came before it.
  In OPERATIONAL it also writes the buffered synchronous RPDOs to their objects (e.g. 0x607A,
  0x6071, 0x60B2).  A SYNC whose length does not fit 0x1019 (no counter byte when 0x1019 > 0, or
  one when 0x1019 = 0) is reported as EMCY 0x8240 once per change and is a SYNC all the same.
* in a cyclic mode in NMT OPERATIONAL -- and in a drive of a SYNC-stepped plant outside a trial,
  in every mode and state -- an io tick may run only with a credit (:meth:`CyclicPdo.tick_ready`;
  the node runtime holds the encoder frame until the SYNC came, whatever order the transport
  delivered them in); every io tick uses one (:meth:`CyclicPdo.consume_sync`).
* the synchronous TPDOs due at a SYNC (types 0–240, counted per TPDO, SYNC start value 0x1800:6)
  are sampled with the values of the latest completed control cycle and go out at once --
  except where SYNC n and io tick n are one control cycle (``lockstep_cycle``: a lockstep trial,
  i.e. a trial armed or running in a cyclic mode, timing.md §7; or a drive of a SYNC-stepped
  plant, docs/robot.md): there the TPDOs carry tick n's sample, going out right after it
  (:meth:`CyclicPdo.after_tick`).  A TPDO still waiting for its tick when the next SYNC comes is
  sampled then, before that SYNC's.
* event-driven TPDOs (254/255) with inhibit time and event timer, and answers to RTR, as
  :mod:`bus.cia301.pdo` describes, checked after every io tick and whenever the node runtime
  serves (:meth:`CyclicPdo.service`).
* watchdogs: an RPDO with an event timer (0x1400+k:5 > 0) that does not come again within it (on
  the drive's clock), and -- with 0x1006 > 0 -- no SYNC within 1.5 × 0x1006 after the last one (on
  :attr:`CyclicPdo.watch_clock`, the drive's clock unless the node gives another) are
  communication errors (``on_error``: the power stage's reaction, EMCY 0x8250 / 0x8100), reported
  once per loss; monitoring starts with the first RPDO / SYNC in OPERATIONAL.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable

from bus.cia301.emcy import EmcyCode
from bus.cia301.nmt import NmtState
from bus.cia301.object_store import ObjectStore
from bus.cia301.pdo import Frame, PdoEngine
from bus.cia301.pdo_parameters import Pdo
from bus.cyclic import SYNC_CREDITS_MAX
from bus.pdo_objects import COMM_CYCLE_PERIOD_INDEX, SYNC_COUNTER_OVERFLOW_INDEX

logger = logging.getLogger(__name__)

#: SYNC watchdog: a SYNC is lost when none came within this many communication cycle periods
SYNC_TIMEOUT_PERIODS = 1.5
#: the NMT states in which a SYNC counts for the next io tick (CiA 301: not in STOPPED)
_SYNC_STATES = (int(NmtState.OPERATIONAL), int(NmtState.PRE_OPERATIONAL))
_OPERATIONAL = int(NmtState.OPERATIONAL)
_PERIOD_KEY = (COMM_CYCLE_PERIOD_INDEX, 0)
_OVERFLOW_KEY = (SYNC_COUNTER_OVERFLOW_INDEX, 0)


class CyclicPdo:
    """SYNC and PDOs of one drive (see the module docstring).

    :param store: the drive's object store.
    :param nmt_state: returns the drive's NMT state.
    :param clock: the drive's time [s].
    :param lockstep_cycle: True while SYNC n and io tick n are one control cycle (a lockstep
        trial, a SYNC-stepped plant).
    :param on_error: a communication error: ("rpdo", PDO number) or ("sync", 0).
    :param on_warning: an EMCY without a reaction: (error code, 5 manufacturer bytes).
    """

    def __init__(
        self,
        store: ObjectStore,
        nmt_state: Callable[[], int],
        clock: Callable[[], float],
        lockstep_cycle: Callable[[], bool] = lambda: False,
        on_error: Callable[[str, int], None] | None = None,
        on_warning: Callable[[int, bytes], None] | None = None,
    ) -> None:
        self._store = store
        self._values = store.values  # 0x1006, 0x1019: read at every SYNC (0 where the EDS has none)
        self._nmt_state = nmt_state
        self.clock = clock
        #: the SYNC watchdog's clock [s] (None: :attr:`clock`)
        self.watch_clock: Callable[[], float] | None = None
        #: a drive of a SYNC-stepped plant: every SYNC is a credit, in every NMT state and over resets
        self.sync_stepped = False
        self.engine = PdoEngine(store, nmt_state, lambda: self.clock(), report=self._length_error)
        self._lockstep_cycle = lockstep_cycle
        self._on_error = on_error
        self._on_warning = on_warning
        #: io ticks the SYNCs received allow (0 .. :data:`bus.cyclic.SYNC_CREDITS_MAX`)
        self.sync_credit = 0
        self._deferred: list[Pdo] | None = None  # TPDOs of the last SYNC waiting for its io tick
        self._out: list[Frame] = []
        self._sync_deadline_s: float | None = None
        self._sync_length_bad = False

    def reset(self, keep_credit: bool = False) -> None:
        """NMT reset communication (no credit), or the drive entered OPERATIONAL
        (``keep_credit``: a SYNC seen in PRE-OPERATIONAL whose io tick has not run yet still
        counts): no buffered RPDO, no TPDO waiting, every counter and timer afresh."""
        self.engine.reset()
        if not (keep_credit or self.sync_stepped):
            self.sync_credit = 0
        self._deferred = None
        self._out.clear()
        self._sync_deadline_s = None
        self._sync_length_bad = False

    @property
    def active(self) -> bool:
        """True in NMT OPERATIONAL (PDOs are processed only there)."""
        return self.engine.active

    def tick_ready(self, cyclic_mode: bool, stepped: bool = False) -> bool:
        """False while an io tick must wait for its SYNC: no credit, and either a cyclic mode
        (``cyclic_mode``) in NMT OPERATIONAL or a drive of a SYNC-stepped plant outside a trial
        (``stepped``: every io tick follows its SYNC, in every mode and state)."""
        return self.sync_credit > 0 or not (stepped or cyclic_mode and self.engine.active)

    def consume_sync(self) -> None:
        """An io tick ran: it used one credit."""
        if self.sync_credit:
            self.sync_credit -= 1

    # ------------------------------------------------------------------ SYNC

    def on_sync(self, counter: int | None = None) -> None:
        """A SYNC frame (``counter``: its counter byte, None without): synchronous RPDOs take
        effect, the next io tick may run, the synchronous TPDOs due are sampled (or wait for the
        tick of a lockstep cycle); in PRE-OPERATIONAL only the credit."""
        engine = self.engine
        nmt = int(self._nmt_state())
        if self.sync_credit < SYNC_CREDITS_MAX and (self.sync_stepped or nmt in _SYNC_STATES):
            self.sync_credit += 1
        if nmt != _OPERATIONAL:
            return
        values = self._values
        overflow = int(values.get(_OVERFLOW_KEY, 0))
        self._check_sync_length(counter, overflow)
        period_us = int(values.get(_PERIOD_KEY, 0))
        self._sync_deadline_s = self._watch_now() + SYNC_TIMEOUT_PERIODS * period_us * 1e-6 if period_us else None
        if self._deferred is not None:  # the last SYNC's tick never came
            self._out.extend(engine.sample(self._deferred))
            self._deferred = None
        if not overflow:
            counter = None  # a counter the drive was not told to expect is not used
        due = engine.on_sync(counter)
        if due:
            if self._lockstep_cycle():
                self._deferred = due
            else:
                self._out.extend(engine.sample(due))

    def grace(self) -> None:
        """The node did not run before now (:meth:`bus.cia301.slave.SlaveNode.after_stall`): the
        SYNC watchdog counts from now, as after a SYNC."""
        if self._sync_deadline_s is not None:
            period_us = int(self._values.get(_PERIOD_KEY, 0))
            self._sync_deadline_s = self._watch_now() + SYNC_TIMEOUT_PERIODS * period_us * 1e-6 if period_us else None

    def _watch_now(self) -> float:
        return (self.clock if self.watch_clock is None else self.watch_clock)()

    def _check_sync_length(self, counter: int | None, overflow: int) -> None:
        """A SYNC whose length does not fit 0x1019 (``overflow``): EMCY 0x8240 once per change."""
        bad = (overflow > 0) != (counter is not None)
        if bad and not self._sync_length_bad and self._on_warning is not None:
            self._on_warning(EmcyCode.SYNC_LENGTH, struct.pack("<BB3x", 0, 0 if counter is None else 1))
        self._sync_length_bad = bad

    # ------------------------------------------------------------------ RPDO, RTR

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A fieldbus frame that may be an RPDO; True when it was one (handled)."""
        return self.engine.on_rpdo(can_id, data)

    def _length_error(self, code: int, number: int) -> None:
        if self._on_warning is not None:
            self._on_warning(code, struct.pack("<BB3x", 0, number))

    def on_rtr(self, can_id: int) -> bool:
        """A remote frame: True when it asked for one of the TPDOs (queued)."""
        frame = self.engine.on_rtr(can_id)
        if frame is None:
            return False
        self._out.append(frame)
        return True

    # ------------------------------------------------------------------ after a tick, timers

    def after_tick(self) -> None:
        """The io tick's sample exists: the TPDOs of a lockstep SYNC, then the event-driven ones."""
        if self._deferred is not None:
            self._out.extend(self.engine.sample(self._deferred))
            self._deferred = None
        out = self.engine.poll(self.clock())  # nothing outside NMT OPERATIONAL
        if out:
            self._out.extend(out)

    def service(self, now: float) -> None:
        """Timers at ``now`` [s] of :attr:`clock`: RPDO deadlines, the SYNC watchdog (at
        :attr:`watch_clock`'s time, if set), event-driven TPDOs."""
        engine = self.engine
        if int(self._nmt_state()) != _OPERATIONAL:
            return
        for number in engine.expired_rpdos(now):
            logger.warning("RPDO%d missed its deadline", number)
            if self._on_error is not None:
                self._on_error("rpdo", number)
        deadline = self._sync_deadline_s
        if deadline is not None:
            watch_now = now if self.watch_clock is None else self.watch_clock()
            if watch_now >= deadline - 1e-9:  # µs sums carry float rounding
                self._sync_deadline_s = None
                logger.warning("no SYNC within %.1f communication cycle periods", SYNC_TIMEOUT_PERIODS)
                if self._on_error is not None:
                    self._on_error("sync", 0)
        out = engine.poll(now)  # nothing once a reaction left NMT OPERATIONAL
        if out:
            self._out.extend(out)

    def next_deadline(self) -> float | None:
        """The earliest time [s] of :attr:`clock` at which :meth:`service` has work (None: none;
        the SYNC watchdog counts here only without a :attr:`watch_clock` of its own)."""
        if not self.engine.active:
            return None
        sync = self._sync_deadline_s if self.watch_clock is None else None
        times = [t for t in (self.engine.next_deadline(), sync) if t is not None]
        return min(times) if times else None

    def timers_idle(self) -> bool:
        """True when no PDO timer runs (:meth:`bus.cia301.pdo.PdoEngine.timers_idle`)."""
        return self.engine.timers_idle()

    def quiet_ticks(self) -> bool:
        """True when an io tick now leaves this side nothing to do: no SYNC credit for it to use
        (:meth:`consume_sync`), no TPDO sampled for it or waiting (:meth:`after_tick`,
        :meth:`pop_tpdos`), no PDO timer (:meth:`timers_idle`: nothing for :meth:`after_tick`'s
        poll). Only frames and the node's service change that (firmware_model/plain_ticks.py)."""
        return not self.sync_credit and self._deferred is None and not self._out and self.engine.timers_idle()

    def watch_deadline(self) -> float | None:
        """When the SYNC watchdog fires [s of :attr:`watch_clock`, else :attr:`clock`] (None: not
        armed)."""
        return self._sync_deadline_s if self.engine.active else None

    # ------------------------------------------------------------------ objects for the node

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID consumed (0x1005)."""
        return self.engine.sync_cob_id()

    def rpdo_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid RPDOs (0x1400..: sub 1)."""
        return list(self.engine.rpdo_cob_ids())

    def rtr_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid TPDOs that answer a remote frame."""
        return sorted(self.engine.tpdo_rtr_ids())

    def pop_tpdos(self) -> list[tuple[int, bytes]]:
        """(COB-ID, payload) of the TPDOs due, in order; the queue is emptied."""
        out = self._out
        if not out:
            return []
        self._out = []
        return out
