"""Bringing the rig's nodes up: the canopen nodes of the four drives and the plant node, their
heartbeats, NMT start and (``--ff-transport pdo``) their PDO configuration.

This module owns

* :class:`RigNodes` — every node as a ``canopen.RemoteNode`` built from its EDS (bus/drive.eds,
  bus/plant.eds) on the given network, with the host's clients over SDO
  (:class:`host.nodes.drive_client.DriveClient`, :class:`host.nodes.plant_client.PlantClient`
  through :class:`host.nodes.sdo_access.SdoAccess`, block transfer for tables and recorder data);
* :class:`BringUp` — NMT reset communication and every node's boot-up (a bus fault heard while
  they are awaited ends the wait as the run's fault: a lost datagram may have been a boot-up); per node: SDO answered,
  a heartbeat producer period (0x1017) and a consumer entry for the host's heartbeat (0x1016:1),
  PDOs configured, NMT START and its first OPERATIONAL heartbeat; the plant node configured; and
  with ``--recover`` the same for a node lost or rebooted between trials.  Once every node's
  heartbeat is watched the watchdog is armed (``on_watched``): a node lost during the rest of the
  bring-up is a fault of the run like any other; an SDO request of the bring-up that fails is one
  :class:`host.nodes.sdo_access.SdoTransportError` / :class:`bus.errors.SdoAbort` (an ``sdo_error``);
* :func:`configure_pdos` — RPDO1 (target position, torque offset) and TPDO1 (position actual,
  torque actual), synchronous, with the canopen library's PDO API (``node.rpdo`` / ``node.tpdo``:
  read, map, save) in NMT PRE-OPERATIONAL (layout: :mod:`bus.cyclic`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import KW_ONLY, InitVar, dataclass, field
from typing import Any

import canopen

from bus.cia301.nmt import (
    CONSUMER_HEARTBEAT_INDEX,
    CONSUMER_TIME_MS,
    HOST_NODE_ID,
    NODE_HEARTBEAT_MS,
    NmtCommand,
    NmtState,
    consumer_entry,
)
from bus.cyclic import CSP_RPDO_MAP, RPDO_NUMBER, TPDO_MAP, TPDO_NUMBER, TRANSMISSION_TYPE, rpdo_cob_id, tpdo_cob_id
from bus.objects import DRIVE_EDS_PATH, DRIVE_NODE_IDS
from bus.plant_objects import DEFAULT_PLANT_NODE_ID as PLANT_NODE_ID
from bus.plant_objects import PLANT_EDS_PATH
from host.experiment.bench import TrialFault
from host.experiment.config import ExperimentConfig
from host.nodes.drive_client import DriveClient
from host.nodes.plant_client import PlantClient
from host.nodes.sdo_access import SdoAccess, sdo_errors
from host.rig.watchdog import Watchdog

logger = logging.getLogger(__name__)

__all__ = ["BringUp", "RigNodes", "configure_pdos"]

#: the five nodes of the rig
NODE_IDS = (*DRIVE_NODE_IDS, PLANT_NODE_ID)
#: how long the nodes get to report OPERATIONAL after NMT START, s
OPERATIONAL_WAIT_S = 5.0
#: how often the boot-up wait looks at the bus (a bus fault heard ends it at once), s
BOOT_POLL_S = 0.05


@dataclass
class RigNodes:
    """The drives and the plant node as canopen nodes and the host's clients of them.

    :ivar remote: node id → ``canopen.RemoteNode`` (drives 1..4, the plant node)
    :ivar drives: the drives' clients in joint order
    :ivar plant: the plant node's client
    :ivar accesses: every node's SDO access (cancelled together when a fault is declared)
    """

    remote: dict[int, canopen.RemoteNode]
    drives: list[DriveClient]
    plant: PlantClient
    accesses: list[SdoAccess]

    @classmethod
    def add_to(cls, network: canopen.Network, sdo_timeout_s: float) -> RigNodes:
        """Add the five nodes to ``network`` from their EDS files, with an SDO response timeout of
        ``sdo_timeout_s`` seconds."""
        remote = {nid: network.add_node(nid, str(DRIVE_EDS_PATH)) for nid in DRIVE_NODE_IDS}
        remote[PLANT_NODE_ID] = network.add_node(PLANT_NODE_ID, str(PLANT_EDS_PATH))
        for node in remote.values():
            node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
        accesses = [SdoAccess(remote[nid]) for nid in NODE_IDS]
        drives = [DriveClient(acc, nid) for acc, nid in zip(accesses, DRIVE_NODE_IDS)]
        return cls(remote, drives, PlantClient(accesses[-1]), accesses)

    def cancel(self, reason: str) -> None:
        """Cancel every SDO request in progress and to come (a fault was declared)."""
        for acc in self.accesses:
            acc.cancel(reason)


def configure_pdos(node: Any) -> tuple[Any, Any]:
    """RPDO1 (target position, torque offset) and TPDO1 (position actual, torque actual) of the
    drive ``node`` (a ``canopen.RemoteNode``), both synchronous, with the canopen library's PDO
    API; the mapping may change only in NMT PRE-OPERATIONAL (CiA 301), so the node is put there
    first. Returns the (RPDO1, TPDO1) map objects.

    :raises SdoTransportError: an SDO request of the configuration was not answered
    :raises SdoAbort: the node refused one
    """
    node.nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)
    with sdo_errors(node.id, "PDO configuration"):
        node.rpdo.read()
        node.tpdo.read()
        for pdo_map, mapping, cob_id in (
            (node.rpdo[RPDO_NUMBER], CSP_RPDO_MAP, rpdo_cob_id(node.id)),
            (node.tpdo[TPDO_NUMBER], TPDO_MAP, tpdo_cob_id(node.id)),
        ):
            pdo_map.clear()
            for index, sub, bits in mapping:
                pdo_map.add_variable(index, sub, bits)
            pdo_map.cob_id = cob_id
            pdo_map.trans_type = TRANSMISSION_TYPE
            pdo_map.enabled = True
            pdo_map.save()
    logger.info("node %d: RPDO1 0x%03X and TPDO1 0x%03X configured", node.id, rpdo_cob_id(node.id), tpdo_cob_id(node.id))
    return node.rpdo[RPDO_NUMBER], node.tpdo[TPDO_NUMBER]


@dataclass(eq=False)
class BringUp:
    """Brings the nodes of ``nodes`` to NMT OPERATIONAL (see the module docstring).

    :ivar network: the fieldbus (NMT broadcasts, boot-up frames)
    :ivar nodes: the nodes and their clients
    :ivar watchdog: hears the heartbeats; a fault it declares meanwhile ends the bring-up
    :ivar cfg: the experiment (the plant node's configuration)
    :ivar wait_s: how long a node may take to boot and answer SDO, s
    :param scale: the timeout scale of the consumer time the nodes get for the host's heartbeat
    :ivar realtime: the plant node paces the ticks to the wall clock
    :ivar on_pdos: with ``--ff-transport pdo``: called with each drive's node id and its
        configured (RPDO1, TPDO1) maps; None: the drives keep their PDOs off
    :ivar on_watched: called once every node's heartbeat is watched (the watchdog is armed then)
    :ivar recoveries: per node brought up again between trials: node, before which trial, and
        whether its heartbeat was lost and/or its boot-up seen
    """

    network: canopen.Network
    nodes: RigNodes
    watchdog: Watchdog
    cfg: ExperimentConfig
    _: KW_ONLY
    wait_s: float
    scale: InitVar[float]
    realtime: bool
    on_pdos: Callable[[int, Any, Any], None] | None = None
    on_watched: Callable[[], None] | None = None
    #: the consumer time the nodes get for the host's heartbeat, ms
    consumer_ms: int = field(init=False)
    recoveries: list[dict[str, Any]] = field(default_factory=list, init=False)

    def __post_init__(self, scale: float) -> None:
        self.consumer_ms = min(round(CONSUMER_TIME_MS * scale), 0xFFFF)

    def start_all(self) -> None:
        """Every node's boot-up awaited, then all five brought up (:meth:`bring_up`)."""
        node_ids, what = set(NODE_IDS), "(are the drive and plant processes running on this bus?)"
        self.await_boot_ups(node_ids, what)
        self.bring_up(node_ids, what, first=True)

    def await_boot_ups(self, node_ids: set[int], what: str) -> None:
        """NMT reset communication (broadcast), then wait for every node's boot-up: a running node
        announces itself again, one still starting (compiling) when it is up. So no SDO request
        goes to a node that is not running yet (it would time out, and canopen logs the abort
        at ERROR level).

        :raises TrialFault: a node did not boot within ``wait_s`` (``what`` says what to check), or
            a bus fault or a node's EMCY was heard meanwhile
            (:meth:`host.rig.watchdog.Watchdog.raise_if_start_fault`)
        """
        booted: set[int] = set()
        all_booted = threading.Event()

        def on_boot_up(can_id: int, data: bytearray, timestamp: float) -> None:
            if data[:1] == bytes([NmtState.BOOT_UP]):
                booted.add(can_id - 0x700)
                if booted >= node_ids:
                    all_booted.set()

        for nid in node_ids:
            self.network.subscribe(0x700 + nid, on_boot_up)
        try:
            self.network.nmt.send_command(NmtCommand.RESET_COMMUNICATION)
            deadline = time.monotonic() + self.wait_s
            while not all_booted.wait(BOOT_POLL_S):
                self.watchdog.raise_if_start_fault()
                if time.monotonic() >= deadline:
                    raise TrialFault(
                        f"no boot-up from node(s) {', '.join(map(str, sorted(node_ids - booted)))} "
                        f"within {self.wait_s:g} s {what}"
                    )
        finally:
            for nid in node_ids:
                self.network.unsubscribe(0x700 + nid, on_boot_up)

    def bring_up(self, node_ids: set[int], what: str, *, first: bool = False) -> None:
        """Wait until ``node_ids`` answer SDO, give them a heartbeat and a consumer of the host's,
        configure their PDOs, NMT-start them and wait for their first operational heartbeat.
        ``first``: the run's first bring-up — once the heartbeats are watched, the boot-ups seen so
        far are forgotten, every node gets a consumer time for its first heartbeat and
        ``on_watched`` is called.

        :raises TrialFault: a node did not answer, did not become operational, or a fault was declared
        """
        remote = self.nodes.remote
        deadline = time.monotonic() + self.wait_s
        waiting = set(node_ids)
        while waiting:
            for nid in sorted(waiting):
                try:
                    remote[nid].sdo.upload(0x1000, 0)
                    waiting.discard(nid)
                except (canopen.SdoCommunicationError, canopen.SdoAbortedError):
                    pass
            self.watchdog.raise_if_start_fault()  # a node that lost the request may have said so
            if waiting and time.monotonic() > deadline:
                raise TrialFault(f"node(s) {', '.join(map(str, sorted(waiting)))} did not answer within {self.wait_s:g} s {what}")
        for nid in sorted(node_ids):
            with sdo_errors(nid, "heartbeat configuration"):
                remote[nid].sdo.download(0x1017, 0, NODE_HEARTBEAT_MS.to_bytes(2, "little"))
                remote[nid].sdo.download(
                    CONSUMER_HEARTBEAT_INDEX, 1, consumer_entry(HOST_NODE_ID, self.consumer_ms).to_bytes(4, "little")
                )
            self.watchdog.events.watch(nid)
        if first:
            self.watchdog.events.report()  # the boot-ups of the start
            self.watchdog.events.grace(time.monotonic())  # a consumer time for every first heartbeat
            if self.on_watched is not None:
                self.on_watched()
        if self.on_pdos is not None:
            for nid in sorted(node_ids & set(DRIVE_NODE_IDS)):
                self.on_pdos(nid, *configure_pdos(remote[nid]))
        for nid in sorted(node_ids):
            remote[nid].nmt.send_command(NmtCommand.START)
        if PLANT_NODE_ID in node_ids:
            cfg = self.cfg
            self.nodes.plant.configure(
                cfg.ts_s, cfg.substeps, cfg.disturbance, cfg.seed, paced=self.realtime, plant_scales=cfg.plant.as_tuple()
            )
        t_end = time.monotonic() + OPERATIONAL_WAIT_S
        while True:
            self.watchdog.raise_if_fault()
            states = self.watchdog.events.states(node_ids)
            if all(s == NmtState.OPERATIONAL for s in states.values()):
                break
            if time.monotonic() > t_end:
                raise TrialFault(f"nodes not operational after NMT start: {states}")
            time.sleep(0.02)
        self.watchdog.events.report()  # forget the boot-ups seen while starting

    def recover(self, trial: int) -> list[int]:
        """Before ``trial``: nodes whose heartbeat was lost or that booted again are waited for (up
        to ``wait_s``) and brought up again; returns the indices of the drives that the host must
        configure again (gains, reference, enable)."""
        report = self.watchdog.events.report()
        lost = set(report.overdue) | set(report.booted)
        if not lost:
            return []
        logger.warning("node(s) %s lost or rebooted before trial %d: waiting for them", sorted(lost), trial)
        self.bring_up(lost, "after losing them")
        for nid in sorted(lost):
            self.recoveries.append(
                {
                    "node": nid,
                    "before_trial": trial,
                    "heartbeat_lost": nid in report.overdue,
                    "boot_up_seen": nid in report.booted,
                }
            )
        return [DRIVE_NODE_IDS.index(n) for n in sorted(lost) if n in DRIVE_NODE_IDS]
