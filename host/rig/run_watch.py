"""The launcher's view of where a run is: the trial and tick on the io channel, the trials in the
summary.

This module owns :class:`RunProgress`, a thread of the launcher that joins the io channel as a
passive member (the hub's bulk delivery: frames up to 20 ms late, in few writes; acceptance filters
for the plant's control frames and the first joint's encoder frame only) and follows the plant's
trials and ticks (:class:`bus.io_frames.TrialTickFollower`, with arrays where the bus gives them).
When a process of the run ends, the launcher takes a :class:`Where` from it — the trial the plant
was in and its tick — and places its ``process_died`` fault with it (the trials the summary kept
decide the position: :func:`host.experiment.faults.position_of`).  A bus that fails (the hub
killed) ends the thread; what it saw last stays.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from dataclasses import dataclass

import can

from bus import io_frames
from bus.bus_features import FRAME_ERR, FrameArrayReceiver
from bus.transports.config import IO, TransportConfig

logger = logging.getLogger(__name__)

__all__ = ["RunProgress", "Where"]


@dataclass(frozen=True)
class Where:
    """The io channel's position: ``trial`` (−1 before the first TRIAL_START), ``tick`` of that
    trial (None before its first encoder frame), ``in_trial`` (between its TRIAL_START and
    TRIAL_STOP)."""

    trial: int = -1
    tick: int | None = None
    in_trial: bool = False


class RunProgress(threading.Thread):
    """Follows the trials and ticks of a run on its io channel (see the module docstring).

    :param transport: the run's transport (the thread opens its own io bus)
    """

    #: longest blocking wait, s (bounds the reaction to :meth:`stop`)
    WAIT_S: float = 0.1

    def __init__(self, transport: TransportConfig) -> None:
        super().__init__(name="run progress", daemon=True)
        self.transport = transport
        self.follower = io_frames.TrialTickFollower()
        self._lock = threading.Lock()
        self._stop_event = threading.Event()
        self._bus: can.BusABC | None = None
        self.error: str | None = None

    def where(self) -> Where:
        """The position now (what the last frames read showed)."""
        with self._lock:
            f = self.follower
            return Where(f.trial, f.tick, f.in_trial)

    def run(self) -> None:
        try:
            bus = self._bus = self.transport.open(IO, passive=True)
            bus.set_filters(
                [
                    {"can_id": io_frames.CONTROL_COB_ID, "can_mask": 0x7FF},
                    {"can_id": io_frames.ENCODER_COB_BASE, "can_mask": 0x7FF},
                ]
            )
            frames = bus.recv_frames if isinstance(bus, FrameArrayReceiver) else None
            while not self._stop_event.is_set():
                if frames is not None:
                    arr = frames(self.WAIT_S)
                    if len(arr):
                        with self._lock:
                            self.follower.on_frame_array(
                                arr["arbitration_id"], arr["data"], arr["length"], (arr["flags"] & FRAME_ERR) == 0
                            )
                else:
                    msg = bus.recv(self.WAIT_S)
                    if msg is not None and not msg.is_error_frame:
                        with self._lock:
                            self.follower.on_frame(msg.arbitration_id, msg.data)
        except (can.CanError, OSError, ValueError) as exc:
            if not self._stop_event.is_set():
                self.error = f"{type(exc).__name__}: {exc}"
                logger.info("run progress stopped: %s", self.error)  # e.g. the hub was killed
        finally:
            if self._bus is not None:
                with contextlib.suppress(can.CanError, OSError):
                    self._bus.shutdown()

    def stop(self) -> None:
        """Stop following (idempotent)."""
        self._stop_event.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=2.0)
