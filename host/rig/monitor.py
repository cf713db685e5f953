"""Passive channel monitors of the host: every frame of a channel counted, classified and logged.

This module owns :class:`ChannelMonitor`: one more plain member of a channel's bus (any
python-can ``BusABC``) read by its own thread, which counts frames and bits
(:class:`bus.busload.BusLoadCounter`), hands every frame to an optional classifier (the bus-time
accounting of :mod:`bus.traffic`) and writes the channel's candump log (:mod:`bus.canlog`).

Reading in bulk
    The monitor sees every frame of the channel — on the io channel 8 per control period — but
    nobody waits for it, so on the hub (whose bulk delivery holds a passive member's frames) it
    reads in rounds: it blocks until a frame is there, takes every
    frame that is waiting, processes them together and then pauses :attr:`ChannelMonitor.ROUND_S`
    before the next round (the frames meanwhile wait in the transport's receive buffer). That
    keeps the monitor from waking up for every frame and competing with the lockstep processes
    for the cores; its thread also runs at a lower priority (nice + :attr:`ChannelMonitor.NICE_INCREMENT`).
    Where the bus returns the waiting frames as one array (:class:`bus.bus_features.FrameArrayReceiver`,
    the hub) and the classifier takes arrays (``classify_frames``), a round is counted, classified and
    logged with numpy, without a Python step (nor a :class:`can.Message`) per frame, and the
    pause between rounds is longer (:attr:`ChannelMonitor.FRAMES_ROUND_S`): more frames per round.
    :meth:`ChannelMonitor.catch_up` waits until everything sent before the call
    has been processed (the summary reads the counters after it).

Waiting for a marker, not for rounds
    At the end of a trial the host waits for an explicit marker (:meth:`ChannelMonitor.wait_until`):
    on the io channel the trial's TRIAL_STOP control frame (:attr:`bus.io_frames.TrialTickFollower.ended`),
    on the fieldbus a frame the transport stamped after the trial's end (:attr:`ChannelMonitor.last_stamp`,
    the receive time every transport gives a frame: the hub's, the kernel's).  While someone waits
    the monitor reads without pauses and notifies after every batch, so the wait costs the time
    the marker takes to arrive, not two reading rounds (each of which blocked up to
    :attr:`ChannelMonitor.WAIT_S` on a channel that had gone quiet); on the hub it first asks for
    the frames held for it (:func:`bus.bus_features.release_held`), so the wait does not include
    the bulk delivery's hold either.

What can go wrong is noted, with the monotonic time it was seen, for the host's watchdog: the bus
failing (:attr:`ChannelMonitor.bus_error`), bus error frames (:attr:`ChannelMonitor.error_frames`),
the log failing (it is flushed after the first reading round that ends
:attr:`ChannelMonitor.LOG_FLUSH_S` or more after a line was written — within about ``LOG_FLUSH_S`` +
:attr:`ChannelMonitor.FRAMES_ROUND_S` —, and once the channel is quiet for
:attr:`ChannelMonitor.WAIT_S`: a launcher killed then loses no more than that), e.g. on a full disk
(:attr:`ChannelMonitor.log_error`: the log stops, the counting goes on). On the io channel the
monitor also follows the trials and ticks as the plant's frames show them
(:attr:`ChannelMonitor.follower`, for a fault's ``tick``; with arrays only the control frames and
the last encoder frame between them are looked at). For ``--inject diskfull@T:N`` the io monitor's
log fails with ``ENOSPC`` once the channel shows tick N of trial T
(:attr:`ChannelMonitor.fail_log_from`; ``on_log_fail_injected`` records it).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Sized
from pathlib import Path

import can
import numpy as np

from bus import io_frames
from bus.bus_features import FRAME_ERR, FrameArrayReceiver, load_of, recv_waiting, release_held
from bus.busload import BusLoadCounter
from bus.can_errors import is_receive_overflow, receive_overflows
from bus.canlog import open_log
from bus.transports.config import IO
from host.experiment.outputs import is_disk_full

logger = logging.getLogger(__name__)

__all__ = ["ChannelMonitor"]


class ChannelMonitor:
    """Counts, classifies and logs the frames of one channel (see the module docstring).

    :param bus: a bus of the channel, owned by the monitor from now on (closed by :meth:`close`)
    :param name: the channel's name (``fieldbus``, ``io``), also the log's channel column
    :param log_path: candump log to write, or None
    :param classify: called with every frame, in order, under :attr:`lock` (or None)
    :param bulk: read in rounds with a pause and at a lower priority; only for a bus that holds the
        frames for its reader meanwhile (the hub's bulk delivery).  A kernel socket (SocketCAN,
        UDP) drops frames once its receive buffer is full, so there the monitor reads continuously.
    :param classify_frames: the classifier for many frames at once (an array of
        :data:`bus.bus_features.FRAME_DTYPE`, in order), used instead of ``classify`` when the bus
        returns arrays (see the module docstring)
    """

    #: pause between two reading rounds, s
    ROUND_S: float = 0.02
    #: the pause when a round is read as arrays: their cost is mostly per round, not per frame
    FRAMES_ROUND_S: float = 0.1
    #: longest blocking wait for a frame, s (bounds the reaction to :meth:`close`)
    WAIT_S: float = 0.1
    #: the log is handed to the kernel at least this often while frames come, s
    LOG_FLUSH_S: float = 0.05
    #: the reading thread's nice increment: nobody waits for a monitor, so it yields the cores
    #: to the lockstep processes (Linux sets the nice value per thread)
    NICE_INCREMENT: int = 10

    def __init__(
        self,
        bus: can.BusABC,
        name: str,
        log_path: Path | None,
        classify: Callable[[can.Message], None] | None = None,
        *,
        bulk: bool = True,
        classify_frames: Callable[[np.ndarray], None] | None = None,
    ) -> None:
        self.bus = bus
        # frames as arrays where the bus offers them (and the classifier takes them)
        self._recv_frames = (
            bus.recv_frames if isinstance(bus, FrameArrayReceiver) and (classify is None or classify_frames is not None) else None
        )
        self._classify_frames = classify_frames
        self.bulk = bool(bulk)
        self.name = name
        self.counter = BusLoadCounter()
        self.log = open_log(log_path, name) if log_path is not None else None
        self.lock = threading.Lock()
        self._classify = classify
        self._stop = threading.Event()
        self._kick = threading.Event()
        self._waiters = 0
        self._rounds = 0
        #: the latest receive time (``Message.timestamp`` scale, s) of a frame processed
        self.last_stamp = float("-inf")
        self._round_done = threading.Condition()
        #: the bus failed: description and monotonic time [s]
        self.bus_error: str | None = None
        self.bus_error_t: float | None = None
        #: the log stopped (a failing write): description, monotonic time [s], was the disk full
        self.log_error: str | None = None
        self.log_error_t: float | None = None
        self.log_disk_full = False
        #: bus error frames seen, and when the first came (monotonic, s)
        self.error_frames = 0
        self.first_error_frame_t: float | None = None
        #: of them, those that say a receiver's queue overflowed (frames lost, not damaged), and the
        #: first one's time (monotonic, s)
        self.overflow_frames = 0
        self.first_overflow_t: float | None = None
        #: io: trials and ticks as the plant's frames show them
        self.follower = io_frames.TrialTickFollower()
        self._is_io = name == IO
        #: fault injection: the log fails from this (trial, tick) of the io channel on
        self.fail_log_from: tuple[int, int] | None = None
        self.on_log_fail_injected: Callable[[int, int | None], None] | None = None
        self._thread = threading.Thread(target=self._run, name=f"monitor {name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        bus = self.bus
        if self.bulk:
            _lower_own_priority(self.NICE_INCREMENT)
        try:
            flush_due: float | None = None  # when the log's unflushed lines must be flushed
            while not self._stop.is_set():
                if self._recv_frames is not None:
                    batch: Sized = self._read_frames()
                else:
                    batch = recv_waiting(bus, self.WAIT_S)
                    if batch:
                        self._process(batch)
                if len(batch) and flush_due is None:
                    flush_due = time.monotonic() + self.LOG_FLUSH_S
                if flush_due is not None and (not len(batch) or time.monotonic() >= flush_due):
                    self._flush_log()
                    flush_due = None
                with self._round_done:
                    self._rounds += 1
                    self._round_done.notify_all()
                if self.bulk and len(batch) and not self._kick.is_set():
                    self._kick.wait(self.ROUND_S if self._recv_frames is None else self.FRAMES_ROUND_S)
        except (can.CanError, OSError, ValueError) as err:  # ValueError: a descriptor closed under us
            if not self._stop.is_set():
                self.bus_error = f"{type(err).__name__}: {err}"
                self.bus_error_t = time.monotonic()
                logger.warning("monitor of %s stopped: %s", self.name, err)
        finally:
            with self._round_done:
                self._rounds += 1
                self._round_done.notify_all()

    def _process(self, batch: list[can.Message]) -> None:
        with self.lock:
            counter, log, classify = self.counter, self.log, self._classify
            follower = self.follower if self._is_io else None
            self.last_stamp = max(self.last_stamp, batch[-1].timestamp)
            for msg in batch:
                counter.add(msg)
                if classify is not None:
                    classify(msg)
                if msg.is_error_frame:
                    self._error_frames(1, int(is_receive_overflow(msg)))
                elif follower is not None:
                    follower.on_frame(msg.arbitration_id, msg.data)
            if log is not None:
                try:
                    self._injected_failure()
                    for msg in batch:
                        log.on_message_received(msg)
                except (OSError, ValueError) as err:  # ValueError: a write to a file closed by a failure
                    self._log_failed(err)

    def _flush_log(self) -> None:
        """Hand the log's lines written so far to the kernel (a failure stops the log, as a write's does)."""
        with self.lock:
            if self.log is not None:
                try:
                    self.log.flush()
                except (OSError, ValueError) as err:
                    self._log_failed(err)

    def _injected_failure(self) -> None:
        """Raise the injected ``ENOSPC`` once the io channel shows :attr:`fail_log_from`."""
        if self.fail_log_from is None or not self._is_io:
            return
        f, (trial, tick) = self.follower, self.fail_log_from
        if f.trial > trial or (f.trial == trial and f.tick is not None and f.tick >= tick):
            self.fail_log_from = None
            if self.on_log_fail_injected is not None:
                self.on_log_fail_injected(f.trial, f.tick)
            raise OSError(errno.ENOSPC, "No space left on device (injected)")

    def _error_frames(self, n: int, overflows: int = 0) -> None:
        """``n`` bus error frames heard, ``overflows`` of them receive overflows."""
        if not n:
            return
        now = time.monotonic()
        if self.first_error_frame_t is None:
            self.first_error_frame_t = now
        if overflows and self.first_overflow_t is None:
            self.first_overflow_t = now
        self.error_frames += n
        self.overflow_frames += overflows

    def _log_failed(self, err: BaseException) -> None:
        """The log stopped (noted once; the frames are still counted)."""
        self.log_error = f"{getattr(err, 'strerror', None) or err}"
        self.log_disk_full = is_disk_full(err)
        self.log_error_t = time.monotonic()
        logger.warning("%s log stopped: %s", self.name, self.log_error)
        log, self.log = self.log, None
        try:
            if log is not None:
                log.stop()
        except (OSError, ValueError):
            pass

    def _read_frames(self) -> np.ndarray:
        """Read and process every frame waiting (after waiting up to :attr:`WAIT_S` for one) as
        arrays: counted, classified and logged without a Python step per frame.  A round reads for
        at most :attr:`FRAMES_ROUND_S`, so that frames that keep coming are still processed in
        rounds (the live view of ``ilcrig robot`` follows the robot)."""
        assert self._recv_frames is not None
        frames = self._recv_frames(self.WAIT_S)
        more = frames
        end = time.monotonic() + self.FRAMES_ROUND_S
        while len(more) and not self._kick.is_set() and time.monotonic() < end:
            more = self._recv_frames(0)
            if len(more):
                frames = np.concatenate((frames, more))
        if len(frames):
            with self.lock:
                self.last_stamp = max(self.last_stamp, float(frames["timestamp"].max()))
                self.counter.merge(load_of(frames))
                if self._classify_frames is not None:
                    self._classify_frames(frames)
                err = (frames["flags"] & FRAME_ERR) != 0
                n_err = int(err.sum())
                self._error_frames(n_err, receive_overflows(frames["arbitration_id"][err], frames["data"][err]))
                if self._is_io:
                    self.follower.on_frame_array(frames["arbitration_id"], frames["data"], frames["length"], ~err)
                if self.log is not None:
                    try:
                        self._injected_failure()
                        self.log.write_frames(frames)
                    except (OSError, ValueError) as exc:
                        self._log_failed(exc)
        return frames

    def catch_up(self, timeout_s: float = 2.0) -> None:
        """Return once every frame that reached this monitor's bus before the call is processed
        (two complete reading rounds later), or after ``timeout_s``.  Where a marker is known, use
        :meth:`wait_until`: a round on a quiet channel blocks up to :attr:`WAIT_S`."""
        with self._round_done:
            target = self._rounds + 2
        self.wait_until(lambda: self._rounds >= target, timeout_s)

    @contextlib.contextmanager
    def unpaused(self) -> Iterator[None]:
        """While the block runs the monitor reads without pausing between rounds (a reader that
        waits for something is not kept waiting by a pause)."""
        with self._round_done:
            self._waiters += 1
            self._kick.set()
        try:
            release_held(self.bus)  # frames the hub holds for this bulk member: now
        except (can.CanError, OSError, ValueError) as err:  # the reading thread notes a failed bus
            logger.debug("%s monitor: release of held frames failed: %s", self.name, err)
        try:
            yield
        finally:
            with self._round_done:
                self._waiters -= 1
                if not self._waiters:
                    self._kick.clear()

    def wait_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Read without pauses until ``done()`` holds (checked after every processed batch), at most
        ``timeout_s`` s; whether it holds.  ``done`` looks at what the monitor noted, e.g. the io
        follower's :attr:`~bus.io_frames.TrialTickFollower.ended` or :attr:`last_stamp`."""
        with self.unpaused(), self._round_done:
            deadline = time.monotonic() + timeout_s
            while not done():
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive():
                    return done()
                self._round_done.wait(left)
            return True

    def close(self) -> None:
        """Stop reading, close the log and the bus."""
        self._stop.set()
        self._kick.set()
        self._thread.join(timeout=2.0)
        with self.lock:
            if self.log is not None:
                try:
                    self.log.stop()
                except (OSError, ValueError) as err:
                    self._log_failed(err)
        try:
            self.bus.shutdown()
        except (can.CanError, OSError) as err:
            logger.debug("closing the %s monitor bus: %s", self.name, err)


def _lower_own_priority(increment: int) -> None:
    """Raise the calling thread's nice value by ``increment`` (Linux: per thread; elsewhere, or if
    refused, nothing happens)."""
    if increment <= 0 or not hasattr(os, "setpriority"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + increment))
    except OSError as err:
        logger.debug("cannot lower the monitor thread's priority: %s", err)
