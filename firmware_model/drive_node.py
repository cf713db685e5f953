"""The drive node runtime: one :class:`~firmware_model.drive.Drive` on two python-can buses,
in one thread (the drive process's main thread).

Owns the glue between the firmware and the io wire, nothing else (no protocol logic, no control
law).  The generic CANopen-slave part (select loop, NMT, boot-up, heartbeat from 0x1017, SDO
server, EMCY frames, ignoring own COB-IDs) is :class:`bus.cia301.slave.SlaveNode`, shared with the
plant node (:mod:`plant.plant_node`); :class:`DriveNode` adds the io side:

* the plant's encoder frame for this node's joint → ``drive.io_tick(tick, count)`` →
  torque frame with the same wire tick; the trial control frame TRIAL_START sets the tick
  origin, and TRIAL_START … TRIAL_STOP tell the drive that the plant paces those ticks
  (``drive.plant_trial``).  The drive gets the tick number *within the trial*
  (architecture.md: n = 0..N-1): the 16-bit wire tick is taken relative to the TRIAL_START
  frame's tick and unwrapped, so trials longer than 65536 ticks work.
* the io bus gets acceptance filters (:meth:`DriveNode.io_filters`: this joint's encoder
  frame and the control frame), so other joints' frames do not even reach the process; any that
  still arrive (a transport without filters) and the node's own torque echo are ignored.
* the fieldbus gets acceptance filters too (:meth:`DriveNode.consumed_fieldbus_ids`: SYNC and the
  valid RPDOs, besides NMT, SDO and heartbeats from :class:`bus.cia301.slave.SlaveNode`): the other
  drives' PDOs and SDO exchanges never reach the process.
* fieldbus SYNC (with its counter byte, if any), RPDO and remote (RTR) frames go to the
  firmware's PDO service (``drive.on_sync`` / ``drive.on_rpdo`` / ``drive.on_rtr``), and the
  TPDOs they make due go out at once.  In a cyclic synchronous mode an encoder frame that arrives
  before its SYNC is held and run when the SYNC comes (``drive.tick_ready``); after every io tick
  the torque frame goes out on io first, then the TPDOs due (``drive.pop_tpdos``) on the fieldbus
  (docs/timing.md §7, the SYNC/PDO lockstep handshake).  Whenever the node serves, the drive's
  timers run (``drive.service``: event-driven TPDOs, RPDO deadlines, the SYNC watchdog) and their
  TPDOs go out; the wait is bounded by ``drive.next_deadline``.
* time: by default the node runtime and the drive share one clock -- the monotonic clock, or the
  ``clock`` given (e.g. a test's manual clock).  With ``lockstep=True`` the drive is one of a
  SYNC-stepped plant (``ilcrig robot``, :meth:`firmware_model.drive.Drive.step_on_sync`): the
  timers of the control cycle (TPDO inhibit time and event timer, RPDO deadlines) count its
  lockstep time -- the control periods of its io ticks, deterministic, standing still while no
  SYNC comes -- and a synchronous TPDO carries the control cycle of its SYNC; what watches or
  serves the master between cycles (heartbeat producer and consumer, SDO timeout, EMCY inhibit
  time, the SYNC watchdog) stays on ``clock``, so a master that pauses its SYNCs still gets
  heartbeats and a master that stops them is noticed.
* one wake-up per period: in lockstep, after an io tick of the SYNC-stepped robot the node waits for
  the next encoder frame alone, at most :attr:`DriveNode.IO_LEAD_S` (2 ms), and takes the fieldbus
  frames that came meanwhile (the period's RPDOs and SYNC, an SDO request) first, in order, when it
  comes -- the order of the frames is what it was, a wake-up for the SYNC alone is saved; past
  ``IO_LEAD_S`` without one (the master paused, or sends only SDOs) the fieldbus wakes the node as
  ever (docs/robot.md "Time").
* a master faster than the robot is served late: in lockstep, the fieldbus frames after a SYNC wait
  in order until its io tick ran (:class:`firmware_model.sync_backlog.SyncBacklog`), so period k
  takes the frames that came before SYNC k and its TPDOs carry it (docs/robot.md "Time").

The drive process (``ilcrig drive``, parsed by :mod:`host.cli.drive`) is :func:`run_drive` with a
typed :class:`DriveOptions`; :func:`run_node` is its core (also for tests).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import can

from bus import io_frames, units
from bus.bus_features import data_frame_sender, frame_answerer
from bus.can_errors import is_receive_overflow
from bus.cia301.answering import AnsweringNode
from bus.cia301.slave import (
    PRODUCER_HEARTBEAT_INDEX,
    SlaveApp,
    exact_id_filters,
    install_sigterm,
    quiet_shutdown,
    select_ready,
)
from bus.exit_codes import EXIT_FAULT, EXIT_OK
from bus.lockstep_process import freeze_heap, numba_without_blas
from firmware_model.sync_backlog import SyncBacklog

if TYPE_CHECKING:
    from firmware_model.plain_ticks import PlainTicks

logger = logging.getLogger(__name__)

_ENABLED = int(io_frames.TorqueStatus.ENABLED)
_FAULT = int(io_frames.TorqueStatus.FAULT)
_SATURATED = int(io_frames.TorqueStatus.SATURATED)
_WARNING = int(io_frames.TorqueStatus.WARNING)

__all__ = [
    "CyclicDriveLike",
    "DriveLike",
    "DriveNode",
    "PRODUCER_HEARTBEAT_INDEX",
    "DriveOptions",
    "install_sigterm",
    "run_drive",
    "run_node",
]


class DriveLike(SlaveApp, Protocol):
    """What the node needs from the firmware (``firmware_model.drive.Drive``): the slave
    application interface (NMT, object access, EMCY) plus the node id, the io tick and the state
    the torque frame reports."""

    node_id: int

    def io_tick(self, tick: int, encoder_count: int) -> int:
        """Torque command [µN·m] of tick ``tick`` (within the trial) for ``encoder_count``."""
        ...

    @property
    def torque_enabled(self) -> bool:
        """True while the power stage applies torque."""
        ...

    @property
    def statusword(self) -> int:
        """CiA 402 statusword 0x6041."""
        ...


@runtime_checkable
class CyclicDriveLike(DriveLike, Protocol):
    """A drive with the SYNC/PDO service (``firmware_model.drive.Drive``); a :class:`DriveLike`
    without these members runs without PDOs."""

    @property
    def tick_ready(self) -> bool:
        """False while an io tick must wait for its SYNC."""
        ...

    clock: Callable[[], float]

    def lockstep_time_s(self) -> float:
        """The drive's lockstep time [s] (the control periods of its io ticks)."""
        ...

    def step_on_sync(self, watch_clock: Callable[[], float]) -> None:
        """Make it a drive of a SYNC-stepped plant (the SYNC watchdog on ``watch_clock``)."""
        ...

    plant_trial: bool  #: the plant runs a trial (io control frames): its ticks are not SYNC's

    def watch_deadline(self) -> float | None:
        """When the SYNC watchdog fires, on the clock given to :meth:`step_on_sync` [s]."""
        ...

    def stall_grace(self) -> None:
        """The node did not run before now: the SYNC watchdog counts from now."""
        ...

    def on_sync(self, counter: int | None = None) -> None:
        """A SYNC frame arrived (``counter``: its counter byte, if any)."""
        ...

    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A fieldbus frame that may be an RPDO; True if it was one."""
        ...

    def on_rtr(self, can_id: int) -> bool:
        """A remote frame; True if it asked for one of the drive's TPDOs."""
        ...

    def rtr_cob_ids(self) -> Iterable[int]:
        """The identifiers of the TPDOs that answer a remote frame."""
        ...

    def service(self, now_s: float | None = None) -> None:
        """The drive's timers at ``now_s`` [s]."""
        ...

    def next_deadline(self) -> float | None:
        """When :meth:`service` has work next [s]."""
        ...

    @property
    def tick_settled(self) -> bool:
        """True when the io ticks left :meth:`service` nothing to do before :meth:`next_deadline`."""
        ...

    def pop_tpdos(self) -> list[tuple[int, bytes]]:
        """(COB-ID, payload) of the TPDOs due after the last io tick."""
        ...

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID consumed (0x1005)."""
        ...

    def rpdo_cob_ids(self) -> Iterable[int]:
        """The 11-bit identifiers of the valid RPDOs."""
        ...


class DriveNode(AnsweringNode):
    """Runs one drive on a fieldbus and an io bus.

    :param drive: the firmware (see :class:`DriveLike`).
    :param fieldbus: python-can bus of the CANopen fieldbus.
    :param io: python-can bus of the io channel (plant ↔ drives).
    :param node_id: CANopen node id (default ``drive.node_id``); joint index = node id − 1.
    :param clock: time source [s] of the node and the drive (monotonic by default).
    :param lockstep: a drive of a SYNC-stepped plant: the control cycle's timers on the drive's
        lockstep time, the rest on ``clock``, the frames after a SYNC waiting for its io tick (see
        the module docstring).
    :param hold_timeout_s: lockstep: the longest wait for a SYNC's io tick while frames wait behind
        it, s (default :attr:`HOLD_TIMEOUT_S`, × ``ILCRIG_TIMEOUT_SCALE``).
    """

    #: lockstep: the longest wait for a SYNC's io tick while frames wait behind it, s
    HOLD_TIMEOUT_S: float = 10.0
    #: lockstep: after an io tick of the robot, the longest wait for the next encoder frame alone
    #: before a fieldbus frame wakes the node again, s (module docstring: one wake-up per period)
    IO_LEAD_S: float = 0.002

    def __init__(
        self,
        drive: DriveLike,
        fieldbus: can.BusABC,
        io: can.BusABC,
        *,
        node_id: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        lockstep: bool = False,
        hold_timeout_s: float | None = None,
    ) -> None:
        cyclic = drive if isinstance(drive, CyclicDriveLike) else None
        if cyclic is not None:
            if lockstep:
                cyclic.step_on_sync(clock)
            else:
                cyclic.clock = clock
        elif lockstep:
            raise ValueError("lockstep time needs a drive with a lockstep clock (firmware_model.drive.Drive)")
        super().__init__(drive, fieldbus, io, node_id=int(drive.node_id if node_id is None else node_id), clock=clock)
        self.drive = drive
        self.joint = self.node_id - 1
        self._encoder_id = io_frames.encoder_cob_id(self.joint)
        self._torque_id = io_frames.torque_cob_id(self.joint)
        self._next_full_tick = 0  # tick number (within the trial) expected next
        self._tick_origin = 0  # wire tick of the trial's tick 0 (from TRIAL_START)
        self._held: tuple[int, int] | None = None  # (count, wire tick) of an encoder frame waiting for its SYNC
        self._io_lead_until = -1.0  # monotonic s: until then a wait is for the io frame alone (IO_LEAD_S)
        self._io_plain = True  # the io frames since the last io_settled() were ticks run at once, nothing else
        # the SYNC/PDO service is a declared optional capability (CyclicDriveLike)
        self._cyclic: CyclicDriveLike | None = cyclic
        self.lockstep = lockstep
        self.syncs_in = 0
        self.tpdos_out = 0
        hold_s = (self.HOLD_TIMEOUT_S if hold_timeout_s is None else hold_timeout_s) * units.timeout_scale()
        sync_id = cyclic.sync_cob_id if cyclic is not None else lambda: -1
        #: lockstep: the fieldbus frames waiting for the period in progress
        self.backlog = SyncBacklog(self.node_id, super()._on_fieldbus, sync_id, self.on_frames_lost, hold_s)
        io.set_filters(self.io_filters())
        # the torque frame of a tick is packed without a can.Message where the bus can (the hub)
        self._send_data_frames = data_frame_sender(io)
        # plain io ticks answered by the transport outside the interpreter where it can (the hub
        # client in C, :meth:`step`); on the monotonic clock only (its deadlines are that clock's).
        # Not in lockstep: a SYNC-stepped drive wakes for its SYNC every period anyway, and the loop
        # handing back to Python for it cost as much as the io side saved (docs/benchmarks.md).
        self._answer = frame_answerer(io) if clock is time.monotonic and not lockstep else None
        self._answer_rx = (self._encoder_id, 1, io_frames.ENCODER_LEN)  # this joint's encoder frame
        # a trial's plain ticks run by the firmware's C core where it can (firmware_model/plain_ticks.py)
        self._plain: PlainTicks | None = None
        if self._answer is not None:
            from firmware_model.plain_ticks import plain_ticks_for  # the firmware's part: imported where it runs

            self._plain = plain_ticks_for(drive, self._answer_tick, clock, self, self._torque_id, self._torque_status)

    # ------------------------------------------------------------------ io

    def io_filters(self) -> can.typechecking.CanFilters:
        """Acceptance filters of the io bus: this joint's encoder frame and the control frame
        (a drive's CAN controller filters in hardware; here the transport does, so the frames
        of the other joints never reach this process)."""
        return exact_id_filters((self._encoder_id, io_frames.CONTROL_COB_ID))

    def on_io(self, msg: can.Message) -> None:
        if msg.is_error_frame:  # its identifier is an error class, never a frame's
            if is_receive_overflow(msg):
                self._io_frames_lost()
            return  # a damaged frame: the plant, which lost it, reports it
        cob = msg.arbitration_id
        if cob == self._encoder_id:
            try:
                count, wire = io_frames.encoder_fields(msg)
            except io_frames.IoFrameError as err:
                logger.warning("node %d: bad encoder frame: %s", self.node_id, err)
                self._io_plain = False
                return
            if self._cyclic is None or self._cyclic.tick_ready:
                self._run_tick(count, wire)
            else:
                self._hold(count, wire)
        elif cob == io_frames.CONTROL_COB_ID:
            self._io_plain = False
            try:
                control = io_frames.decode_control(msg)
            except io_frames.IoFrameError as err:
                logger.warning("node %d: bad control frame: %s", self.node_id, err)
                return
            if control.command == io_frames.IoControlCommand.TRIAL_START:
                self._tick_origin = control.tick
                self._next_full_tick = 0
            if self._cyclic is not None:
                self._cyclic.plant_trial = control.command == io_frames.IoControlCommand.TRIAL_START
                if self._cyclic.plant_trial:
                    self.backlog.no_ticks()
            self._held = None
        # anything else (our own torque echo, other joints' frames) is not for us

    def _hold(self, count: int, wire: int) -> None:
        """An encoder frame that came before its SYNC waits for it."""
        self._io_plain = False
        if self._held is not None:
            logger.warning("node %d: encoder frame of wire tick %d replaced before its SYNC", self.node_id, self._held[1])
        self._held = (count, wire)

    def _io_frames_lost(self) -> None:
        """The io receiver lost frames (a receive-overflow error frame): an encoder or control
        frame never comes. The drive's optional ``io_frames_lost(next_tick)`` faults at once; a
        drive without it is left to the plant's tick deadline."""
        self._io_plain = False
        hook = getattr(self.drive, "io_frames_lost", None)
        if hook is not None:
            hook(self._next_full_tick)

    def _run_tick(self, count: int, wire: int) -> None:
        """Run the io tick of the encoder frame (``count``, ``wire`` tick): torque frame on io, then
        the TPDOs due on the fieldbus."""
        self._send_tick(self._tick_data(count, wire))

    def _tick_data(self, count: int, wire: int) -> bytes:
        """Run the io tick of the encoder frame (``count``, ``wire`` tick): the torque frame's data."""
        rel = (wire - self._tick_origin) & io_frames.TICK_MASK
        tick = self._next_full_tick + io_frames.tick_diff(rel, self._next_full_tick)
        self._next_full_tick = tick + 1
        torque = int(self.drive.io_tick(tick, count))
        return io_frames.torque_data(wire, torque, self._torque_status())

    def _send_tick(self, data: bytes, tpdos: list[tuple[int, bytes]] | None = None) -> None:
        """After an io tick: its torque frame (``data``) on io, then the TPDOs due (``tpdos``, or
        the drive's) on the fieldbus; the frames waiting behind the tick's SYNC go on."""
        self._send_data_frames(((self._torque_id, data),))
        self.frames_out += 1
        cyclic = self._cyclic  # a lockstep drive always has one
        if self.lockstep and cyclic is not None and not cyclic.plant_trial:
            self._io_lead_until = time.monotonic() + self.IO_LEAD_S
        self._send_tpdos(tpdos)
        if self.backlog.frames:
            self._io_plain = False  # the frames behind its SYNC are handled now
        self.backlog.tick_ran()

    # ------------------------------------------------------------------ plain ticks in C

    def step(self, max_wait_s: float) -> int:
        """:meth:`SlaveNode.step`; while the last wake-up left the service nothing to do, first
        the plain io ticks that come before its deadline, answered by the io transport outside the
        interpreter (:class:`bus.cia301.answering.AnsweringNode`: the hub client's C loop waits,
        reads the encoder frame, calls :meth:`_answer_tick` -- or, while the trial's ticks are
        plain, the firmware's C core, :mod:`firmware_model.plain_ticks` --, writes the torque
        frame). It hands back
        at the service's deadline, at a fieldbus frame, at any other io frame (control frames,
        frames held for a SYNC, anything unexpected: :meth:`on_io` as ever) and after a tick that was
        not plain; the order of frames and the service are those of the Python path
        (tests/test_drive_answer.py)."""
        answer = self._answer
        if answer is None or self._held is not None or not self.answering_now():
            return super().step(max_wait_s)
        plain = self._plain
        if plain is None or not self.backlog.quiet:
            return self.step_answering(answer, self._answer_rx, self._answer_tick, max_wait_s)
        on_frame = plain.on_frame(self._next_full_tick, self._tick_origin, self.frames_out, self._serve_by_s)
        try:
            return self.step_answering(answer, self._answer_rx, on_frame, max_wait_s)
        finally:
            plain.disarm()

    def after_stall(self, due_s: float, now_s: float) -> None:
        """:meth:`SlaveNode.after_stall`, the drive's SYNC watchdog too."""
        super().after_stall(due_s, now_s)
        if self._cyclic is not None:
            self._cyclic.stall_grace()

    def _wait_ready(self, fds: list[int], wait: float) -> tuple[bool, bool]:
        """:meth:`SlaveNode._wait_ready`; in lockstep within :attr:`IO_LEAD_S` of the robot's last io
        tick (and no encoder frame held for its SYNC), the wait is for the io frame alone, whose
        wake-up takes the fieldbus frames first (module docstring: one wake-up per period)."""
        lead = self._io_lead_until - time.monotonic()
        if lead <= 0.0 or self._held is not None:
            return super()._wait_ready(fds, wait)
        if select_ready(fds[1:], min(wait, lead)):
            return True, True  # the fieldbus is drained first: its SYNC and RPDOs came before this frame
        return super()._wait_ready(fds, 0.0)  # the deadline or the lead's end: whatever waits, at once

    def ticks_text(self) -> str:
        """Where the io ticks ran, for the drive's log: ``io ticks: 3004 answered in C, 3000 of them run in C``."""
        ran = "" if self._plain is None else f", {self._plain.ticks} of them run in C"
        return f"io ticks: {self.answered} answered in C{ran}"

    def stopped_plain(self) -> bool:
        """The tick the loop stopped at only had TPDOs after it: still nothing for the service, as in
        :meth:`SlaveNode.step`."""
        return self._io_plain

    def _answer_tick(self, _index: int, data: bytes) -> tuple[tuple[int, bytes]] | None:
        """An encoder frame read in C (:meth:`step`): its tick runs; the torque frame when the
        tick was plain (nothing else to send, nothing for the service before its deadline), else
        None once the Python path sent what it had (:meth:`_send_tick`)."""
        count, wire = io_frames.encoder_data_fields(data)
        cyclic = self._cyclic
        if cyclic is not None and not cyclic.tick_ready:
            self._hold(count, wire)
            return None
        torque = self._tick_data(count, wire)
        tpdos = cyclic.pop_tpdos() if cyclic is not None else []
        settled = cyclic is not None and cyclic.tick_settled and self._clock() < self._serve_by_s
        if tpdos or self.backlog.frames or not settled:
            if not settled:
                self._io_plain = False  # the service looks at once (step(0.0))
            self._send_tick(torque, tpdos)
            return None
        self.frames_out += 1
        self.backlog.tick_ran()
        return ((self._torque_id, torque),)

    def io_settled(self) -> bool:
        """The io frames of this wake-up were encoder frames whose ticks ran at once (no control
        frame, none held for its SYNC, no fieldbus frame released behind one) and the drive has
        nothing for its service (:attr:`firmware_model.drive.Drive.tick_settled`: no EMCY, no PDO
        timer): the node's service may wait for its deadline."""
        plain, self._io_plain = self._io_plain, True
        return plain and self._cyclic is not None and self._cyclic.tick_settled

    def _on_fieldbus(self, msg: can.Message) -> None:
        """Lockstep: a frame that comes while a SYNC waits for its io tick waits too, in order."""
        if self.backlog.offer(msg):
            self._fieldbus_plain = False  # held: its deadline and its release are the service's
        else:
            super()._on_fieldbus(msg)

    def fieldbus_settled(self) -> bool:
        """The fieldbus frames of this wake-up (SYNCs and RPDOs, handled at once) set no timer of
        the drive that falls due before the node serves anyway: the SYNC watchdog and the backlog's
        hold (:meth:`next_deadline`) lie beyond it. EMCYs and PDO timers are
        :meth:`io_settled`'s question (:attr:`firmware_model.drive.Drive.tick_settled`)."""
        due = self.next_deadline()
        return due is None or due >= self._serve_by_s

    def _send_tpdos(self, tpdos: list[tuple[int, bytes]] | None = None) -> None:
        """The TPDOs ``tpdos`` (default: those the drive has due), on the fieldbus."""
        if tpdos is None:
            if self._cyclic is None:
                return
            tpdos = self._cyclic.pop_tpdos()
        for cob_id, data in tpdos:
            self._send(self.fieldbus, cob_id, data)
            self.tpdos_out += 1

    def consumed_fieldbus_ids(self) -> set[int]:
        """SYNC (0x1005), the valid RPDOs' identifiers (0x1400..: sub 1) and those of the TPDOs that
        answer a remote frame, as the firmware has them now (the acceptance filters follow every
        SDO write of these objects)."""
        drive = self._cyclic
        if drive is None:
            return set()
        return {drive.sync_cob_id(), *drive.rpdo_cob_ids(), *drive.rtr_cob_ids()}

    def on_fieldbus(self, msg: can.Message) -> None:
        drive = self._cyclic
        if drive is None:
            return
        cob = msg.arbitration_id
        if msg.is_remote_frame:
            if drive.on_rtr(cob):
                self._send_tpdos()
        elif cob == drive.sync_cob_id():
            self.syncs_in += 1
            if self.lockstep and not drive.plant_trial:
                self.backlog.sync_handled(self._clock())
            drive.on_sync(int(msg.data[0]) if msg.dlc >= 1 else None)
            self._send_tpdos()
            if self._held is not None and drive.tick_ready:
                (count, wire), self._held = self._held, None
                self._run_tick(count, wire)
        else:
            drive.on_rpdo(cob, bytes(msg.data))

    def on_service(self, now: float) -> None:
        """The drive's timers (event-driven TPDOs, RPDO deadlines, the SYNC watchdog); their TPDOs
        go out (their EMCYs right after, with the node's)."""
        drive = self._cyclic
        if drive is not None:
            drive.service(None if self.lockstep else now)  # lockstep: the control cycle's timers at the drive's time
            self._send_tpdos()
        self.backlog.expire(now)

    def next_deadline(self) -> float | None:
        """The drive's next timer on the node's clock (lockstep: the SYNC watchdog alone; the
        control cycle's timers fall due with io ticks, which are frames)."""
        drive = self._cyclic
        if drive is None:
            return None
        if not self.lockstep:
            return drive.next_deadline()
        times = [t for t in (drive.watch_deadline(), self.backlog.deadline()) if t is not None]
        return min(times) if times else None

    def _torque_status(self) -> int:
        """Torque-frame status bits from ``drive.torque_enabled`` and the CiA 402 statusword
        (fault 0x0008, warning 0x0080, internal limit 0x0800 → SATURATED)."""
        bits = _ENABLED if self.drive.torque_enabled else 0
        sw = int(self.drive.statusword)
        if sw & 0x0008:
            bits |= _FAULT
        if sw & 0x0800:
            bits |= _SATURATED
        if sw & 0x0080:
            bits |= _WARNING
        return bits


def run_node(
    node_id: int,
    fieldbus_config: dict[str, Any],
    io_config: dict[str, Any],
    stop: threading.Event | None = None,
    *,
    param_dir: str | None = None,
    lockstep: bool = False,
    firmware: str = "python",
) -> str | None:
    """Drive process entry: build the Drive and both buses, serve until stopped, clean up.

    :param node_id: CANopen node id 1..4.
    :param fieldbus_config: keyword arguments of ``can.Bus`` for the fieldbus.
    :param io_config: keyword arguments of ``can.Bus`` for the io channel.
    :param stop: stop event; by default a new one set by SIGTERM/SIGINT.
    :param param_dir: folder of the parameters 0x1010 saves (``node<id>.json``); None: in memory.
    :param lockstep: a drive of a SYNC-stepped plant (:class:`DriveNode`, ``ilcrig robot``).
    :param firmware: the control period's implementation (``--firmware``, :mod:`firmware_model.firmware_select`).
    :returns: None, or why the node stopped early (a bus failed; the drive faulted first).
    """
    from firmware_model.control_law import warm_up
    from firmware_model.drive import Drive  # the firmware is only needed in the process

    with numba_without_blas(f"drive {node_id}"):  # its integer kernel needs no BLAS: 0.3 s of CPU less at start
        warm_up()  # before boot-up: the host's boot wait covers the JIT, the first trial does not
    if stop is None:
        stop = threading.Event()
        install_sigterm(stop)
    drive = Drive(node_id, param_dir=param_dir, firmware=firmware)
    fieldbus = can.Bus(**fieldbus_config)
    try:
        io = can.Bus(**io_config)
        try:
            node = DriveNode(drive, fieldbus, io, node_id=node_id, lockstep=lockstep)
            if firmware == "pil":  # the heartbeat goes on while the control period waits for its target
                from firmware_model import pil_link

                pil_link.on_wait = node.heartbeat_if_due
            freeze_heap(f"drive {node_id}")
            node.run(stop)
            logger.info("node %d: %s", node_id, node.ticks_text())
        finally:
            quiet_shutdown(io)
    finally:
        quiet_shutdown(fieldbus)
    drive.power_off("process-stop")
    return node.bus_error


@dataclass(frozen=True)
class DriveOptions:
    """The drive process's options (``ilcrig drive``)."""

    #: CANopen node id, 1..127 (1..4: the robot's joints)
    node_id: int
    #: keyword arguments of ``can.Bus`` for the fieldbus
    fieldbus_config: dict[str, Any] = field(default_factory=dict)
    #: keyword arguments of ``can.Bus`` for the io channel
    io_config: dict[str, Any] = field(default_factory=dict)
    #: folder of the parameters 0x1010 saves (``node<id>.json``); None: in memory
    param_dir: str | None = None
    #: a drive of a SYNC-stepped plant (``ilcrig robot``)
    lockstep: bool = False
    #: the control period's implementation (``--firmware``: python, c, pil)
    firmware: str = "python"


def run_drive(opts: DriveOptions, stop: threading.Event | None = None) -> int:
    """The drive process: :func:`run_node` with ``opts``; returns the exit code (3 when a bus failed
    and the node stopped early, 0 otherwise)."""
    lost = run_node(
        opts.node_id,
        opts.fieldbus_config,
        opts.io_config,
        stop,
        param_dir=opts.param_dir,
        lockstep=opts.lockstep,
        firmware=opts.firmware,
    )
    return EXIT_FAULT if lost else EXIT_OK
