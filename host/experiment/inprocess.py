"""Composition root of ``ilcrig sim``: the only host module (with the CLI's role dispatch) that
imports the drive firmware.  It wires four firmware drives and the true plant in one process,
no IPC.

In-process lockstep is exactly the rig's tick protocol without frames: per tick the plant's
encoder counts go to each drive's ``io_tick`` and the returned integer torques drive the
plant's zero-order-hold step.  The host talks to the drives through their object dictionary
(the :class:`~firmware_model.drive.Drive` implements the object-access protocol
:class:`bus.cia301.sdo.ObjectAccess`), the same path an SDO client takes in the rig.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from bus import units
from bus.cia301.nmt import NmtCommand
from bus.objects import DRIVE_NODE_IDS
from firmware_model.drive import Drive
from host.experiment.config import ExperimentConfig
from host.experiment.faults import FaultKind, FaultRecord
from host.experiment.loop import TrialFault
from host.nodes.drive_client import DriveClient
from plant.disturbance import disturbance_torque
from plant.params import default_true_plant
from plant.simulator import Plant, PlantError

logger = logging.getLogger(__name__)



def make_plant(cfg: ExperimentConfig) -> Plant:
    """The true plant of an experiment (same construction in every mode)."""
    return Plant(default_true_plant(), cfg.ts_s, cfg.substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)


class InProcessBench:
    """Four firmware drives and the plant in this process, ticked in lockstep."""

    def __init__(self, cfg: ExperimentConfig) -> None:
        self.cfg = cfg
        self.plant = make_plant(cfg)
        self.firmware = [Drive(node) for node in DRIVE_NODE_IDS]
        self.drives = [DriveClient(fw, node) for fw, node in zip(self.firmware, DRIVE_NODE_IDS)]
        self.emcy: list[dict[str, Any]] = []
        self._tick: int | None = None

    def start(self) -> None:
        for fw in self.firmware:
            fw.nmt_command(NmtCommand.START)

    def run_trial(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray) -> None:
        dist = disturbance_torque(self.cfg.disturbance, self.cfg.seed, trial, n_ticks, self.cfg.ts_s)
        plant, fws = self.plant, self.firmware
        plant.reset(q0, qd0)
        tau = np.zeros(4, dtype=np.int64)
        ticks = [fw.io_tick for fw in fws]
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
            self._collect_emcy(trial)
            msg = f"plant error at tick {n} of trial {trial}: {exc}"
            raise TrialFault(msg, FaultRecord(kind=FaultKind.PLANT_ERROR, message=msg, node="plant", trial=trial,
                                              tick=n, detected_by="plant")) from exc
        self._tick = None
        faults = self._collect_emcy(trial)
        if faults:
            first = faults[0]
            fw = self.firmware[DRIVE_NODE_IDS.index(first["node"])]
            tick = int.from_bytes(fw.read_object(0x2120, 3), "little")
            msg = "; ".join(f"node {e['node']}: EMCY 0x{e['code']:04X}" for e in faults)
            raise TrialFault(msg, FaultRecord(kind=FaultKind.EMCY, message=msg, node=f"drive{first['node']}",
                                              node_id=first["node"], trial=trial, tick=tick,
                                              detected_by=f"drive{first['node']}", latency_ms=0.0,
                                              latency_basis="same process"))

    def _collect_emcy(self, trial: int) -> list[dict[str, Any]]:
        """Move pending EMCY frames into the log; return the new fault (non-reset) ones."""
        faults = []
        for node, fw in zip(DRIVE_NODE_IDS, self.firmware):
            for code, reg, _data in fw.pop_emcy():
                entry = {"node": node, "code": code, "register": reg, "trial": trial}
                self.emcy.append(entry)
                if code != 0:
                    faults.append(entry)
        return faults

    def recover(self, trial: int) -> list[int]:
        """Nothing reboots in one process: no drive needs setting up again."""
        return []

    def info(self) -> dict[str, Any]:
        return {"emcy": self.emcy}

    def progress(self) -> int | None:
        """The tick of the trial in progress (None between trials)."""
        return self._tick

    def close(self) -> None:
        for fw in self.firmware:
            try:
                fw.nmt_command(NmtCommand.STOP)  # removes torque
            except Exception:  # closing must never hide the original error
                logger.debug("stopping drive failed", exc_info=True)

    def safe_state(self) -> list[dict[str, Any]]:
        """Per drive after :meth:`close`: torque off (NMT STOPPED), its CiA 402 state."""
        return [{"node": f"drive{nid}", "node_id": nid, "torque": "on" if fw.torque_enabled else "off",
                 "nmt": fw.nmt_state.name, "cia402": fw.cia402_state.name,
                 "evidence": "in-process firmware: NMT STOPPED"}
                for nid, fw in zip(DRIVE_NODE_IDS, self.firmware)]
