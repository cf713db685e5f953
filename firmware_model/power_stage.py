"""The power stage of one drive: CiA 402 device control, torque on/off, quick stop, faults,
communication errors and their reactions, EMCY, and the SAFE-STATE record.

Owns the CiA 402 state machine (:class:`firmware_model.cia402.Cia402StateMachine`, driven by the
controlword 0x6040), the torque enable, the error register 0x1001, the error code 0x603F, the
error history 0x1003 and the queue of EMCY messages the node runtime sends
(:meth:`PowerStage.pop_emcy`; none is queued in NMT STOPPED, CiA 301).

* **Torque** is on exactly in CiA 402 Operation enabled and Quick stop active (during the stop
  ramp, and holding after it with 0x605A = 5, 6): the statusword always says what the power stage
  does.  NMT does not switch torque; leaving NMT OPERATIONAL is an abort connection (below), so
  after NMT START the drive stays torque-free until the controlword sequence enables it.  When
  torque comes on, the velocity estimator and the operation mode start afresh; when it goes off,
  a running trial ends in FAULT and the loop's torque state is cleared.
* **Quick stop** (controlword bit 2 = 0 in Operation enabled, or 0x6007 = 3): Quick stop active;
  0x605A says how (0: torque off at once → Switch on disabled; 1 / 5: the profile deceleration
  0x6084, 2 / 6: the quick stop deceleration 0x6085, from the demand velocity down to 0 on the
  control cycles); the control cycle after the ramp reached standstill completes the quick stop
  -- a quick stop begun at standstill lasts one control cycle, so Quick stop active is always
  seen -- 1 and 2 end in Switch on disabled (transition 12), 5 and 6 stay in Quick stop active
  holding the position (statusword bit 10) and accept Enable operation (transition 16).
* **Faults** (:meth:`PowerStage.fault`: following error 0x8611, tick sequence 0x8200, bus lost
  0x8100, the PIL target died or stopped answering 0x6100) enter CiA 402 Fault at once (the
  fault reaction takes no time), end an armed or running trial in FAULT with the cause in
  0x2120:4, set 0x1001/0x603F, record 0x1003, remove torque and queue an EMCY.
* **Communication errors** (:meth:`PowerStage.communication_error`: the host's heartbeat lost
  0x8130, an RPDO deadline 0x8250, SYNC lost 0x8100): EMCY, 0x1001 (generic + communication),
  0x1003, an armed or running trial ends in FAULT, then the abort connection reaction of 0x6007
  and the NMT reaction of 0x1029:1 (0 pre-operational, 1 none, 2 stopped).  In NMT STOPPED a lost
  heartbeat is only logged (the master stopped the node on purpose).
* **Frames lost** (:meth:`PowerStage.frames_lost`: the fieldbus receiver overflowed): EMCY 0x8110,
  0x1001 (generic + communication), 0x1003, then the NMT reaction of 0x1029:1; only when that
  reaction leaves NMT OPERATIONAL is it an abort connection (0x6007 has no event of its own for
  it, CiA 402), as any leaving of OPERATIONAL.
* **Abort connection** (:meth:`PowerStage.abort_connection`: a communication error, or NMT
  STOP / ENTER PRE-OPERATIONAL from OPERATIONAL / RESET COMMUNICATION), only while torque is on,
  by 0x6007: 0 nothing, 1 Fault (0x603F = the error's code), 2 Disable voltage (Switch on
  disabled), 3 Quick stop (by 0x605A).  An NMT command that aborts the connection (0x6007 ≠ 0)
  is recorded like an error: EMCY 0x8100 (none in STOPPED) with the cause 7 and the new NMT
  state, 0x1001, 0x1003.
* **Fault reset** (a rising edge of controlword bit 7): leaves Fault (transition 15), clears
  0x1001 and 0x603F (0x1003 keeps its entries) and queues EMCY 0x0000; outside Fault it clears
  a communication error's 0x1001 the same way.
* Every time torque goes off one ``SAFE-STATE`` record (:mod:`bus.safe_state`) is logged with
  the reason and the trial tick, and one when a fault comes while torque was off already.
* The statusword 0x6041 is the state's pattern, bit 11 (internal limit) when the torque was
  clamped, the operation mode's bits 10/12/13 in Operation enabled, and bit 10 in Quick stop
  active once at standstill.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Mapping
from typing import Protocol

import numpy as np
import numpy.typing as npt

from bus.cia301.emcy import EmcyCode, ErrorHistory, ErrorRegister
from bus.cia301.nmt import NmtState
from bus.cia301.object_store import Key, Value
from bus.objects import (
    AbortConnectionOption,
    Cia402State,
    ErrorBehaviour,
    FaultCause,
    Obj,
    QuickStopOption,
    Statusword,
    TrialState,
)
from bus.pil_fault import PIL_NO_TICK, PilFailure
from bus.safe_state import TORQUE_ON_TAG, format_safe_state
from firmware_model import control_law
from firmware_model.cia402 import Cia402StateMachine
from firmware_model.playback import TrialPlayback

logger = logging.getLogger(__name__)

Emcy = tuple[int, int, bytes]
_S = Cia402State
_FAULT_STATES = (_S.FAULT, _S.FAULT_REACTION_ACTIVE)
_TORQUE_STATES = (_S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE)
_STAY_OPTIONS = (QuickStopOption.SLOW_DOWN_RAMP_STAY, QuickStopOption.QUICK_STOP_RAMP_STAY)
_COMM = ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION
_TARGET_REACHED = int(Statusword.TARGET_REACHED)
_ABORT_CONNECTION = (Obj.ABORT_CONNECTION_OPTION, 0)
_QUICK_STOP_OPTION = (Obj.QUICK_STOP_OPTION, 0)
_ERROR_BEHAVIOUR = (Obj.ERROR_BEHAVIOUR, 1)
#: 0x605A option -> the object of its deceleration (0: no ramp, torque off at once)
_STOP_RAMP: dict[int, int] = {
    QuickStopOption.SLOW_DOWN_RAMP: Obj.PROFILE_DECELERATION,
    QuickStopOption.SLOW_DOWN_RAMP_STAY: Obj.PROFILE_DECELERATION,
    QuickStopOption.QUICK_STOP_RAMP: Obj.QUICK_STOP_DECELERATION,
    QuickStopOption.QUICK_STOP_RAMP_STAY: Obj.QUICK_STOP_DECELERATION,
}


class MotionHooks(Protocol):
    """What the power stage needs from the operation modes (:class:`firmware_model.modes.Motion`)."""

    def on_torque_on(self) -> None:
        """Torque came on: the selected mode starts from the actual position."""

    def begin_quick_stop(self, deceleration_index: int) -> None:
        """Start the stop ramp with the deceleration of object ``deceleration_index`` (it runs on
        the next control cycles and calls :meth:`PowerStage.quick_stop_done` at its end)."""


class PowerStage:
    """CiA 402 device control and the torque enable of one drive (see the module docstring).

    :param node_id: CANopen node id (log records).
    :param st: the control loop's state array (:func:`firmware_model.control_law.new_state`).
    :param trial: the drive's trial playback (ended by a fault or a loss of torque).
    :param nmt_state: returns the drive's NMT state.
    :param values: the object values (0x6007, 0x605A, 0x1029 are read when they apply).

    :ivar motion: the operation modes (set by the drive once they exist).
    :ivar nmt_reaction: applies the NMT state 0x1029 asks for after a communication error.
    """

    def __init__(
        self,
        node_id: int,
        st: npt.NDArray[np.int64],
        trial: TrialPlayback,
        nmt_state: Callable[[], NmtState],
        values: Mapping[Key, Value] | None = None,
    ) -> None:
        self.node_id = node_id
        self._st = st
        self._trial = trial
        self._nmt_state = nmt_state
        self._values: Mapping[Key, Value] = values if values is not None else {}
        self.sm = Cia402StateMachine()
        self.motion: MotionHooks | None = None
        self.nmt_reaction: Callable[[NmtState], None] | None = None
        #: True while torque is applied
        self.on = False
        self.error_register = 0
        self.error_code = 0
        self.history = ErrorHistory()
        self._emcy: list[Emcy] = []
        self._reason = ""  # why torque goes off now (empty: from the state)
        self._fault_tick = -1
        self._stopped = False  # Quick stop active and at standstill (holding)

    def reset(self, reason: str = "") -> None:
        """NMT reset node: Switch on disabled, no error, empty history, no EMCY pending (the
        torque enable follows at the next :meth:`update`; ``reason``: its SAFE-STATE reason)."""
        self.sm.reset()
        self.error_register = 0
        self.error_code = 0
        self.history.clear()
        self._emcy.clear()
        self._reason = reason
        self._fault_tick = -1
        self._stopped = False

    def _option(self, key: Key, default: int) -> int:
        value = self._values.get(key)
        return default if value is None else int(value)

    # ------------------------------------------------------------------ state

    @property
    def state(self) -> Cia402State:
        return self.sm.state

    @property
    def in_fault(self) -> bool:
        """True in CiA 402 Fault (or Fault reaction active)."""
        return self.sm.state in _FAULT_STATES

    @property
    def quick_stopping(self) -> bool:
        """True in Quick stop active (ramping or holding)."""
        return self.sm.state == _S.QUICK_STOP_ACTIVE

    def statusword(self, mode_bits: int) -> int:
        """0x6041; ``mode_bits``: the operation mode's bits 10/12/13, set in Operation enabled."""
        state = self.sm.state
        sw = self.sm.statusword(bool(self._st[control_law.S_LIMITED]) and self.on)
        if state == _S.OPERATION_ENABLED:
            return sw | mode_bits
        if state == _S.QUICK_STOP_ACTIVE and self._stopped:
            return sw | _TARGET_REACHED
        return sw

    @property
    def emcy_pending(self) -> bool:
        """True while EMCY messages wait for :meth:`pop_emcy`."""
        return bool(self._emcy)

    def pop_emcy(self) -> list[Emcy]:
        """Pending EMCY messages ``(error code, error register, 5 manufacturer bytes)``, oldest
        first; the queue is emptied."""
        out, self._emcy = self._emcy, []
        return out

    def clear_history(self) -> None:
        """0x1003:0 := 0."""
        self.history.clear()

    def _record(self, code: int, register: int, mfr: bytes) -> None:
        """An error: 0x1003, and its EMCY unless the node is STOPPED."""
        self.history.push(code)
        if self._nmt_state() != NmtState.STOPPED:
            self._emcy.append((int(code), int(register), mfr))

    def warning(self, code: int, mfr: bytes) -> None:
        """An error without a reaction (an RPDO too short, a SYNC of the wrong length): EMCY,
        0x1001 communication bit, 0x1003."""
        self.error_register |= int(_COMM)
        self._record(code, self.error_register, mfr)
        logger.warning("node %d: EMCY 0x%04X", self.node_id, code)

    # ------------------------------------------------------------------ commands

    def controlword(self, value: int) -> None:
        """0x6040 written: CiA 402 transition, quick stop, fault reset."""
        before = self.sm.state
        qs_option = self._option(_QUICK_STOP_OPTION, QuickStopOption.QUICK_STOP_RAMP)
        self.sm.controlword(value, qs_to_enabled=qs_option in _STAY_OPTIONS)
        after = self.sm.state
        if self.sm.reset_edge and (before == _S.FAULT or (after not in _FAULT_STATES and self.error_register)):
            self.error_register = 0
            self.error_code = 0
            self._emcy.append((EmcyCode.ERROR_RESET, 0, bytes(5)))
            logger.info("node %d fault reset", self.node_id)
        if after == _S.QUICK_STOP_ACTIVE and before != _S.QUICK_STOP_ACTIVE:
            self._begin_quick_stop(qs_option)
        if before == _S.QUICK_STOP_ACTIVE and after == _S.OPERATION_ENABLED and self.motion is not None:
            self.motion.on_torque_on()  # transition 16: the mode starts afresh where the drive is
        if after != _S.QUICK_STOP_ACTIVE:
            self._stopped = False
        self.update()

    def _begin_quick_stop(self, option: int) -> None:
        """Quick stop active entered: the stop of 0x605A."""
        self._stopped = False
        decel = _STOP_RAMP.get(option)
        logger.info("node %d: quick stop (0x605A = %d)", self.node_id, option)
        if decel is None:  # 0: torque off at once
            self.sm.quick_stop_complete()
            return
        if self.motion is None:  # no control cycles to ramp on
            self.quick_stop_done()
            return
        self.motion.begin_quick_stop(decel)

    def quick_stop_done(self) -> None:
        """The stop ramp is complete (the control cycle after the one that reached standstill):
        Switch on disabled (0x605A = 1, 2) or holding in Quick stop active (5, 6)."""
        if self.sm.state != _S.QUICK_STOP_ACTIVE:
            return
        if self._option(_QUICK_STOP_OPTION, QuickStopOption.QUICK_STOP_RAMP) in _STAY_OPTIONS:
            self._stopped = True
            logger.info("node %d: quick stop at standstill, holding", self.node_id)
            return
        self.sm.quick_stop_complete()
        self.update()

    def update(self) -> None:
        """Apply the torque enable of the current CiA 402 state."""
        power = self.sm.state in _TORQUE_STATES
        was = self.on
        self.on = power
        st = self._st
        trial = self._trial
        if power and not was:
            st[control_law.S_HAVE_PREV] = 0
            st[control_law.S_VF] = 0
            st[control_law.S_VEST] = 0
            st[control_law.S_ERR] = 0
            st[control_law.S_VINT] = 0
            st[control_law.S_FE_COUNT] = 0
            trial.on_torque_on()
            if self.motion is not None:
                self.motion.on_torque_on()
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
        self._reason = ""

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
        trial.on_fault(cause)
        self.sm.fault()
        self.error_register = int(register)
        self.error_code = int(code)
        self._record(code, register, mfr)
        logger.warning("node %d fault %s (EMCY 0x%04X)", self.node_id, cause.name, code)
        was_on = self.on
        self._reason = reason
        self.update()
        if not was_on:  # torque was off already: record the fault reaction all the same
            self._reason = reason
            self._log_safe_state(self._fault_tick)
            self._reason = ""
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

    def io_frames_lost(self, next_tick: int) -> int:
        """io frames were lost in the drive's io receiver (it overflowed): an encoder or control
        frame of the plant never came, so the tick sequence is broken from ``next_tick`` (the tick
        within the trial expected next) on. EMCY 0x8110 (CAN overrun) with cause 10 and that tick,
        at once -- the plant would only notice the tick it never gets at its tick deadline."""
        logger.warning("node %d: io frames lost before tick %d", self.node_id, next_tick)
        return self.fault(
            EmcyCode.CAN_OVERRUN,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.IO_FRAMES_LOST,
            struct.pack("<BH2x", FaultCause.IO_FRAMES_LOST, next_tick & 0xFFFF),
        )

    def target_failed(self, failure: PilFailure, message: str) -> int:
        """The processor-in-the-loop target failed (``--firmware pil``; ``message``: what the link
        said): the drive's internal error, EMCY 0x6100 with the cause, ``failure`` and the trial
        tick (U24, 0xFFFFFF outside a trial).  Returns the torque of the tick, 0 [µN·m]."""
        trial = self._trial
        tick = trial.next_tick if trial.state == TrialState.RUNNING else PIL_NO_TICK
        logger.error("%s (tick %s): torque off", message, tick if tick != PIL_NO_TICK else "-")
        mfr = struct.pack("<BB", FaultCause.PIL_TARGET, int(failure)) + (tick & PIL_NO_TICK).to_bytes(3, "little")
        register = ErrorRegister.GENERIC | ErrorRegister.MANUFACTURER
        return self.fault(EmcyCode.INTERNAL_SOFTWARE, register, FaultCause.PIL_TARGET, mfr, reason="fault-pil_target")

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

    # ------------------------------------------------------------------ communication errors

    def communication_error(self, code: EmcyCode, cause: FaultCause, mfr: bytes, reason: str) -> None:
        """A communication error (see the module docstring): EMCY, 0x1001, 0x1003, the trial,
        then 0x6007 and 0x1029."""
        self.error_register |= int(_COMM)
        self._record(code, self.error_register, mfr)
        logger.warning("node %d: communication error %s (EMCY 0x%04X)", self.node_id, cause.name, code)
        if self._trial.playing:
            self._fault_tick = self._trial.next_tick if self._trial.state == TrialState.RUNNING else -1
        self._trial.on_fault(cause)
        self.abort_connection(code, reason)
        self._fault_tick = -1
        self._error_behaviour()

    def _error_behaviour(self) -> None:
        """The NMT reaction of 0x1029:1 to a communication error (0 pre-operational from
        OPERATIONAL, 1 none, 2 stopped)."""
        behaviour = self._option(_ERROR_BEHAVIOUR, ErrorBehaviour.PRE_OPERATIONAL)
        react = self.nmt_reaction
        if react is None:
            return
        nmt = self._nmt_state()
        if behaviour == ErrorBehaviour.PRE_OPERATIONAL and nmt == NmtState.OPERATIONAL:
            react(NmtState.PRE_OPERATIONAL)
        elif behaviour == ErrorBehaviour.STOPPED and nmt != NmtState.STOPPED:
            react(NmtState.STOPPED)

    def frames_lost(self) -> None:
        """Fieldbus frames were lost (the receiver overflowed): EMCY 0x8110 "CAN overrun", 0x1001
        (generic + communication), 0x1003, then the NMT reaction of 0x1029:1; a reaction that
        leaves NMT OPERATIONAL while torque is on is an abort connection (0x6007), as any leaving
        of OPERATIONAL is -- an armed or running trial then ends in FAULT."""
        self.error_register |= int(_COMM)
        self._record(EmcyCode.CAN_OVERRUN, self.error_register, struct.pack("<B4x", FaultCause.CAN_OVERRUN))
        logger.warning("node %d: fieldbus frames lost (EMCY 0x%04X)", self.node_id, EmcyCode.CAN_OVERRUN)
        operational = self._nmt_state() == NmtState.OPERATIONAL
        self._error_behaviour()
        if not operational or self._nmt_state() == NmtState.OPERATIONAL or not self.on:
            return
        if self._option(_ABORT_CONNECTION, AbortConnectionOption.FAULT) == AbortConnectionOption.NO_ACTION:
            return
        if self._trial.state == TrialState.RUNNING:
            self._fault_tick = self._trial.next_tick
        if self._trial.playing:
            self._trial.on_fault(FaultCause.CAN_OVERRUN)
        self.abort_connection(EmcyCode.CAN_OVERRUN, "can-overrun")
        self._fault_tick = -1

    def heartbeat_lost(self, node_id: int) -> None:
        """The heartbeat of ``node_id`` (the host) was lost: a communication error with EMCY
        0x8130, except in NMT STOPPED (only logged)."""
        if self._nmt_state() == NmtState.STOPPED:
            logger.info("node %d: heartbeat of node %d lost while NMT STOPPED (nothing to do)", self.node_id, node_id)
            return
        self.communication_error(
            EmcyCode.HEARTBEAT_ERROR,
            FaultCause.HEARTBEAT,
            struct.pack("<BB3x", FaultCause.HEARTBEAT, node_id & 0xFF),
            reason=f"heartbeat-of-node-{node_id}-lost",
        )

    def abort_connection(self, code: int, reason: str) -> None:
        """The reaction of 0x6007 while torque is on (see the module docstring); ``code``: the
        error code of a Fault, ``reason``: the SAFE-STATE reason."""
        if not self.on:
            return
        option = self._option(_ABORT_CONNECTION, AbortConnectionOption.FAULT)
        logger.info("node %d: abort connection (%s): 0x6007 = %d", self.node_id, reason, option)
        if option == AbortConnectionOption.FAULT:
            self._fault_tick = self._trial.next_tick if self._trial.state == TrialState.RUNNING else self._fault_tick
            self.sm.fault()
            self.error_register |= int(_COMM)
            self.error_code = int(code)
            self._reason = reason
            self.update()
        elif option == AbortConnectionOption.DISABLE_VOLTAGE:
            self.sm.disable_voltage()
            self._reason = reason
            self.update()
        elif option == AbortConnectionOption.QUICK_STOP:
            if self.sm.state == _S.OPERATION_ENABLED:
                self.sm.quick_stop()
                self._reason = reason
                self._begin_quick_stop(self._option(_QUICK_STOP_OPTION, QuickStopOption.QUICK_STOP_RAMP))
                self.update()

    def nmt_left_operational(self, command: int, reason: str) -> None:
        """NMT STOP, ENTER PRE-OPERATIONAL from OPERATIONAL, or RESET COMMUNICATION (``command``:
        its specifier, ``reason``: the SAFE-STATE reason) while torque is on and 0x6007 is not 0:
        EMCY 0x8100 (none in STOPPED) with the cause and the command, 0x1001, 0x1003, an armed or
        running trial ends in FAULT, then the abort connection reaction."""
        if not self.on or self._option(_ABORT_CONNECTION, AbortConnectionOption.FAULT) == AbortConnectionOption.NO_ACTION:
            return
        self.error_register |= int(_COMM)
        self._record(EmcyCode.COMMUNICATION, self.error_register, struct.pack("<BB3x", FaultCause.NMT_ABORT, int(command)))
        if self._trial.state == TrialState.RUNNING:
            self._fault_tick = self._trial.next_tick
        if self._trial.playing:
            self._trial.on_fault(FaultCause.NMT_ABORT)
        self.abort_connection(EmcyCode.COMMUNICATION, reason)
        self._fault_tick = -1

    def _log_safe_state(self, tick: int) -> None:
        """One SAFE-STATE record: torque is off now, and why."""
        nmt = NmtState(self._nmt_state())
        if self._reason:
            reason = self._reason
        elif self.in_fault:
            reason = f"fault-{FaultCause(self._trial.fault_cause).name.lower()}"
        else:
            reason = f"cia402-{self.sm.state.name.lower()}"
        logger.info(
            format_safe_state(
                f"drive{self.node_id}", reason, cia402=self.sm.state.name, nmt=nmt.name, tick=tick if tick >= 0 else "-"
            )
        )
