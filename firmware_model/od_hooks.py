"""The drive's object-dictionary hooks: what reading or writing an object does in the firmware.

Owns the link between the object store (:class:`bus.cia301.object_store.ObjectStore`, values
loaded from ``bus/drive.eds``) and the parts of the drive: read hooks give the live value
(statusword, actual position/velocity/torque, error register, trial and recorder state), write
hooks act on a write and may refuse it with :class:`bus.errors.SdoAbort`:

* 0x6040 controlword → the power stage (:mod:`firmware_model.power_stage`), then the selected
  mode's bits (:mod:`firmware_model.motion`); 0x6060 mode of operation → the motion layer;
  0x6062 position demand from it;
* 0x1003 error history (sub 0: number of errors, writing 0 clears, any other value 0x06090030;
  subs 1..8 the errors, newest first) → the power stage's history;
* 0x1005 COB-ID SYNC: bit 30 (generate SYNC) and 29-bit identifiers are refused (0x06090030): the
  drive consumes SYNC, it does not produce it, and a restricted CAN-ID of CiA 301 (Table 3) is refused
  too (0x06090030); 0x1014 COB-ID EMCY: the rules of
  :func:`bus.cia301.emcy.check_emcy_cob_id` (0x06090030); 0x1019 synchronous counter overflow:
  only while 0x1006 is 0 (else 0x08000022, CiA 301), 1 is refused (0x06090030);
* 0x605A quick stop option: 3, 4 (current / voltage limit) are refused (0x06090030); 0x6098
  homing method: only 35 and 37 (0x06090030);
* 0x2103, 0x2120:1, 0x2200..0x2202, 0x2210 → trial playback (:mod:`firmware_model.playback`);
* the loop parameters, written into the control law's ``st`` array in its fixed-point formats
  (:mod:`bus.fixedpoint`): gains 0x2110 (Kp Q16 µN·m/count, Kd Q16 µN·m/(count/s), velocity
  filter Q15), control period 0x2300 [µs] (tick rate Hz Q12) and its CiA 402 form 0x60C2
  (value · 10^index s), max torque 0x6072 [‰ of 0x6076] (limit in µN·m), following-error window
  0x6065 [counts] (0xFFFFFFFF: check off) and its time-out 0x6066 [ms] (whole control periods:
  the error must stay outside the window longer than it), the control structure 0x2110:4 (0 PD, 1 cascade)
  and the cascade's gains 0x60FB:1–3 (position P Q16 1/s, velocity and torque feed-forward Q16)
  and 0x60F9:1/2 (velocity PI; the I gain is kept per control period, Kvi · Ts).  They cannot
  change while a trial is armed or running (abort 0x08000022).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from bus import fixedpoint as fp
from bus.cia301.emcy import check_emcy_cob_id
from bus.cia301.object_store import ObjectStore, Value
from bus.errors import AbortCode, SdoAbort
from bus.objects import (
    GainsSub,
    HomingMethod,
    InterpolationPeriodSub,
    Obj,
    PositionControlSub,
    QuickStopOption,
    RecorderSub,
    TableSub,
    TrialCommand,
    TrialSub,
    VelocityControlSub,
)
from bus.pdo_objects import COB_ID_MASK_11, PDO_EXTENDED, SYNC_PRODUCER, is_restricted_can_id
from firmware_model import control_law
from firmware_model.motion import Motion
from firmware_model.playback import TABLE_ROWS, TrialPlayback
from firmware_model.power_stage import PowerStage

_GAIN_SLOTS = {
    GainsSub.KP: control_law.P_KP,
    GainsSub.KD: control_law.P_KD,
    GainsSub.VEL_FILTER: control_law.P_ALPHA,
    GainsSub.LOOP: control_law.P_LOOP,
}
_POSITION_CONTROL_SLOTS = {
    PositionControlSub.KPP: control_law.P_KPP,
    PositionControlSub.VELOCITY_FF: control_law.P_KVFF,
    PositionControlSub.TORQUE_FF: control_law.P_KTFF,
}
_FE_WINDOW_OFF = 0xFFFFFFFF
_QUICK_STOP_OPTIONS = frozenset(int(o) for o in QuickStopOption)
_HOMING_METHODS = frozenset(int(m) for m in HomingMethod)


def eds_default(store: ObjectStore, index: int, sub: int) -> int:
    """The EDS DefaultValue of a numeric object.

    :raises ValueError: the EDS gives none.
    """
    default = store.vars[(index, sub)].default
    if default is None:
        raise ValueError(f"the EDS gives no DefaultValue for 0x{index:04X}:{sub}")
    return int(default)


def period_repr(period_us: int) -> tuple[int, int]:
    """0x60C2 (value, index) of a control period [µs]: period = value · 10^index s, value 0..255,
    the finest index that holds it exactly, else the nearest value of a coarser index."""
    v = period_us
    idx = -6
    while v % 10 == 0 and idx < -1:
        v //= 10
        idx += 1
    while v > 255:  # not exactly representable: nearest with a coarser index
        v = (v + 5) // 10
        idx += 1
    return v, idx


class ObjectHooks:
    """The read and write hooks of one drive's objects (see the module docstring).

    :param store: the drive's object store (the hooks are installed into it).
    :param st: the control loop's state array (parameters and actual values).
    :param trial: trial playback.
    :param power: the power stage.
    :param motion: the operation modes.
    :param rated_mnm: rated torque 0x6076 [mN·m].
    """

    def __init__(
        self,
        store: ObjectStore,
        st: npt.NDArray[np.int64],
        trial: TrialPlayback,
        power: PowerStage,
        motion: Motion,
        rated_mnm: int,
    ) -> None:
        self.store = store
        self._values = store.values
        self._st = st
        self._trial = trial
        self._power = power
        self._motion = motion
        self._rated_mnm = rated_mnm
        self._install()

    def statusword(self) -> int:
        """0x6041 now."""
        return self._power.statusword(self._motion.mode.status_bits())

    def apply_parameters(self) -> None:
        """Write the loop parameters of the current object values into ``st`` (after a reset)."""
        v = self._values
        for sub in GainsSub:
            self._set_gain(sub, int(v[(Obj.GAINS, sub)]))
        self._set_period(int(v[(Obj.CONTROL_PERIOD, 0)]))
        self._set_max_torque(int(v[(Obj.MAX_TORQUE, 0)]))
        self._set_fe_window(int(v[(Obj.FOLLOWING_ERROR_WINDOW, 0)]))
        self._set_fe_time_out()
        for psub in PositionControlSub:
            self._set_position_control(psub, int(v[(Obj.POSITION_CONTROL, psub)]))
        self._st[control_law.P_KVP] = int(v[(Obj.VELOCITY_CONTROL, VelocityControlSub.KVP)])
        self._set_kvi()

    # ------------------------------------------------------------------ installation

    def _install(self) -> None:
        r = self.store.read_hooks
        w = self.store.write_hooks
        st, trial, power, values = self._st, self._trial, self._power, self._values
        r[(Obj.ERROR_REGISTER, 0)] = lambda: power.error_register
        r[(Obj.ERROR_CODE, 0)] = lambda: power.error_code
        r[(Obj.ERROR_HISTORY, 0)] = lambda: len(power.history)
        for sub in range(1, power.history.size + 1):
            if (Obj.ERROR_HISTORY, sub) in self.store.vars:
                r[(Obj.ERROR_HISTORY, sub)] = functools.partial(power.history.entry, sub)
        r[(Obj.STATUSWORD, 0)] = self.statusword
        r[(Obj.MODES_OF_OPERATION_DISPLAY, 0)] = lambda: values[(Obj.MODES_OF_OPERATION, 0)]
        r[(Obj.POSITION_DEMAND, 0)] = self._motion.demand_position
        r[(Obj.POSITION_ACTUAL, 0)] = lambda: int(st[control_law.S_POS])
        r[(Obj.VELOCITY_ACTUAL, 0)] = lambda: int(st[control_law.S_VEST])
        permille = self._motion.steps.torque_units_to_permille  # the firmware's (firmware_select.PeriodSteps)
        r[(Obj.TORQUE_ACTUAL, 0)] = lambda: permille(int(st[control_law.S_TAU]), self._rated_mnm)
        r[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.VALUE)] = lambda: self._period_repr()[0]
        r[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.INDEX)] = lambda: self._period_repr()[1]
        for index in TABLE_ROWS:
            r[(index, 0)] = functools.partial(trial.read_table, index)
            w[(index, 0)] = functools.partial(self._write_table, index)
        r[(Obj.TABLE, TableSub.LENGTH)] = lambda: trial.n_table
        r[(Obj.TABLE, TableSub.LOADED)] = lambda: trial.loaded
        r[(Obj.TRIAL, TrialSub.STATE)] = lambda: int(trial.state)
        r[(Obj.TRIAL, TrialSub.TICKS)] = lambda: trial.ticks_done
        r[(Obj.TRIAL, TrialSub.FAULT_CAUSE)] = lambda: int(trial.fault_cause)
        r[(Obj.RECORDER, RecorderSub.STATUS)] = lambda: int(trial.rec_status)
        r[(Obj.RECORDER, RecorderSub.SAMPLES)] = lambda: trial.recorded
        r[(Obj.RECORDER_DATA, 0)] = trial.read_recorder

        w[(Obj.ERROR_HISTORY, 0)] = self._write_error_history
        w[(Obj.COB_ID_SYNC, 0)] = self._write_sync_cob_id
        w[(Obj.COB_ID_EMCY, 0)] = self._write_emcy_cob_id
        w[(Obj.SYNC_COUNTER_OVERFLOW, 0)] = self._write_sync_counter_overflow
        w[(Obj.QUICK_STOP_OPTION, 0)] = self._write_quick_stop_option
        w[(Obj.HOMING_METHOD, 0)] = self._write_homing_method
        w[(Obj.CONTROLWORD, 0)] = self._write_controlword
        w[(Obj.MODES_OF_OPERATION, 0)] = lambda v: self._motion.select(int(v))
        w[(Obj.FOLLOWING_ERROR_WINDOW, 0)] = self._parameter_hook("the following-error window", self._set_fe_window)
        w[(Obj.FOLLOWING_ERROR_TIME_OUT, 0)] = self._parameter_hook(
            "the following-error time-out", lambda ms: self._set_fe_time_out(time_out_ms=ms)
        )
        w[(Obj.MAX_TORQUE, 0)] = self._parameter_hook("the max torque", self._set_max_torque)
        w[(Obj.TABLE, TableSub.LENGTH)] = lambda v: trial.write_length(int(v))
        for sub in GainsSub:
            w[(Obj.GAINS, sub)] = self._parameter_hook("the gains", functools.partial(self._set_gain, sub))
        for psub in PositionControlSub:
            w[(Obj.POSITION_CONTROL, psub)] = self._parameter_hook(
                "the position control parameters", functools.partial(self._set_position_control, psub)
            )
        w[(Obj.VELOCITY_CONTROL, VelocityControlSub.KVP)] = self._parameter_hook("the velocity loop gain", self._set_kvp)
        w[(Obj.VELOCITY_CONTROL, VelocityControlSub.KVI)] = self._parameter_hook(
            "the velocity loop integral gain", lambda ki: self._set_kvi(ki)
        )
        w[(Obj.TRIAL, TrialSub.COMMAND)] = self._write_trial_command
        w[(Obj.CONTROL_PERIOD, 0)] = self._parameter_hook("the control period", self._set_period)
        w[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.VALUE)] = lambda v: self._write_interp(int(v), None)
        w[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.INDEX)] = lambda v: self._write_interp(None, int(v))

    # ------------------------------------------------------------------ communication and profile objects

    def _write_controlword(self, value: Value) -> None:
        cw = int(value)
        self._power.controlword(cw)
        self._motion.on_controlword(cw)

    def _write_error_history(self, value: Value) -> None:
        if int(value) != 0:
            raise SdoAbort(AbortCode.VALUE_RANGE, "0x1003:0 accepts only 0 (clear the error history)")
        self._power.clear_history()

    @staticmethod
    def _write_sync_cob_id(value: Value) -> None:
        v = int(value)
        if v & SYNC_PRODUCER:
            raise SdoAbort(AbortCode.VALUE_RANGE, "the drive consumes SYNC; it cannot produce it (0x1005 bit 30)")
        if v & PDO_EXTENDED or v & 0xDFFFF800:
            raise SdoAbort(AbortCode.VALUE_RANGE, f"COB-ID SYNC 0x{v:08X}: only an 11-bit identifier is supported")
        if is_restricted_can_id(v & COB_ID_MASK_11):
            can_id = v & COB_ID_MASK_11
            raise SdoAbort(AbortCode.VALUE_RANGE, f"COB-ID SYNC 0x{v:08X}: CAN-ID 0x{can_id:03X} is restricted (CiA 301 Table 3)")

    def _write_emcy_cob_id(self, value: Value) -> None:
        try:
            check_emcy_cob_id(int(self._values[(Obj.COB_ID_EMCY, 0)]), int(value))
        except ValueError as err:
            raise SdoAbort(AbortCode.VALUE_RANGE, str(err)) from None

    def _write_sync_counter_overflow(self, value: Value) -> None:
        if int(self._values[(Obj.COMM_CYCLE_PERIOD, 0)]) != 0:
            raise SdoAbort(AbortCode.DEVICE_STATE, "0x1019 can change only while 0x1006 is 0")
        if int(value) == 1:
            raise SdoAbort(AbortCode.VALUE_RANGE, "synchronous counter overflow value 1 is reserved (0 or 2..240)")

    @staticmethod
    def _write_quick_stop_option(value: Value) -> None:
        if int(value) not in _QUICK_STOP_OPTIONS:
            supported = ", ".join(str(int(o)) for o in QuickStopOption)
            raise SdoAbort(AbortCode.VALUE_RANGE, f"quick stop option {int(value)} not supported ({supported})")

    @staticmethod
    def _write_homing_method(value: Value) -> None:
        if int(value) not in _HOMING_METHODS:
            raise SdoAbort(AbortCode.VALUE_RANGE, f"homing method {int(value)} not supported (35, 37: on the current position)")

    def _parameter_hook(self, what: str, setter: Callable[[int], None]) -> Callable[[Value], None]:
        """The write hook of a loop parameter: refused while a trial is armed or running."""

        def hook(value: Value) -> None:
            self._trial.require_not_playing(f"changing {what}")
            setter(int(value))

        return hook

    # ------------------------------------------------------------------ loop parameters

    def _set_gain(self, sub: GainsSub, value: int) -> None:
        self._st[_GAIN_SLOTS[sub]] = value

    def _set_position_control(self, sub: PositionControlSub, value: int) -> None:
        self._st[_POSITION_CONTROL_SLOTS[sub]] = value

    def _set_kvp(self, value: int) -> None:
        self._st[control_law.P_KVP] = value

    def _set_kvi(self, ki_q16: int | None = None, period_us: int | None = None) -> None:
        """The velocity loop's integral gain per control period (0x60F9:2 · 0x2300, nearest)."""
        v = self._values
        ki = int(v[(Obj.VELOCITY_CONTROL, VelocityControlSub.KVI)]) if ki_q16 is None else ki_q16
        period = int(v[(Obj.CONTROL_PERIOD, 0)]) if period_us is None else period_us
        self._st[control_law.P_KVI] = fp.ki_per_tick_q16(ki, period)

    def _set_fe_time_out(self, time_out_ms: int | None = None, period_us: int | None = None) -> None:
        """0x6066 [ms] as whole control periods: a following error longer than it is a fault."""
        v = self._values
        ms = int(v[(Obj.FOLLOWING_ERROR_TIME_OUT, 0)]) if time_out_ms is None else time_out_ms
        period = int(v[(Obj.CONTROL_PERIOD, 0)]) if period_us is None else period_us
        self._st[control_law.P_FE_TICKS] = ms * 1000 // period

    def _set_fe_window(self, value: int) -> None:
        self._st[control_law.P_FE_WINDOW] = -1 if value == _FE_WINDOW_OFF else value

    def _set_max_torque(self, permille: int) -> None:
        self._st[control_law.P_TLIM] = fp.torque_limit_units(permille, self._rated_mnm)

    def _set_period(self, period_us: int) -> None:
        self._st[control_law.P_RATE] = fp.rate_q12_from_period_us(period_us)
        self._set_kvi(period_us=period_us)
        self._set_fe_time_out(period_us=period_us)

    def _period_repr(self) -> tuple[int, int]:
        return period_repr(int(self._values[(Obj.CONTROL_PERIOD, 0)]))

    def _write_interp(self, value: int | None, index: int | None) -> None:
        """0x60C2 sub 1 or 2 written: the control period 0x2300 becomes value · 10^index s."""
        cur_v, cur_i = self._period_repr()
        v = cur_v if value is None else value
        i = cur_i if index is None else index
        scaled = v * 10 ** (i + 6)  # µs; the EDS limits the index to -6..-1
        period = self.store.vars[(Obj.CONTROL_PERIOD, 0)]
        if period.min is None or period.max is None:
            raise ValueError("the EDS gives no LowLimit/HighLimit for 0x2300")
        if not period.min <= int(scaled) <= period.max:
            raise SdoAbort(AbortCode.VALUE_RANGE, f"period {scaled} µs outside [{period.min}, {period.max}]")
        self._trial.require_not_playing("changing the control period")
        self._set_period(int(scaled))
        self._values[(Obj.CONTROL_PERIOD, 0)] = int(scaled)

    # ------------------------------------------------------------------ trial objects

    def _write_table(self, index: int, data: Value) -> None:
        if not isinstance(data, bytes):  # the EDS makes the tables DOMAINs: decoded as bytes
            raise TypeError(f"table 0x{index:04X} must be bytes, got {type(data).__name__}")
        self._trial.write_table(index, data)

    def _write_trial_command(self, value: Value) -> None:
        mode = self._motion.mode
        if int(value) == TrialCommand.ARM and not mode.PLAYS_TRIALS:
            raise SdoAbort(AbortCode.DEVICE_STATE, f"mode of operation {mode.CODE} plays no trials (-1, 8, 9, 10 do)")
        self._trial.command(int(value), needs_tables=mode.NEEDS_TABLES, in_fault=self._power.in_fault)
