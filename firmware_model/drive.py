"""One emulated servo drive: the composition of its parts, NMT state and the interface the node
runtime and ``ilcrig sim`` call.

Owns :class:`Drive`, the facade over the drive's parts, and its NMT state machine (CiA 301:
start, stop, pre-operational, reset node, reset communication):

* the object store (:class:`bus.cia301.object_store.ObjectStore`, values described by
  ``bus/drive.eds``, reached as bytes through :meth:`Drive.read_object` /
  :meth:`Drive.write_object`, which raise :class:`bus.errors.SdoAbort` with CiA 301 abort codes)
  and its hooks (:mod:`firmware_model.od_hooks`);
* trial playback: tables, trial state, recorder (:mod:`firmware_model.playback`);
* the operation modes, what an io tick computes (:mod:`firmware_model.modes`);
* the power stage: CiA 402, torque on/off, faults, EMCY, SAFE-STATE records
  (:mod:`firmware_model.power_stage`);
* the cyclic PDO exchange and the SYNC pacing of io ticks (:mod:`firmware_model.cyclic_pdo`);
* the fixed-point control loop state they share (:mod:`firmware_model.control_law`).

An io tick (:meth:`Drive.io_tick`) gives torque 0 unless the power stage is on (NMT
OPERATIONAL and CiA 402 Operation enabled); otherwise the selected operation mode computes it.
The CANopen protocol layer (SDO server, NMT frames, heartbeat, EMCY frames, PDO frames) is
:mod:`firmware_model.drive_node`; formats and units: :mod:`bus.fixedpoint`, indices:
:mod:`bus.objects`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from bus import fixedpoint as fp
from bus.cia301.nmt import NmtCommand, NmtState
from bus.cia301.object_store import ObjectStore
from bus.errors import IlcrigError
from bus.objects import DRIVE_EDS_PATH, Cia402State, Obj, TableSub, TrialState
from firmware_model import control_law
from firmware_model.cyclic_pdo import CyclicPdo
from firmware_model.modes import Motion, MotionContext
from firmware_model.od_hooks import ObjectHooks, eds_default
from firmware_model.playback import TrialPlayback
from firmware_model.power_stage import Emcy, PowerStage

logger = logging.getLogger(__name__)

DEFAULT_EDS_PATH: Path = DRIVE_EDS_PATH

_S_POS = control_law.S_POS


class NmtCommandError(IlcrigError, ValueError):
    """Unknown NMT command specifier."""


class Drive:
    """One drive's firmware (see the module docstring).

    :param node_id: CANopen node id 1..127.
    :param eds_path: EDS describing the object dictionary.
    :raises ValueError: bad node id, or an EDS without the defaults/limits the drive needs.

    :ivar store: the object store.
    :ivar trial: trial playback.
    :ivar motion: the operation modes.
    :ivar power: the power stage.
    :ivar pdo: SYNC and PDOs.
    """

    def __init__(self, node_id: int, eds_path: str | Path = DEFAULT_EDS_PATH) -> None:
        if not 1 <= int(node_id) <= 127:
            raise ValueError(f"node id must be 1..127, got {node_id}")
        self.node_id = int(node_id)
        self.nmt_state: NmtState = NmtState.INITIALISING
        self.store = ObjectStore(eds_path, self.node_id)
        rated_mnm = eds_default(self.store, Obj.RATED_TORQUE, 0)
        self._st = control_law.new_state()
        self.trial = TrialPlayback(self.node_id, eds_default(self.store, Obj.TABLE, TableSub.CAPACITY))
        self.power = PowerStage(self.node_id, self._st, self.trial, lambda: self.nmt_state)
        self.motion = Motion(self.node_id, MotionContext(self._st, self.trial, self.store.values, rated_mnm, self.power))
        self.pdo = CyclicPdo(self.store, lambda: int(self.nmt_state))
        self.objects = ObjectHooks(self.store, self._st, self.trial, self.power, self.motion, rated_mnm)
        self._reset_application()
        self._reset_communication()
        self.nmt_state = NmtState.PRE_OPERATIONAL  # boot-up done
        self.power.update()

    # ------------------------------------------------------------------ state

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
        """True when NMT operational and CiA 402 Operation enabled."""
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
            0x08000022 not allowed in the current state.
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
        if cmd == NmtCommand.START:
            self.nmt_state = NmtState.OPERATIONAL
        elif cmd == NmtCommand.STOP:
            self.nmt_state = NmtState.STOPPED
        elif cmd == NmtCommand.ENTER_PRE_OPERATIONAL:
            self.nmt_state = NmtState.PRE_OPERATIONAL
        elif cmd == NmtCommand.RESET_NODE:
            self.nmt_state = NmtState.INITIALISING
            self.power.update()
            self._reset_application()
            self._reset_communication()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        else:
            self.nmt_state = NmtState.INITIALISING
            self._reset_communication()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        logger.debug("node %d NMT %s -> %s", self.node_id, cmd.name, self.nmt_state.name)
        self.power.update()
        return self.nmt_state

    def pop_emcy(self) -> list[Emcy]:
        """Pending EMCY messages ``(error code, error register, 5 manufacturer bytes)``,
        oldest first; the queue is emptied."""
        return self.power.pop_emcy()

    def heartbeat_lost(self, node_id: int) -> None:
        """CiA 301 heartbeat consumer event: producer ``node_id`` (the host) went silent.

        In NMT STOPPED only logged (torque is off and the master stopped the node on purpose);
        otherwise a fault: torque off, CiA 402 Fault, trial stopped, EMCY 0x8130."""
        self.power.heartbeat_lost(node_id)

    def bus_lost(self, reason: str) -> None:
        """The fieldbus or io bus failed (e.g. the hub is gone): torque off, CiA 402 Fault (no
        EMCY can be sent)."""
        self.power.bus_lost(reason)

    def power_off(self, reason: str) -> None:
        """The drive process stops (SIGTERM, the end of a run): the power stage goes off; a
        SAFE-STATE record is logged if torque was still on."""
        self.power.power_off(reason)

    # ------------------------------------------------------------------ the io tick

    def io_tick(self, tick: int, encoder_count: int) -> int:
        """One control tick: encoder count (int32 counts) in, torque command (µN·m) out."""
        if not self.power.on:
            self._st[_S_POS] = fp.sat32(encoder_count)
            self.pdo.consume_sync()
            return 0
        mode = self.motion.mode
        if mode.CYCLIC:
            self.pdo.consume_sync()
        return mode.tick(tick, encoder_count)

    # ------------------------------------------------------------------ SYNC and PDOs

    @property
    def cyclic_active(self) -> bool:
        """True when io ticks are paced by SYNC: a cyclic mode and NMT OPERATIONAL."""
        return self.motion.mode.CYCLIC and self.pdo.active

    @property
    def tick_ready(self) -> bool:
        """False while an io tick must wait for its SYNC (:mod:`firmware_model.cyclic_pdo`)."""
        return self.pdo.tick_ready(self.motion.mode.CYCLIC)

    def on_sync(self) -> None:
        """A SYNC frame: synchronous RPDOs take effect, the next io tick may run."""
        self.pdo.on_sync()

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A fieldbus frame that may be an RPDO; True when it was one (handled)."""
        return self.pdo.on_rpdo(can_id, data)

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID this drive consumes (0x1005)."""
        return self.pdo.sync_cob_id()

    def rpdo_cob_ids(self) -> list[int]:
        """The 11-bit identifiers of the valid RPDOs (0x1400..: sub 1)."""
        return self.pdo.rpdo_cob_ids()

    def pop_tpdos(self) -> list[tuple[int, bytes]]:
        """(COB-ID, payload) of the TPDOs due after the last io tick."""
        return self.pdo.pop_tpdos()

    # ------------------------------------------------------------------ resets

    def _reset_application(self) -> None:
        """NMT reset node: the application objects 0x2000..0xFFFF and every part start afresh."""
        self.store.reset(0x2000, 0xFFFF)
        self.power.reset()
        self.trial.reset()
        self.motion.reset()
        self.pdo.consume_sync()
        self._st[:] = control_law.new_state()
        self.objects.apply_parameters()

    def _reset_communication(self) -> None:
        """NMT reset communication: the communication objects 0x1000..0x1FFF and the PDO state."""
        self.store.reset(0x1000, 0x1FFF)
        self.pdo.reset()
