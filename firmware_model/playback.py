"""Trial playback of one drive: the reference and feed-forward tables, the trial state and the
data recorder.

Owns the objects 0x2103 (table length N, loaded mask), 0x2200..0x2202 (reference position [counts],
reference velocity [counts/s], feed-forward [µN·m] tables, int32 each), 0x2120 (trial command,
state, ticks done, fault cause) and 0x2130/0x2210 (recorder status, samples, data), and the
arrays behind them (:mod:`firmware_model.control_law` layout): ``tables`` int32 (3, capacity + 1)
whose last column is the *hold slot* (the reference held while no trial plays) and ``rec``
int32 (4, capacity).

Trial states (:class:`bus.objects.TrialState`):

* IDLE → ARMED by the arm command (0x2120:1 = 1): table playback needs N > 0 and all three
  tables loaded, a cyclic mode only N > 0 (the set-points come by PDO); refused while running or
  while the drive is in CiA 402 Fault;
* ARMED → RUNNING at io tick 0 (:meth:`TrialPlayback.start`, called by the operation mode); the
  recorder is RECORDING and ticks must then come 1, 2, ... in order (:attr:`TrialPlayback.next_tick`);
* RUNNING → DONE after tick N-1: the recorder is COMPLETE and the hold slot takes the last table
  entry (PD + last feed-forward hold the end of the trial);
* RUNNING → FAULT or IDLE (:meth:`TrialPlayback.stop`: a fault, torque lost, the stop command):
  the recorder is STOPPED with the ticks done so far, the hold slot takes the last entry played.

Gains, limits, period, tables and the table length cannot change while a trial is ARMED or
RUNNING (:meth:`TrialPlayback.require_not_playing`, abort 0x08000022).
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt

from bus import fixedpoint as fp
from bus.errors import AbortCode, SdoAbort
from bus.objects import FaultCause, Obj, RecorderStatus, TableLoaded, TrialCommand, TrialState
from firmware_model import control_law

logger = logging.getLogger(__name__)

#: table object index → row of ``tables``
TABLE_ROWS: dict[int, int] = {
    Obj.REF_POSITION_TABLE: control_law.ROW_REF_POS,
    Obj.REF_VELOCITY_TABLE: control_law.ROW_REF_VEL,
    Obj.FEEDFORWARD_TABLE: control_law.ROW_FF,
}
_TABLE_BITS = (TableLoaded.REF_POSITION, TableLoaded.REF_VELOCITY, TableLoaded.FEEDFORWARD)


class TrialPlayback:
    """The trial, its tables and its recorder (see the module docstring).

    :param node_id: CANopen node id (log messages).
    :param capacity: table and recorder length [samples] (0x2103:3).
    """

    # set by reset (called from __init__)
    n_table: int
    loaded: int
    state: TrialState
    rec_status: RecorderStatus
    next_tick: int
    fault_cause: FaultCause
    capture_hold: bool

    def __init__(self, node_id: int, capacity: int) -> None:
        self.node_id = node_id
        self.capacity = capacity
        self.tables: npt.NDArray[np.int32] = control_law.new_tables(capacity)
        self.rec: npt.NDArray[np.int32] = control_law.new_recorder(capacity)
        self.reset()

    def reset(self) -> None:
        """NMT reset node: no tables, no trial, empty recorder, hold where the drive is at the
        first tick with torque."""
        self.tables[:] = 0
        self.rec[:] = 0
        self.n_table = 0
        self.loaded = 0
        self.state = TrialState.IDLE
        self.rec_status = RecorderStatus.EMPTY
        self.next_tick = 0
        self.fault_cause = FaultCause.NONE
        #: the next tick without a trial holds its encoder count (set when torque comes on, the
        #: mode changes or a reset; cleared by that tick and by the end of a trial)
        self.capture_hold = True

    # ------------------------------------------------------------------ state

    @property
    def playing(self) -> bool:
        """True while the trial is ARMED or RUNNING."""
        return self.state in (TrialState.ARMED, TrialState.RUNNING)

    @property
    def ticks_done(self) -> int:
        """0x2120:3: ticks played in the current or last trial (0 when IDLE)."""
        return self.next_tick if self.state != TrialState.IDLE else 0

    @property
    def recorded(self) -> int:
        """0x2130:2: samples in the recorder."""
        if self.state in (TrialState.IDLE, TrialState.ARMED) and self.rec_status == RecorderStatus.EMPTY:
            return 0
        return self.next_tick

    def require_not_playing(self, what: str) -> None:
        """:raises SdoAbort: 0x08000022 while the trial is ARMED or RUNNING."""
        if self.playing:
            raise SdoAbort(AbortCode.DEVICE_STATE, f"{what} not allowed while the trial is {TrialState(self.state).name}")

    # ------------------------------------------------------------------ trial command

    def command(self, value: int, *, needs_tables: bool, in_fault: bool) -> None:
        """0x2120:1: arm (1) or stop (0) the trial.

        :param needs_tables: the operation mode plays the tables (all three must be loaded).
        :param in_fault: the drive is in CiA 402 Fault (arming is refused).
        :raises SdoAbort: 0x08000022 arming refused (running, in fault, tables missing).
        """
        if value != TrialCommand.ARM:
            if self.state == TrialState.RUNNING:
                self.stop(TrialState.IDLE)
            self.state = TrialState.IDLE
            return
        if self.state == TrialState.RUNNING:
            raise SdoAbort(AbortCode.DEVICE_STATE, "trial already running")
        if in_fault:
            raise SdoAbort(AbortCode.DEVICE_STATE, "drive in fault; reset it first")
        if not needs_tables:
            if self.n_table == 0:
                raise SdoAbort(AbortCode.DEVICE_STATE, "set the trial length 0x2103:1 first")
        elif self.n_table == 0 or self.loaded != TableLoaded.ALL:
            raise SdoAbort(AbortCode.DEVICE_STATE, f"tables not loaded (mask 0x{self.loaded:X}, N={self.n_table})")
        self.state = TrialState.ARMED
        self.rec_status = RecorderStatus.EMPTY
        self.next_tick = 0
        self.fault_cause = FaultCause.NONE
        logger.debug("node %d trial armed, N=%d", self.node_id, self.n_table)

    # ------------------------------------------------------------------ transitions

    def start(self) -> None:
        """ARMED → RUNNING at tick 0."""
        self.state = TrialState.RUNNING
        self.rec_status = RecorderStatus.RECORDING
        self.next_tick = 0
        logger.debug("node %d trial started, N=%d", self.node_id, self.n_table)

    def finish(self) -> None:
        """RUNNING → DONE after tick N-1: hold the last table entry."""
        n = self.n_table
        self.state = TrialState.DONE
        self.rec_status = RecorderStatus.COMPLETE
        self.tables[:, self.capacity] = self.tables[:, n - 1]
        self.capture_hold = False
        logger.debug("node %d trial done", self.node_id)

    def stop(self, state: TrialState) -> None:
        """End the trial in ``state``; a running one keeps its recorder (STOPPED) and holds where it
        stopped, should torque come back without a new trial."""
        if self.state == TrialState.RUNNING:
            self.rec_status = RecorderStatus.STOPPED
            n = max(self.next_tick - 1, 0)
            self.tables[:, self.capacity] = self.tables[:, n]
        self.state = state

    def on_fault(self, cause: FaultCause) -> None:
        """A drive fault: an armed or running trial ends in FAULT; 0x2120:4 says why."""
        if self.playing:
            self.stop(TrialState.FAULT)
        self.fault_cause = cause

    def on_torque_on(self) -> None:
        """Torque came on: outside a finished trial, the next tick holds its encoder count."""
        self.capture_hold = self.state != TrialState.DONE

    def hold_here(self, encoder_count: int) -> None:
        """If a hold is to be captured: hold ``encoder_count`` [counts] (velocity 0, no
        feed-forward)."""
        if self.capture_hold:
            self.capture_hold = False
            self.tables[:, self.capacity] = (fp.sat32(encoder_count), 0, 0)

    # ------------------------------------------------------------------ objects

    def write_length(self, n: int) -> None:
        """0x2103:1: a new length N unloads the tables."""
        self.require_not_playing("changing the table length")
        if n != self.n_table:
            self.loaded = 0
            self.n_table = n

    def read_table(self, index: int) -> bytes:
        """0x2200..0x2202: the loaded table (N int32), empty when not loaded."""
        row = TABLE_ROWS[index]
        if not self.loaded & _TABLE_BITS[row]:
            return b""
        return self.tables[row, : self.n_table].astype("<i4").tobytes()

    def write_table(self, index: int, data: bytes) -> None:
        """0x2200..0x2202: download a table of exactly N int32.

        :raises SdoAbort: 0x08000022 playing or N not set, 0x06070010 wrong length.
        """
        self.require_not_playing("table download")
        n = self.n_table
        if n == 0:
            raise SdoAbort(AbortCode.DEVICE_STATE, "set the table length 0x2103:1 first")
        if len(data) != 4 * n:
            raise SdoAbort(AbortCode.LENGTH_MISMATCH, f"table needs {4 * n} bytes (N={n}), got {len(data)}")
        row = TABLE_ROWS[index]
        self.tables[row, :n] = np.frombuffer(data, dtype="<i4")
        self.loaded |= _TABLE_BITS[row]

    def read_recorder(self) -> bytes:
        """0x2210: the recorded samples (4 rows of int32).

        :raises SdoAbort: 0x08000022 while recording.
        """
        if self.rec_status == RecorderStatus.RECORDING:
            raise SdoAbort(AbortCode.DEVICE_STATE, "recorder is recording")
        return self.rec[:, : self.recorded].astype("<i4").tobytes()
