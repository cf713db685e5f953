"""The host's side of the cyclic SYNC/PDO lockstep (``--ff-transport pdo``, docs/timing.md §7).

This module owns :class:`SyncProducer`: during a trial the host is the SYNC producer; per tick n
it sends the four drives' RPDO1 (the set-points of n: target position, torque offset), one SYNC,
then waits for the four TPDO1 of n (position actual, torque actual) before the next tick's
set-points.  The PDO maps come from :func:`host.rig.bring_up.configure_pdos`; the TPDOs arrive in
canopen's notifier thread and queue up here.  The frames it sent and received are counted
(:attr:`SyncProducer.frames`, for the summary).
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Callable
from typing import Any

import canopen
import numpy as np

from bus.cyclic import decode_tpdo
from bus.objects import DRIVE_NODE_IDS
from bus.units import timeout_scale
from host.experiment.bench import CyclicActuals, CyclicSetpoints, TrialFault
from host.experiment.faults import FaultRecord

logger = logging.getLogger(__name__)

__all__ = ["FIRST_TPDO_TIMEOUT_S", "TPDO_TIMEOUT_S", "SyncProducer"]

#: longest wait for the four TPDOs of one tick (× ILCRIG_TIMEOUT_SCALE), s; the first tick of a
#: trial waits as long as the plant does for its first torque frames
TPDO_TIMEOUT_S = 2.0
FIRST_TPDO_TIMEOUT_S = 10.0
#: the node id of the wake-up entry in the TPDO queue (no drive has it)
_WAKE = 0


class SyncProducer:
    """SYNC + RPDO out, TPDO in, one tick at a time (see the module docstring).

    :param network: the fieldbus (the SYNC producer is ``network.sync``)
    :param raise_if_fault: raises the declared fault (:class:`host.experiment.bench.TrialFault`), if any
    :param explain_missing: called before a missing TPDO is reported (with the timeout scale): the
        bench waits briefly for the plant node's own fault, which explains it better
    :ivar frames: the SYNC, RPDO and TPDO frames of every trial so far
    """

    def __init__(
        self,
        network: canopen.Network,
        raise_if_fault: Callable[[], None],
        explain_missing: Callable[[float], None] | None = None,
    ) -> None:
        self.network = network
        self.raise_if_fault = raise_if_fault
        self.explain_missing = explain_missing
        self.frames = {"sync": 0, "rpdo": 0, "tpdo": 0}
        self._tpdos: queue.Queue[tuple[int, bytes]] = queue.Queue()
        self._rpdo_maps: dict[int, Any] = {}
        self._subscribed: set[int] = set()

    def attach(self, node_id: int, rpdo: Any, tpdo: Any) -> None:
        """Use drive ``node_id``'s configured RPDO1 map ``rpdo`` and hear its TPDO1 map ``tpdo``
        (once per node: the map object, and its callbacks, live on when it is configured again)."""
        self._rpdo_maps[node_id] = rpdo
        if node_id not in self._subscribed:
            self._subscribed.add(node_id)
            tpdo.add_callback(lambda m, nid=node_id: self._tpdos.put((nid, bytes(m.data))))

    def wake(self, record: FaultRecord | None = None) -> None:
        """Wake a :meth:`stream` waiting for TPDOs (a fault was declared: ``record``); it then
        raises the fault."""
        self._tpdos.put((_WAKE, b""))

    def stream(self, trial: int, n_ticks: int, cyclic: CyclicSetpoints) -> CyclicActuals:
        """The lockstep of one trial: per tick n the four RPDOs with the set-points of n, one
        SYNC, then the four TPDOs of n. Returns their actuals.

        :raises TrialFault: a TPDO missing or twice in a tick, or a fault declared meanwhile
        """
        while True:  # TPDOs of an earlier, faulted trial
            try:
                self._tpdos.get_nowait()
            except queue.Empty:
                break
        index = {nid: j for j, nid in enumerate(DRIVE_NODE_IDS)}
        rpdos = [self._rpdo_maps[nid] for nid in DRIVE_NODE_IDS]
        n_drives = len(rpdos)
        pos = np.zeros((n_ticks, n_drives), dtype=np.int64)
        torque = np.zeros((n_ticks, n_drives), dtype=np.int64)
        target, offset = cyclic.target_counts, cyclic.torque_offset_permille
        scale = timeout_scale()
        sync = self.network.sync
        for n in range(n_ticks):
            for j, rpdo in enumerate(rpdos):
                rpdo[0].raw = int(target[n, j])
                rpdo[1].raw = int(offset[n, j])
                rpdo.transmit()
            sync.transmit()
            self.frames["rpdo"] += n_drives
            self.frames["sync"] += 1
            seen = [False] * n_drives
            deadline = time.monotonic() + (FIRST_TPDO_TIMEOUT_S if n == 0 else TPDO_TIMEOUT_S) * scale
            for _ in range(n_drives):
                try:
                    nid, data = self._tpdos.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    missing = [DRIVE_NODE_IDS[j] for j in range(n_drives) if not seen[j]]
                    if self.explain_missing is not None:
                        self.explain_missing(scale)
                    raise TrialFault(f"trial {trial}: no TPDO from drive(s) {missing} for tick {n}") from None
                if nid == _WAKE:
                    self.raise_if_fault()
                    continue
                j = index[nid]
                if seen[j]:
                    raise TrialFault(f"trial {trial}: two TPDOs from drive {nid} in tick {n}")
                seen[j] = True
                pos[n, j], torque[n, j] = decode_tpdo(data)
            self.frames["tpdo"] += n_drives
        return CyclicActuals(pos, torque)
