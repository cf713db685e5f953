"""The power stage of one drive: CiA 402 device control, torque on/off, faults and EMCY, and the
SAFE-STATE record.

Owns the CiA 402 state machine (:class:`firmware_model.cia402.Cia402StateMachine`, driven by the
controlword 0x6040), the torque enable, the error register 0x1001 and error code 0x603F, and the
queue of EMCY messages the node runtime sends (:meth:`PowerStage.pop_emcy`).

* torque is on exactly while NMT is OPERATIONAL **and** CiA 402 is Operation enabled
  (:meth:`PowerStage.update`, called after every NMT command and controlword).  When it comes
  on, the velocity estimator starts afresh; when it goes off, a running trial ends in FAULT
  (cause NONE) and the loop's torque state is cleared.
* a fault (:meth:`PowerStage.fault`: following error 0x8611, tick sequence 0x8200, heartbeat
  of the host lost 0x8130, bus lost 0x8100) enters CiA 402 Fault, ends an armed or running trial
  in FAULT with the cause in 0x2120:4, sets 0x1001/0x603F, removes torque and queues an EMCY.
  The fault reset (controlword bit 7 rising edge) clears 0x1001/0x603F and queues EMCY 0x0000.
* loss of the host's heartbeat in NMT STOPPED is only logged (torque is off and the master
  stopped the node on purpose).
* every time torque goes off, one ``SAFE-STATE`` record (:mod:`bus.safe_state`) is logged with
  the reason (the fault, the NMT state or the CiA 402 state) and the trial tick, and one when a
  fault comes while torque was off already.
* the statusword 0x6041 is the state's pattern, bit 11 (internal limit) when the torque was
  clamped, and the operation mode's bits 12/13 while torque is on.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from bus.cia301.emcy import EmcyCode, ErrorRegister
from bus.cia301.nmt import NmtState
from bus.objects import Cia402State, FaultCause, TrialState
from bus.safe_state import TORQUE_ON_TAG, format_safe_state
from firmware_model import control_law
from firmware_model.cia402 import Cia402StateMachine
from firmware_model.playback import TrialPlayback

logger = logging.getLogger(__name__)

Emcy = tuple[int, int, bytes]
_FAULT_STATES = (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE)


class PowerStage:
    """CiA 402 device control and the torque enable of one drive (see the module docstring).

    :param node_id: CANopen node id (log records).
    :param st: the control loop's state array (:func:`firmware_model.control_law.new_state`).
    :param trial: the drive's trial playback (ended by a fault or a loss of torque).
    :param nmt_state: returns the drive's NMT state.
    """

    def __init__(self, node_id: int, st: npt.NDArray[np.int64], trial: TrialPlayback, nmt_state: Callable[[], NmtState]) -> None:
        self.node_id = node_id
        self._st = st
        self._trial = trial
        self._nmt_state = nmt_state
        self.sm = Cia402StateMachine()
        #: True while torque is applied
        self.on = False
        self.error_register = 0
        self.error_code = 0
        self._emcy: list[Emcy] = []
        self._fault_reason = ""
        self._fault_tick = -1

    def reset(self) -> None:
        """NMT reset node: Switch on disabled, no error, no EMCY pending (the torque enable
        follows at the next :meth:`update`)."""
        self.sm.reset()
        self.error_register = 0
        self.error_code = 0
        self._emcy.clear()
        self._fault_reason = ""
        self._fault_tick = -1

    # ------------------------------------------------------------------ state

    @property
    def state(self) -> Cia402State:
        return self.sm.state

    @property
    def in_fault(self) -> bool:
        """True in CiA 402 Fault (or Fault reaction active)."""
        return self.sm.state in _FAULT_STATES

    def statusword(self, mode_bits: int) -> int:
        """0x6041; ``mode_bits``: the operation mode's bits 12/13, set while torque is on."""
        on = self.on
        sw = self.sm.statusword(bool(self._st[control_law.S_LIMITED]) and on)
        return sw | mode_bits if on else sw

    def pop_emcy(self) -> list[Emcy]:
        """Pending EMCY messages ``(error code, error register, 5 manufacturer bytes)``, oldest
        first; the queue is emptied."""
        out, self._emcy = self._emcy, []
        return out

    # ------------------------------------------------------------------ commands

    def controlword(self, value: int) -> None:
        """0x6040 written: CiA 402 transition; a fault reset clears the error and queues EMCY 0x0000."""
        before = self.sm.state
        self.sm.controlword(value)
        if before == Cia402State.FAULT and self.sm.state != Cia402State.FAULT:
            self.error_register = 0
            self.error_code = 0
            self._emcy.append((EmcyCode.ERROR_RESET, 0, bytes(5)))
            logger.info("node %d fault reset", self.node_id)
        self.update()

    def update(self) -> None:
        """Apply the torque enable of the current NMT and CiA 402 states."""
        power = self._nmt_state() == NmtState.OPERATIONAL and self.sm.state == Cia402State.OPERATION_ENABLED
        was = self.on
        self.on = power
        st = self._st
        trial = self._trial
        if power and not was:
            st[control_law.S_HAVE_PREV] = 0
            st[control_law.S_VF] = 0
            st[control_law.S_VEST] = 0
            trial.on_torque_on()
            logger.info("%s node=drive%d", TORQUE_ON_TAG, self.node_id)
        elif was and not power:
            running = trial.state == TrialState.RUNNING
            tick = trial.next_tick if running else self._fault_tick
            if running:
                logger.warning("node %d torque enable lost during a trial", self.node_id)
                trial.stop(TrialState.FAULT)
            self._log_safe_state(tick)
            st[control_law.S_TAU] = 0
            st[control_law.S_TAU_FB] = 0
            st[control_law.S_VEST] = 0
            st[control_law.S_LIMITED] = 0

    def power_off(self, reason: str) -> None:
        """The drive process stops: the power stage goes off; a SAFE-STATE record is logged if
        torque was still on."""
        if self.on:
            self.on = False
            logger.info(
                format_safe_state(
                    f"drive{self.node_id}", reason, cia402=self.sm.state.name, nmt=NmtState(self._nmt_state()).name, tick="-"
                )
            )

    # ------------------------------------------------------------------ faults

    def fault(self, code: EmcyCode, register: int, cause: FaultCause, mfr: bytes, reason: str = "") -> int:
        """A fault (see the module docstring); ``mfr``: the EMCY's 5 manufacturer bytes,
        ``reason``: the SAFE-STATE reason (default ``fault-<cause>``).  Returns the torque of the
        tick, 0 [µN·m]."""
        trial = self._trial
        self._fault_tick = trial.next_tick if trial.state == TrialState.RUNNING else -1
        self._fault_reason = reason
        trial.on_fault(cause)
        self.sm.fault()
        self.error_register = int(register)
        self.error_code = int(code)
        self._emcy.append((int(code), int(register), mfr))
        logger.warning("node %d fault %s (EMCY 0x%04X)", self.node_id, cause.name, code)
        was_on = self.on
        self.update()
        if not was_on:  # torque was off already: record the fault reaction all the same
            self._log_safe_state(self._fault_tick)
        self._fault_reason = ""
        self._fault_tick = -1
        return 0

    def following_error(self, error_counts: int) -> int:
        """|position error| exceeded 0x6065: EMCY 0x8611 with the error [counts]."""
        return self.fault(
            EmcyCode.FOLLOWING_ERROR,
            ErrorRegister.GENERIC | ErrorRegister.DEVICE_PROFILE,
            FaultCause.FOLLOWING_ERROR,
            struct.pack("<Bi", FaultCause.FOLLOWING_ERROR, error_counts),
        )

    def sequence_error(self, expected: int, tick: int) -> int:
        """An io tick out of sequence: EMCY 0x8200 with the expected and the received tick."""
        logger.warning("node %d io tick %d, expected %d", self.node_id, tick, expected)
        return self.fault(
            EmcyCode.PROTOCOL_ERROR,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.TICK_SEQUENCE,
            struct.pack("<BHH", FaultCause.TICK_SEQUENCE, expected & 0xFFFF, int(tick) & 0xFFFF),
        )

    def heartbeat_lost(self, node_id: int) -> None:
        """The heartbeat of ``node_id`` (the host) was lost: a fault with EMCY 0x8130, except in
        NMT STOPPED (only logged)."""
        if self._nmt_state() == NmtState.STOPPED:
            logger.info("node %d: heartbeat of node %d lost while NMT STOPPED (torque off already)", self.node_id, node_id)
            return
        self.fault(
            EmcyCode.HEARTBEAT_ERROR,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.HEARTBEAT,
            struct.pack("<BB3x", FaultCause.HEARTBEAT, node_id & 0xFF),
            reason=f"heartbeat-of-node-{node_id}-lost",
        )

    def bus_lost(self, reason: str) -> None:
        """The fieldbus or io bus failed: a fault (its EMCY cannot be sent)."""
        self.fault(
            EmcyCode.COMMUNICATION,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.BUS_LOST,
            struct.pack("<B4x", FaultCause.BUS_LOST),
            reason="bus-lost",
        )
        logger.warning("node %d: bus lost (%s): torque off", self.node_id, reason)

    def _log_safe_state(self, tick: int) -> None:
        """One SAFE-STATE record: torque is off now, and why."""
        nmt = NmtState(self._nmt_state())
        if self.in_fault:
            reason = self._fault_reason or f"fault-{FaultCause(self._trial.fault_cause).name.lower()}"
        elif nmt != NmtState.OPERATIONAL:
            reason = f"nmt-{nmt.name.lower()}"
        else:
            reason = f"cia402-{self.sm.state.name.lower()}"
        logger.info(
            format_safe_state(
                f"drive{self.node_id}", reason, cia402=self.sm.state.name, nmt=nmt.name, tick=tick if tick >= 0 else "-"
            )
        )
