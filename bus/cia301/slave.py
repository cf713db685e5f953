"""Generic CANopen-slave runtime on two python-can buses (fieldbus + io), in one thread.

This module owns what every node of the rig does on the wire, independent of its application
(the drive firmware, the test-bench plant):

* :class:`SlaveNode` — the select loop over the fieldbus and the io bus; NMT (COB-ID 0) →
  ``app.nmt_command(cs)``; SDO requests (0x600 + id) → :class:`bus.cia301.sdo.SdoServer` on the app's
  object access, responses on 0x580 + id; boot-up on start and after an NMT reset; producer
  heartbeat (0x700 + id) every 0x1017 ms (re-read after every completed SDO transfer); EMCY
  frames for every entry of ``app.pop_emcy()`` (the app queues none in NMT STOPPED) by
  :class:`bus.cia301.emcy_producer.EmcyProducer` (0x1014 COB-ID, 0x1015 inhibit time).  SDO is
  silent in the NMT state STOPPED (CiA 301); NMT and heartbeat always work.  Heartbeat consumer (object 0x1016,
  re-read like 0x1017): a configured producer (the host) silent for its consumer time calls the
  app's optional ``heartbeat_lost(node_id)`` once.  A fieldbus error frame that says the receiver
  overflowed (frames lost, :mod:`bus.can_errors`) calls the app's optional ``frames_lost()``; other
  error frames are passed over.  A bus that fails (the hub gone) ends
  :meth:`SlaveNode.run` after calling the app's optional ``bus_lost(reason)``; :attr:`SlaveNode.bus_error`
  then says why.  Frames carrying this node's own
  COB-IDs are ignored (udp_multicast echoes a sender's frames back to it).  Fieldbus acceptance
  filters (:meth:`SlaveNode.fieldbus_filters`): the node accepts only what it consumes (NMT, its
  SDO requests, the heartbeats it watches, and the subclass's :meth:`SlaveNode.consumed_fieldbus_ids`,
  e.g. SYNC and RPDOs), as a drive's CAN controller filters in hardware; the transport applies
  them (the hub and SocketCAN before the frame reaches the process), so the other nodes' PDOs
  cost this process nothing.  They are recomputed after every completed SDO transfer and NMT reset,
  and set *before* the SDO response goes out: a master that reconfigures a COB-ID and then
  uses it is never filtered away.  Remote frames (RTR) go to :meth:`SlaveNode.on_fieldbus` like
  any frame the node consumes.  io frames are
  handed to the subclass hook :meth:`SlaveNode.on_io`; :meth:`SlaveNode.on_service` and
  :meth:`SlaveNode.next_deadline` let a subclass run its own timers in the same loop.
* :func:`install_sigterm` — SIGTERM/SIGINT set a stop event (process entry points);
  :func:`quiet_shutdown` — closing a role's bus on the way out, never raising.

Waiting: ``select()`` on both buses' ``fileno()`` where both have one (udp_multicast,
socketcan, the ilcrig hub), otherwise short-timeout polling (``virtual``); a bus that keeps
frames in a local queue (:class:`bus.bus_features.BufferedReceiver`, the ilcrig hub) is read
without waiting while its queue holds frames, and one that returns all waiting frames at once
(:class:`bus.bus_features.BatchReceiver`, the ilcrig hub) is read with one call per readiness.

Time: heartbeat period, SDO transfer timeout and subclass deadlines use ``clock`` (monotonic
wall clock by default: protocol timing only, never a model; the control loop is paced by the
plant's io frames).
"""

from __future__ import annotations

import logging
import math
import select
import signal
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

import can

from bus.bus_features import batch_receiver, pending_check
from bus.can_errors import is_receive_overflow
from bus.cia301.emcy_producer import EmcyProducer
from bus.cia301.nmt import (
    CONSUMER_HEARTBEAT_INDEX,
    NMT_COB_ID,
    NmtCommand,
    NmtFrameError,
    NmtState,
    NodeHeartbeatConsumer,
    decode_consumer_entry,
    encode_heartbeat,
    heartbeat_cob_id,
    heartbeat_node_id,
    nmt_addresses,
)
from bus.cia301.sdo import SdoServer, sdo_request_cob_id, sdo_response_cob_id
from bus.errors import SdoAbort
from bus.fastmsg import new_message
from bus.run_queue import carrier_ledger

logger = logging.getLogger(__name__)

#: Object index of the producer heartbeat time (U16, ms).
PRODUCER_HEARTBEAT_INDEX = 0x1017


def exact_id_filters(ids: Iterable[int]) -> can.typechecking.CanFilters:
    """python-can acceptance filters passing exactly the 11-bit identifiers ``ids`` (standard
    frames only), in ascending order."""
    return [can.typechecking.CanFilter(can_id=cob, can_mask=0x7FF, extended=False) for cob in sorted(ids)]


class SlaveApp(Protocol):
    """What :class:`SlaveNode` needs from the application behind the node."""

    @property
    def nmt_state(self) -> int: ...

    def nmt_command(self, cs: int) -> Any: ...

    def read_object(self, index: int, sub: int) -> bytes: ...

    def write_object(self, index: int, sub: int, data: bytes) -> None: ...

    def pop_emcy(self) -> Sequence[tuple[int, int, bytes]]: ...


def select_ready(fds: list[int], wait: float) -> list[int]:
    """The descriptors of ``fds`` readable within ``wait`` [s] (``select``), for a node's wait.

    :raises can.CanOperationError: a bus closed its descriptor under us
    """
    try:
        return select.select(fds, (), (), wait)[0]
    except ValueError as err:
        raise can.CanOperationError(f"bus closed: {err}") from err


def bus_filenos(*buses: can.BusABC) -> list[int] | None:
    """The file descriptors of ``buses`` for a node's ``select`` (None: one of them has none, e.g. ``virtual``)."""
    fds = []
    for bus in buses:
        try:
            fd = bus.fileno()
        except (NotImplementedError, AttributeError, OSError):
            return None
        if fd is None or fd < 0:
            return None
        fds.append(fd)
    return fds


class SlaveNode:
    """One CANopen slave on a fieldbus and an io bus; subclasses add the io protocol.

    :param app: the application (see :class:`SlaveApp`).
    :param fieldbus: python-can bus of the CANopen fieldbus.
    :param io: python-can bus of the io channel (plant ↔ drives).
    :param node_id: CANopen node id 1..127.
    :param clock: monotonic time source [s] for heartbeat, SDO timeout and deadlines.
    """

    #: Longest single wait [s]: bounds the reaction time to the stop event.
    MAX_WAIT_S: float = 0.05
    #: Poll timeout [s] per bus when the buses have no file descriptor (e.g. ``virtual``).
    POLL_S: float = 0.0005

    def __init__(
        self, app: SlaveApp, fieldbus: can.BusABC, io: can.BusABC, *, node_id: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.app = app
        self.fieldbus = fieldbus
        self.io = io
        self.node_id = int(node_id)
        self._clock = clock
        self.sdo = SdoServer(self.node_id, app)
        self._sdo_rx = sdo_request_cob_id(self.node_id)
        self._sdo_tx = sdo_response_cob_id(self.node_id)
        self._hb_id = heartbeat_cob_id(self.node_id)
        self.emcy = EmcyProducer(self.node_id, app, lambda cob_id, data: self._send(self.fieldbus, cob_id, data))
        self._own_fieldbus_ids = {self._sdo_tx, self._hb_id} | self.emcy.own_ids()
        self._heartbeat_ms = 0
        self._next_heartbeat_s: float | None = None
        self.consumer = NodeHeartbeatConsumer(carrier_ledger(fieldbus))  # the hub's waits for a CPU excuse
        self._fds = bus_filenos(fieldbus, io)
        # buses that read several frames per system call keep them in a local queue that
        # select() does not see (bus.bus_features.BufferedReceiver)
        self._io_pending = pending_check(io)
        self._fieldbus_pending = pending_check(fieldbus)
        # all frames of one readiness in one call where the bus can (bus.bus_features.BatchReceiver)
        self._io_batch = batch_receiver(io)
        self._fieldbus_batch = batch_receiver(fieldbus)
        self.frames_in = 0
        self.frames_out = 0
        #: fieldbus identifiers the acceptance filters pass (None: filters not set yet)
        self._fieldbus_ids: frozenset[int] | None = None
        #: why :meth:`run` ended early: the bus failed (None while it works)
        self.bus_error: str | None = None
        #: the last service was left out (:meth:`io_settled`): :attr:`_due_s` still holds
        self._settled = False
        #: in :meth:`run`, when the loop last read its clock [s] (None: stepped from outside, e.g. a test)
        self._ran_s: float | None = None
        #: when the service has work next [s of the clock]: the earliest deadline (inf: none), as
        #: the last service left it (for :meth:`io_settled`)
        self._due_s = 0.0
        #: the service runs at least this often while io frames keep coming [s of the clock]: the
        #: bound of a deadline an :meth:`io_settled` missed
        self._serve_by_s = 0.0
        #: every fieldbus frame of this wake-up went to :meth:`on_fieldbus` (no NMT, SDO, heartbeat,
        #: error or remote frame): :meth:`fieldbus_settled` may vouch for them
        self._fieldbus_plain = True

    # ------------------------------------------------------------------ subclass hooks

    def on_io(self, msg: can.Message) -> None:
        """One frame received on the io bus (default: ignored)."""

    def on_service(self, now: float) -> None:
        """Called after every wait/drain round with the current clock time [s]."""

    def next_deadline(self) -> float | None:
        """Clock time [s] by which :meth:`on_service` must run next (None = no deadline)."""
        return None

    def io_settled(self) -> bool:
        """True when the io frames just handled left the service nothing to do before the
        deadlines known at the start of the wake-up: no deadline moved earlier, nothing waits to be
        sent. :meth:`step` then leaves the service out (default False: it serves every wake-up)."""
        return False

    def fieldbus_settled(self) -> bool:
        """As :meth:`io_settled`, for a wake-up's fieldbus frames, all given to :meth:`on_fieldbus`
        (e.g. a SYNC and its RPDOs): nothing due before :attr:`_serve_by_s` (default False)."""
        return False

    def on_nmt_reset(self, command: NmtCommand) -> None:
        """Called after the app handled an NMT reset, before the boot-up frame is sent."""

    def on_heartbeat_lost(self, node_id: int) -> None:
        """The heartbeat consumer lost producer ``node_id`` (default: the app's optional
        ``heartbeat_lost(node_id)``)."""
        hook = getattr(self.app, "heartbeat_lost", None)
        if hook is not None:
            hook(node_id)

    def on_frames_lost(self) -> None:
        """The fieldbus lost frames: its receiver overflowed (an error frame of
        :func:`bus.can_errors.is_receive_overflow`; default: the app's optional
        ``frames_lost()``)."""
        hook = getattr(self.app, "frames_lost", None)
        if hook is not None:
            hook()

    def on_fieldbus(self, msg: can.Message) -> None:
        """A fieldbus frame that is not NMT, this node's SDO request or its own (e.g. SYNC, PDOs;
        default: ignored)."""

    def consumed_fieldbus_ids(self) -> set[int]:
        """11-bit fieldbus identifiers the subclass consumes in :meth:`on_fieldbus` (e.g. SYNC, the
        valid RPDOs), for the acceptance filters; asked again after every completed SDO transfer
        and NMT reset (default: none)."""
        return set()

    # ------------------------------------------------------------------ acceptance filters

    def fieldbus_ids(self) -> frozenset[int]:
        """The 11-bit identifiers this node accepts on the fieldbus: NMT, its SDO requests, the
        heartbeats of the producers it consumes (0x1016) and :meth:`consumed_fieldbus_ids`."""
        ids = {NMT_COB_ID, self._sdo_rx}
        ids.update(heartbeat_cob_id(n) for n in self.consumer.producers)
        ids.update(self.consumed_fieldbus_ids())
        return frozenset(ids)

    def fieldbus_filters(self) -> can.typechecking.CanFilters:
        """python-can acceptance filters of :meth:`fieldbus_ids`."""
        return exact_id_filters(self.fieldbus_ids())

    def _refresh_fieldbus_filters(self) -> None:
        """Set the fieldbus acceptance filters if what the node consumes changed."""
        ids = self.fieldbus_ids()
        if ids == self._fieldbus_ids:
            return
        self._fieldbus_ids = ids
        self.fieldbus.set_filters(exact_id_filters(ids))
        logger.debug("node %d: fieldbus accepts %s", self.node_id, " ".join(f"0x{c:03X}" for c in sorted(ids)))

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Send the boot-up frame and start the heartbeat."""
        self._send(self.fieldbus, self._hb_id, encode_heartbeat(NmtState.BOOT_UP))
        self._reload_heartbeat(force=True)
        self._reload_consumers()
        self._reload_emcy()
        self._refresh_fieldbus_filters()
        logger.info(
            "node %d: booted, heartbeat %d ms, %s", self.node_id, self._heartbeat_ms, "select()" if self._fds else "polling"
        )

    def run(self, stop: threading.Event) -> None:
        """:meth:`start`, then serve until ``stop`` is set or a bus fails (then the app's optional
        ``bus_lost(reason)`` is called and :attr:`bus_error` is set; no exception escapes)."""
        try:
            self.start()
            self._ran_s = self._clock()  # from now on a stall between two steps is found too
            while not stop.is_set():
                self.step(self.MAX_WAIT_S)
        except (can.CanError, OSError) as exc:
            self.bus_error = f"{type(exc).__name__}: {exc}"
            logger.error("node %d: bus lost (%s): stopping", self.node_id, self.bus_error)
            hook = getattr(self.app, "bus_lost", None)
            if hook is not None:
                hook(self.bus_error)
            return
        logger.info("node %d: stopped (%d frames in, %d out)", self.node_id, self.frames_in, self.frames_out)

    def step(self, max_wait_s: float) -> int:
        """Wait up to ``max_wait_s`` [s] (less if a heartbeat or a subclass deadline is due) for
        frames, process every frame waiting on both buses (the fieldbus first: a SYNC or an NMT
        command is handled before the io frame it caused, which the transport can only have
        delivered after it), then send due heartbeat, EMCY and SDO-timeout frames and call
        :meth:`on_service` -- left out after a wake-up whose frames the subclass vouches for (io
        frames: :meth:`io_settled`; fieldbus frames, all of them for :meth:`on_fieldbus`:
        :meth:`fieldbus_settled` too), until the earliest deadline or :attr:`MAX_WAIT_S` after the
        last service.

        :return: number of frames received.
        """
        now = self._clock()
        self.ran_at(now, self._ran_s)  # run(): did this process run between two steps?
        if not self._settled:
            self._due_s = self._earliest_due()
            self._serve_by_s = min(self._due_s, now + self.MAX_WAIT_S)
        wait = self._due_s - now
        if wait > max_wait_s:
            wait = max_wait_s
        if wait < 0.0:
            wait = 0.0
        wake_s = now + wait  # the latest this wake-up is due
        self._settled = False
        self._fieldbus_plain = True
        fds = self._fds
        if fds is not None:
            io_ready = self._io_pending()
            fieldbus_ready = self._fieldbus_pending()
            if not (io_ready or fieldbus_ready):
                io_ready, fieldbus_ready = self._wait_ready(fds, wait)
            fieldbus_frames = self._drain(self.fieldbus) if fieldbus_ready else 0
            handled = fieldbus_frames + (self._drain(self.io) if io_ready else 0)
        else:
            fieldbus_frames = self._drain(self.fieldbus)
            handled = fieldbus_frames + self._drain(self.io)
            if not handled:
                end = self._clock() + wait
                while True:
                    msg = self.io.recv(timeout=self.POLL_S)
                    if msg is not None:
                        fieldbus_frames = self._drain(self.fieldbus)
                        self.on_io(msg)
                        handled = fieldbus_frames + 1 + self._drain(self.io)
                        break
                    msg = self.fieldbus.recv(timeout=0)
                    if msg is not None:
                        self._on_fieldbus(msg)
                        fieldbus_frames = 1 + self._drain(self.fieldbus)
                        handled = fieldbus_frames + self._drain(self.io)
                        break
                    if self._clock() >= end:
                        break
        self.frames_in += handled
        now = self._clock()
        self.ran_at(now, wake_s)
        vouched = not fieldbus_frames or (self._fieldbus_plain and self.fieldbus_settled())
        if handled and now < self._serve_by_s and vouched and self.io_settled():
            self._settled = True  # frames the subclass vouches for, nothing due: the service would find no work
            return handled
        self._service(now)
        self.on_service(now)
        self.emcy.flush(now)
        return handled

    def ran_at(self, now_s: float, due_s: float | None) -> None:
        """This node runs at ``now_s``, due at ``due_s`` (None: no bound): later by over ``consumer.stall_s`` is a stall."""
        if due_s is not None and now_s - due_s > self.consumer.stall_s:
            self.after_stall(due_s, now_s)
        if self._ran_s is not None:
            self._ran_s = now_s

    def after_stall(self, due_s: float, now_s: float) -> None:
        """Run again at ``now_s``, over half the shortest consumer time after ``due_s`` (this process did not
        run): the timers that watch others judge from now -- heartbeat consumer, SDO timeout, a subclass's own."""
        self.consumer.after_stall(self.node_id, due_s, now_s)
        self.sdo.grace(now_s)

    def _wait_ready(self, fds: list[int], wait: float) -> tuple[bool, bool]:
        """Wait up to ``wait`` [s] for a frame on either bus (``fds``: fieldbus, io): (io ready, fieldbus ready)."""
        ready = select_ready(fds, wait)
        return (fds[1] in ready, fds[0] in ready) if ready else (False, False)

    def _earliest_due(self) -> float:
        """When the service has work next [s; inf: no deadline]: the heartbeat,
        :meth:`next_deadline`, the heartbeat consumer, a waiting EMCY, the SDO transfer's timeout."""
        earliest = math.inf
        near = (self._next_heartbeat_s, self.next_deadline(), self.consumer.next_deadline())
        for due in (*near, self.emcy.next_deadline(), self.sdo.next_deadline()):
            if due is not None and due < earliest:
                earliest = due
        return earliest

    def _drain(self, bus: can.BusABC) -> int:
        """Handle every frame waiting on ``bus`` (one batch: what arrives meanwhile makes the bus
        ready again for the next :meth:`step`)."""
        if bus is self.io:
            handler, msgs = self.on_io, self._io_batch()
        else:
            handler, msgs = self._on_fieldbus, self._fieldbus_batch()
        for msg in msgs:
            handler(msg)
        return len(msgs)

    # ------------------------------------------------------------------ periodic

    def _service(self, now: float) -> None:
        for producer in self.consumer.expired(now):
            level = logging.INFO if int(self.app.nmt_state) == NmtState.STOPPED else logging.WARNING
            logger.log(
                level,
                "node %d: heartbeat of node %d lost (consumer time %.0f ms)",
                self.node_id,
                producer,
                1000 * self.consumer.producers.get(producer, 0.0),
            )
            self.on_heartbeat_lost(producer)
        self.emcy.flush(now)
        abort = self.sdo.tick(now)
        if abort is not None:
            self._send(self.fieldbus, self._sdo_tx, abort)
        self.heartbeat_if_due(now)

    def heartbeat_if_due(self, now: float | None = None) -> None:
        """The heartbeat (0x1017) if it is due at ``now`` [s] (default the node's clock): from
        :meth:`step`, and from a wait inside the application that could outlast a heartbeat period
        (a drive waiting for its processor-in-the-loop target, :mod:`firmware_model.pil_link`)."""
        due = self._next_heartbeat_s
        if due is None:
            return
        if now is None:
            now = self._clock()
        if now >= due:
            self._send(self.fieldbus, self._hb_id, encode_heartbeat(int(self.app.nmt_state)))
            period = self._heartbeat_ms / 1000.0
            # keep the phase; skip missed beats instead of bursting
            self._next_heartbeat_s = due + period
            if self._next_heartbeat_s <= now:
                self._next_heartbeat_s = now + period

    def _reload_heartbeat(self, force: bool = False) -> None:
        """Re-read 0x1017 [ms]; restart the heartbeat timer if it changed (or ``force``)."""
        try:
            period_ms = int.from_bytes(self.app.read_object(PRODUCER_HEARTBEAT_INDEX, 0)[:2], "little")
        except SdoAbort:
            period_ms = 0
        if period_ms == self._heartbeat_ms and not force:
            return
        self._heartbeat_ms = period_ms
        self._next_heartbeat_s = self._clock() + period_ms / 1000.0 if period_ms else None

    def _reload_emcy(self) -> None:
        """Re-read the EMCY's 0x1014 / 0x1015 (:meth:`bus.cia301.emcy_producer.EmcyProducer.reload`)
        and with them the node's own fieldbus identifiers."""
        self.emcy.reload()
        self._own_fieldbus_ids = {self._sdo_tx, self._hb_id} | self.emcy.own_ids()

    def _reload_consumers(self) -> None:
        """Re-read the consumer heartbeat entries 0x1016:1..n (:func:`consumer_entries`)."""
        entries = consumer_entries(self.app)
        if entries != self.consumer.producers:
            logger.info(
                "node %d: heartbeat consumer %s", self.node_id, {n: f"{1000 * t:.0f} ms" for n, t in entries.items()} or "off"
            )
        self.consumer.configure(entries)

    # ------------------------------------------------------------------ fieldbus

    def _on_fieldbus(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            self._fieldbus_plain = False
        if msg.is_error_frame:
            if is_receive_overflow(msg):
                logger.warning("node %d: fieldbus frames lost (receive overflow)", self.node_id)
                self.on_frames_lost()
            return
        if msg.is_extended_id:
            return
        if msg.is_remote_frame:
            self.on_fieldbus(msg)  # e.g. a request for a TPDO
            return
        cob = msg.arbitration_id
        if cob in self._own_fieldbus_ids:
            return  # our own frame, echoed
        producer = heartbeat_node_id(cob)
        if producer is not None:
            self._fieldbus_plain = False
            self.consumer.on_heartbeat(producer, self._clock())
        elif cob == NMT_COB_ID:
            self._fieldbus_plain = False
            self._on_nmt(bytes(msg.data))
        elif cob == self._sdo_rx:
            self._fieldbus_plain = False
            if int(self.app.nmt_state) == NmtState.STOPPED:
                return
            response = self.sdo.handle(bytes(msg.data), now_s=self._clock())
            if not self.sdo.busy:
                self._reload_heartbeat()
                self._reload_consumers()
                self._reload_emcy()
                # before the response: the master may use a new COB-ID as soon as it has it
                self._refresh_fieldbus_filters()
            if response is not None:
                for data in [response] if isinstance(response, bytes) else response:
                    self._send(self.fieldbus, self._sdo_tx, data)
        else:
            self.on_fieldbus(msg)

    def _on_nmt(self, data: bytes) -> None:
        try:
            command = nmt_addresses(data, self.node_id)
        except NmtFrameError as err:
            logger.warning("node %d: ignoring NMT frame %s: %s", self.node_id, data.hex(), err)
            return
        if command is None:
            return
        logger.info("node %d: NMT %s", self.node_id, command.name)
        self.app.nmt_command(int(command))
        if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self.sdo = SdoServer(self.node_id, self.app)  # drops any transfer
            self.on_nmt_reset(command)
            self._reload_heartbeat(force=True)
            self._reload_consumers()
            self._reload_emcy()
            self._refresh_fieldbus_filters()
            self._send(self.fieldbus, self._hb_id, encode_heartbeat(NmtState.BOOT_UP))

    # ------------------------------------------------------------------ send

    def send_emcy(self, code: int, register: int, data: bytes = b"") -> None:
        """Send one EMCY frame now (unless the node is STOPPED or 0x1014 says the EMCY is not valid)."""
        self.emcy.send_now(code, register, data)

    def _send(self, bus: can.BusABC, cob_id: int, data: bytes) -> None:
        bus.send(new_message(cob_id, bytearray(data)))
        self.frames_out += 1


def consumer_entries(app: SlaveApp) -> dict[int, float]:
    """The heartbeat producers ``app``'s 0x1016:1..n consume, node id -> consumer time [s] (an app
    without 0x1016 consumes nothing)."""
    entries: dict[int, float] = {}
    try:
        count = app.read_object(CONSUMER_HEARTBEAT_INDEX, 0)[0]
        for sub in range(1, count + 1):
            entry = decode_consumer_entry(int.from_bytes(app.read_object(CONSUMER_HEARTBEAT_INDEX, sub)[:4], "little"))
            if entry is not None:
                entries[entry[0]] = entry[1] / 1000.0
    except (SdoAbort, IndexError):
        return {}
    return entries


def install_sigterm(stop: threading.Event) -> None:
    """Make SIGTERM (and SIGINT) set ``stop`` (only possible from the main thread)."""

    def _handler(signum: int, _frame: object) -> None:
        logger.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGTERM, _handler)
    signal.signal(signal.SIGINT, _handler)


def quiet_shutdown(bus: can.BusABC) -> None:
    """Close a bus that may have failed already (the hub gone): never raise on the way out."""
    try:
        bus.shutdown()
    except (can.CanError, OSError) as err:
        logger.debug("closing %s: %s", bus, err)
