"""Passive channel monitors of the host: every frame of a channel counted, classified and logged.

This module owns :class:`ChannelMonitor`: one more plain member of a channel's bus (any
python-can ``BusABC``) read by its own thread, which counts frames and bits
(:class:`bus.busload.BusLoadCounter`), hands every frame to an optional classifier (the bus-time
accounting of :mod:`bus.bustime`) and writes the channel's candump log (:mod:`bus.canlog`).

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
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Sized
from pathlib import Path

import can
import numpy as np

from bus.bus_features import FrameArrayReceiver, load_of, recv_waiting
from bus.busload import BusLoadCounter
from bus.canlog import open_log

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
    #: the reading thread's nice increment: nobody waits for a monitor, so it yields the cores
    #: to the lockstep processes (Linux sets the nice value per thread)
    NICE_INCREMENT: int = 10

    def __init__(self, bus: can.BusABC, name: str, log_path: Path | None,
                 classify: Callable[[can.Message], None] | None = None, *, bulk: bool = True,
                 classify_frames: Callable[[np.ndarray], None] | None = None) -> None:
        self.bus = bus
        # frames as arrays where the bus offers them (and the classifier takes them)
        self._recv_frames = (bus.recv_frames if isinstance(bus, FrameArrayReceiver) and (
            classify is None or classify_frames is not None) else None)
        self._classify_frames = classify_frames
        self.bulk = bool(bulk)
        self.name = name
        self.counter = BusLoadCounter()
        self.log = open_log(log_path, name) if log_path is not None else None
        self.lock = threading.Lock()
        self._classify = classify
        self._stop = threading.Event()
        self._kick = threading.Event()
        self._rounds = 0
        self._round_done = threading.Condition()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"monitor {name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        bus = self.bus
        if self.bulk:
            _lower_own_priority(self.NICE_INCREMENT)
        try:
            while not self._stop.is_set():
                if self._recv_frames is not None:
                    batch: Sized = self._read_frames()
                else:
                    batch = recv_waiting(bus, self.WAIT_S)
                    if batch:
                        self._process(batch)
                with self._round_done:
                    self._rounds += 1
                    self._round_done.notify_all()
                if self.bulk and len(batch) and not self._kick.is_set():
                    self._kick.wait(self.ROUND_S if self._recv_frames is None else self.FRAMES_ROUND_S)
        except can.CanOperationError as err:
            if not self._stop.is_set():
                self.error = err
                logger.warning("monitor of %s stopped: %s", self.name, err)
        finally:
            with self._round_done:
                self._rounds += 1
                self._round_done.notify_all()

    def _process(self, batch: list[can.Message]) -> None:
        with self.lock:
            counter, log, classify = self.counter, self.log, self._classify
            for msg in batch:
                counter.add(msg)
                if classify is not None:
                    classify(msg)
                if log is not None:
                    log.on_message_received(msg)

    def _read_frames(self) -> np.ndarray:
        """Read and process every frame waiting (after waiting up to :attr:`WAIT_S` for one) as
        arrays: counted, classified and logged without a Python step per frame."""
        assert self._recv_frames is not None
        frames = self._recv_frames(self.WAIT_S)
        more = frames
        while len(more):
            more = self._recv_frames(0)
            if len(more):
                frames = np.concatenate((frames, more))
        if len(frames):
            with self.lock:
                self.counter.merge(load_of(frames))
                if self._classify_frames is not None:
                    self._classify_frames(frames)
                if self.log is not None:
                    self.log.write_frames(frames)
        return frames

    def catch_up(self, timeout_s: float = 2.0) -> None:
        """Return once every frame that reached this monitor's bus before the call is processed
        (two complete reading rounds later), or after ``timeout_s``."""
        if not self._thread.is_alive():
            return
        with self._round_done:
            target = self._rounds + 2
            self._kick.set()
            try:
                deadline = time.monotonic() + timeout_s
                while self._rounds < target and self._thread.is_alive():
                    left = deadline - time.monotonic()
                    if left <= 0 or not self._round_done.wait(left):
                        break
            finally:
                self._kick.clear()

    def close(self) -> None:
        """Stop reading, close the log and the bus."""
        self._stop.set()
        self._kick.set()
        self._thread.join(timeout=2.0)
        with self.lock:
            if self.log is not None:
                self.log.stop()
        self.bus.shutdown()


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
