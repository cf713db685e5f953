"""Every CiA 402 transition of the drive's state machine, with statusword values."""

from __future__ import annotations

import pytest

from bus.objects import STATUSWORD_PATTERN, state_from_statusword
from firmware_model.cia402 import Cia402State as S
from firmware_model.cia402 import Cia402StateMachine, Statusword

SHUTDOWN, SWITCH_ON, ENABLE_OP, DISABLE_OP, DISABLE_VOLTAGE, QUICK_STOP = 0x06, 0x07, 0x0F, 0x07, 0x00, 0x02
FAULT_RESET = 0x80


def _machine_in(state: S) -> Cia402StateMachine:
    sm = Cia402StateMachine()
    path = {
        S.SWITCH_ON_DISABLED: [],
        S.READY_TO_SWITCH_ON: [SHUTDOWN],
        S.SWITCHED_ON: [SHUTDOWN, SWITCH_ON],
        S.OPERATION_ENABLED: [SHUTDOWN, SWITCH_ON, ENABLE_OP],
        S.QUICK_STOP_ACTIVE: [SHUTDOWN, SWITCH_ON, ENABLE_OP, QUICK_STOP],
    }[state]
    for cw in path:
        sm.controlword(cw)
    assert sm.state == state
    return sm


def test_power_on_reaches_switch_on_disabled() -> None:
    sm = Cia402StateMachine()
    assert sm.state == S.SWITCH_ON_DISABLED
    assert sm.last_transition == 1
    assert sm.statusword() == 0x0240  # 0x0040 + remote


@pytest.mark.parametrize(
    ("start", "cw", "end", "transition"),
    [
        (S.SWITCH_ON_DISABLED, SHUTDOWN, S.READY_TO_SWITCH_ON, 2),
        (S.READY_TO_SWITCH_ON, SWITCH_ON, S.SWITCHED_ON, 3),
        (S.READY_TO_SWITCH_ON, ENABLE_OP, S.OPERATION_ENABLED, 4),  # 3 + 4 in one step
        (S.SWITCHED_ON, ENABLE_OP, S.OPERATION_ENABLED, 4),
        (S.OPERATION_ENABLED, DISABLE_OP, S.SWITCHED_ON, 5),
        (S.SWITCHED_ON, SHUTDOWN, S.READY_TO_SWITCH_ON, 6),
        (S.READY_TO_SWITCH_ON, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, 7),
        (S.READY_TO_SWITCH_ON, QUICK_STOP, S.SWITCH_ON_DISABLED, 7),
        (S.OPERATION_ENABLED, SHUTDOWN, S.READY_TO_SWITCH_ON, 8),
        (S.OPERATION_ENABLED, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, 9),
        (S.SWITCHED_ON, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, 10),
        (S.SWITCHED_ON, QUICK_STOP, S.SWITCH_ON_DISABLED, 10),
        (S.OPERATION_ENABLED, QUICK_STOP, S.QUICK_STOP_ACTIVE, 11),
        (S.QUICK_STOP_ACTIVE, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, 12),
    ],
)
def test_transition(start: S, cw: int, end: S, transition: int) -> None:
    sm = _machine_in(start)
    assert sm.controlword(cw) == end
    assert sm.last_transition == transition


@pytest.mark.parametrize(
    ("start", "cw"),
    [
        (S.SWITCH_ON_DISABLED, SWITCH_ON),
        (S.SWITCH_ON_DISABLED, ENABLE_OP),
        (S.SWITCH_ON_DISABLED, QUICK_STOP),
        (S.QUICK_STOP_ACTIVE, ENABLE_OP),  # transition 16 not supported
        (S.QUICK_STOP_ACTIVE, SHUTDOWN),
        (S.OPERATION_ENABLED, FAULT_RESET),  # fault reset outside Fault does nothing
    ],
)
def test_no_transition(start: S, cw: int) -> None:
    sm = _machine_in(start)
    assert sm.controlword(cw) == start


@pytest.mark.parametrize(
    ("state", "statusword"),
    [
        (S.SWITCH_ON_DISABLED, 0x0240),
        (S.READY_TO_SWITCH_ON, 0x0231),
        (S.SWITCHED_ON, 0x0233),
        (S.OPERATION_ENABLED, 0x0237),
        (S.QUICK_STOP_ACTIVE, 0x0217),
    ],
)
def test_statusword_values(state: S, statusword: int) -> None:
    sm = _machine_in(state)
    sw = sm.statusword()
    assert sw == statusword
    mask, value = STATUSWORD_PATTERN[state]
    assert sw & mask == value
    assert state_from_statusword(sw) == state


def test_internal_limit_bit_only_when_enabled() -> None:
    sm = _machine_in(S.OPERATION_ENABLED)
    assert sm.statusword(internal_limit=True) == 0x0A37
    assert sm.statusword(internal_limit=True) & Statusword.INTERNAL_LIMIT
    sm.controlword(DISABLE_OP)
    assert not sm.statusword(internal_limit=True) & Statusword.INTERNAL_LIMIT


@pytest.mark.parametrize(
    "start", [S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE]
)
def test_fault_and_fault_reset(start: S) -> None:
    sm = _machine_in(start)
    sm.fault()
    assert sm.state == S.FAULT
    assert sm.last_transition == 14
    assert sm.statusword() == 0x0208
    assert state_from_statusword(sm.statusword()) == S.FAULT
    # commands are ignored in Fault
    for cw in (SHUTDOWN, SWITCH_ON, ENABLE_OP):
        assert sm.controlword(cw) == S.FAULT
    # bit 7 must rise: the controlword was 0x0F (bit 7 low), so 0x80 is a rising edge ...
    assert sm.controlword(FAULT_RESET) == S.SWITCH_ON_DISABLED
    assert sm.last_transition == 15
    assert sm.statusword() == 0x0240


def test_fault_reset_needs_a_rising_edge() -> None:
    sm = _machine_in(S.OPERATION_ENABLED)
    sm.controlword(FAULT_RESET)  # bit 7 high before the fault: no effect while enabled
    assert sm.state == S.OPERATION_ENABLED
    sm.fault()
    assert sm.controlword(FAULT_RESET) == S.FAULT  # still high: no edge
    assert sm.controlword(0x00) == S.FAULT
    assert sm.controlword(FAULT_RESET | SHUTDOWN) == S.SWITCH_ON_DISABLED  # edge; other bits ignored


def test_fault_reaction_active_statusword() -> None:
    sm = _machine_in(S.OPERATION_ENABLED)
    sm.state = S.FAULT_REACTION_ACTIVE  # the transient state (the drive completes it at once)
    assert sm.statusword() & 0x004F == 0x000F
    assert state_from_statusword(sm.statusword()) == S.FAULT_REACTION_ACTIVE
    sm.fault_reaction_complete()
    assert sm.state == S.FAULT and sm.last_transition == 14


def test_fault_enters_via_reaction_state() -> None:
    sm = _machine_in(S.OPERATION_ENABLED)
    seen = []
    orig = sm._go

    def spy(new: S, t: int) -> None:
        seen.append((new, t))
        orig(new, t)

    sm._go = spy  # type: ignore[method-assign]
    sm.fault()
    assert seen == [(S.FAULT_REACTION_ACTIVE, 13), (S.FAULT, 14)]


def test_decode_rejects_garbage() -> None:
    with pytest.raises(ValueError, match="0x0029"):
        state_from_statusword(0x0029)
