"""Operation modes of one drive (CiA 402 0x6060): what an io tick computes while torque is on.

Owns the base class of the modes (:class:`OperationMode`) and the modes that play trials: table
playback and the cyclic synchronous modes.  Profile position and homing are
:mod:`firmware_model.positioning`; the mode selected now, the quick-stop ramp and the homing
offset are :mod:`firmware_model.motion`.  Each mode turns (tick, encoder count [counts]) into a
torque [µN·m] with the drive's control-period kernel (:attr:`MotionContext.control_tick`: the
firmware it runs, :mod:`firmware_model.firmware_select`); the trial bookkeeping (tick 0
starts an armed trial, then ticks must come in order, N ticks end it) is the same for every mode
that plays trials (:meth:`OperationMode.in_sequence`).  A tick out of sequence and a following
error are faults of the power stage (:class:`FaultSink`).

* table playback (-1, manufacturer specific): the PD loop follows the reference tables with
  the feed-forward table; with no trial playing it holds the hold slot (the encoder count of the
  first tick after torque came on, velocity 0, no feed-forward; after a trial, the last entry).
  At tick 0 the velocity estimator starts at the reference velocity of sample 0 (the alignment
  assumption).
* CSP (8, cyclic synchronous position; statusword bit 13 = following error within 0x6066): the
  PD loop closes on 0x607A target position; the
  velocity reference is the backward difference of successive targets,
  ``(p[n] − p[n−1])·rate`` in the loop's Q12 arithmetic, rounded and saturated to int32 (0 on
  the first tick of a trial, after a mode change and when torque comes on; the firmware's ``csp_velocity_ref``,
  :attr:`MotionContext.steps`); the feed-forward is 0x60B2 torque offset
  [‰ of 0x6076].
* CSV (9, cyclic synchronous velocity): the position demand integrates 0x60FF target velocity
  [counts/s] in the profile generator's Q16 (:mod:`firmware_model.profile`; it starts at the
  actual position when torque comes on, the mode is selected or a trial starts); the PD loop
  closes on it with the velocity reference 0x60FF and the feed-forward 0x60B2.
* CST (10, cyclic synchronous torque): torque = 0x6071 + 0x60B2 [‰ of 0x6076], no feedback (in
  either loop structure) and no following-error check, clamped to 0x6072.

"The PD loop" below is the drive's feedback structure (0x2110:4): the PD loop of 0x2110:1/2, or the
cascade of 0x60FB/0x60F9 (:mod:`firmware_model.control_law`).

The cyclic modes (:attr:`OperationMode.CYCLIC`) are paced by SYNC while NMT OPERATIONAL
(:mod:`firmware_model.cyclic_pdo`) and set statusword bit 12 ("drive follows the command
value") in Operation enabled.  A trial in a cyclic mode records N samples from tick 0 exactly as
table playback does.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np
import numpy.typing as npt

from bus import fixedpoint as fp
from bus.cia301.object_store import Key, Value
from bus.objects import ModeOfOperation, Obj, TrialState
from firmware_model import control_law
from firmware_model.firmware_select import ControlTick, PeriodSteps, period_steps_for
from firmware_model.playback import TrialPlayback
from firmware_model.profile import ProfileGenerator

logger = logging.getLogger(__name__)

_RUNNING = TrialState.RUNNING
_S_VF, _S_HAVE_PREV, _S_ERR = control_law.S_VF, control_law.S_HAVE_PREV, control_law.S_ERR
_S_POS, _S_VEST = control_law.S_POS, control_law.S_VEST
_P_KP, _P_KD, _P_FE, _P_RATE = control_law.P_KP, control_law.P_KD, control_law.P_FE_WINDOW, control_law.P_RATE
_TARGET_POSITION = (Obj.TARGET_POSITION, 0)
_TARGET_TORQUE = (Obj.TARGET_TORQUE, 0)
_TORQUE_OFFSET = (Obj.TORQUE_OFFSET, 0)
_TARGET_VELOCITY = (Obj.TARGET_VELOCITY, 0)
_PERIOD = (Obj.CONTROL_PERIOD, 0)
_P_LOOP = control_law.P_LOOP


class FaultSink(Protocol):
    """Where a mode reports its faults (:class:`firmware_model.power_stage.PowerStage`); each
    returns the torque of the tick, 0 [µN·m]."""

    def following_error(self, error_counts: int) -> int: ...

    def sequence_error(self, expected: int, tick: int) -> int: ...


@dataclass(frozen=True)
class MotionContext:
    """What the modes of one drive work on.

    :ivar st: the control loop's state array (:func:`firmware_model.control_law.new_state`).
    :ivar trial: the drive's trial playback (tables, recorder, tick sequence).
    :ivar values: the object values of the drive's object store (set-points).
    :ivar rated_mnm: rated torque 0x6076 [mN·m] (‰ set-points → µN·m).
    :ivar faults: where faults go.
    :ivar gen: the profile generator the profile-based modes and the quick-stop ramp share.
    :ivar control_tick: the drive's control-period kernel, the firmware it runs
        (:func:`firmware_model.firmware_select.control_tick_for`; default: the Python model).
    :ivar steps: the period's other integer steps of that firmware (CSP velocity reference,
        profile velocity in counts/s, 0x6077; :func:`firmware_model.firmware_select.period_steps_for`).
    """

    st: npt.NDArray[np.int64]
    trial: TrialPlayback
    values: dict[Key, Value]
    rated_mnm: int
    faults: FaultSink
    gen: ProfileGenerator
    control_tick: ControlTick = control_law.control_tick
    steps: PeriodSteps = field(default_factory=lambda: period_steps_for("python"))


class OperationMode(ABC):
    """One mode of operation (see the module docstring), working on ``ctx``."""

    #: the 0x6060 value
    CODE: ClassVar[int]
    #: io ticks are paced by SYNC while NMT OPERATIONAL
    CYCLIC: ClassVar[bool] = False
    #: the trial plays the tables 0x2200..0x2202 (they must be loaded to arm)
    NEEDS_TABLES: ClassVar[bool] = False
    #: a trial (0x2120) can be armed in this mode
    PLAYS_TRIALS: ClassVar[bool] = True
    #: statusword bits 10/12/13 in Operation enabled (:meth:`status_bits`)
    STATUS_BITS: ClassVar[int] = 0

    def __init__(self, ctx: MotionContext) -> None:
        self.st = ctx.st
        self.trial = ctx.trial
        self.values = ctx.values
        self.rated_mnm = ctx.rated_mnm
        self.faults = ctx.faults
        self.gen = ctx.gen
        self.control_tick = ctx.control_tick
        self.steps = ctx.steps

    def reset(self) -> None:  # noqa: B027 - a mode without state between ticks has nothing to forget
        """Forget what earlier ticks left (NMT reset node, this mode selected again)."""

    def on_enable(self) -> None:  # noqa: B027 - most modes start from the encoder by themselves
        """Torque came on, or this mode was selected with torque on: start from the actual
        position."""

    def on_controlword(self, cw: int, enabled: bool) -> None:  # noqa: B027 - only some modes use bits 4..9
        """0x6040 written (``enabled``: the drive is in Operation enabled): the mode's bits."""

    def on_rehome(self, delta_counts: int) -> None:  # noqa: B027 - a mode without positions to move
        """The position was redefined by ``delta_counts`` (homing): move what the mode holds."""

    def status_bits(self) -> int:
        """Statusword bits 10/12/13 in Operation enabled."""
        return self.STATUS_BITS

    def demand(self) -> tuple[int, int]:
        """The motion now as (position [counts], velocity [counts/s]): where a quick stop ramp
        starts (by default the actual position and velocity estimate)."""
        return int(self.st[_S_POS]), int(self.st[_S_VEST])

    def period_us(self) -> int:
        """The control period 0x2300 [µs]."""
        return int(self.values[_PERIOD])

    def initial_velocity(self) -> int:
        """Velocity estimator state at tick 0 of a trial [counts/s] (0: no previous target)."""
        return 0

    def start_trial(self) -> None:
        """Tick 0 of an armed trial: the velocity estimator starts afresh, the trial runs."""
        st = self.st
        st[_S_HAVE_PREV] = 0
        st[_S_VF] = self.initial_velocity() << fp.VEL_STATE_Q
        st[control_law.S_VINT] = 0
        self.trial.start()

    def in_sequence(self, tick: int) -> bool:
        """Trial bookkeeping before io tick ``tick``: running, it must be the next tick; armed, it
        must be tick 0, which starts the trial; otherwise any tick holds.  False: out of sequence."""
        state = self.trial.state
        if state == _RUNNING:
            return tick == self.trial.next_tick
        if state == TrialState.ARMED:
            if tick != 0:
                return False
            self.start_trial()
        return True

    @abstractmethod
    def tick(self, tick: int, encoder_count: int) -> int:
        """One io tick with torque on: torque command [µN·m]."""

    def _sequence_fault(self, tick: int) -> int:
        trial = self.trial
        return self.faults.sequence_error(trial.next_tick if trial.state == _RUNNING else 0, tick)

    def _following_error_fault(self, rec_index: int) -> int:
        """A following error on the tick recorded at ``rec_index`` (-1: none): the plant gets no
        torque on this tick, and the recorder says so."""
        error = int(self.st[_S_ERR])
        if rec_index >= 0:
            self.trial.rec[control_law.REC_TAU, rec_index] = 0
        return self.faults.following_error(error)


class TablePlaybackMode(OperationMode):
    """-1: follow the reference and feed-forward tables (see the module docstring)."""

    CODE = ModeOfOperation.TABLE_PLAYBACK
    NEEDS_TABLES = True

    def initial_velocity(self) -> int:
        return int(self.trial.tables[control_law.ROW_REF_VEL, 0])

    def tick(self, tick: int, encoder_count: int) -> int:
        if not self.in_sequence(tick):
            return self._sequence_fault(tick)
        trial = self.trial
        if trial.state != _RUNNING:
            trial.hold_here(encoder_count)
            tau, status = self.control_tick(encoder_count, trial.capacity, -1, self.st, trial.tables, trial.rec)
            if status:
                return self._following_error_fault(-1)
            return tau
        tau, status = self.control_tick(encoder_count, tick, tick, self.st, trial.tables, trial.rec)
        trial.next_tick = tick + 1
        if status:
            return self._following_error_fault(tick)
        if trial.next_tick == trial.n_table:
            trial.finish()
        return tau


class CyclicSynchronousMode(OperationMode, ABC):
    """A cyclic synchronous mode: the set-points of the tick come from objects written by RPDO
    (or SDO) and go through a one-column table into the control law."""

    CYCLIC = True
    STATUS_BITS = 0x1000  # CSx: the drive follows the command value

    def __init__(self, ctx: MotionContext) -> None:
        super().__init__(ctx)
        self._setpoint = control_law.new_tables(0)  # column 0: the set-points of the tick
        # column 0's three rows written through a flat view: no numpy call per set-point and tick
        self._column = self._setpoint.ravel().data

    def _offset_units(self) -> int:
        """0x60B2 torque offset [µN·m]."""
        return int(self.values[_TORQUE_OFFSET]) * self.rated_mnm  # ‰ of mN·m = µN·m

    @abstractmethod
    def _control(self, encoder_count: int, rec_index: int) -> tuple[int, int]:
        """The control law on this tick's set-points: (torque [µN·m], kernel status)."""

    def tick(self, tick: int, encoder_count: int) -> int:
        if not self.in_sequence(tick):
            return self._sequence_fault(tick)
        trial = self.trial
        playing = trial.state == _RUNNING
        rec_index = tick if playing else -1
        tau, status = self._control(encoder_count, rec_index)
        if playing:
            trial.next_tick = tick + 1
        if status:
            return self._following_error_fault(rec_index)
        if playing and trial.next_tick == trial.n_table:
            trial.finish()
        return tau


class CspMode(CyclicSynchronousMode):
    """8: cyclic synchronous position (see the module docstring)."""

    CODE = ModeOfOperation.CSP

    def __init__(self, ctx: MotionContext) -> None:
        super().__init__(ctx)
        self._prev_target: int | None = None  # 0x607A of the previous tick [counts]

    def reset(self) -> None:
        self._prev_target = None

    def on_enable(self) -> None:
        """Torque on: no previous target (the first period's velocity reference is 0). The last
        target of an earlier enable may be far from this one (a master that disables, writes the
        target where the joint stands now and enables again): their difference as a velocity
        reference is a torque kick at enable, which grows with each disable/enable cycle."""
        self._prev_target = None

    def start_trial(self) -> None:
        self._prev_target = None  # no previous target in a new trial
        super().start_trial()

    def on_rehome(self, delta_counts: int) -> None:
        self._prev_target = None  # the next target is in the new coordinates

    def status_bits(self) -> int:
        """Bit 12, and bit 13 (following error) while |e| is above 0x6065, not yet for longer than
        0x6066 (then it is a fault)."""
        return self.STATUS_BITS | (0x2000 if int(self.st[control_law.S_FE_COUNT]) > 0 else 0)

    def demand(self) -> tuple[int, int]:
        sp = self._setpoint
        if self._prev_target is None:
            return super().demand()
        return int(sp[0, 0]), int(sp[1, 0])

    def _control(self, encoder_count: int, rec_index: int) -> tuple[int, int]:
        st = self.st
        target = int(self.values[_TARGET_POSITION])
        prev = self._prev_target
        vref = 0 if prev is None else self.steps.csp_velocity_ref(target, prev, int(st[_P_RATE]))
        self._prev_target = target
        col = self._column
        col[0], col[1], col[2] = target, vref, fp.sat32(self._offset_units())
        return self.control_tick(encoder_count, 0, rec_index, st, self._setpoint, self.trial.rec)


class CsvMode(CyclicSynchronousMode):
    """9: cyclic synchronous velocity (see the module docstring)."""

    CODE = ModeOfOperation.CSV

    def on_enable(self) -> None:
        self.gen.reset(int(self.st[_S_POS]))

    def start_trial(self) -> None:
        self.gen.reset(int(self.st[_S_POS]))  # the demand starts where the drive is
        super().start_trial()

    def demand(self) -> tuple[int, int]:
        return self.gen.position_counts, int(self.values[_TARGET_VELOCITY])

    def _control(self, encoder_count: int, rec_index: int) -> tuple[int, int]:
        gen = self.gen
        v_target = int(self.values[_TARGET_VELOCITY])
        gen.step_velocity(fp.per_tick_q16(v_target, self.period_us(), 1))
        col = self._column
        col[0], col[1], col[2] = gen.position_counts, v_target, fp.sat32(self._offset_units())
        return self.control_tick(encoder_count, 0, rec_index, self.st, self._setpoint, self.trial.rec)


class CstMode(CyclicSynchronousMode):
    """10: cyclic synchronous torque (see the module docstring)."""

    CODE = ModeOfOperation.CST

    def _control(self, encoder_count: int, rec_index: int) -> tuple[int, int]:
        st, sp = self.st, self._setpoint
        target_torque = int(self.values[_TARGET_TORQUE]) * self.rated_mnm
        saved = int(st[_P_KP]), int(st[_P_KD]), int(st[_P_FE]), int(st[_P_LOOP])
        st[_P_KP] = st[_P_KD] = 0  # no feedback
        st[_P_LOOP] = control_law.LOOP_PD  # (in either structure)
        st[_P_FE] = -1  # no following-error check
        sp[0, 0] = fp.sat32(encoder_count)
        sp[1, 0] = 0
        sp[2, 0] = fp.sat32(target_torque + self._offset_units())
        try:
            return self.control_tick(encoder_count, 0, rec_index, st, sp, self.trial.rec)
        finally:
            st[_P_KP], st[_P_KD], st[_P_FE], st[_P_LOOP] = saved
