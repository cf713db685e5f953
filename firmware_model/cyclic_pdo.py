"""The cyclic PDO exchange of one drive: SYNC, RPDOs, TPDOs, and the SYNC pacing of io ticks.

Owns the drive's use of the CiA 301 PDO service (:class:`bus.cia301.pdo.PdoEngine`: the PDO
communication and mapping objects 0x1400/0x1600/0x1800/0x1A00, the SYNC COB-ID 0x1005) and the
SYNC credit (docs/canopen-objects.md §10, docs/timing.md §7):

* a SYNC (:meth:`CyclicPdo.on_sync`) writes the buffered synchronous RPDOs to their objects
  (0x607A target position, 0x6071 target torque, 0x60B2 torque offset; only in NMT OPERATIONAL)
  and grants one io tick (one credit per SYNC, in PRE-OPERATIONAL too; at most
  :data:`bus.cyclic.SYNC_CREDITS_MAX` kept: a SYNC the drive sees before the io tick of the one
  before it — the plant steps the robot one period per SYNC and may have both queued — is not lost);
* in a cyclic mode in NMT OPERATIONAL, an io tick may run only with that credit
  (:meth:`CyclicPdo.tick_ready`; the node runtime holds the encoder frame until the SYNC came)
  and uses it up (:meth:`CyclicPdo.consume_sync`);
* after the tick the cycle's TPDOs are due (:meth:`CyclicPdo.pop_tpdos`), so they carry the
  sample of that tick.
"""

from __future__ import annotations

from collections.abc import Callable

from bus.cia301.nmt import NmtState
from bus.cia301.object_store import ObjectStore
from bus.cia301.pdo import PdoEngine
from bus.cyclic import SYNC_CREDITS_MAX


class CyclicPdo:
    """SYNC and PDOs of one drive (see the module docstring).

    :param store: the drive's object store.
    :param nmt_state: returns the drive's NMT state.
    """

    def __init__(self, store: ObjectStore, nmt_state: Callable[[], int]) -> None:
        self.engine = PdoEngine(store, nmt_state)
        self._nmt_state = nmt_state
        #: io ticks the SYNCs received allow (0 .. :data:`bus.cyclic.SYNC_CREDITS_MAX`)
        self.sync_credit = 0

    def reset(self) -> None:
        """NMT reset communication: no buffered RPDO, no credit."""
        self.engine.reset()
        self.sync_credit = 0

    @property
    def active(self) -> bool:
        """True in NMT OPERATIONAL (PDOs are processed only there)."""
        return self.engine.active

    def tick_ready(self, cyclic_mode: bool) -> bool:
        """False while an io tick must wait for its SYNC: in a cyclic mode (``cyclic_mode``), NMT
        OPERATIONAL and no credit."""
        return self.sync_credit > 0 or not (cyclic_mode and self.engine.active)

    def consume_sync(self) -> None:
        """An io tick ran (or was refused): it used one credit."""
        if self.sync_credit:
            self.sync_credit -= 1

    def on_sync(self) -> None:
        """A SYNC frame: synchronous RPDOs take effect (NMT OPERATIONAL), the next io tick may run
        (also in PRE-OPERATIONAL, where CiA 301 consumes SYNC too: a drive started between a SYNC
        and its io tick runs that tick at once)."""
        if self.engine.active:
            self.engine.on_sync()
        if self._nmt_state() in (NmtState.OPERATIONAL, NmtState.PRE_OPERATIONAL) and self.sync_credit < SYNC_CREDITS_MAX:
            self.sync_credit += 1

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A fieldbus frame that may be an RPDO; True when it was one (handled)."""
        return self.engine.on_rpdo(can_id, data)

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID consumed (0x1005)."""
        return self.engine.sync_cob_id()

    def rpdo_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid RPDOs (0x1400..: sub 1)."""
        return list(self.engine.rpdo_cob_ids())

    def pop_tpdos(self) -> list[tuple[int, bytes]]:
        """(COB-ID, payload) of the TPDOs due after the last io tick."""
        return self.engine.collect_tpdos()
