"""Profile position (0x6060 = 1) and homing (6): the operation modes that move or define the
position from a set-point handshake on the controlword.

Owns :class:`ProfilePositionMode` and :class:`HomingMode` (registered with the other modes in
:mod:`firmware_model.motion`).  Both run the profile generator of :mod:`firmware_model.profile`
(position demand in counts Q16) and close the PD loop on its demand, feed-forward 0; neither
plays trials (0x2120 arming is refused).

**Profile position** (CiA 402-2 §12), in Operation enabled:

* a rising edge of controlword bit 4 (new set-point) while statusword bit 12 (set-point
  acknowledge) is 0 takes 0x607A: absolute, or with bit 6 relative to the last target (the
  buffered one if any); with bit 5 (change immediately) or no move in progress it becomes the
  target at once, else it waits in a one-deep buffer and becomes the target when the move ends
  (single set-points).  Bit 12 goes to 1; it returns to 0 once bit 4 is 0 and the buffer is
  free (then the next set-point can be given);
* the move is the trapezoidal profile of 0x6081 profile velocity [counts/s], 0x6083 profile
  acceleration and 0x6084 profile deceleration [counts/s²], converted per control cycle with
  :func:`bus.fixedpoint.per_tick_q16`; it always ends exactly on the target;
* bit 8 (halt) decelerates with 0x6084 to standstill and holds; clearing it resumes the move;
* statusword bit 10 (target reached), CiA 402: the demand is on the target with no set-point
  waiting and the *actual* position has been within 0x6067 position window [counts] of the target
  for 0x6068 position window time [ms] (whole control periods; 0x6067 = 0xFFFFFFFF: the window is
  off, bit 10 follows the demand), or halted at standstill.  Bit 13 (following error): |e| is
  above 0x6065 but not yet for longer than 0x6066 (then it is a fault, 0x8611).
* torque on, or the mode selected with torque on: the demand starts at the actual position,
  which is the target (reached).

**Homing** in Operation enabled: a rising edge of bit 4 starts the method of 0x6098.  Methods 35
and 37 (homing on the current position, CiA 402-2 §10.7) need no motion: the position actual
becomes 0x607C home offset at once (every position of the drive moves by the same amount:
:meth:`firmware_model.motion.Motion.rehome`); statusword bit 12 (homing attained) and bit 10
(target reached) are 1.  Before the start (mode selected): bit 12 = 0, bit 10 = 1 ("not
started").  The drive holds its position meanwhile.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from bus import fixedpoint as fp
from bus.objects import Controlword, HomingMethod, ModeOfOperation, Obj, Statusword
from firmware_model import control_law
from firmware_model.modes import MotionContext, OperationMode

logger = logging.getLogger(__name__)

_S_POS = control_law.S_POS
_NEW_SETPOINT = int(Controlword.NEW_SETPOINT)
_IMMEDIATELY = int(Controlword.CHANGE_IMMEDIATELY)
_RELATIVE = int(Controlword.RELATIVE)
_HALT = int(Controlword.HALT)
_REACHED = int(Statusword.TARGET_REACHED)
_ACK = int(Statusword.SETPOINT_ACKNOWLEDGE)
_ATTAINED = int(Statusword.HOMING_ATTAINED)
_HOMING_ERROR = int(Statusword.FOLLOWING_ERROR)  # bit 13: homing error in homing mode
_TARGET_POSITION = (Obj.TARGET_POSITION, 0)
_PROFILE_VELOCITY = (Obj.PROFILE_VELOCITY, 0)
_PROFILE_ACCELERATION = (Obj.PROFILE_ACCELERATION, 0)
_PROFILE_DECELERATION = (Obj.PROFILE_DECELERATION, 0)
_HOME_OFFSET = (Obj.HOME_OFFSET, 0)
_POSITION_WINDOW = (Obj.POSITION_WINDOW, 0)
_POSITION_WINDOW_TIME = (Obj.POSITION_WINDOW_TIME, 0)
_WINDOW_OFF = 0xFFFFFFFF
_FOLLOWING_ERROR = int(Statusword.FOLLOWING_ERROR)
_S_FE_COUNT = control_law.S_FE_COUNT
_HOMING_METHOD = (Obj.HOMING_METHOD, 0)
_CURRENT_POSITION_METHODS = frozenset(int(m) for m in HomingMethod)


#: the in-window time that counts as "reached" whatever 0x6068 says (its maximum, 65 535 ms)
_REACHED_NOW = 65_535_000


class _ProfileMode(OperationMode):
    """A mode that follows the profile generator's demand with the PD loop."""

    PLAYS_TRIALS = False

    def __init__(self, ctx: MotionContext) -> None:
        super().__init__(ctx)
        self._setpoint = control_law.new_tables(0)

    def _rates(self) -> tuple[int, int, int]:
        """(profile velocity, acceleration, deceleration) per control cycle, Q16."""
        period, v = self.period_us(), self.values
        return (
            fp.per_tick_q16(int(v[_PROFILE_VELOCITY]), period, 1),
            fp.per_tick_q16(int(v[_PROFILE_ACCELERATION]), period, 2),
            fp.per_tick_q16(int(v[_PROFILE_DECELERATION]), period, 2),
        )

    def demand(self) -> tuple[int, int]:
        gen = self.gen
        return gen.position_counts, self.steps.velocity_from_tick_q16(gen.v, self.period_us())

    def _follow(self, encoder_count: int) -> int:
        """The PD loop on the generator's demand this cycle: torque [µN·m]."""
        gen, sp = self.gen, self._setpoint
        sp[0, 0], sp[1, 0], sp[2, 0] = gen.position_counts, self.steps.velocity_from_tick_q16(gen.v, self.period_us()), 0
        tau, status = self.control_tick(encoder_count, 0, -1, self.st, sp, self.trial.rec)
        if status:
            return self._following_error_fault(-1)
        return tau


class ProfilePositionMode(_ProfileMode):
    """1: profile position (see the module docstring)."""

    CODE = ModeOfOperation.PROFILE_POSITION

    def __init__(self, ctx: MotionContext) -> None:
        super().__init__(ctx)
        self.reset()

    def reset(self) -> None:
        self.target = 0  #: the target of the move [counts]
        self.moving = False
        self.buffered: int | None = None  #: the next target, waiting for the move to end [counts]
        self.ack = False
        self._bit4 = False
        self._halt = False
        self._in_window_us = 0  #: how long the actual position has been in the position window [µs]

    def on_enable(self) -> None:
        here = int(self.st[_S_POS])
        self.gen.reset(here)
        self.target = here
        self.moving = False
        self.buffered = None
        self.ack = False
        self._in_window_us = _REACHED_NOW  # the actual position is the target

    def on_rehome(self, delta_counts: int) -> None:
        self.target = fp.sat32(self.target + delta_counts)
        if self.buffered is not None:
            self.buffered = fp.sat32(self.buffered + delta_counts)

    def on_controlword(self, cw: int, enabled: bool) -> None:
        bit4 = bool(cw & _NEW_SETPOINT)
        self._halt = bool(cw & _HALT)
        if enabled and bit4 and not self._bit4 and not self.ack:
            value = int(self.values[_TARGET_POSITION])
            if cw & _RELATIVE:
                base = self.buffered if self.buffered is not None else self.target
                value = fp.sat32(base + value)
            if cw & _IMMEDIATELY or not self.moving:
                self.target, self.moving, self.buffered = value, True, None
            else:
                self.buffered = value
            self.ack = True
            logger.debug("pp: set-point %d (%s)", value, "now" if self.buffered is None else "buffered")
        self._bit4 = bit4
        if not bit4 and self.buffered is None:
            self.ack = False

    @property
    def target_reached(self) -> bool:
        if self._halt:
            return self.gen.standstill
        if self.moving or self.buffered is not None:
            return False
        if int(self.values[_POSITION_WINDOW]) == _WINDOW_OFF:
            return True
        return self._in_window_us > 0 and self._in_window_us >= int(self.values[_POSITION_WINDOW_TIME]) * 1000

    def status_bits(self) -> int:
        following = _FOLLOWING_ERROR if int(self.st[_S_FE_COUNT]) > 0 else 0
        return (_REACHED if self.target_reached else 0) | (_ACK if self.ack else 0) | following

    def _track_window(self) -> None:
        """After a tick: how long the actual position has stayed in the position window."""
        window = int(self.values[_POSITION_WINDOW])
        if self.moving or self.buffered is not None or abs(self.target - int(self.st[_S_POS])) > window:
            self._in_window_us = 0
        else:
            self._in_window_us = min(self._in_window_us + self.period_us(), _REACHED_NOW)

    def tick(self, tick: int, encoder_count: int) -> int:
        v_max, acc, dec = self._rates()
        gen = self.gen
        if self._halt:
            gen.step_stop(dec)
        elif gen.step_to(self.target, v_max, acc, dec):
            if self.buffered is not None:
                self.target, self.buffered = self.buffered, None
                if not self._bit4:
                    self.ack = False
            else:
                self.moving = False
        tau = self._follow(encoder_count)
        self._track_window()
        return tau


class HomingMode(_ProfileMode):
    """6: homing on the current position (see the module docstring).

    :param rehome: redefines the position by a number of counts (the motion layer's).
    """

    CODE = ModeOfOperation.HOMING

    def __init__(self, ctx: MotionContext, rehome: Callable[[int], None] | None = None) -> None:
        super().__init__(ctx)
        self.rehome = rehome
        self.reset()

    def reset(self) -> None:
        self.attained = False
        self.error = False
        self._bit4 = False

    def on_enable(self) -> None:
        self.gen.reset(int(self.st[_S_POS]))

    def on_controlword(self, cw: int, enabled: bool) -> None:
        bit4 = bool(cw & _NEW_SETPOINT)
        if enabled and bit4 and not self._bit4:
            method = int(self.values[_HOMING_METHOD])
            if method in _CURRENT_POSITION_METHODS and self.rehome is not None:
                self.rehome(int(self.values[_HOME_OFFSET]) - int(self.st[_S_POS]))
                self.attained, self.error = True, False
                logger.info("homing (method %d): position actual := %d", method, int(self.st[_S_POS]))
            else:
                self.attained, self.error = False, True
        self._bit4 = bit4

    def status_bits(self) -> int:
        return _REACHED | (_ATTAINED if self.attained else 0) | (_HOMING_ERROR if self.error else 0)

    def tick(self, tick: int, encoder_count: int) -> int:
        _, _, dec = self._rates()
        self.gen.step_stop(dec)  # no homing motion: hold where the drive is
        return self._follow(encoder_count)
