"""Host side of the plant node (the plant on the fieldbus): configuration, trial start,
status, waiting for the end of a trial.

Owns the host's view of the bench's object dictionary (:mod:`bus.plant_objects`,
``bus/plant.eds``).  Like :class:`host.nodes.drive_client.DriveClient` it only calls
``access.read_object(index, sub) -> bytes`` and ``access.write_object(index, sub, data)``; in the rig the
access is :class:`host.nodes.sdo_access.SdoAccess` over a canopen ``RemoteNode``.  Imports only
:mod:`bus` (plus the object-access protocol :class:`bus.cia301.sdo.ObjectAccess`).
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy.typing as npt

from bus.cia301.sdo import ObjectAccess
from bus.errors import IlcrigError
from bus.objects import u8 as _u8  # SDO payload encoders
from bus.objects import u16 as _u16
from bus.objects import u32 as _u32
from bus.plant_objects import (
    PLANT_SCALE_SUBS,
    PLANT_SCALES_AS_BUILT,
    ConfigSub,
    CounterSub,
    DeadlineMisses,
    DisturbanceKind,
    InitialStateError,
    PlantCommand,
    PlantFault,
    PlantObj,
    PlantStatus,
    PlantTrialSub,
    TrialTiming,
    disturbance_code,
    pack_initial_state,
    plant_scale_error,
    unpack_deadline_misses,
    unpack_trial_timing,
)

logger = logging.getLogger(__name__)

__all__ = ["PlantClient", "PlantState", "PlantClientError", "PlantInputError", "PlantTrialFault", "PlantTimeoutError"]

_U32_MAX = 0xFFFFFFFF
_F64 = struct.Struct("<d")


class PlantClientError(IlcrigError):
    """The plant node did not do what the host asked."""


class PlantInputError(PlantClientError, ValueError):
    """A host-side value the bench cannot represent (period not in whole µs, seed range...)."""


class PlantTrialFault(PlantClientError):
    """The trial ended in fault (see :attr:`state`)."""

    def __init__(self, message: str, state: PlantState) -> None:
        super().__init__(message)
        self.state = state


class PlantTimeoutError(PlantClientError, TimeoutError):
    """The trial did not end within the host's timeout (it was aborted)."""


#: what a plant fault says ({node}: the drive's node id, {tick}: the tick)
_FAULT_TEXT: dict[PlantFault, str] = {
    PlantFault.TICK_TIMEOUT: "drive {node} did not answer tick {tick}",
    PlantFault.TICK_SEQUENCE: "torque frame of drive {node} out of sequence at tick {tick}",
    PlantFault.BAD_FRAME: "malformed torque frame of drive {node} at tick {tick}",
    PlantFault.HOST_LOST: "the host's heartbeat was lost at tick {tick}",
    PlantFault.PLANT: "plant error at tick {tick}",
    PlantFault.ABORTED: "aborted at tick {tick}",
    PlantFault.FRAMES_LOST: "fieldbus frames lost in the plant node's receiver (receive overflow) at tick {tick}",
    PlantFault.IO_FRAMES_LOST: "io frames lost in the plant node's receiver (receive overflow) at tick {tick}",
}


@dataclass(frozen=True)
class PlantState:
    """0x2410 as read back."""

    status: PlantStatus
    ticks_done: int
    fault: PlantFault
    fault_tick: int
    fault_node: int

    def describe(self) -> str:
        """One line for messages and logs."""
        if self.status != PlantStatus.FAULT:
            return f"{self.status.name.lower()}, {self.ticks_done} ticks done"
        if self.fault == PlantFault.BAD_FRAME and not self.fault_node:
            what = f"bus error frame (a damaged frame) on io at tick {self.fault_tick}"
        else:
            text = _FAULT_TEXT.get(self.fault, f"fault code {int(self.fault)} at tick {{tick}}")
            what = text.format(node=self.fault_node, tick=self.fault_tick)
        return f"fault: {what} ({self.ticks_done} ticks done)"


class PlantClient:
    """Host-side client of the plant node.

    :param access: object access (``read``/``write`` bytes).
    """

    def __init__(self, access: ObjectAccess) -> None:
        self.access = access

    def _read_uint(self, index: int, sub: int) -> int:
        return int.from_bytes(self.access.read_object(index, sub), "little", signed=False)

    # ------------------------------------------------------------------ configuration

    def configure(
        self,
        ts_s: float,
        substeps: int,
        disturbance: str | int,
        seed: int,
        *,
        paced: bool = False,
        plant_scales: Sequence[float] = PLANT_SCALES_AS_BUILT,
    ) -> None:
        """Write the control period, RK4 sub-steps, disturbance kind, seed, pacing and the
        plant-uncertainty factors (0x2400).

        :param paced: real time: tick n starts at t0 + n·Ts on the plant's clock (else lockstep as
            fast as possible).

        :param ts_s: control period, s; must be a whole number of µs so the bench's
            Ts = µs / 10⁶ is the very same float (determinism).
        :param substeps: RK4 sub-steps per period, 1..1000.
        :param disturbance: name (``none``/``repetitive``/``nonrepetitive``/``both``) or code 0..3.
        :param seed: 0..2³²−1.
        :param plant_scales: (inertia, mass, friction, payload) factors on the emulated robot
            (``plant.params.PlantScales``; exact float64 bits, REAL64).
        :raises PlantInputError: a value the bench cannot represent exactly.
        """
        period_us = round(float(ts_s) * 1e6)
        if not 1 <= period_us <= 1_000_000 or period_us / 1_000_000 != float(ts_s):
            raise PlantInputError(f"control period must be a whole number of µs in 1 µs..1 s, got {ts_s!r} s")
        if int(substeps) != substeps or not 1 <= int(substeps) <= 1000:
            raise PlantInputError(f"substeps must be an integer 1..1000, got {substeps!r}")
        try:
            kind = disturbance_code(disturbance) if isinstance(disturbance, str) else DisturbanceKind(disturbance)
        except ValueError as err:
            raise PlantInputError(str(err)) from None
        if int(seed) != seed or not 0 <= int(seed) <= _U32_MAX:
            raise PlantInputError(f"seed must be an integer 0..{_U32_MAX}, got {seed!r}")
        scales = tuple(float(v) for v in plant_scales)
        if len(scales) != len(PLANT_SCALE_SUBS):
            raise PlantInputError(f"plant_scales needs {len(PLANT_SCALE_SUBS)} factors, got {len(scales)}")
        for sub, value in zip(PLANT_SCALE_SUBS, scales):
            why = plant_scale_error(sub, value)
            if why is not None:
                raise PlantInputError(why)
        cfg = PlantObj.CONFIG
        self.access.write_object(cfg, ConfigSub.CONTROL_PERIOD_US, _u32(period_us))
        self.access.write_object(cfg, ConfigSub.SUBSTEPS, _u16(int(substeps)))
        self.access.write_object(cfg, ConfigSub.DISTURBANCE, _u8(int(kind)))
        self.access.write_object(cfg, ConfigSub.SEED, _u32(int(seed)))
        self.access.write_object(cfg, ConfigSub.PACING, _u8(int(bool(paced))))
        for sub, value in zip(PLANT_SCALE_SUBS, scales):
            self.access.write_object(cfg, sub, _F64.pack(value))
        logger.debug(
            "bench configured: Ts = %d µs, %d sub-steps, disturbance %s, seed %d, %s",
            period_us,
            substeps,
            kind.label,
            seed,
            "paced" if paced else "lockstep",
        )

    def trial_timing(self) -> TrialTiming:
        """0x2440: the last trial's wall-clock timing as the plant measured it (diagnostics)."""
        return unpack_trial_timing(self.access.read_object(PlantObj.TRIAL_TIMING, 0))

    def deadline_misses(self) -> DeadlineMisses:
        """0x2441: the last trial's deadline misses (the first 64) as the plant measured them
        (diagnostics; empty unless the trial was paced)."""
        return unpack_deadline_misses(self.access.read_object(PlantObj.DEADLINE_MISSES, 0))

    def configuration(self) -> dict[str, Any]:
        """0x2400 as read back: ts_s, substeps, disturbance (name), seed, plant_scales."""
        cfg = PlantObj.CONFIG
        return {
            "ts_s": self._read_uint(cfg, ConfigSub.CONTROL_PERIOD_US) / 1_000_000,
            "substeps": self._read_uint(cfg, ConfigSub.SUBSTEPS),
            "disturbance": DisturbanceKind(self._read_uint(cfg, ConfigSub.DISTURBANCE)).label,
            "seed": self._read_uint(cfg, ConfigSub.SEED),
            "plant_scales": tuple(_F64.unpack(self.access.read_object(cfg, sub))[0] for sub in PLANT_SCALE_SUBS),
        }

    # ------------------------------------------------------------------ trial

    def start_trial(self, trial: int, n_ticks: int, q0: npt.ArrayLike, qd0: npt.ArrayLike) -> None:
        """Write the initial state (exact float64 bits), trial index, N, then command START.

        :raises PlantInputError: bad q0/qd0 or out-of-range trial / n_ticks.
        :raises bus.errors.SdoAbort: the bench refused (e.g. 0x08000022, a trial is running).
        """
        if int(trial) != trial or not 0 <= int(trial) <= _U32_MAX:
            raise PlantInputError(f"trial index must be an integer 0..{_U32_MAX}, got {trial!r}")
        if int(n_ticks) != n_ticks or not 1 <= int(n_ticks) <= _U32_MAX:
            raise PlantInputError(f"n_ticks must be an integer 1..{_U32_MAX}, got {n_ticks!r}")
        try:
            state = pack_initial_state(q0, qd0)
        except InitialStateError as err:
            raise PlantInputError(str(err)) from None
        t = PlantObj.TRIAL
        self.access.write_object(PlantObj.INITIAL_STATE, 0, state)
        self.access.write_object(t, PlantTrialSub.TRIAL_INDEX, _u32(int(trial)))
        self.access.write_object(t, PlantTrialSub.N_TICKS, _u32(int(n_ticks)))
        self.access.write_object(t, PlantTrialSub.COMMAND, _u8(PlantCommand.START))

    def abort(self) -> None:
        """Command ABORT (no effect when no trial runs)."""
        self.access.write_object(PlantObj.TRIAL, PlantTrialSub.COMMAND, _u8(PlantCommand.ABORT))

    def status(self) -> PlantState:
        t = PlantObj.TRIAL
        return PlantState(
            status=PlantStatus(self._read_uint(t, PlantTrialSub.STATUS)),
            ticks_done=self._read_uint(t, PlantTrialSub.TICKS_DONE),
            fault=PlantFault(self._read_uint(t, PlantTrialSub.FAULT_CODE)),
            fault_tick=self._read_uint(t, PlantTrialSub.FAULT_TICK),
            fault_node=self._read_uint(t, PlantTrialSub.FAULT_NODE),
        )

    def wait_trial(self, timeout_s: float, poll_s: float = 0.02) -> PlantState:
        """Poll the status (0x2410:4, one SDO upload) every ``poll_s`` s until the trial is no
        longer running, then read the whole state.

        :return: the final state (status DONE).
        :raises PlantTrialFault: the trial ended in fault (or the bench is idle: never started).
        :raises PlantTimeoutError: still running after ``timeout_s`` s (the trial is aborted).
        """
        deadline = time.monotonic() + timeout_s
        while True:
            # while the trial runs, one SDO upload (the status) per poll; the whole state once it ended
            if self._read_uint(PlantObj.TRIAL, PlantTrialSub.STATUS) == PlantStatus.RUNNING and time.monotonic() < deadline:
                time.sleep(poll_s)
                continue
            state = self.status()
            if state.status == PlantStatus.DONE:
                return state
            if state.status == PlantStatus.FAULT:
                raise PlantTrialFault(f"plant node: {state.describe()}", state)
            if state.status == PlantStatus.IDLE:
                raise PlantTrialFault("plant node is idle: the trial was never started (node reset?)", state)
            if time.monotonic() >= deadline:
                try:
                    self.abort()
                except IlcrigError:
                    logger.warning("aborting the timed-out trial failed", exc_info=True)
                raise PlantTimeoutError(
                    f"plant node: trial still running after {timeout_s:g} s ({state.ticks_done} ticks done); aborted"
                )
            time.sleep(poll_s)

    def counters(self) -> dict[str, int]:
        """0x2430: io frames sent/received, tick timeouts, trials completed, last trial µs."""
        c = PlantObj.COUNTERS
        return {
            "io_sent": self._read_uint(c, CounterSub.IO_SENT),
            "io_received": self._read_uint(c, CounterSub.IO_RECEIVED),
            "tick_timeouts": self._read_uint(c, CounterSub.TICK_TIMEOUTS),
            "trials_done": self._read_uint(c, CounterSub.TRIALS_DONE),
            "last_trial_us": self._read_uint(c, CounterSub.LAST_TRIAL_US),
        }
