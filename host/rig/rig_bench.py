"""The rig as the trial loop's bench: a :class:`host.experiment.bench.Bench` whose four drives and
plant are other processes, reached only over CAN with the ``canopen`` library.

This module owns :class:`RigBench`, which puts the rig's parts together on a canopen network that
the caller made and hands over (the ``ilcrig host`` role, :func:`host.rig.host_role.run_host_role`):

* the channel monitors and the bus-time accounting (:class:`host.rig.channels.RigChannels`);
* the watchdog and its fault classification (:class:`host.rig.watchdog.Watchdog`), hearing every
  node's heartbeats and EMCYs; a fault it declares cancels the SDO requests in progress and wakes
  the SYNC producer;
* the host's heartbeat producer (:class:`host.rig.host_heartbeat.HostHeartbeat`);
* the nodes and their bring-up, PDO configuration included (:mod:`host.rig.bring_up`);
* the trials (:class:`host.rig.trial_runner.TrialRunner`) and, with ``--ff-transport pdo``, the
  SYNC/RPDO/TPDO streaming (:class:`host.rig.pdo_stream.SyncProducer`);
* the end: every drive still alive torque-free with the evidence from the bus
  (:func:`host.rig.shutdown.bring_to_safe_state`) while the watchdog still watches, and a fault
  seen after the trial loop's last step — between its last trial and the drives' safe state, or
  an SDO request of the shutdown that failed — as :meth:`RigBench.closing_fault`; the facts for the
  summary (:meth:`RigBench.info`).

Every SDO error of canopen's own objects that leaves the bring-up or the recovery is the project's
(:func:`host.nodes.sdo_access.sdo_errors`): an ``sdo_error`` through the run's one fault path.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, cast

import canopen
import numpy as np

from bus.cia301.nmt import CONSUMER_TIME_MS, HOST_HEARTBEAT_MS, HOST_NODE_ID, NODE_HEARTBEAT_MS
from bus.objects import DRIVE_NODE_IDS
from bus.traffic import DEFAULT_BITRATE
from bus.transports.config import FIELDBUS, IO, TransportConfig
from bus.transports.hub.client import NOTHING_IN
from bus.units import timeout_scale
from host.experiment.bench import CyclicActuals, CyclicSetpoints
from host.experiment.config import ExperimentConfig
from host.experiment.faults import FaultRecord
from host.nodes.drive_client import DriveClient
from host.nodes.sdo_access import sdo_errors
from host.rig.bring_up import BringUp, RigNodes
from host.rig.bus_accounting import BusTimeAccounting
from host.rig.channels import RigChannels
from host.rig.fault_classify import sdo_fault
from host.rig.host_heartbeat import LEASE_CONSUMER_TIMES, HostHeartbeat
from host.rig.pdo_stream import SyncProducer
from host.rig.shutdown import bring_to_safe_state
from host.rig.trial_runner import TrialRunner
from host.rig.watchdog import Watchdog

logger = logging.getLogger(__name__)

__all__ = ["RigBench"]

#: the SDO response timeout (× ILCRIG_TIMEOUT_SCALE), s: generous, 7 processes share 2 cores and a
#: starved node answers late, not never
SDO_TIMEOUT_S = 5.0


class RigBench:
    """Drives and plant as CANopen nodes on the fieldbus (see the module docstring).

    :param cfg: the experiment
    :param network: the canopen network of the fieldbus, handed over by the caller, who keeps owning
        its bus (and disconnects it after :meth:`close`); not connected yet, or connected
    :param transport: the run's transport (the monitors open their own buses of it)
    :param out_dir: the run folder (candump logs, injection records), or None
    :param wait_s: how long a node may take to boot and answer, s
    :param pause_s: a pause before every trial but the first, s
    :param recover_s: > 0: a node lost or rebooted *between* trials is waited for (up to
        ``wait_s``) and set up again instead of ending the run (during a trial it always ends it)
    :param realtime: the plant node paces the ticks to the wall clock
    :param io_bitrate: the io channel's bit rate for the bus-time figures, bit/s
    :param fieldbus_bitrate: the fieldbus's bit rate for the bus-time figures, bit/s
    :param bus_time_hub: the hub carries both channels in bus time (``--bus-time``)
    :param rt_scheduling: how the launcher scheduled the lockstep processes of a real-time run
        (:func:`host.rig.realtime.raise_lockstep_priority`)
    """

    def __init__(
        self,
        cfg: ExperimentConfig,
        network: canopen.Network,
        transport: TransportConfig,
        *,
        out_dir: Path | None,
        wait_s: float = 20.0,
        pause_s: float = 0.0,
        recover_s: float = 0.0,
        realtime: bool = False,
        io_bitrate: int = DEFAULT_BITRATE,
        fieldbus_bitrate: int = DEFAULT_BITRATE,
        bus_time_hub: bool = False,
        rt_scheduling: dict[str, Any] | None = None,
        firmware: str = "python",
    ) -> None:
        self.cfg = cfg
        #: the drives' firmware as the launcher started them (``--firmware``; recorded, not checked)
        self.firmware = firmware
        self.network = network
        self.transport = transport
        self.out_dir = out_dir
        self.pause_s = pause_s
        self.recover_s = recover_s
        self.realtime = realtime
        self.rt_scheduling = rt_scheduling
        #: the hub carries the channels in bus time at these bit rates (``--bus-time``), or None
        self.bus_time_hub = {FIELDBUS: int(fieldbus_bitrate), IO: int(io_bitrate)} if bus_time_hub else None
        self.scale = timeout_scale()
        self._t_start = time.monotonic()
        self._safe_state: list[dict[str, Any]] = []
        self._closing_fault: FaultRecord | None = None
        self._closed = False
        self.nodes: RigNodes | None = None
        self._heartbeat: HostHeartbeat | None = None
        self.bus_time = BusTimeAccounting(
            io_bitrate=io_bitrate,
            fieldbus_bitrate=fieldbus_bitrate,
            ts_s=cfg.ts_s,
            trial_s=round(2 * cfg.cycle_s / cfg.ts_s) * cfg.ts_s,
            heartbeat_ms=NODE_HEARTBEAT_MS,
            n_nodes=len(DRIVE_NODE_IDS) + 2,
        )  # the drives, the plant node and the host (HOST_HEARTBEAT_MS, the same)
        self.channels = RigChannels(transport, out_dir, self.bus_time)  # closes itself if it fails
        watchdog = self.watchdog = Watchdog(
            network,
            self.channels,
            bus_name="hub" if transport.needs_hub else transport.name,
            out_dir=out_dir,
            scale=self.scale,
            tolerate_lost_between_trials=recover_s > 0,
            t_start=self._t_start,
        )
        try:
            if network.notifier is None:
                cast(list[Any], network.listeners).append(watchdog.fieldbus_errors)
                network.connect()
            else:
                network.notifier.add_listener(watchdog.fieldbus_errors)
            nodes = self.nodes = RigNodes.add_to(network, SDO_TIMEOUT_S * self.scale)
            for nid, node in nodes.remote.items():
                watchdog.events.listen_to(nid, node)
            watchdog.on_fault(lambda record: nodes.cancel(f"the run stopped: {record.message}"))
            streamer = self.streamer = SyncProducer(network, watchdog.raise_if_fault) if cfg.ff_transport == "pdo" else None
            self.trials = TrialRunner(nodes.plant, watchdog, streamer, marks=self.channels)
            if streamer is not None:
                streamer.explain_missing = self.trials.explain_missing_tpdo
                watchdog.on_fault(streamer.wake)
            self.bring_up = BringUp(
                network,
                nodes,
                watchdog,
                cfg,
                wait_s=wait_s,
                scale=self.scale,
                realtime=realtime,
                on_pdos=streamer.attach if streamer is not None else None,
                on_watched=watchdog.arm,
            )
            # the beats from a thread of C on a member of their own where the hub can (host_heartbeat.py)
            own_bus = transport.open(FIELDBUS, can_filters=NOTHING_IN) if transport.needs_hub else None
            self._heartbeat = watchdog.producer = HostHeartbeat(
                network,
                HOST_HEARTBEAT_MS / 1000.0,
                own_bus=own_bus,
                lease_s=LEASE_CONSUMER_TIMES * CONSUMER_TIME_MS * self.scale / 1000.0,
            )
            self._heartbeat.start()
            watchdog.start()
        except Exception:
            self.close()
            raise

    # -- Bench protocol ----------------------------------------------------------------
    @property
    def drives(self) -> list[DriveClient]:
        """The drives' clients in joint order."""
        return self.nodes.drives if self.nodes is not None else []

    def start(self) -> None:
        """Every node booted and brought up (:meth:`host.rig.bring_up.BringUp.start_all`); from the
        moment every node's heartbeat is watched the watchdog ends the run on any fault."""
        with sdo_errors(None, "bring-up"):
            self.bring_up.start_all()
        self.watchdog.arm()

    def hold_heartbeat(self, seconds: float | None) -> None:
        """The host's heartbeat goes on for ``seconds`` whether or not the host's interpreter runs
        (a law's code runs meanwhile); None: back to its usual lease (:meth:`HostHeartbeat.hold`)."""
        if self._heartbeat is not None:
            self._heartbeat.hold(seconds)

    def recover(self, trial: int) -> list[int]:
        """Before ``trial``: with ``recover_s`` > 0, nodes whose heartbeat was lost or that booted
        again are waited for and brought up again; returns the indices of the drives that the host
        must configure again (gains, reference, enable). Without it (the default) a lost node has
        ended the run already (the watchdog)."""
        watchdog = self.watchdog
        watchdog.trial = trial
        if trial > 0 and self.pause_s > 0:
            time.sleep(self.pause_s)
        watchdog.raise_if_fault()
        if self.recover_s <= 0:
            watchdog.check_settled()
            watchdog.raise_if_fault()
            return []
        with sdo_errors(None, "recovery"):
            return self.bring_up.recover(trial)

    def run_trial(
        self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray, cyclic: CyclicSetpoints | None = None
    ) -> CyclicActuals | None:
        return self.trials.run(trial, n_ticks, q0, qd0, cyclic)

    def describe_fault(self, exc: BaseException, trial: int) -> FaultRecord | None:
        """What the host knows about ``exc``: the watchdog's record, else the bench's state."""
        return self.watchdog.describe(exc, trial)

    def progress(self) -> int | None:
        """The last tick of the current trial as the io channel shows it (0 while it runs and none
        was seen yet, None outside a trial; at most the trial's last tick N − 1: the plant's
        encoder frame of tick N is the state after it)."""
        tick = self.channels.trial_tick(self.watchdog.trial)
        if tick is not None:
            tick = min(tick, self.cfg.n_ticks - 1)
        return 0 if tick is None and self.watchdog.in_trial else tick

    def closing_fault(self) -> FaultRecord | None:
        """After :meth:`close`: the fault the watchdog declared (also one it declared after the
        trial loop's last step, which nobody raised), or a failed SDO request of the shutdown."""
        return self.watchdog.fault or self._closing_fault

    def info(self) -> dict[str, Any]:
        """Transport, per-channel frame counts, bus time, heartbeat timing, trial timing, EMCYs,
        recoveries (and with PDOs the SYNC/RPDO/TPDO frame counts)."""
        wall = time.monotonic() - self._t_start
        return {
            "transport": self.transport.as_dict(),
            "channels": self.channels.info(wall),
            "channels_basis": "every frame seen on the channel since the host started; emulator_throughput_bits_per_s: "
            "their bits (worst-case stuffing) per second of wall time, a speed of the emulator, "
            "not a bus load (see bus_time)",
            "bus_time": self.bus_time.summary(len(self.trials.timings)),
            "bus_time_hub": self.bus_time_hub,
            "elapsed_s": wall,
            "heartbeat": {
                "host_node_id": HOST_NODE_ID,
                "host_period_ms": HOST_HEARTBEAT_MS,
                "node_period_ms": NODE_HEARTBEAT_MS,
                "consumer_time_ms": CONSUMER_TIME_MS * self.scale,
                "host_stalls": list(self.watchdog.stalls),
            },
            "timing": self.trials.timing(self.cfg.ts_s, self.realtime, self.rt_scheduling),
            "emcy": self.watchdog.events.emcy,
            "recoveries": self.bring_up.recoveries,
            "firmware": self.firmware,
        } | ({"pdo_frames": dict(self.streamer.frames)} if self.streamer is not None else {})

    def safe_state(self) -> list[dict[str, Any]]:
        """Per drive, after :meth:`close`: torque off and the evidence from the bus."""
        return list(self._safe_state)

    def close(self) -> None:
        """Every drive still alive to a torque-free state with the evidence from the heartbeats
        (:func:`host.rig.shutdown.bring_to_safe_state`) — the watchdog armed until then: what it
        sees now (a node lost, an EMCY, this process stopped a moment ago) and while the drives
        stop is the run's fault (:meth:`closing_fault`) — then stop the host's heartbeat, the
        watchdog and the monitors. The network stays with its owner. Never raises."""
        if self._closed:
            return
        self._closed = True
        watchdog = self.watchdog
        try:
            watchdog.check_settled()
        except Exception:  # noqa: BLE001 - closing must go on
            logger.debug("final watchdog round failed", exc_info=True)
        trial_running = watchdog.in_trial or self.channels.running_tick() is not None
        self._safe_state, errors = bring_to_safe_state(self.network, self.nodes, watchdog, trial_running=trial_running)
        watchdog.watch_round()
        watchdog.disarm()
        if errors and watchdog.fault is None:
            self._closing_fault = sdo_fault(errors[0], watchdog.trial, time.monotonic())
        if self._heartbeat is not None:
            self._heartbeat.stop()
        watchdog.stop()
        self.channels.close()
