"""Host side of one drive: configuration, table download, enable, trial arming, trace upload.

Owns the host's view of the drive's object dictionary.  It only calls
``access.read_object(index, sub) -> bytes`` and ``access.write_object(index, sub, data)``, so the same
code drives an in-process firmware (the ``Drive`` object itself, wired by
:mod:`host.sim.inprocess`) and a drive over CAN (:class:`host.nodes.sdo_access.SdoAccess`).  Imports only
:mod:`bus` (object indices, fixed-point converters, units).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bus import fixedpoint as fp
from bus import units
from bus.cia301.sdo import ObjectAccess
from bus.errors import IlcrigError
from bus.objects import (
    FOLLOWING_ERROR_OFF,
    RATED_TORQUE_MNM,
    Cia402State,
    ControlCommand,
    GainsSub,
    Obj,
    RecorderStatus,
    RecorderSub,
    TableSub,
    TrialCommand,
    TrialState,
    TrialSub,
    pack_int32,
    state_from_statusword,
    unpack_int32,
    unpack_recorder,
)
from bus.objects import i32 as _i32
from bus.objects import u8 as _u8  # SDO payload encoders
from bus.objects import u16 as _u16
from bus.objects import u32 as _u32

logger = logging.getLogger(__name__)


class DriveClientError(IlcrigError):
    """The drive did not do what the host asked."""


class DriveStateError(DriveClientError):
    """The drive's CiA 402 state is not the expected one."""


class DriveInputError(DriveClientError, ValueError):
    """Bad host-side input (shapes, lengths)."""


@dataclass(frozen=True)
class DriveTrialStatus:
    """0x2120 / 0x2200 as read back."""

    state: TrialState
    ticks: int
    recorder: RecorderStatus
    recorded_samples: int
    fault_cause: int


@dataclass(frozen=True)
class DriveTrace:
    """One trial's recorder contents (int32, as the drive recorded them) plus float views.

    :ivar position_counts: encoder position, counts
    :ivar velocity_counts_s: velocity estimate, counts/s
    :ivar torque_units: torque command applied, µN·m
    :ivar torque_fb_units: feedback part (before the clamp), µN·m
    """

    position_counts: npt.NDArray[np.int32]
    velocity_counts_s: npt.NDArray[np.int32]
    torque_units: npt.NDArray[np.int32]
    torque_fb_units: npt.NDArray[np.int32]

    def __len__(self) -> int:
        return int(self.position_counts.shape[0])

    @property
    def q_rad(self) -> npt.NDArray[np.float64]:
        return self.position_counts.astype(np.float64) * units.RAD_PER_COUNT

    @property
    def qd_rad_s(self) -> npt.NDArray[np.float64]:
        return self.velocity_counts_s.astype(np.float64) * units.RAD_PER_COUNT

    @property
    def tau_nm(self) -> npt.NDArray[np.float64]:
        return self.torque_units.astype(np.float64) * units.TORQUE_LSB_NM

    @property
    def tau_fb_nm(self) -> npt.NDArray[np.float64]:
        return self.torque_fb_units.astype(np.float64) * units.TORQUE_LSB_NM

    @property
    def tau_ff_nm(self) -> npt.NDArray[np.float64]:
        """Applied minus feedback torque (= the feed-forward value unless clamped), N·m."""
        return (self.torque_units.astype(np.float64) - self.torque_fb_units) * units.TORQUE_LSB_NM


class DriveClient:
    """Host-side client of one drive.

    :param access: object access (``read``/``write`` bytes).
    :param node_id: the drive's node id (for messages and logs).
    """

    def __init__(self, access: ObjectAccess, node_id: int) -> None:
        self.access = access
        self.node_id = int(node_id)
        self._rated_mnm: int | None = None

    # ------------------------------------------------------------------ primitives

    def _read_uint(self, index: int, sub: int) -> int:
        return int.from_bytes(self.access.read_object(index, sub), "little", signed=False)

    def _read_int(self, index: int, sub: int) -> int:
        return int.from_bytes(self.access.read_object(index, sub), "little", signed=True)

    def rated_torque_mnm(self) -> int:
        """0x6076 (cached)."""
        if self._rated_mnm is None:
            self._rated_mnm = self._read_uint(Obj.RATED_TORQUE, 0) or RATED_TORQUE_MNM
        return self._rated_mnm

    def statusword(self) -> int:
        return self._read_uint(Obj.STATUSWORD, 0)

    def state(self) -> Cia402State:
        return state_from_statusword(self.statusword())

    # ------------------------------------------------------------------ configuration

    def configure(
        self,
        kp_nm_per_rad: float,
        kd_nms_per_rad: float,
        vel_filter: float = 1.0,
        torque_limit_nm: float | None = None,
        following_error_rad: float | None = None,
    ) -> None:
        """Write gains (Q16, :mod:`bus.fixedpoint`), velocity filter coefficient (Q15),
        torque limit (0x6072, per-thousand of 0x6076) and following-error window (0x6065,
        counts; ``None`` keeps the drive's value, ``inf`` switches the check off).

        :raises bus.fixedpoint.FixedPointRangeError: a value not representable.
        """
        kp = fp.kp_to_fixed(kp_nm_per_rad)
        kd = fp.kd_to_fixed(kd_nms_per_rad)
        a = fp.vel_filter_to_fixed(vel_filter)
        self.access.write_object(Obj.GAINS, GainsSub.KP, _i32(kp))
        self.access.write_object(Obj.GAINS, GainsSub.KD, _i32(kd))
        self.access.write_object(Obj.GAINS, GainsSub.VEL_FILTER, _u16(a))
        if torque_limit_nm is not None:
            permille = fp.torque_nm_to_permille(torque_limit_nm, self.rated_torque_mnm())
            self.access.write_object(Obj.MAX_TORQUE, 0, _u16(permille))
        if following_error_rad is not None:
            if following_error_rad == float("inf"):
                window = FOLLOWING_ERROR_OFF
            else:
                if not following_error_rad > 0:
                    raise DriveInputError(f"following error window must be > 0 rad, got {following_error_rad}")
                window = min(int(np.ceil(following_error_rad / units.RAD_PER_COUNT)), FOLLOWING_ERROR_OFF - 1)
            self.access.write_object(Obj.FOLLOWING_ERROR_WINDOW, 0, _u32(window))
        logger.debug("node %d configured: Kp=%d Kd=%d a=%d (fixed)", self.node_id, kp, kd, a)

    def gains(self) -> tuple[float, float, float]:
        """(Kp N·m/rad, Kd N·m·s/rad, filter coefficient) as the drive holds them."""
        kp = self._read_int(Obj.GAINS, GainsSub.KP)
        kd = self._read_int(Obj.GAINS, GainsSub.KD)
        a = self._read_uint(Obj.GAINS, GainsSub.VEL_FILTER)
        return fp.kp_from_fixed(kp), fp.kd_from_fixed(kd), fp.vel_filter_from_fixed(a)

    def _set_length(self, n: int) -> None:
        if n < 1:
            raise DriveInputError("a table needs at least one sample")
        if self.table_length() != n:  # rewriting the same length keeps loaded tables
            self.access.write_object(Obj.TABLE, TableSub.LENGTH, _u32(n))

    def set_trial_length(self, n: int) -> None:
        """0x2103:1 = ``n`` samples: the recorder length of a trial in a cyclic mode (no tables).

        :raises DriveInputError: ``n`` < 1.
        """
        self._set_length(int(n))

    def set_mode(self, mode: int) -> None:
        """0x6060 modes of operation (-1 table playback, 1 profile position, 6 homing, 8 CSP, 9 CSV, 10 CST), checked with 0x6061.

        :raises DriveStateError: the display does not show the new mode.
        """
        self.access.write_object(Obj.MODES_OF_OPERATION, 0, int(mode).to_bytes(1, "little", signed=True))
        shown = self._read_int(Obj.MODES_OF_OPERATION_DISPLAY, 0)
        if shown != int(mode):
            raise DriveStateError(f"node {self.node_id}: mode of operation display is {shown}, expected {mode}")

    def table_length(self) -> int:
        """0x2103:1, samples (0 = not set)."""
        return self._read_uint(Obj.TABLE, TableSub.LENGTH)

    def load_reference(self, q_rad: npt.ArrayLike, qd_rad_s: npt.ArrayLike) -> None:
        """Download the reference position (counts) and velocity (counts/s) tables.

        :raises DriveInputError: shapes differ or are not 1-D.
        """
        q = np.asarray(q_rad, dtype=np.float64)
        qd = np.asarray(qd_rad_s, dtype=np.float64)
        if q.ndim != 1 or q.shape != qd.shape:
            raise DriveInputError(f"q and qd must be 1-D of equal length, got {q.shape} and {qd.shape}")
        self._set_length(q.shape[0])
        self.access.write_object(Obj.REF_POSITION_TABLE, 0, pack_int32(units.rad_to_counts_array(q)))
        self.access.write_object(Obj.REF_VELOCITY_TABLE, 0, pack_int32(units.rad_s_to_counts_s_array(qd)))

    def load_feedforward(self, tau_nm: npt.ArrayLike) -> None:
        """Download the feed-forward torque table (µN·m).

        :raises DriveInputError: not 1-D, or a length different from the reference's.
        """
        tau = np.asarray(tau_nm, dtype=np.float64)
        if tau.ndim != 1:
            raise DriveInputError(f"tau must be 1-D, got shape {tau.shape}")
        n = self.table_length()
        if n == 0:
            self._set_length(tau.shape[0])
        elif tau.shape[0] != n:
            raise DriveInputError(f"feed-forward has {tau.shape[0]} samples, the drive's tables {n}")
        self.access.write_object(Obj.FEEDFORWARD_TABLE, 0, pack_int32(units.nm_to_torque_units_array(tau)))

    def read_table(self, index: int) -> npt.NDArray[np.int32]:
        """Read a table back (int32)."""
        return unpack_int32(self.access.read_object(index, 0))

    # ------------------------------------------------------------------ CiA 402

    def _command(self, cw: int, expect: Cia402State) -> None:
        self.access.write_object(Obj.CONTROLWORD, 0, _u16(cw))
        sw = self.statusword()
        state = state_from_statusword(sw)
        if state != expect:
            raise DriveStateError(
                f"node {self.node_id}: after controlword 0x{cw:04X} statusword is 0x{sw:04X} "
                f"({state.name}), expected {expect.name}"
            )

    def enable(self) -> None:
        """Shutdown -> Switch on -> Enable operation, checking the statusword after each.

        :raises DriveStateError: the drive is in fault or did not follow.
        """
        state = self.state()
        if state in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE):
            raise DriveStateError(f"node {self.node_id} is in {state.name}; call fault_reset() first")
        if state == Cia402State.OPERATION_ENABLED:
            return
        if state == Cia402State.QUICK_STOP_ACTIVE:
            self._command(ControlCommand.DISABLE_VOLTAGE, Cia402State.SWITCH_ON_DISABLED)
        self._command(ControlCommand.SHUTDOWN, Cia402State.READY_TO_SWITCH_ON)
        self._command(ControlCommand.SWITCH_ON, Cia402State.SWITCHED_ON)
        self._command(ControlCommand.ENABLE_OPERATION, Cia402State.OPERATION_ENABLED)

    def disable(self) -> None:
        """Disable voltage (torque off) -> Switch on disabled."""
        self._command(ControlCommand.DISABLE_VOLTAGE, Cia402State.SWITCH_ON_DISABLED)

    def fault_reset(self) -> None:
        """Rising edge of controlword bit 7 (0x0000 then 0x0080) -> Switch on disabled."""
        self.access.write_object(Obj.CONTROLWORD, 0, _u16(ControlCommand.DISABLE_VOLTAGE))
        self._command(ControlCommand.FAULT_RESET, Cia402State.SWITCH_ON_DISABLED)
        self.access.write_object(Obj.CONTROLWORD, 0, _u16(ControlCommand.DISABLE_VOLTAGE))

    # ------------------------------------------------------------------ trial

    def arm_trial(self) -> None:
        """Arm playback: the drive starts at io tick 0."""
        self.access.write_object(Obj.TRIAL, TrialSub.COMMAND, _u8(TrialCommand.ARM))

    def trial_status(self) -> DriveTrialStatus:
        return DriveTrialStatus(
            state=TrialState(self._read_uint(Obj.TRIAL, TrialSub.STATE)),
            ticks=self._read_uint(Obj.TRIAL, TrialSub.TICKS),
            recorder=RecorderStatus(self._read_uint(Obj.RECORDER, RecorderSub.STATUS)),
            recorded_samples=self._read_uint(Obj.RECORDER, RecorderSub.SAMPLES),
            fault_cause=self._read_uint(Obj.TRIAL, TrialSub.FAULT_CAUSE),
        )

    def read_trace(self) -> DriveTrace:
        """Upload the recorder (4 int32 planes).

        :raises DriveClientError: the recorder is still recording.
        """
        n = self._read_uint(Obj.RECORDER, RecorderSub.SAMPLES)
        status = RecorderStatus(self._read_uint(Obj.RECORDER, RecorderSub.STATUS))
        if status == RecorderStatus.RECORDING:
            raise DriveClientError(f"node {self.node_id}: recorder still recording ({n} samples)")
        planes = unpack_recorder(self.access.read_object(Obj.RECORDER_DATA, 0), n)
        return DriveTrace(planes[0].copy(), planes[1].copy(), planes[2].copy(), planes[3].copy())
