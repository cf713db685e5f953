"""One emulated servo drive: object dictionary, NMT state, CiA 402, trial playback, recorder.

Owns the drive's application layer.  The object dictionary is loaded from
``bus/drive.eds`` with :func:`canopen.objectdictionary.import_od` (metadata: data
type, access, default, limits); values are kept here and reached as bytes through
:meth:`Drive.read_object` / :meth:`Drive.write_object`, which raise
:class:`bus.errors.SdoAbort` with CiA 301 abort codes.  Object callbacks link the
dictionary to the live fixed-point loop (:mod:`firmware_model.control_law`) and to the
CiA 402 state machine (:mod:`firmware_model.cia402`).  The CANopen protocol layer
(SDO server, NMT frames, heartbeat, EMCY frames) is :mod:`firmware_model.drive_node`, which
calls this class; formats and units: :mod:`bus.fixedpoint`, indices: :mod:`bus.objects`.

Tick semantics (:meth:`Drive.io_tick`):

* torque is 0 unless NMT is operational **and** CiA 402 is Operation enabled;
* no trial playing (idle/done): PD holds the hold slot -- the encoder count seen on
  the first tick after enabling (velocity reference 0, no feed-forward), or after a
  trial the last table entry (PD + last feed-forward);
* armed: the next tick must be tick 0, which starts playback (velocity estimator reset
  to the reference velocity of sample 0, the alignment assumption); then ticks must be
  1, 2, ... in order.  A missing, duplicate or stale tick is a fault (EMCY 0x8200);
* after tick N-1 the trial is done and the recorder complete;
* |position error| > 0x6065 is a fault (EMCY 0x8611).  A fault enters CiA 402 Fault,
  sets 0x1001/0x603F, removes torque and queues an EMCY (:meth:`Drive.pop_emcy`);
  fault reset (controlword bit 7 rising edge) queues EMCY 0x0000.

If the torque enable is lost while a trial is running (disable, NMT stop), the trial
ends in state FAULT (cause NONE) and the recorder is STOPPED.

Loss of the host (heartbeat consumer 0x1016, :meth:`Drive.heartbeat_lost`) or of the bus
(:meth:`Drive.bus_lost`) is a fault like the others: torque off, CiA 402 Fault, EMCY 0x8130
(heartbeat; a lost bus cannot carry one).  Only in NMT STOPPED, where torque is off already and
the master stopped the node on purpose, a lost heartbeat is just logged.  Gains (0x2110), the
following-error window (0x6065), the max torque (0x6072), the tables and the control period
cannot change while a trial is armed or running (abort 0x08000022).  Every time torque goes
off, one ``SAFE-STATE`` record (:mod:`bus.safe_state`) is logged with the reason.

Cyclic synchronous modes (0x6060 = 8 CSP, 10 CST; docs/canopen-objects.md §10, docs/timing.md §7):
the set-points arrive by RPDO (or SDO) in 0x607A target position [counts], 0x6071 target
torque and 0x60B2 torque offset [‰ of 0x6076]; the PDO service is :class:`bus.cia301.pdo.PdoEngine`.

* CSP: the PD loop closes on 0x607A; the velocity reference is the backward difference of
  successive targets, ``(p[n] − p[n−1])·rate`` in the loop's Q12 arithmetic (0 on the first tick
  of a trial, as the table's velocity sample 0); the feed-forward is 0x60B2.
* CST: torque = 0x6071 + 0x60B2 (no feedback, no following-error check), clamped to 0x6072.
* While the drive is NMT OPERATIONAL in a cyclic mode, an io tick may run only after a SYNC
  (:meth:`Drive.on_sync`, one credit per SYNC, not accumulated): the node runtime holds the
  encoder frame until the SYNC came (:attr:`Drive.tick_ready`); after the tick the cycle's
  TPDOs are due (:meth:`Drive.pop_tpdos`).
* a trial (arm 0x2120:1 = 1, needs only the table length 0x2103:1 = N, no tables) records N
  samples from tick 0, exactly as in table playback.
"""

from __future__ import annotations

import functools
import logging
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bus import fixedpoint as fp
from bus.cia301.emcy import EmcyCode, ErrorRegister
from bus.cia301.nmt import NmtCommand, NmtState
from bus.cia301.pdo import PdoEngine
from bus.cia301.slave import ObjectStore
from bus.errors import AbortCode, IlcrigError, SdoAbort
from bus.objects import (
    DRIVE_EDS_PATH,
    Cia402State,
    FaultCause,
    GainsSub,
    InterpolationPeriodSub,
    ModeOfOperation,
    Obj,
    RecorderStatus,
    RecorderSub,
    TableLoaded,
    TableSub,
    TrialCommand,
    TrialState,
    TrialSub,
)
from bus.safe_state import TORQUE_ON_TAG, format_safe_state
from firmware_model import control_law
from firmware_model.cia402 import Cia402StateMachine

logger = logging.getLogger(__name__)

DEFAULT_EDS_PATH: Path = DRIVE_EDS_PATH

_TABLE_ROWS: dict[int, int] = {Obj.REF_POSITION_TABLE: 0, Obj.REF_VELOCITY_TABLE: 1, Obj.FEEDFORWARD_TABLE: 2}
_TABLE_BITS = (TableLoaded.REF_POSITION, TableLoaded.REF_VELOCITY, TableLoaded.FEEDFORWARD)

Value = int | float | bytes | str
Key = tuple[int, int]


class NmtCommandError(IlcrigError, ValueError):
    """Unknown NMT command specifier."""


class Drive:
    """One drive's firmware.

    :param node_id: CANopen node id 1..127.
    :param eds_path: EDS describing the object dictionary.
    :raises ValueError: bad node id, or an EDS without the defaults/limits the drive needs.
    """

    # trial and fault state, set by _reset_application (called from __init__)
    _n_table: int
    _loaded: int
    _trial_state: TrialState
    _rec_status: RecorderStatus
    _next_tick: int
    _fault_cause: FaultCause
    _error_register: int
    _error_code: int
    _capture_hold: bool
    _power: bool

    def __init__(self, node_id: int, eds_path: str | Path = DEFAULT_EDS_PATH) -> None:
        if not 1 <= int(node_id) <= 127:
            raise ValueError(f"node id must be 1..127, got {node_id}")
        self.node_id = int(node_id)
        # object values, access/size/limit checks and hooks: the CANopen slave object store
        # that the plant node uses too (bus/cia301/slave.py)
        self.store = ObjectStore(eds_path, self.node_id)
        self.od = self.store.od
        self._vars = self.store.vars
        self._capacity = self._eds_default(Obj.TABLE, TableSub.CAPACITY)
        self._rated_mnm = self._eds_default(Obj.RATED_TORQUE, 0)
        self._st = control_law.new_state()
        self._tables = control_law.new_tables(self._capacity)
        self._rec = control_law.new_recorder(self._capacity)
        self._sm = Cia402StateMachine()
        self._emcy: list[tuple[int, int, bytes]] = []
        self._values = self.store.values
        self._read_hooks = self.store.read_hooks
        self._write_hooks = self.store.write_hooks
        self.pdo = PdoEngine(self.store, lambda: int(self.nmt_state))
        self._cyc = control_law.new_tables(0)  # column 0: the cyclic set-points of the tick
        self._cyc_prev_target: int | None = None
        self._sync_credit = 0
        self._install_hooks()
        self.nmt_state: NmtState = NmtState.INITIALISING
        self._reset_application()
        self._reset_communication()
        self.nmt_state = NmtState.PRE_OPERATIONAL  # boot-up done
        self._update_power()

    # ------------------------------------------------------------------ public API

    @property
    def cia402_state(self) -> Cia402State:
        return self._sm.state

    @property
    def statusword(self) -> int:
        sw = self._sm.statusword(bool(self._st[control_law.S_LIMITED]) and self._power)
        if self._power and self._mode != ModeOfOperation.TABLE_PLAYBACK:
            sw |= 0x1000  # CSx: drive follows the command value
        return sw

    @property
    def _mode(self) -> int:
        return int(self._values[(Obj.MODES_OF_OPERATION, 0)])

    # ------------------------------------------------------------------ SYNC and PDOs

    @property
    def cyclic_active(self) -> bool:
        """True when io ticks are paced by SYNC: a cyclic mode and NMT OPERATIONAL."""
        return self._mode != ModeOfOperation.TABLE_PLAYBACK and self.pdo.active

    @property
    def tick_ready(self) -> bool:
        """False while an io tick must wait for its SYNC (see the module docstring)."""
        return self._sync_credit > 0 or not self.cyclic_active

    def on_sync(self) -> None:
        """A SYNC frame: synchronous RPDOs take effect, the next io tick may run."""
        if self.pdo.active:
            self.pdo.on_sync()
            self._sync_credit = 1

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A fieldbus frame that may be an RPDO; True when it was one (handled)."""
        return self.pdo.on_rpdo(can_id, data)

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID this drive consumes (0x1005)."""
        return self.pdo.sync_cob_id()

    def rpdo_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid RPDOs (0x1400..: sub 1)."""
        return list(self.pdo.rpdo_cob_ids())

    def pop_tpdos(self) -> list[tuple[int, bytes]]:
        """(COB-ID, payload) of the TPDOs due after the last io tick."""
        return self.pdo.collect_tpdos()

    @property
    def trial_state(self) -> TrialState:
        return TrialState(self._trial_state)

    @property
    def torque_enabled(self) -> bool:
        """True when NMT operational and CiA 402 Operation enabled."""
        return self._power

    def pop_emcy(self) -> list[tuple[int, int, bytes]]:
        """Pending EMCY messages ``(error code, error register, 5 manufacturer bytes)``,
        oldest first; the queue is emptied."""
        out, self._emcy = self._emcy, []
        return out

    def heartbeat_lost(self, node_id: int) -> None:
        """CiA 301 heartbeat consumer event: producer ``node_id`` (the host) went silent.

        In NMT STOPPED only logged (torque is off and the master stopped the node on purpose);
        otherwise a fault: torque off, CiA 402 Fault, trial stopped, EMCY 0x8130."""
        if self.nmt_state == NmtState.STOPPED:
            logger.info("node %d: heartbeat of node %d lost while NMT STOPPED (torque off already)", self.node_id, node_id)
            return
        self._fault_reason = f"heartbeat-of-node-{node_id}-lost"
        self._fault(
            EmcyCode.HEARTBEAT_ERROR,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.HEARTBEAT,
            struct.pack("<BB3x", FaultCause.HEARTBEAT, node_id & 0xFF),
        )

    def bus_lost(self, reason: str) -> None:
        """The fieldbus or io bus failed (e.g. the hub is gone): torque off, CiA 402 Fault (no
        EMCY can be sent)."""
        self._fault_reason = "bus-lost"
        self._fault(
            EmcyCode.COMMUNICATION,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.BUS_LOST,
            struct.pack("<B4x", FaultCause.BUS_LOST),
        )
        logger.warning("node %d: bus lost (%s): torque off", self.node_id, reason)

    def power_off(self, reason: str) -> None:
        """The drive process stops (SIGTERM, the end of a run): the power stage goes off; a
        SAFE-STATE record is logged if torque was still on."""
        if self._power:
            self._power = False
            logger.info(
                format_safe_state(
                    f"drive{self.node_id}", reason, cia402=self._sm.state.name, nmt=NmtState(self.nmt_state).name, tick="-"
                )
            )

    def nmt_command(self, cs: int) -> NmtState:
        """Apply an NMT command specifier; returns the new NMT state.

        Reset node / reset communication end in pre-operational (the protocol layer
        then sends the boot-up frame).

        :raises NmtCommandError: unknown command specifier.
        """
        try:
            cmd = NmtCommand(cs)
        except ValueError:
            raise NmtCommandError(f"unknown NMT command specifier 0x{int(cs):02X}") from None
        if cmd == NmtCommand.START:
            self.nmt_state = NmtState.OPERATIONAL
        elif cmd == NmtCommand.STOP:
            self.nmt_state = NmtState.STOPPED
        elif cmd == NmtCommand.ENTER_PRE_OPERATIONAL:
            self.nmt_state = NmtState.PRE_OPERATIONAL
        elif cmd == NmtCommand.RESET_NODE:
            self.nmt_state = NmtState.INITIALISING
            self._update_power()
            self._reset_application()
            self._reset_communication()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        else:
            self.nmt_state = NmtState.INITIALISING
            self._reset_communication()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        logger.debug("node %d NMT %s -> %s", self.node_id, cmd.name, self.nmt_state.name)
        self._update_power()
        return self.nmt_state

    def read_object(self, index: int, sub: int) -> bytes:
        """Read an object as bytes (little endian).

        :raises SdoAbort: 0x06020000 no object, 0x06090011 no sub-index, 0x06010001
            write-only, 0x08000022 not readable now (recorder while recording).
        """
        return self.store.read_object(index, sub)

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        """Write an object from bytes (little endian).

        :raises SdoAbort: 0x06020000 / 0x06090011 unknown, 0x06010002 read-only,
            0x06070010 wrong length, 0x06090030/31/32 value range/too high/too low,
            0x08000022 not allowed in the current state.
        """
        self.store.write_object(index, sub, data)

    def io_tick(self, tick: int, encoder_count: int) -> int:
        """One control tick: encoder count (int32 counts) in, torque command (µN·m) out."""
        if not self._power:
            self._st[control_law.S_POS] = min(max(encoder_count, fp.INT32_MIN), fp.INT32_MAX)
            self._sync_credit = 0
            return 0
        if self._mode != ModeOfOperation.TABLE_PLAYBACK:
            return self._cyclic_tick(tick, encoder_count)
        if not self._tick_in_sequence(tick):
            return self._sequence_fault(tick)
        if self._trial_state != TrialState.RUNNING:
            if self._capture_hold:
                self._capture_hold = False
                self._tables[:, self._capacity] = (min(max(encoder_count, fp.INT32_MIN), fp.INT32_MAX), 0, 0)
            tau, status = control_law.control_tick(encoder_count, self._capacity, -1, self._st, self._tables, self._rec)
            if status:
                return self._following_error_fault(-1)
            return tau
        n = tick
        tau, status = control_law.control_tick(encoder_count, n, n, self._st, self._tables, self._rec)
        self._next_tick = n + 1
        if status:
            return self._following_error_fault(n)
        if self._next_tick == self._n_table:
            self._finish_trial()
        return tau

    def _cyclic_tick(self, tick: int, encoder_count: int) -> int:
        """One tick in CSP / CST with the set-points in 0x607A, 0x6071, 0x60B2."""
        self._sync_credit = 0
        if not self._tick_in_sequence(tick):
            return self._sequence_fault(tick)
        playing = self._trial_state == TrialState.RUNNING
        rec_idx = tick if playing else -1
        st, v, cyc = self._st, self._values, self._cyc
        offset = int(v[(Obj.TORQUE_OFFSET, 0)]) * self._rated_mnm  # ‰ → µN·m
        if self._mode == ModeOfOperation.CSP:
            target = int(v[(Obj.TARGET_POSITION, 0)])
            prev = self._cyc_prev_target
            vref = (
                0
                if prev is None
                else fp.sat32(fp.rshift_round(fp.sat32(target - prev) * int(st[control_law.P_RATE]), fp.VEL_STATE_Q))
            )
            self._cyc_prev_target = target
            cyc[0, 0], cyc[1, 0], cyc[2, 0] = target, vref, fp.sat32(offset)
            tau, status = control_law.control_tick(encoder_count, 0, rec_idx, st, cyc, self._rec)
        else:  # CST: no feedback, no following-error check
            target_torque = int(v[(Obj.TARGET_TORQUE, 0)]) * self._rated_mnm
            saved = int(st[control_law.P_KP]), int(st[control_law.P_KD]), int(st[control_law.P_FE_WINDOW])
            st[control_law.P_KP] = st[control_law.P_KD] = 0
            st[control_law.P_FE_WINDOW] = -1
            cyc[0, 0] = fp.sat32(encoder_count)
            cyc[1, 0] = 0
            cyc[2, 0] = fp.sat32(target_torque + offset)
            try:
                tau, status = control_law.control_tick(encoder_count, 0, rec_idx, st, cyc, self._rec)
            finally:
                st[control_law.P_KP], st[control_law.P_KD], st[control_law.P_FE_WINDOW] = saved
        if playing:
            self._next_tick = tick + 1
        if status:
            return self._following_error_fault(rec_idx)
        if playing and self._next_tick == self._n_table:
            self._finish_trial()
        return tau

    # ------------------------------------------------------------------ trial logic

    def _tick_in_sequence(self, tick: int) -> bool:
        """Trial bookkeeping before io tick ``tick``: running, it must be the next tick; armed, it
        must be tick 0, which starts the trial; idle, any tick holds.  False: out of sequence."""
        ts = self._trial_state
        if ts == TrialState.RUNNING:
            return tick == self._next_tick
        if ts == TrialState.ARMED:
            if tick != 0:
                return False
            self._start_trial()
        return True

    def _start_trial(self) -> None:
        st = self._st
        st[control_law.S_HAVE_PREV] = 0
        # table playback: the reference velocity of sample 0; CSP/CST: 0 (no previous target)
        v0 = int(self._tables[1, 0]) if self._mode == ModeOfOperation.TABLE_PLAYBACK else 0
        st[control_law.S_VF] = v0 << fp.VEL_STATE_Q
        self._trial_state = TrialState.RUNNING
        self._rec_status = RecorderStatus.RECORDING
        self._next_tick = 0
        self._cyc_prev_target = None  # CSP: no previous target in a new trial
        logger.debug("node %d trial started, N=%d", self.node_id, self._n_table)

    def _finish_trial(self) -> None:
        n = self._n_table
        self._trial_state = TrialState.DONE
        self._rec_status = RecorderStatus.COMPLETE
        self._tables[:, self._capacity] = self._tables[:, n - 1]
        self._capture_hold = False
        logger.debug("node %d trial done", self.node_id)

    def _stop_trial(self, state: TrialState) -> None:
        if self._trial_state == TrialState.RUNNING:
            self._rec_status = RecorderStatus.STOPPED
            # hold where the trial stopped, should torque come back without a new trial
            n = max(self._next_tick - 1, 0)
            self._tables[:, self._capacity] = self._tables[:, n]
        self._trial_state = state

    @property
    def _recorded(self) -> int:
        if self._trial_state in (TrialState.IDLE, TrialState.ARMED) and self._rec_status == RecorderStatus.EMPTY:
            return 0
        return self._next_tick

    def _fault(self, code: EmcyCode, register: int, cause: FaultCause, mfr: bytes) -> int:
        self._fault_tick = self._next_tick if self._trial_state == TrialState.RUNNING else -1
        if self._trial_state in (TrialState.RUNNING, TrialState.ARMED):
            self._stop_trial(TrialState.FAULT)
        self._fault_cause = cause
        self._sm.fault()
        self._error_register = int(register)
        self._error_code = int(code)
        self._emcy.append((int(code), int(register), mfr))
        logger.warning("node %d fault %s (EMCY 0x%04X)", self.node_id, cause.name, code)
        was_on = self._power
        self._update_power()
        if not was_on:  # torque was off already: record the fault reaction all the same
            self._log_safe_state(self._fault_tick)
        self._fault_reason = ""
        return 0

    def _following_error_fault(self, n: int) -> int:
        e = int(self._st[control_law.S_ERR])
        if n >= 0:
            self._rec[control_law.REC_TAU, n] = 0  # the plant gets no torque on this tick
        return self._fault(
            EmcyCode.FOLLOWING_ERROR,
            ErrorRegister.GENERIC | ErrorRegister.DEVICE_PROFILE,
            FaultCause.FOLLOWING_ERROR,
            struct.pack("<Bi", FaultCause.FOLLOWING_ERROR, e),
        )

    def _sequence_fault(self, tick: int) -> int:
        expected = self._next_tick if self._trial_state == TrialState.RUNNING else 0
        logger.warning("node %d io tick %d, expected %d", self.node_id, tick, expected)
        return self._fault(
            EmcyCode.PROTOCOL_ERROR,
            ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION,
            FaultCause.TICK_SEQUENCE,
            struct.pack("<BHH", FaultCause.TICK_SEQUENCE, expected & 0xFFFF, int(tick) & 0xFFFF),
        )

    def _update_power(self) -> None:
        power = self.nmt_state == NmtState.OPERATIONAL and self._sm.state == Cia402State.OPERATION_ENABLED
        was = getattr(self, "_power", False)
        self._power = power
        st = self._st
        if power and not was:
            st[control_law.S_HAVE_PREV] = 0
            st[control_law.S_VF] = 0
            st[control_law.S_VEST] = 0
            self._capture_hold = self._trial_state != TrialState.DONE
            logger.info("%s node=drive%d", TORQUE_ON_TAG, self.node_id)
        elif was and not power:
            tick = self._next_tick if self._trial_state == TrialState.RUNNING else self._fault_tick
            if self._trial_state == TrialState.RUNNING:
                logger.warning("node %d torque enable lost during a trial", self.node_id)
                self._stop_trial(TrialState.FAULT)
            self._log_safe_state(tick)
            st[control_law.S_TAU] = 0
            st[control_law.S_TAU_FB] = 0
            st[control_law.S_VEST] = 0
            st[control_law.S_LIMITED] = 0

    def _log_safe_state(self, tick: int) -> None:
        """One SAFE-STATE record: torque is off now, and why."""
        if self._sm.state in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE):
            reason = self._fault_reason or f"fault-{FaultCause(self._fault_cause).name.lower()}"
        elif self.nmt_state != NmtState.OPERATIONAL:
            reason = f"nmt-{NmtState(self.nmt_state).name.lower()}"
        else:
            reason = f"cia402-{self._sm.state.name.lower()}"
        logger.info(
            format_safe_state(
                f"drive{self.node_id}",
                reason,
                cia402=self._sm.state.name,
                nmt=NmtState(self.nmt_state).name,
                tick=tick if tick >= 0 else "-",
            )
        )

    # ------------------------------------------------------------------ resets

    def _reset_application(self) -> None:
        self.store.reset(0x2000, 0xFFFF)
        self._sm.reset()
        self._tables[:] = 0
        self._rec[:] = 0
        self._n_table = 0
        self._loaded = 0
        self._trial_state = TrialState.IDLE
        self._rec_status = RecorderStatus.EMPTY
        self._next_tick = 0
        self._fault_cause = FaultCause.NONE
        self._fault_reason = ""
        self._fault_tick = -1
        self._error_register = 0
        self._error_code = 0
        self._capture_hold = True
        self._cyc_prev_target = None
        self._sync_credit = 0
        self._emcy.clear()
        st = control_law.new_state()
        self._st[:] = st
        v = self._values
        self._set_gains(GainsSub.KP, int(v[(Obj.GAINS, GainsSub.KP)]))
        self._set_gains(GainsSub.KD, int(v[(Obj.GAINS, GainsSub.KD)]))
        self._set_gains(GainsSub.VEL_FILTER, int(v[(Obj.GAINS, GainsSub.VEL_FILTER)]))
        self._set_period(int(v[(Obj.CONTROL_PERIOD, 0)]))
        self._set_max_torque(int(v[(Obj.MAX_TORQUE, 0)]))
        self._set_fe_window(int(v[(Obj.FOLLOWING_ERROR_WINDOW, 0)]))

    def _reset_communication(self) -> None:
        self.store.reset(0x1000, 0x1FFF)
        self.pdo.reset()
        self._sync_credit = 0

    # ------------------------------------------------------------------ object plumbing

    def _eds_default(self, index: int, sub: int) -> int:
        """The EDS DefaultValue of a numeric object.

        :raises ValueError: the EDS gives none.
        """
        default = self._vars[(index, sub)].default
        if default is None:
            raise ValueError(f"the EDS gives no DefaultValue for 0x{index:04X}:{sub}")
        return int(default)

    def _install_hooks(self) -> None:
        r = self._read_hooks
        w = self._write_hooks
        st = self._st
        r[(Obj.ERROR_REGISTER, 0)] = lambda: self._error_register
        r[(Obj.ERROR_CODE, 0)] = lambda: self._error_code
        r[(Obj.STATUSWORD, 0)] = lambda: self.statusword
        r[(Obj.MODES_OF_OPERATION_DISPLAY, 0)] = lambda: self._values[(Obj.MODES_OF_OPERATION, 0)]
        r[(Obj.POSITION_ACTUAL, 0)] = lambda: int(st[control_law.S_POS])
        r[(Obj.VELOCITY_ACTUAL, 0)] = lambda: int(st[control_law.S_VEST])
        r[(Obj.TORQUE_ACTUAL, 0)] = lambda: fp.torque_units_to_permille(int(st[control_law.S_TAU]), self._rated_mnm)
        r[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.VALUE)] = lambda: self._period_repr()[0]
        r[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.INDEX)] = lambda: self._period_repr()[1]
        for index in _TABLE_ROWS:
            r[(index, 0)] = functools.partial(self._read_table, index)
            w[(index, 0)] = functools.partial(self._write_table, index)
        r[(Obj.TABLE, TableSub.LENGTH)] = lambda: self._n_table
        r[(Obj.TABLE, TableSub.LOADED)] = lambda: self._loaded
        r[(Obj.TRIAL, TrialSub.STATE)] = lambda: int(self._trial_state)
        r[(Obj.TRIAL, TrialSub.TICKS)] = lambda: self._next_tick if self._trial_state != TrialState.IDLE else 0
        r[(Obj.TRIAL, TrialSub.FAULT_CAUSE)] = lambda: int(self._fault_cause)
        r[(Obj.RECORDER, RecorderSub.STATUS)] = lambda: int(self._rec_status)
        r[(Obj.RECORDER, RecorderSub.SAMPLES)] = lambda: self._recorded
        r[(Obj.RECORDER_DATA, 0)] = self._read_recorder

        w[(Obj.CONTROLWORD, 0)] = self._write_controlword
        w[(Obj.MODES_OF_OPERATION, 0)] = self._write_mode
        w[(Obj.FOLLOWING_ERROR_WINDOW, 0)] = lambda v: self._write_fe_window(int(v))
        w[(Obj.MAX_TORQUE, 0)] = lambda v: self._write_max_torque(int(v))
        w[(Obj.TABLE, TableSub.LENGTH)] = self._write_table_length
        for sub in GainsSub:
            w[(Obj.GAINS, sub)] = self._gains_hook(sub)
        w[(Obj.TRIAL, TrialSub.COMMAND)] = self._write_trial_command
        w[(Obj.CONTROL_PERIOD, 0)] = self._write_period
        w[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.VALUE)] = lambda v: self._write_interp(int(v), None)
        w[(Obj.INTERPOLATION_PERIOD, InterpolationPeriodSub.INDEX)] = lambda v: self._write_interp(None, int(v))

    # ------------------------------------------------------------------ object callbacks

    def _require_not_playing(self, what: str) -> None:
        if self._trial_state in (TrialState.ARMED, TrialState.RUNNING):
            raise SdoAbort(AbortCode.DEVICE_STATE, f"{what} not allowed while the trial is {TrialState(self._trial_state).name}")

    def _write_controlword(self, value: Value) -> None:
        before = self._sm.state
        self._sm.controlword(int(value))
        if before == Cia402State.FAULT and self._sm.state != Cia402State.FAULT:
            self._error_register = 0
            self._error_code = 0
            self._emcy.append((EmcyCode.ERROR_RESET, 0, bytes(5)))
            logger.info("node %d fault reset", self.node_id)
        self._update_power()

    def _write_mode(self, value: Value) -> None:
        if value not in (ModeOfOperation.TABLE_PLAYBACK, ModeOfOperation.CSP, ModeOfOperation.CST):
            raise SdoAbort(AbortCode.VALUE_RANGE, f"mode of operation {value!r} not supported (-1, 8, 10)")
        if value != self._mode:
            self._require_not_playing("changing the mode of operation")
            self._cyc_prev_target = None
            self._capture_hold = True  # table playback holds where the drive is now
            logger.debug("node %d mode of operation %s", self.node_id, value)

    def _write_fe_window(self, value: int) -> None:
        self._require_not_playing("changing the following-error window")
        self._set_fe_window(value)

    def _write_max_torque(self, permille: int) -> None:
        self._require_not_playing("changing the max torque")
        self._set_max_torque(permille)

    def _write_gains(self, sub: GainsSub, value: int) -> None:
        self._require_not_playing("changing the gains")
        self._set_gains(sub, value)

    def _set_fe_window(self, value: int) -> None:
        self._st[control_law.P_FE_WINDOW] = -1 if value == 0xFFFFFFFF else value

    def _set_max_torque(self, permille: int) -> None:
        self._st[control_law.P_TLIM] = fp.torque_limit_units(permille, self._rated_mnm)

    def _gains_hook(self, sub: GainsSub) -> Callable[[Value], None]:
        """The write hook of 0x2110:``sub`` (refused while a trial is armed or running)."""
        return lambda v: self._write_gains(sub, int(v))

    def _set_gains(self, sub: GainsSub, value: int) -> None:
        slot = {GainsSub.KP: control_law.P_KP, GainsSub.KD: control_law.P_KD, GainsSub.VEL_FILTER: control_law.P_ALPHA}[sub]
        self._st[slot] = value

    def _set_period(self, period_us: int) -> None:
        self._st[control_law.P_RATE] = fp.rate_q12_from_period_us(period_us)

    def _write_period(self, value: Value) -> None:
        self._require_not_playing("changing the control period")
        self._set_period(int(value))

    def _period_repr(self) -> tuple[int, int]:
        """0x60C2 (value, index) for the control period: period = value · 10^index s."""
        v = int(self._values[(Obj.CONTROL_PERIOD, 0)])
        idx = -6
        while v % 10 == 0 and idx < -1:
            v //= 10
            idx += 1
        while v > 255:  # not exactly representable: nearest with a coarser index
            v = (v + 5) // 10
            idx += 1
        return v, idx

    def _write_interp(self, value: int | None, index: int | None) -> None:
        cur_v, cur_i = self._period_repr()
        v = cur_v if value is None else value
        i = cur_i if index is None else index
        scaled = v * 10 ** (i + 6)  # µs; the EDS limits the index to -6..-1
        period = self._vars[(Obj.CONTROL_PERIOD, 0)]
        if period.min is None or period.max is None:
            raise ValueError("the EDS gives no LowLimit/HighLimit for 0x2300")
        if not period.min <= int(scaled) <= period.max:
            raise SdoAbort(AbortCode.VALUE_RANGE, f"period {scaled} µs outside [{period.min}, {period.max}]")
        self._write_period(int(scaled))
        self._values[(Obj.CONTROL_PERIOD, 0)] = int(scaled)

    def _write_table_length(self, value: Value) -> None:
        self._require_not_playing("changing the table length")
        n = int(value)
        if n != self._n_table:
            self._loaded = 0
            self._n_table = n

    def _read_table(self, index: int) -> bytes:
        row = _TABLE_ROWS[Obj(index)]
        if not self._loaded & _TABLE_BITS[row]:
            return b""
        return self._tables[row, : self._n_table].astype("<i4").tobytes()

    def _write_table(self, index: int, data: Value) -> None:
        self._require_not_playing("table download")
        assert isinstance(data, bytes)
        n = self._n_table
        if n == 0:
            raise SdoAbort(AbortCode.DEVICE_STATE, "set the table length 0x2103:1 first")
        if len(data) != 4 * n:
            raise SdoAbort(AbortCode.LENGTH_MISMATCH, f"table needs {4 * n} bytes (N={n}), got {len(data)}")
        row = _TABLE_ROWS[Obj(index)]
        self._tables[row, :n] = np.frombuffer(data, dtype="<i4")
        self._loaded |= _TABLE_BITS[row]

    def _write_trial_command(self, value: Value) -> None:
        if value == TrialCommand.ARM:
            if self._trial_state == TrialState.RUNNING:
                raise SdoAbort(AbortCode.DEVICE_STATE, "trial already running")
            if self._sm.state in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE):
                raise SdoAbort(AbortCode.DEVICE_STATE, "drive in fault; reset it first")
            if self._mode != ModeOfOperation.TABLE_PLAYBACK:
                if self._n_table == 0:
                    raise SdoAbort(AbortCode.DEVICE_STATE, "set the trial length 0x2103:1 first")
            elif self._n_table == 0 or self._loaded != TableLoaded.ALL:
                raise SdoAbort(AbortCode.DEVICE_STATE, f"tables not loaded (mask 0x{self._loaded:X}, N={self._n_table})")
            self._trial_state = TrialState.ARMED
            self._rec_status = RecorderStatus.EMPTY
            self._next_tick = 0
            self._fault_cause = FaultCause.NONE
            logger.debug("node %d trial armed, N=%d", self.node_id, self._n_table)
        else:
            if self._trial_state == TrialState.RUNNING:
                self._stop_trial(TrialState.IDLE)
            elif self._trial_state == TrialState.ARMED:
                self._trial_state = TrialState.IDLE
            else:
                self._trial_state = TrialState.IDLE

    def _read_recorder(self) -> bytes:
        if self._rec_status == RecorderStatus.RECORDING:
            raise SdoAbort(AbortCode.DEVICE_STATE, "recorder is recording")
        n = self._recorded
        return self._rec[:, :n].astype("<i4").tobytes()
