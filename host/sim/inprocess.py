"""The in-process bench of ``ilcrig sim`` and the API: with :mod:`host.sim` (its composition
root) and the CLI's drive role, the only host code that imports the drive firmware.  It wires four
firmware drives and the true plant in one process, no IPC.

In-process lockstep is exactly the rig's tick protocol without frames: per tick the plant's
encoder counts go to each drive's ``io_tick`` and the returned integer torques drive the
plant's zero-order-hold step.  The host talks to the drives through their object dictionary
(the :class:`~firmware_model.drive.Drive` implements the object-access protocol
:class:`bus.cia301.sdo.ObjectAccess`), the same path an SDO client takes in the rig.

With the pdo feed-forward transport the bench configures each drive's PDOs with the same CiA 301
writes the rig host makes through the canopen library (:func:`bus.cyclic.pdo_config_writes`, in
PRE-OPERATIONAL before NMT start) and runs per tick exactly the rig's SYNC/PDO handshake without
frames (docs/timing.md §7): RPDO1 payload bytes → ``Drive.on_rpdo``, ``Drive.on_sync``, the io tick,
then the TPDO bytes of ``Drive.pop_tpdos`` decoded as the host decodes them.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from bus import units
from bus.cia301.nmt import NmtCommand
from bus.cyclic import decode_tpdo, encode_csp_rpdo, pdo_config_writes, rpdo_cob_id, tpdo_cob_id
from bus.objects import DRIVE_NODE_IDS, ControlCommand, Obj
from bus.pil_fault import pil_target_fault
from firmware_model.drive import Drive
from firmware_model.firmware_select import DEFAULT_FIRMWARE, check_firmware
from host.experiment.bench import CyclicActuals, CyclicSetpoints, TrialFault
from host.experiment.config import ExperimentConfig
from host.experiment.faults import FaultKind, FaultRecord
from host.nodes.drive_client import DriveClient
from plant.disturbance import disturbance_torque
from plant.params import default_true_plant, scaled_true_plant
from plant.simulator import Plant, PlantError

logger = logging.getLogger(__name__)


def make_plant(cfg: ExperimentConfig) -> Plant:
    """The true plant of an experiment (same construction in every mode): the emulated robot with the
    experiment's plant-uncertainty factors (``cfg.plant``)."""
    true_plant = scaled_true_plant(default_true_plant(), cfg.plant)
    return Plant(true_plant, cfg.ts_s, cfg.substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)


class InProcessBench:
    """Four firmware drives and the plant in this process, ticked in lockstep.

    :param firmware: the drives' control-period implementation (``--firmware``, one of
        :data:`firmware_model.firmware_select.FIRMWARES`; recorded in ``summary["bench"]["firmware"]``)
    :raises InputError: a firmware this installation cannot run
    """

    def __init__(self, cfg: ExperimentConfig, firmware: str = DEFAULT_FIRMWARE) -> None:
        self.cfg = cfg
        self.plant = make_plant(cfg)
        self.firmware_kind = check_firmware(firmware)
        self.firmware = [Drive(node, firmware=firmware) for node in DRIVE_NODE_IDS]
        self.drives = [DriveClient(fw, node) for fw, node in zip(self.firmware, DRIVE_NODE_IDS)]
        self.emcy: list[dict[str, Any]] = []
        self._tick: int | None = None

    def start(self) -> None:
        for node, fw in zip(DRIVE_NODE_IDS, self.firmware):
            if self.cfg.ff_transport == "pdo":  # PDO mapping: in PRE-OPERATIONAL, as in the rig
                for index, sub, value, size in pdo_config_writes(node):
                    fw.write_object(index, sub, value.to_bytes(size, "little"))
            fw.nmt_command(NmtCommand.START)

    def run_trial(
        self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray, cyclic: CyclicSetpoints | None = None
    ) -> CyclicActuals | None:
        if cyclic is not None:
            return self._run_cyclic_trial(trial, n_ticks, q0, qd0, cyclic)
        dist = self._begin(trial, n_ticks, q0, qd0)
        plant = self.plant
        tau = np.zeros(4, dtype=np.int64)
        ticks = [fw.io_tick for fw in self.firmware]
        n = 0
        try:
            for n in range(n_ticks):
                self._tick = n
                c = plant.encoder_counts()
                tau[0] = ticks[0](n, int(c[0]))
                tau[1] = ticks[1](n, int(c[1]))
                tau[2] = ticks[2](n, int(c[2]))
                tau[3] = ticks[3](n, int(c[3]))
                plant.step(tau, dist[n])
        except PlantError as exc:
            raise self._plant_fault(trial, n, exc) from exc
        self._end(trial)
        return None

    def _begin(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray) -> np.ndarray:
        """Reset the plant to (q0 [rad], qd0 [rad/s]); the trial's disturbance torque (N, 4) [N·m]."""
        self.plant.reset(q0, qd0)
        return disturbance_torque(self.cfg.disturbance, self.cfg.seed, trial, n_ticks, self.cfg.ts_s)

    def _plant_fault(self, trial: int, n: int, exc: PlantError) -> TrialFault:
        """The trial's fault for a plant error at tick ``n`` (the drives' EMCYs are collected)."""
        self._collect_emcy(trial)
        msg = f"plant error at tick {n} of trial {trial}: {exc}"
        return TrialFault(
            msg, FaultRecord(kind=FaultKind.PLANT_ERROR, message=msg, node="plant", trial=trial, tick=n, detected_by="plant")
        )

    def _end(self, trial: int) -> None:
        """After the last tick: an EMCY of the trial is its fault."""
        self._tick = None
        faults = self._collect_emcy(trial)
        if faults:
            raise self._emcy_fault(trial, faults)

    def _emcy_fault(self, trial: int, faults: list[dict[str, Any]]) -> TrialFault:
        """The trial's fault for the EMCYs ``faults`` (the first names node and tick)."""
        first = faults[0]
        fw = self.firmware[DRIVE_NODE_IDS.index(first["node"])]
        tick = int.from_bytes(fw.read_object(0x2120, 3), "little")
        msg = "; ".join(f"node {e['node']}: {e['pil'][0] + ', ' if e['pil'] else ''}EMCY 0x{e['code']:04X}" for e in faults)
        return TrialFault(
            msg,
            FaultRecord(
                kind=FaultKind.EMCY,
                message=msg,
                node=f"drive{first['node']}",
                node_id=first["node"],
                trial=trial,
                tick=tick,
                detected_by=f"drive{first['node']}",
                latency_ms=0.0,
                latency_basis="same process",
            ),
        )

    def _run_cyclic_trial(
        self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray, cyclic: CyclicSetpoints
    ) -> CyclicActuals:
        """The rig's per-tick SYNC/PDO handshake without frames: RPDO1 bytes, SYNC, io tick, TPDO1."""
        dist = self._begin(trial, n_ticks, q0, qd0)
        plant, fws = self.plant, self.firmware
        tau = np.zeros(4, dtype=np.int64)
        pos = np.zeros((n_ticks, 4), dtype=np.int64)
        torque = np.zeros((n_ticks, 4), dtype=np.int64)
        rx = [rpdo_cob_id(node) for node in DRIVE_NODE_IDS]
        tx = [tpdo_cob_id(node) for node in DRIVE_NODE_IDS]
        target, offset = cyclic.target_counts, cyclic.torque_offset_permille
        n = 0
        try:
            for n in range(n_ticks):
                self._tick = n
                c = plant.encoder_counts()
                for j, fw in enumerate(fws):
                    fw.on_rpdo(rx[j], encode_csp_rpdo(int(target[n, j]), int(offset[n, j])))
                for fw in fws:
                    fw.on_sync()
                for j, fw in enumerate(fws):
                    tau[j] = fw.io_tick(n, int(c[j]))
                    for cob, data in fw.pop_tpdos():
                        if cob == tx[j]:
                            pos[n, j], torque[n, j] = decode_tpdo(data)
                plant.step(tau, dist[n])
        except PlantError as exc:
            raise self._plant_fault(trial, n, exc) from exc
        self._end(trial)
        return CyclicActuals(pos, torque)

    def _collect_emcy(self, trial: int) -> list[dict[str, Any]]:
        """Move pending EMCY frames into the log; return the new fault (non-reset) ones."""
        faults = []
        for node, fw in zip(DRIVE_NODE_IDS, self.firmware):
            for code, reg, data in fw.pop_emcy():
                entry = {"node": node, "code": code, "register": reg, "trial": trial}
                self.emcy.append(entry)
                if code != 0:
                    faults.append(entry | {"pil": pil_target_fault(code, data)})
        return faults

    def recover(self, trial: int) -> list[int]:
        """Nothing reboots in one process: no drive needs setting up again."""
        return []

    def info(self) -> dict[str, Any]:
        return {"emcy": self.emcy, "firmware": self.firmware_kind}

    def progress(self) -> int | None:
        """The tick of the trial in progress (None between trials)."""
        return self._tick

    def close(self) -> None:
        """As the rig's host does: CiA 402 disable voltage (torque off, Switch on disabled; a drive
        in Fault stays there), then NMT STOP — the drives end without an abort-connection fault."""
        for fw in self.firmware:
            try:
                fw.write_object(Obj.CONTROLWORD, 0, int(ControlCommand.DISABLE_VOLTAGE).to_bytes(2, "little"))
            except Exception:  # closing must never hide the original error
                logger.debug("disable voltage failed", exc_info=True)
            try:
                fw.nmt_command(NmtCommand.STOP)  # removes torque
            except Exception:  # closing must never hide the original error
                logger.debug("stopping drive failed", exc_info=True)

    def safe_state(self) -> list[dict[str, Any]]:
        """Per drive after :meth:`close`: torque off (NMT STOPPED), its CiA 402 state."""
        return [
            {
                "node": f"drive{nid}",
                "node_id": nid,
                "torque": "on" if fw.torque_enabled else "off",
                "nmt": fw.nmt_state.name,
                "cia402": fw.cia402_state.name,
                "evidence": "in-process firmware: CiA 402 disable voltage, NMT STOPPED",
            }
            for nid, fw in zip(DRIVE_NODE_IDS, self.firmware)
        ]
