"""One emulated servo drive: the composition of its parts, NMT state, its time, and the interface
the node runtime and ``ilcrig sim`` call.

Owns :class:`Drive`, the facade over the drive's parts, its NMT state machine (CiA 301: start,
stop, pre-operational, reset node, reset communication) and its clock:

* the object store (:class:`bus.cia301.object_store.ObjectStore`, values described by
  ``bus/drive.eds``, reached as bytes through :meth:`Drive.read_object` /
  :meth:`Drive.write_object`, which raise :class:`bus.errors.SdoAbort` with CiA 301 abort codes),
  its hooks (:mod:`firmware_model.od_hooks`) and the saved parameters 0x1010/0x1011
  (:class:`bus.cia301.storage.ParameterStorage`: a file per node under ``param_dir``, or memory);
* trial playback: tables, trial state, recorder (:mod:`firmware_model.playback`);
* the motion layer: operation modes, quick-stop ramp, homing offset (:mod:`firmware_model.motion`,
  :mod:`firmware_model.modes`, :mod:`firmware_model.positioning`, :mod:`firmware_model.profile`);
* the power stage: CiA 402, torque on/off, faults, communication errors, EMCY, SAFE-STATE records
  (:mod:`firmware_model.power_stage`);
* the cyclic PDO exchange, its timers and the SYNC pacing of io ticks
  (:mod:`firmware_model.cyclic_pdo`);
* the fixed-point control loop state they share (:mod:`firmware_model.control_law`).

An io tick (:meth:`Drive.io_tick`) is the drive's control cycle: it gives torque 0 unless the
power stage is on (CiA 402 Operation enabled or Quick stop active); otherwise the motion layer
computes it (a cyclic mode only after its SYNC while NMT OPERATIONAL).  NMT switches no torque:
leaving OPERATIONAL (STOP, ENTER PRE-OPERATIONAL, RESET COMMUNICATION) is an abort connection for
the power stage (0x6007), entering it restarts the PDO counters and timers.

Time: the drive's timers (TPDO inhibit time and event timer, RPDO deadlines, the SYNC watchdog)
read :attr:`Drive.clock` [s].  By default it is the drive's *lockstep time*
(:meth:`Drive.lockstep_time_s`: the control periods of the io ticks run so far, 0x2300 each, an
integer count of µs -- deterministic, the same in every run); the node runtime may give the
monotonic clock instead (:class:`firmware_model.drive_node.DriveNode`), or make it a drive of a
SYNC-stepped plant (:meth:`Drive.step_on_sync`, ``ilcrig robot``): lockstep time for the timers of
the control cycle, the monotonic clock for the SYNC watchdog; such a drive (robot mode) boots with the servo
drive's cascade (0x2110:4 = 1, :data:`ROBOT_MODE_DEFAULTS`) where ``ilcrig sim``/``run`` keep the
paper's PD loop.  The per-period work is
:meth:`Drive.io_tick` followed by :meth:`Drive.service`.

The CANopen protocol layer (SDO server, NMT frames, heartbeat, EMCY frames, PDO frames) is
:mod:`firmware_model.drive_node`; formats and units: :mod:`bus.fixedpoint`, indices:
:mod:`bus.objects`.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from pathlib import Path

from bus import fixedpoint as fp
from bus.cia301.emcy import EmcyCode
from bus.cia301.nmt import NmtCommand, NmtState
from bus.cia301.object_store import Key, ObjectStore, Value
from bus.cia301.storage import ParameterStorage
from bus.errors import IlcrigError
from bus.objects import (
    DRIVE_EDS_PATH,
    Cia402State,
    FaultCause,
    GainsSub,
    LoopStructure,
    Obj,
    TableSub,
    TrialState,
    TrialSub,
)
from firmware_model import control_law
from firmware_model.cyclic_pdo import CyclicPdo
from firmware_model.firmware_select import DEFAULT_FIRMWARE, control_tick_for, period_steps_for
from firmware_model.modes import MotionContext
from firmware_model.motion import Motion
from firmware_model.od_hooks import ObjectHooks, eds_default
from firmware_model.pil_link import PilError
from firmware_model.playback import TrialPlayback
from firmware_model.power_stage import Emcy, PowerStage
from firmware_model.profile import ProfileGenerator

logger = logging.getLogger(__name__)

DEFAULT_EDS_PATH: Path = DRIVE_EDS_PATH

_S_POS = control_law.S_POS
_PERIOD = (Obj.CONTROL_PERIOD, 0)
#: objects that are commands or set-points, not parameters: 0x1010 does not save them
NOT_PARAMETERS = frozenset(
    {
        (Obj.CONTROLWORD, 0),
        (Obj.TARGET_POSITION, 0),
        (Obj.TARGET_TORQUE, 0),
        (Obj.TARGET_VELOCITY, 0),
        (Obj.TORQUE_OFFSET, 0),
        (Obj.TRIAL, TrialSub.COMMAND),
        (Obj.TABLE, TableSub.LENGTH),
        (Obj.ERROR_HISTORY, 0),
    }
)


#: robot mode (:meth:`Drive.step_on_sync`, ``ilcrig robot``): the values it boots with where they
#: differ from the EDS defaults -- a servo drive's cascade instead of the paper's PD loop
ROBOT_MODE_DEFAULTS: dict[Key, Value] = {(Obj.GAINS, GainsSub.LOOP): int(LoopStructure.CASCADE)}


class NmtCommandError(IlcrigError, ValueError):
    """Unknown NMT command specifier."""


class Drive:
    """One drive's firmware (see the module docstring).

    :param node_id: CANopen node id 1..127.
    :param eds_path: EDS describing the object dictionary.
    :param clock: the drive's time [s] for its timers (default: :meth:`lockstep_time_s`).
    :param param_dir: where 0x1010 saves the parameters (a file per node); None: in memory.
    :param firmware: the implementation of the control period it runs, one of
        :data:`firmware_model.firmware_select.FIRMWARES` (``python``: the reference model; ``c``:
        the C core, software in the loop).
    :raises ValueError: bad node id, or an EDS without the defaults/limits the drive needs.
    :raises InputError: a firmware this installation cannot run.

    :ivar store: the object store.
    :ivar trial: trial playback.
    :ivar motion: the motion layer.
    :ivar power: the power stage.
    :ivar pdo: SYNC and PDOs.
    :ivar time_us: the lockstep time: control periods of the io ticks run so far [µs].
    """

    def __init__(
        self,
        node_id: int,
        eds_path: str | Path = DEFAULT_EDS_PATH,
        *,
        clock: Callable[[], float] | None = None,
        param_dir: str | Path | None = None,
        firmware: str = DEFAULT_FIRMWARE,
    ) -> None:
        if not 1 <= int(node_id) <= 127:
            raise ValueError(f"node id must be 1..127, got {node_id}")
        self.node_id = int(node_id)
        self.nmt_state: NmtState = NmtState.INITIALISING
        self.time_us = 0
        self.clock: Callable[[], float] = clock if clock is not None else self.lockstep_time_s
        #: a drive of a SYNC-stepped plant (:meth:`step_on_sync`)
        self.sync_stepped = False
        #: the values this drive boots with over the EDS defaults (robot mode: ROBOT_MODE_DEFAULTS)
        self.role_defaults: dict[Key, Value] = {}
        #: the plant runs a trial (its io control frames TRIAL_START … TRIAL_STOP): the plant paces
        #: those ticks, not SYNC
        self.plant_trial = False
        self.store = ObjectStore(eds_path, self.node_id)
        self.storage = ParameterStorage(self.node_id, param_dir, exclude=NOT_PARAMETERS)
        self.storage.restore(self.store, 0x1000, 0xFFFF)
        rated_mnm = eds_default(self.store, Obj.RATED_TORQUE, 0)
        self._st = control_law.new_state()
        values = self.store.values
        self.trial = TrialPlayback(self.node_id, eds_default(self.store, Obj.TABLE, TableSub.CAPACITY))
        self.power = PowerStage(self.node_id, self._st, self.trial, lambda: self.nmt_state, values)
        #: the firmware this drive runs (``--firmware``)
        self.firmware = firmware
        kernel = control_tick_for(firmware, self.node_id)
        steps = period_steps_for(firmware)
        ctx = MotionContext(self._st, self.trial, values, rated_mnm, self.power, ProfileGenerator(), kernel, steps)
        self.motion = Motion(self.node_id, ctx, self.power)
        self.power.motion = self.motion
        self.power.nmt_reaction = self._nmt_error_reaction
        self.pdo = CyclicPdo(
            self.store,
            lambda: int(self.nmt_state),
            lambda: self.clock(),
            lockstep_cycle=lambda: self.sync_stepped or (self.motion.mode.CYCLIC and self.trial.playing),
            on_error=self._pdo_error,
            on_warning=self.power.warning,
        )
        self.objects = ObjectHooks(self.store, self._st, self.trial, self.power, self.motion, rated_mnm)
        self.storage.install(self.store)
        self._reset_application()
        self._reset_communication()
        self.nmt_state = NmtState.PRE_OPERATIONAL  # boot-up done
        self.power.update()

    # ------------------------------------------------------------------ state

    def lockstep_time_s(self) -> float:
        """The lockstep time [s]: the control periods of the io ticks run so far."""
        return self.time_us / 1_000_000  # correctly rounded: k ms here equals k / 1000.0 elsewhere

    def step_on_sync(self, watch_clock: Callable[[], float]) -> None:
        """Make this a drive of a SYNC-stepped plant (``ilcrig robot``: every io tick follows a
        SYNC, docs/robot.md): outside a trial (the drive's, or the plant's:
        :attr:`plant_trial`) an io tick waits for its SYNC in every mode and
        NMT state (every SYNC is a credit, kept over NMT resets), a synchronous TPDO carries the
        control cycle of its SYNC, the timers of the control cycle (TPDO inhibit time and event
        timer, RPDO deadlines) count the lockstep time, and the SYNC watchdog -- which must see
        time pass while no SYNC comes -- runs on ``watch_clock`` [s] (the monotonic clock)."""
        self.sync_stepped = self.pdo.sync_stepped = True
        self.clock = self.lockstep_time_s
        self.pdo.watch_clock = watch_clock
        self.role_defaults = dict(ROBOT_MODE_DEFAULTS)
        self._apply_role_defaults()
        self.storage.restore(self.store, 0x2000, 0xFFFF)
        self.objects.apply_parameters()

    def _apply_role_defaults(self) -> None:
        """The role's boot values (:attr:`role_defaults`) over the EDS defaults."""
        for key, value in self.role_defaults.items():
            self.store.values[key] = value

    def stall_grace(self) -> None:
        """The node did not run before now (a stall of its process or the machine): the SYNC
        watchdog counts from now (:meth:`firmware_model.cyclic_pdo.CyclicPdo.grace`)."""
        self.pdo.grace()

    def watch_deadline(self) -> float | None:
        """When the SYNC watchdog fires, on the clock given to :meth:`step_on_sync` [s] (None:
        not armed)."""
        return self.pdo.watch_deadline()

    @property
    def cia402_state(self) -> Cia402State:
        return self.power.state

    @property
    def statusword(self) -> int:
        """CiA 402 statusword 0x6041."""
        return self.objects.statusword()

    @property
    def trial_state(self) -> TrialState:
        return TrialState(self.trial.state)

    @property
    def torque_enabled(self) -> bool:
        """True while the power stage applies torque (Operation enabled, Quick stop active)."""
        return self.power.on

    # ------------------------------------------------------------------ object access, NMT, EMCY

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
            0x08000020 cannot store, 0x08000022 not allowed in the current state.
        """
        self.store.write_object(index, sub, data)

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
        old = self.nmt_state
        if cmd == NmtCommand.START:
            if old != NmtState.OPERATIONAL:
                self.pdo.reset(keep_credit=True)  # counters and timers start afresh in OPERATIONAL
            self.nmt_state = NmtState.OPERATIONAL
        elif cmd == NmtCommand.STOP:
            self.nmt_state = NmtState.STOPPED
            self.power.nmt_left_operational(cmd, "nmt-stopped")
        elif cmd == NmtCommand.ENTER_PRE_OPERATIONAL:
            self.nmt_state = NmtState.PRE_OPERATIONAL
            if old == NmtState.OPERATIONAL:
                self.power.nmt_left_operational(cmd, "nmt-pre_operational")
        elif cmd == NmtCommand.RESET_NODE:
            self.nmt_state = NmtState.INITIALISING
            self._reset_application()
            self._reset_communication()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        else:
            self.power.nmt_left_operational(cmd, "nmt-reset_communication")
            self.nmt_state = NmtState.INITIALISING
            self._reset_communication()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        logger.debug("node %d NMT %s -> %s", self.node_id, cmd.name, self.nmt_state.name)
        self.power.update()
        return self.nmt_state

    def _nmt_error_reaction(self, state: NmtState) -> None:
        """0x1029: the NMT state after a communication error (the power stage reacted already)."""
        logger.warning("node %d: communication error: NMT %s -> %s (0x1029)", self.node_id, self.nmt_state.name, state.name)
        self.nmt_state = state

    def pop_emcy(self) -> list[Emcy]:
        """Pending EMCY messages ``(error code, error register, 5 manufacturer bytes)``,
        oldest first; the queue is emptied."""
        return self.power.pop_emcy()

    def heartbeat_lost(self, node_id: int) -> None:
        """CiA 301 heartbeat consumer event: producer ``node_id`` (the host) went silent.

        In NMT STOPPED only logged; otherwise a communication error (EMCY 0x8130, 0x6007, 0x1029)."""
        self.power.heartbeat_lost(node_id)

    def frames_lost(self) -> None:
        """The fieldbus receiver overflowed (CiA 301 EMCY 0x8110 CAN overrun): recorded, and the
        NMT reaction of 0x1029:1 (:meth:`firmware_model.power_stage.PowerStage.frames_lost`)."""
        self.power.frames_lost()

    def io_frames_lost(self, next_tick: int) -> None:
        """The io receiver overflowed before tick ``next_tick`` (within the trial): a fault, EMCY
        0x8110 cause 10 (:meth:`firmware_model.power_stage.PowerStage.io_frames_lost`)."""
        self.power.io_frames_lost(next_tick)

    def bus_lost(self, reason: str) -> None:
        """The fieldbus or io bus failed (e.g. the hub is gone): torque off, CiA 402 Fault (no
        EMCY can be sent)."""
        self.power.bus_lost(reason)

    def power_off(self, reason: str) -> None:
        """The drive process stops (SIGTERM, the end of a run): the power stage goes off; a
        SAFE-STATE record is logged if torque was still on."""
        self.power.power_off(reason)

    def _pdo_error(self, kind: str, number: int) -> None:
        """A watchdog of the PDO service fired: an RPDO deadline or the SYNC."""
        if kind == "rpdo":
            self.power.communication_error(
                EmcyCode.RPDO_TIMEOUT,
                FaultCause.RPDO_TIMEOUT,
                struct.pack("<BB3x", FaultCause.RPDO_TIMEOUT, number),
                reason=f"rpdo{number}-timeout",
            )
        else:
            self.power.communication_error(
                EmcyCode.COMMUNICATION, FaultCause.SYNC_LOST, struct.pack("<B4x", FaultCause.SYNC_LOST), reason="sync-lost"
            )

    # ------------------------------------------------------------------ the io tick (one control period)

    def io_tick(self, tick: int, encoder_count: int) -> int:
        """One control cycle: encoder count (int32 counts) in, torque command (µN·m) out."""
        self.time_us += int(self.store.values[_PERIOD])
        motion = self.motion
        pdo = self.pdo
        pdo.consume_sync()
        if self.power.quick_stopping:
            motion.finish_quick_stop()  # the ramp reached standstill in the last cycle
        if not self.power.on:
            self._st[_S_POS] = fp.sat32(motion.position(encoder_count))
            pdo.after_tick()
            return 0
        try:
            tau = motion.tick(tick, motion.position(encoder_count))
        except PilError as err:  # the PIL target died or stopped answering: the drive's internal error
            tau = self.power.target_failed(err.failure, str(err))
        pdo.after_tick()
        return tau

    def service(self, now_s: float | None = None) -> None:
        """The drive's timers at ``now_s`` [s] (default: :attr:`clock`): RPDO deadlines, the SYNC
        watchdog, event-driven TPDOs (the node runtime calls it whenever it serves)."""
        self.pdo.service(self.clock() if now_s is None else now_s)

    def next_deadline(self) -> float | None:
        """The earliest time [s] on :attr:`clock` at which :meth:`service` has work."""
        return self.pdo.next_deadline()

    @property
    def tick_settled(self) -> bool:
        """True when the io ticks so far left :meth:`service` nothing to do before
        :meth:`next_deadline`: no EMCY waits and no PDO timer runs (an event-driven TPDO, an RPDO
        deadline); the node may then leave out its service after a tick."""
        return not self.power.emcy_pending and self.pdo.timers_idle()

    # ------------------------------------------------------------------ SYNC and PDOs

    @property
    def cyclic_active(self) -> bool:
        """True when io ticks are paced by SYNC: a cyclic mode and NMT OPERATIONAL."""
        return self.motion.mode.CYCLIC and self.pdo.active

    @property
    def tick_ready(self) -> bool:
        """False while an io tick must wait for its SYNC (:mod:`firmware_model.cyclic_pdo`)."""
        stepped = self.sync_stepped and not (self.plant_trial or self.trial.playing)
        return self.pdo.tick_ready(self.motion.mode.CYCLIC, stepped)

    def on_sync(self, counter: int | None = None) -> None:
        """A SYNC frame (``counter``: its counter byte, if any): synchronous RPDOs take effect,
        the next io tick may run, the synchronous TPDOs due are sampled."""
        self.pdo.on_sync(counter)

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A fieldbus frame that may be an RPDO; True when it was one (handled)."""
        return self.pdo.on_rpdo(can_id, data)

    def on_rtr(self, can_id: int) -> bool:
        """A remote frame: True when it asked for a TPDO of this drive (then due)."""
        return self.pdo.on_rtr(can_id)

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID this drive consumes (0x1005)."""
        return self.pdo.sync_cob_id()

    def rpdo_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid RPDOs (0x1400..: sub 1)."""
        return self.pdo.rpdo_cob_ids()

    def rtr_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid TPDOs that answer a remote frame."""
        return self.pdo.rtr_cob_ids()

    def pop_tpdos(self) -> list[tuple[int, bytes]]:
        """(COB-ID, payload) of the TPDOs due, in order; the queue is emptied."""
        return self.pdo.pop_tpdos()

    # ------------------------------------------------------------------ resets

    def _reset_application(self) -> None:
        """NMT reset node: the application objects 0x2000..0xFFFF (EDS defaults, then what 0x1010
        saved) and every part start afresh."""
        self.store.reset(0x2000, 0xFFFF)
        self._apply_role_defaults()
        self.storage.restore(self.store, 0x2000, 0xFFFF)
        self.power.reset("nmt-reset_node")
        self.trial.reset()
        self.motion.reset()
        self._st[:] = control_law.new_state()
        self.objects.apply_parameters()

    def _reset_communication(self) -> None:
        """NMT reset communication: the communication objects 0x1000..0x1FFF (EDS defaults, then
        what 0x1010 saved) and the PDO state."""
        self.store.reset(0x1000, 0x1FFF)
        self.storage.restore(self.store, 0x1000, 0x1FFF)
        self.pdo.reset()
