"""Composition root: the only host module that imports the drive firmware and the plant
simulator.  It wires them for ``ilcrig sim`` (all in one process, no IPC) and is where the
role launchers of ``ilcrig run`` live.

In-process lockstep is exactly the rig's tick protocol without frames: per tick the plant's
encoder counts go to each drive's ``io_tick`` and the returned integer torques drive the
plant's zero-order-hold step.  The host talks to the drives through their object dictionary
(``Drive.access()``), the same path an SDO client takes in the rig.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from bus import units
from firmware_model.drive import Drive
from host.config import ExperimentConfig
from host.drive_client import DriveClient
from host.experiment import TrialFault
from plant.disturbance import disturbance_torque
from plant.params import default_true_plant
from plant.simulator import Plant, PlantError

logger = logging.getLogger(__name__)

NODE_IDS: tuple[int, ...] = (1, 2, 3, 4)
NMT_START = 0x01


def make_plant(cfg: ExperimentConfig) -> Plant:
    """The true plant of an experiment (same construction in every mode)."""
    return Plant(default_true_plant(), cfg.ts_s, cfg.substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)


class InProcessBench:
    """Four firmware drives and the plant in this process, ticked in lockstep."""

    def __init__(self, cfg: ExperimentConfig) -> None:
        self.cfg = cfg
        self.plant = make_plant(cfg)
        self.firmware = [Drive(node) for node in NODE_IDS]
        self.drives = [DriveClient(fw.access(), node) for fw, node in zip(self.firmware, NODE_IDS)]
        self.emcy: list[dict[str, Any]] = []

    def start(self) -> None:
        for fw in self.firmware:
            fw.nmt_command(NMT_START)

    def run_trial(self, trial: int, n_ticks: int, q0: np.ndarray, qd0: np.ndarray) -> None:
        dist = disturbance_torque(self.cfg.disturbance, self.cfg.seed, trial, n_ticks, self.cfg.ts_s)
        plant, fws = self.plant, self.firmware
        plant.reset(q0, qd0)
        tau = np.zeros(4, dtype=np.int64)
        ticks = [fw.io_tick for fw in fws]
        try:
            for n in range(n_ticks):
                c = plant.encoder_counts()
                tau[0] = ticks[0](n, int(c[0]))
                tau[1] = ticks[1](n, int(c[1]))
                tau[2] = ticks[2](n, int(c[2]))
                tau[3] = ticks[3](n, int(c[3]))
                plant.step(tau, dist[n])
        except PlantError as exc:
            self._collect_emcy(trial)
            raise TrialFault(f"plant error at tick {n} of trial {trial}: {exc}") from exc
        faults = self._collect_emcy(trial)
        if faults:
            raise TrialFault("; ".join(f"node {e['node']}: EMCY 0x{e['code']:04X}" for e in faults))

    def _collect_emcy(self, trial: int) -> list[dict[str, Any]]:
        """Move pending EMCY frames into the log; return the new fault (non-reset) ones."""
        faults = []
        for node, fw in zip(NODE_IDS, self.firmware):
            for code, reg, _data in fw.pop_emcy():
                entry = {"node": node, "code": code, "register": reg, "trial": trial}
                self.emcy.append(entry)
                if code != 0:
                    faults.append(entry)
        return faults

    def info(self) -> dict[str, Any]:
        return {"emcy": self.emcy}

    def close(self) -> None:
        for fw in self.firmware:
            try:
                fw.nmt_command(0x02)  # stop: removes torque
            except Exception:  # closing must never hide the original error
                logger.debug("stopping drive failed", exc_info=True)


# -- the plant role of ``ilcrig run`` (the test-bench node) ------------------------------------

import threading  # noqa: E402

from bus.transport import TransportConfig  # noqa: E402


def run_plant_role(transport: TransportConfig, node_id: int = 32,
                   stop: threading.Event | None = None) -> None:
    """Plant process entry (``ilcrig plant``): the test-bench node on both buses of
    ``transport`` (a :class:`bus.transport.TransportConfig`), serving until SIGTERM/SIGINT or
    ``stop`` (a :class:`threading.Event`) is set; the buses are closed on the way out.

    The plant is the true plant of :func:`make_plant` (``default_true_plant``, encoder and
    torque LSBs of :mod:`bus.units`), rebuilt only when the host changes Ts or the sub-steps;
    the disturbance is :func:`plant.disturbance.disturbance_torque`.
    """
    from bus.bench_node import BenchNode
    from bus.slave import install_sigterm
    from plant.simulator import warm_up

    if stop is None:
        stop = threading.Event()
        install_sigterm(stop)
    true_plant = default_true_plant()
    logger.info("plant role: kernels ready in %.2f s", warm_up(true_plant))

    def plant_factory(ts_s: float, substeps: int) -> Plant:
        return Plant(true_plant, ts_s, substeps, units.RAD_PER_COUNT, units.TORQUE_LSB_NM)

    fieldbus = transport.open("fieldbus")
    try:
        io = transport.open("io")
        try:
            scale = units.timeout_scale()
            BenchNode(fieldbus, io, plant_factory=plant_factory, disturbance_fn=disturbance_torque,
                      node_id=node_id, tick_timeout_s=2.0 * scale, first_tick_timeout_s=10.0 * scale).run(stop)
        finally:
            io.shutdown()
    finally:
        fieldbus.shutdown()
