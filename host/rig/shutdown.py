"""The end of a rig run on the host's side: every drive still alive torque-free, and the evidence
of it taken from the bus.

This module owns :func:`bring_to_safe_state`: after a completed run the live drives get CiA 402
disable voltage by SDO (a trial still running on the plant node is aborted first), then NMT STOP
goes to all nodes; after a fault (or with the fieldbus failing) only NMT STOP is sent (the
watchdog sent it already when it declared the fault).  The evidence is each drive's next
heartbeat reporting STOPPED (:func:`safe_state_evidence`) — every drive heard during the run is
waited for, not only those heard a moment ago (after a pause of the whole machine every heartbeat
is late) — one entry per drive for the summary's ``safe_state``; a drive not heard is left to its
own fault reaction (its log says, see :mod:`bus.safe_state`; the launcher reads it).  The watchdog
stays armed meanwhile (a node lost while stopping is a fault of the run), and an SDO request of the
shutdown that fails is returned to the bench, which makes it the run's ``sdo_error``.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import canopen

from bus.errors import SdoAbort
from bus.objects import DRIVE_NODE_IDS
from host.nodes.sdo_access import SdoTransportError
from host.rig.bring_up import RigNodes
from host.rig.fault_classify import node_name
from host.rig.watchdog import Watchdog, nmt_stop_all

logger = logging.getLogger(__name__)

__all__ = ["bring_to_safe_state", "safe_state_evidence"]


def bring_to_safe_state(
    network: canopen.Network, nodes: RigNodes | None, watchdog: Watchdog, *, trial_running: bool
) -> tuple[list[dict[str, Any]], list[SdoTransportError | SdoAbort]]:
    """Every drive still alive torque-free (see the module docstring); returns the evidence, one
    entry per drive, and the SDO errors of the shutdown (none after a fault). Never raises.

    :param nodes: the nodes (None: they were never added; only NMT STOP is sent)
    :param trial_running: a trial may still run on the plant node (it is aborted first)
    """
    bus_ok = watchdog.fieldbus_ok
    alive = watchdog.events.alive(time.monotonic())
    heard = {nid for nid, t in watchdog.events.last_heard().items() if t is not None}
    how = "NMT STOP"
    errors: list[SdoTransportError | SdoAbort] = []
    if bus_ok and watchdog.fault is None and nodes is not None:
        if trial_running:
            try:
                nodes.plant.abort()
            except Exception:  # noqa: BLE001 - closing must never hide the original error
                logger.debug("abort of the plant node's trial failed", exc_info=True)
        for nid, drive in zip(DRIVE_NODE_IDS, nodes.drives):
            if nid not in alive:
                continue
            try:
                drive.disable()  # CiA 402 disable voltage: torque off, Switch on disabled
            except (SdoTransportError, SdoAbort) as exc:
                logger.info("disable of drive %d failed: %s", nid, exc)
                if watchdog.fault is None:
                    errors.append(exc)
            except Exception:  # noqa: BLE001
                logger.debug("disable of drive %d failed", nid, exc_info=True)
        how = "CiA 402 disable voltage, NMT STOP"
    t_stop = time.monotonic()
    watchdog.stopped_at = t_stop
    sent = bus_ok and nmt_stop_all(network)
    return safe_state_evidence(watchdog, heard if sent else set(), t_stop, how), errors


def safe_state_evidence(watchdog: Watchdog, alive: set[int], t_stop: float, how: str) -> list[dict[str, Any]]:
    """Wait (at most one consumer time and a heartbeat period) for the heartbeat of every node of
    ``alive`` — the drives and the plant node — to report STOPPED after ``t_stop``
    (``time.monotonic()``, s): a node that does not (it died or stalled while the run ended) is then
    overdue for the watchdog, which is still armed; one entry per drive saying how its torque was
    removed (``how``) and what shows it."""
    deadline = t_stop + watchdog.consumer_s + watchdog.period_s
    seen: dict[int, float] = {}
    while True:
        for nid in alive:
            if nid not in seen and (t := watchdog.events.stopped_since(nid, t_stop)) is not None:
                seen[nid] = t
        if all(n in seen for n in alive) or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    out = []
    for nid in DRIVE_NODE_IDS:
        entry: dict[str, Any] = {"node": node_name(nid), "node_id": nid, "torque": "unknown", "nmt": None}
        if nid in seen:
            entry.update(
                torque="off",
                nmt="STOPPED",
                evidence=f"{how}; its heartbeat reported STOPPED {1000 * (seen[nid] - t_stop):.0f} ms later",
            )
        elif nid in alive:
            entry["evidence"] = f"{how} sent; no STOPPED heartbeat within {1000 * (deadline - t_stop):.0f} ms (its log says more)"
        else:
            entry["evidence"] = "no heartbeat (the node or the bus is lost): its own fault reaction applies (see its log)"
        out.append(entry)
    return out
