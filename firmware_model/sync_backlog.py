"""The fieldbus frames of a drive of a SYNC-stepped robot that wait for a period: a master faster than
the robot is served late, never dropped (docs/robot.md "Time").

Owns :class:`SyncBacklog`, used by :class:`firmware_model.drive_node.DriveNode` in lockstep mode
(``ilcrig robot``): the drive handles its fieldbus frames in the order they came, and a SYNC is
handled through only when its io tick (the period the plant steps for it) has run.  While a SYNC
waits for its io tick, every later fieldbus frame -- RPDOs, SYNCs, SDO requests, NMT commands,
remote frames; not heartbeats, which say who is alive, nor error frames -- waits in order; after
the tick the frames are handled in order up to the next SYNC, which waits for its own tick.  So
period k takes exactly the RPDOs (and SDO writes, NMT commands) that came before SYNC k, its TPDOs
carry period k, and a master's sequence gives the same periods however fast it sends and however
loaded the machine is.

Bounds: SYNCs always wait (the robot steps every SYNC; the plant's bound,
:data:`bus.cyclic.SYNC_BACKLOG_MAX`, makes a master that outruns it a robot fault); of the other
frames at most :data:`bus.cyclic.FRAME_BACKLOG_MAX` wait, one more is lost as in a CAN controller's
full receive queue (``lost``: the drive's EMCY 0x8110, once per overflow).  A SYNC whose io tick
does not come within ``hold_timeout_s`` while frames wait (the plant stopped stepping: its robot
mode switched off, the plant gone) lets the frames go unheld until the next io tick.

May import: ``bus`` and python-can (a part of the drive's node runtime; no firmware).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable

import can

from bus.cia301.nmt import heartbeat_node_id
from bus.cyclic import FRAME_BACKLOG_MAX

logger = logging.getLogger(__name__)

__all__ = ["SyncBacklog"]


class SyncBacklog:
    """The frames waiting behind a SYNC whose io tick has not run (see the module docstring).

    :param node_id: the drive's node id (log messages).
    :param handle: handles one fieldbus frame (the node runtime's own handling).
    :param sync_cob_id: the SYNC identifier the drive consumes now (0x1005).
    :param lost: frames were lost (the backlog was full).
    :param hold_timeout_s: the longest wait for a SYNC's io tick while frames wait, s.
    :param max_frames: frames other than SYNC that may wait.
    """

    def __init__(
        self,
        node_id: int,
        handle: Callable[[can.Message], None],
        sync_cob_id: Callable[[], int],
        lost: Callable[[], None],
        hold_timeout_s: float,
        max_frames: int = FRAME_BACKLOG_MAX,
    ) -> None:
        self.node_id = node_id
        self._handle = handle
        self._sync_cob_id = sync_cob_id
        self._lost = lost
        self.hold_timeout_s = hold_timeout_s
        self.max_frames = max_frames
        self.frames: deque[tuple[can.Message, bool]] = deque()  # (frame, is SYNC), in order
        self.most = 0  #: the most frames that waited at once
        self.lost_frames = 0  #: frames lost past ``max_frames``
        self._others = 0  # frames other than SYNC waiting
        self.sync_waiting = False  #: a SYNC was handled whose io tick has not run
        self._since = 0.0  # when it was handled, s
        self._off = False  # its io tick did not come in time: frames go unheld until the next tick
        self._releasing = False
        self._overflowed = False

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def quiet(self) -> bool:
        """No frame waits, no SYNC waits for its io tick, none timed out: an io tick changes nothing here."""
        return not (self.frames or self.sync_waiting or self._off)

    # ------------------------------------------------------------------ events

    def offer(self, msg: can.Message) -> bool:
        """A fieldbus frame came: True when it waits (or was lost), False when it is to be handled now."""
        if not (self.sync_waiting or self.frames) or self._off or self._releasing:
            return False
        if msg.is_error_frame or (not msg.is_remote_frame and heartbeat_node_id(msg.arbitration_id) is not None):
            return False
        is_sync = not msg.is_remote_frame and msg.arbitration_id == self._sync_cob_id()
        if not is_sync:
            if self._others >= self.max_frames:
                self.lost_frames += 1
                if not self._overflowed:
                    self._overflowed = True
                    logger.warning(
                        "node %d: %d fieldbus frames wait for the period in progress: frames lost", self.node_id, len(self.frames)
                    )
                    self._lost()
                return True
            self._others += 1
        frames = self.frames
        frames.append((msg, is_sync))
        if len(frames) > self.most:
            self.most = len(frames)
        return True

    def sync_handled(self, now_s: float) -> None:
        """A SYNC of the robot was handled: the frames after it wait until its io tick ran."""
        if not self._off:
            self.sync_waiting = True
            self._since = now_s

    def tick_ran(self) -> None:
        """An io tick ran: the frames waiting behind its SYNC are handled, up to the next SYNC."""
        if self.sync_waiting or self._off:
            self.sync_waiting = self._off = False
            self._release()

    def no_ticks(self) -> None:
        """The plant's ticks are not SYNC's (a trial): nothing waits for them."""
        if self.sync_waiting:
            self.sync_waiting = False
            self._release()

    def deadline(self) -> float | None:
        """When :meth:`expire` lets the frames go (None: nothing waits for a tick)."""
        return self._since + self.hold_timeout_s if self.sync_waiting and self.frames else None

    def expire(self, now_s: float) -> None:
        """No io tick within ``hold_timeout_s`` of its SYNC: the frames go unheld until the next tick."""
        due = self.deadline()
        if due is None or now_s < due:
            return
        logger.warning(
            "node %d: no io tick within %.1f s of its SYNC (the plant stopped stepping): %d frames go unheld",
            self.node_id,
            self.hold_timeout_s,
            len(self.frames),
        )
        self._off, self.sync_waiting = True, False
        self._release()

    def _release(self) -> None:
        """The frames waiting, in order, up to the next SYNC that waits for its io tick."""
        if self._releasing:
            return
        self._releasing = True
        frames = self.frames
        handle = self._handle
        try:
            while frames and (self._off or not self.sync_waiting):
                msg, is_sync = frames.popleft()
                if not is_sync:
                    self._others -= 1
                handle(msg)
        finally:
            self._releasing = False
        if not frames:
            self._overflowed = False
