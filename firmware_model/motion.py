"""The motion layer of one drive: the operation mode selected by 0x6060, the quick-stop ramp and
the homing offset.

Owns :class:`Motion` and the registry of the supported modes (:data:`MODE_CLASSES`, one
:class:`firmware_model.modes.OperationMode` subclass per 0x6060 value: -1 table playback, 1 profile
position, 6 homing, 8 CSP, 9 CSV, 10 CST -- exactly the modes 0x6502 lists):

* an io tick with torque on runs the selected mode (:meth:`Motion.tick`), or in Quick stop
  active the stop ramp: the demand (where the mode was going, :meth:`OperationMode.demand`)
  decelerates with the deceleration 0x605A chose (0x6084 or 0x6085, per control cycle in Q16)
  to standstill and then holds, the PD loop following it.  The ramp runs on the control cycles
  after the quick stop began -- at least one, also from standstill -- and the cycle after the one
  that reached standstill tells the power stage, before anything else
  (:meth:`Motion.finish_quick_stop`, then
  :meth:`firmware_model.power_stage.PowerStage.quick_stop_done`): Quick stop active lasts at least
  one whole control cycle, and whatever samples the statusword with that cycle (a synchronous
  TPDO of a lockstep cycle too) sees it.  A trial playing when the quick stop begins ends in FAULT.
* the homing offset: the position the drive works with is ``sat32(encoder count + offset)``;
  homing (:meth:`Motion.rehome`) changes the offset and moves every position the drive holds
  (the loop's last and previous count, the hold slot, the profile demand, the modes' targets) by
  the same amount, so nothing jumps.  NMT reset node sets it to 0.
* 0x6060 written (:meth:`Motion.select`): the new mode starts afresh (from the actual position
  when torque is on); refused while a trial is armed or running (0x08000022) and for a mode the
  drive does not have (0x06090030).
* 0x6062 position demand: the position set-point of the last control cycle (the actual position
  while torque is off).
"""

from __future__ import annotations

import logging
from typing import Protocol

from bus import fixedpoint as fp
from bus.errors import AbortCode, SdoAbort
from bus.objects import ModeOfOperation, Obj, TrialState
from firmware_model import control_law
from firmware_model.modes import (
    CspMode,
    CstMode,
    CsvMode,
    FaultSink,
    MotionContext,
    OperationMode,
    TablePlaybackMode,
)
from firmware_model.positioning import HomingMode, ProfilePositionMode

logger = logging.getLogger(__name__)

#: the supported modes of operation, by 0x6060 value
MODE_CLASSES: dict[int, type[OperationMode]] = {
    cls.CODE: cls for cls in (TablePlaybackMode, ProfilePositionMode, HomingMode, CspMode, CsvMode, CstMode)
}

_S_POS, _S_PREV, _S_ERR = control_law.S_POS, control_law.S_PREV_COUNT, control_law.S_ERR


class PowerLike(FaultSink, Protocol):
    """What the motion layer needs from the power stage (:class:`firmware_model.power_stage.PowerStage`)."""

    @property
    def on(self) -> bool: ...

    @property
    def quick_stopping(self) -> bool: ...

    def quick_stop_done(self) -> None: ...


class Motion:
    """The modes of one drive, the one selected by 0x6060, the quick-stop ramp and the homing
    offset (see the module docstring).

    :param node_id: CANopen node id (log messages).
    :param ctx: what the modes work on (``ctx.faults`` is the power stage).

    :ivar mode: the mode selected now.
    :ivar offset: homing offset: position = encoder count + offset [counts].
    """

    def __init__(self, node_id: int, ctx: MotionContext, power: PowerLike) -> None:
        self.node_id = node_id
        self._ctx = ctx
        self._values = ctx.values
        self._trial = ctx.trial
        self._st = ctx.st
        self._control_tick = ctx.control_tick
        #: the firmware's integer steps of a period besides its kernel (firmware_select.PeriodSteps)
        self.steps = ctx.steps
        self._velocity_from_tick_q16 = ctx.steps.velocity_from_tick_q16
        self._power = power
        self.gen = ctx.gen
        self.modes: dict[int, OperationMode] = {}
        for code, cls in MODE_CLASSES.items():
            self.modes[code] = HomingMode(ctx, self.rehome) if cls is HomingMode else cls(ctx)
        self.mode: OperationMode = self.modes[ModeOfOperation.TABLE_PLAYBACK]
        self.offset = 0
        self._qs_decel: tuple[int, int] = (Obj.QUICK_STOP_DECELERATION, 0)
        self._qs_reached = False  # the stop ramp reached standstill in a control cycle
        self._qs_done = False  # ... and the power stage was told
        self._qs_setpoint = control_law.new_tables(0)
        self.reset()

    def reset(self) -> None:
        """NMT reset node: every mode starts afresh; the selected one is 0x6060's value; no homing
        offset."""
        for mode in self.modes.values():
            mode.reset()
        key = (Obj.MODES_OF_OPERATION, 0)
        if int(self._values[key]) not in self.modes:  # e.g. a saved value of another firmware
            logger.warning("node %d: mode of operation %s not supported: -1", self.node_id, self._values[key])
            self._values[key] = int(ModeOfOperation.TABLE_PLAYBACK)
        self.mode = self.modes[int(self._values[key])]
        self.offset = 0
        self.gen.reset(0)

    def select(self, code: int) -> None:
        """0x6060 written: select mode ``code``.

        :raises SdoAbort: 0x06090030 mode not supported, 0x08000022 a trial is armed or running.
        """
        mode = self.modes.get(code)
        if mode is None:
            supported = ", ".join(str(c) for c in sorted(self.modes))
            raise SdoAbort(AbortCode.VALUE_RANGE, f"mode of operation {code!r} not supported ({supported})")
        if mode is self.mode:
            return
        self._trial.require_not_playing("changing the mode of operation")
        mode.reset()
        self._trial.capture_hold = True  # the hold is where the drive is now
        self.mode = mode
        if self._power.on:
            mode.on_enable()
        logger.debug("node %d mode of operation %s", self.node_id, code)

    # ------------------------------------------------------------------ events of the power stage

    def on_torque_on(self) -> None:
        """Torque came on: the selected mode starts from the actual position."""
        self.mode.on_enable()

    def on_controlword(self, cw: int) -> None:
        """0x6040 written (after the power stage took it): the mode's bits."""
        self.mode.on_controlword(cw, self._power.on and not self._power.quick_stopping)

    def begin_quick_stop(self, deceleration_index: int) -> None:
        """Quick stop active entered: the ramp starts at the mode's demand and runs from the next
        control cycle on."""
        if self._trial.playing:
            logger.warning("node %d: quick stop during a trial", self.node_id)
            self._trial.stop(TrialState.FAULT)
        self._qs_decel = (deceleration_index, 0)
        self._qs_reached = False
        self._qs_done = False
        if not isinstance(self.mode, (ProfilePositionMode, HomingMode, CsvMode)):
            pos, vel = self.mode.demand()
            self.gen.reset(pos, fp.per_tick_q16(vel, self.mode.period_us(), 1))

    def finish_quick_stop(self) -> None:
        """At the start of a control cycle in Quick stop active: once the ramp reached standstill in
        an earlier cycle, the power stage completes the quick stop (transition 12, or holding)."""
        if self._qs_reached and not self._qs_done:
            self._qs_done = True
            self._power.quick_stop_done()

    # ------------------------------------------------------------------ io tick

    def tick(self, tick: int, count: int) -> int:
        """One io tick with torque on at position ``count`` (offset applied): torque [µN·m]."""
        if not self._power.quick_stopping:
            return self.mode.tick(tick, count)
        gen, sp = self.gen, self._qs_setpoint
        period = self.mode.period_us()
        gen.step_stop(fp.per_tick_q16(int(self._values[self._qs_decel]), period, 2))
        sp[0, 0], sp[1, 0], sp[2, 0] = gen.position_counts, self._velocity_from_tick_q16(gen.v, period), 0
        tau, status = self._control_tick(count, 0, -1, self._st, sp, self._trial.rec)
        if status:
            return self._power.following_error(int(self._st[_S_ERR]))
        if gen.standstill:
            self._qs_reached = True
        return tau

    def position(self, encoder_count: int) -> int:
        """The drive's position of ``encoder_count``: with the homing offset, saturated."""
        return fp.sat32(encoder_count + self.offset) if self.offset else encoder_count

    def demand_position(self) -> int:
        """0x6062: the position set-point of the last control cycle [counts]."""
        st = self._st
        if not self._power.on:
            return int(st[_S_POS])
        return fp.sat32(int(st[_S_POS]) + int(st[_S_ERR]))

    # ------------------------------------------------------------------ homing

    def rehome(self, delta_counts: int) -> None:
        """Redefine the position by ``delta_counts`` (see the module docstring)."""
        delta = int(delta_counts)
        st = self._st
        self.offset += delta
        st[_S_POS] = fp.sat32(int(st[_S_POS]) + delta)
        st[_S_PREV] = fp.sat32(int(st[_S_PREV]) + delta)
        tables, hold = self._trial.tables, self._trial.capacity
        tables[control_law.ROW_REF_POS, hold] = fp.sat32(int(tables[control_law.ROW_REF_POS, hold]) + delta)
        self.gen.shift(delta)
        for mode in self.modes.values():
            mode.on_rehome(delta)
