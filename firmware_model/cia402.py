"""CiA 402 device-control state machine of the drive (controlword -> state -> statusword).

Owns the power-state logic.  The encodings (controlword/statusword bits, state
patterns) are shared with the host and live in :mod:`bus.objects`; they are
re-exported here.

Transitions implemented (CiA 402 numbering, docs/canopen-objects.md §5):

====  =================================  ========================================
 no.  from -> to                          trigger
====  =================================  ========================================
 0,1  start -> Not ready -> SO disabled   automatic (construction / :meth:`reset`)
 2    SO disabled -> Ready                Shutdown (bits 2,1 = 1, bit 0 = 0)
 3    Ready -> Switched on                Switch on (0x07)
 3+4  Ready -> Operation enabled          Enable operation (0x0F) in one step
 4    Switched on -> Operation enabled    Enable operation (0x0F)
 5    Operation enabled -> Switched on    Disable operation (0x07)
 6    Switched on -> Ready                Shutdown
 7    Ready -> SO disabled                Disable voltage (bit 1 = 0) or Quick stop
 8    Operation enabled -> Ready          Shutdown
 9    Operation enabled -> SO disabled    Disable voltage
10    Switched on -> SO disabled          Disable voltage or Quick stop
11    Operation enabled -> Quick stop     Quick stop (bit 2 = 0, bit 1 = 1)
12    Quick stop active -> SO disabled    Disable voltage, or the quick stop completed
                                         (:meth:`quick_stop_complete`, 0x605A = 0, 1, 2)
13    any -> Fault reaction active        :meth:`fault`
14    Fault reaction active -> Fault      automatic (:meth:`fault` completes it at once)
15    Fault -> SO disabled                rising edge of bit 7 (fault reset)
16    Quick stop active -> Op. enabled    Enable operation (0x0F), only when the quick stop
                                         option allows it (0x605A = 5, 6: ``qs_to_enabled``)
====  =================================  ========================================

While bit 7 is set no other command is decoded.  What happens in Quick stop active (the
stop ramp, the torque) is the power stage's (:mod:`firmware_model.power_stage`).
"""

from __future__ import annotations

import logging

from bus.objects import (
    STATUSWORD_PATTERN,
    Cia402State,
    ControlCommand,
    Controlword,
    Statusword,
    state_from_statusword,
)

logger = logging.getLogger(__name__)

__all__ = [
    "STATUSWORD_PATTERN",
    "Cia402State",
    "Cia402StateMachine",
    "ControlCommand",
    "Controlword",
    "Statusword",
    "state_from_statusword",
]

_S = Cia402State
#: states in which the power stage has voltage (statusword bit 4)
_VOLTAGE_STATES = frozenset(
    {_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON, _S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE, _S.FAULT_REACTION_ACTIVE}
)
#: each state's statusword without bit 11 as a plain int (the drives read it every tick: int
#: arithmetic instead of IntFlag's, which runs in Python)
_STATUSWORD_OF: dict[int, int] = {
    int(st): int(STATUSWORD_PATTERN[st][1])
    | int(Statusword.REMOTE)
    | (int(Statusword.VOLTAGE_ENABLED) if st in _VOLTAGE_STATES else 0)
    for st in _S
}
_INTERNAL_LIMIT = int(Statusword.INTERNAL_LIMIT)
#: controlword bits as plain ints (decoded at every controlword write, i.e. every RPDO)
_CW_SWITCH_ON = int(Controlword.SWITCH_ON)
_CW_ENABLE_VOLTAGE = int(Controlword.ENABLE_VOLTAGE)
_CW_QUICK_STOP = int(Controlword.QUICK_STOP)
_CW_ENABLE_OPERATION = int(Controlword.ENABLE_OPERATION)
_CW_FAULT_RESET = int(Controlword.FAULT_RESET)


class Cia402StateMachine:
    """The CiA 402 power state machine.

    :ivar state: current :class:`Cia402State`.
    :ivar last_transition: number of the last transition taken (None if the last
        controlword caused none).
    :ivar reset_edge: the last controlword had a rising edge of bit 7 (fault reset).
    """

    def __init__(self) -> None:
        self.state: Cia402State = _S.NOT_READY_TO_SWITCH_ON
        self.last_transition: int | None = 0
        self.reset_edge = False
        self._last_cw: int = 0
        self.reset()

    def reset(self) -> None:
        """Power-on / NMT reset node: Not ready to switch on -> Switch on disabled (0, 1)."""
        self.state = _S.NOT_READY_TO_SWITCH_ON
        self._last_cw = 0
        self._go(_S.SWITCH_ON_DISABLED, 1)

    def _go(self, new: Cia402State, transition: int) -> None:
        if new != self.state:
            logger.debug("CiA 402 %s -> %s (transition %d)", self.state.name, new.name, transition)
        self.state = new
        self.last_transition = transition

    def controlword(self, cw: int, qs_to_enabled: bool = False) -> Cia402State:
        """Apply a controlword write; returns the new state.  ``qs_to_enabled``: transition 16
        (Quick stop active -> Operation enabled by Enable operation) is allowed."""
        cw = int(cw) & 0xFFFF
        rising_reset = bool(cw & _CW_FAULT_RESET) and not (self._last_cw & _CW_FAULT_RESET)
        self.reset_edge = rising_reset
        self._last_cw = cw
        self.last_transition = None
        s = self.state
        if cw & _CW_FAULT_RESET:
            if rising_reset and s == _S.FAULT:
                self._go(_S.SWITCH_ON_DISABLED, 15)
            return self.state
        if s in (_S.FAULT, _S.FAULT_REACTION_ACTIVE, _S.NOT_READY_TO_SWITCH_ON):
            return s
        so = bool(cw & _CW_SWITCH_ON)
        ev = bool(cw & _CW_ENABLE_VOLTAGE)
        qs = bool(cw & _CW_QUICK_STOP)  # 0 = quick stop requested
        eo = bool(cw & _CW_ENABLE_OPERATION)
        if not ev:  # Disable voltage
            self.disable_voltage()
        elif not qs:  # Quick stop
            self.quick_stop()
        elif not so:  # Shutdown
            t = {_S.SWITCH_ON_DISABLED: 2, _S.SWITCHED_ON: 6, _S.OPERATION_ENABLED: 8}.get(s)
            if t is not None:
                self._go(_S.READY_TO_SWITCH_ON, t)
        elif not eo:  # Switch on / Disable operation
            if s == _S.READY_TO_SWITCH_ON:
                self._go(_S.SWITCHED_ON, 3)
            elif s == _S.OPERATION_ENABLED:
                self._go(_S.SWITCHED_ON, 5)
        else:  # Enable operation
            if s == _S.SWITCHED_ON:
                self._go(_S.OPERATION_ENABLED, 4)
            elif s == _S.READY_TO_SWITCH_ON:
                self._go(_S.OPERATION_ENABLED, 4)  # 3 + 4 in one step
            elif s == _S.QUICK_STOP_ACTIVE and qs_to_enabled:
                self._go(_S.OPERATION_ENABLED, 16)
        return self.state

    def quick_stop(self) -> Cia402State:
        """Quick stop by the drive itself (an abort connection with 0x6007 = 3): transition 11
        from Operation enabled, 7 / 10 from Ready to switch on / Switched on."""
        s = self.state
        if s == _S.OPERATION_ENABLED:
            self._go(_S.QUICK_STOP_ACTIVE, 11)
        elif s == _S.READY_TO_SWITCH_ON:
            self._go(_S.SWITCH_ON_DISABLED, 7)
        elif s == _S.SWITCHED_ON:
            self._go(_S.SWITCH_ON_DISABLED, 10)
        return self.state

    def disable_voltage(self) -> Cia402State:
        """Disable voltage by the drive itself (an abort connection with 0x6007 = 2): transitions
        7, 9, 10, 12."""
        t = {_S.READY_TO_SWITCH_ON: 7, _S.OPERATION_ENABLED: 9, _S.SWITCHED_ON: 10, _S.QUICK_STOP_ACTIVE: 12}.get(self.state)
        if t is not None:
            self._go(_S.SWITCH_ON_DISABLED, t)
        return self.state

    def quick_stop_complete(self) -> Cia402State:
        """Transition 12 at the end of a quick stop whose option ends in Switch on disabled."""
        if self.state == _S.QUICK_STOP_ACTIVE:
            self._go(_S.SWITCH_ON_DISABLED, 12)
        return self.state

    def fault(self) -> Cia402State:
        """A fault: transition 13 to Fault reaction active, then 14 to Fault at once
        (the emulated fault reaction -- removing torque -- takes no time)."""
        if self.state not in (_S.FAULT, _S.FAULT_REACTION_ACTIVE):
            self._go(_S.FAULT_REACTION_ACTIVE, 13)
        self.fault_reaction_complete()
        return self.state

    def fault_reaction_complete(self) -> None:
        """Transition 14 (automatic)."""
        if self.state == _S.FAULT_REACTION_ACTIVE:
            self._go(_S.FAULT, 14)

    @property
    def operation_enabled(self) -> bool:
        return self.state == _S.OPERATION_ENABLED

    def statusword(self, internal_limit: bool = False) -> int:
        """Statusword: the state's pattern value (CiA 402 table), plus bit 4 (voltage
        enabled) in the powered states, bit 9 (remote) always and bit 11 (internal limit)
        when the torque was clamped.  A healthy enabled drive reads 0x0237."""
        sw = _STATUSWORD_OF[self.state]
        if internal_limit and self.state == _S.OPERATION_ENABLED:
            sw |= _INTERNAL_LIMIT
        return sw
