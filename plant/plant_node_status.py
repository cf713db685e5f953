"""The outcome of the plant node's trials as the host reads it: status, fault record, EMCY and
timing.

Owns :class:`TrialStatus`: the trial status and fault fields of 0x2410 (status, fault code, fault
tick, fault node), the error register 0x1001, the message of the last fault (logs and summaries),
the duration of the last trial [s] (0x2430:5) and its timing and deadline misses (0x2440, 0x2441,
from :class:`plant.pacing.TickPacer`).  A fault (:meth:`TrialStatus.fault`) sets the FAULT status
with code, tick and node, the error register of its EMCY (:data:`bus.plant_objects.FAULT_EMCY`)
and returns the EMCY to send, whose manufacturer bytes are
:func:`bus.plant_objects.fault_emcy_data`.  Names and encodings: :mod:`bus.plant_objects`.
"""

from __future__ import annotations

import logging

from bus.plant_objects import (
    FAULT_EMCY,
    DeadlineMiss,
    DeadlineMisses,
    PlantFault,
    PlantStatus,
    TrialTiming,
    fault_emcy_data,
)
from plant.pacing import TickPacer

logger = logging.getLogger(__name__)

Emcy = tuple[int, int, bytes]


def fault_emcy(fault: PlantFault, node: int, tick: int) -> Emcy:
    """The EMCY ``(error code, error register, 5 manufacturer bytes)`` of ``fault`` involving drive
    ``node`` (0: none) at trial tick ``tick``."""
    code, register = FAULT_EMCY[fault]
    return code, register, fault_emcy_data(fault, node, tick)


class TrialStatus:
    """Status, fault record and timing of the plant node's trials (see the module docstring).

    :param node_id: CANopen node id (log messages).
    """

    # set by reset (called from __init__)
    status: PlantStatus
    fault_code: PlantFault
    fault_tick: int
    fault_node: int
    error_register: int
    last_trial_s: float

    def __init__(self, node_id: int) -> None:
        self.node_id = node_id
        #: the last fault's message (logs and summaries; kept across resets)
        self.last_fault_message = ""
        self.timing = TrialTiming(False, 0, 0, 0, 0, 0, 0)
        self.misses = DeadlineMisses(0)
        self.reset()

    def reset(self) -> None:
        """NMT reset node: IDLE, no fault, error register 0."""
        self.status = PlantStatus.IDLE
        self.fault_code = PlantFault.NONE
        self.fault_tick = self.fault_node = 0
        self.error_register = 0
        self.last_trial_s = 0.0

    def begin(self) -> None:
        """The start command: RUNNING from now on, no fault."""
        self.status = PlantStatus.RUNNING
        self.fault_code = PlantFault.NONE
        self.fault_tick = self.fault_node = 0

    def done(self, duration_s: float) -> None:
        """The trial completed after ``duration_s`` [s] (wall clock)."""
        self.status = PlantStatus.DONE
        self.last_trial_s = duration_s

    def fault(self, fault: PlantFault, node: int, tick: int, message: str, duration_s: float) -> Emcy:
        """The trial ended with ``fault`` at ``tick``, involving drive ``node`` (0: none), after
        ``duration_s`` [s]; returns the EMCY to send."""
        self.status = PlantStatus.FAULT
        self.fault_code = fault
        self.fault_tick = tick
        self.fault_node = node
        self.last_fault_message = message
        self.last_trial_s = duration_s
        emcy = fault_emcy(fault, node, tick)
        self.error_register = emcy[1]
        logger.warning("node %d: trial fault %s: %s", self.node_id, fault.name, message)
        return emcy

    def bus_lost(self, tick: int) -> None:
        """The trial was cut at ``tick`` by a failing bus (no EMCY can be sent)."""
        self.status = PlantStatus.FAULT
        self.fault_code = PlantFault.ABORTED
        self.fault_tick = tick

    def record_timing(self, pacer: TickPacer) -> None:
        """Keep the ended trial's timing for 0x2440 and its misses for 0x2441."""
        r = pacer.result()
        self.timing = TrialTiming(
            r.paced,
            r.ticks,
            round(r.duration_s * 1e6),
            r.deadline_misses,
            round(r.lateness_p50_s * 1e6),
            round(r.lateness_p99_s * 1e6),
            round(r.lateness_max_s * 1e6),
        )
        # t0 on the node clock (CLOCK_MONOTONIC in the role): a tool on the machine can match the
        # misses with a kernel trace of the same clock (benchmarks/rt_attribution.py)
        self.misses = DeadlineMisses(
            round(r.t0_s * 1e9) if r.paced else 0,
            tuple(DeadlineMiss(m.tick, round(m.started_late_s * 1e6), round(m.overrun_s * 1e6)) for m in r.missed),
        )
        if r.paced:
            logger.info(
                "node %d: paced trial: %d deadline misses, lateness p50 %.0f µs, p99 %.0f µs, max %.0f µs",
                self.node_id,
                r.deadline_misses,
                r.lateness_p50_s * 1e6,
                r.lateness_p99_s * 1e6,
                r.lateness_max_s * 1e6,
            )
