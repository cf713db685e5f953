"""A node whose io transport may answer a trial's plain io ticks outside the interpreter.

Owns :class:`AnsweringNode`, the part the drive node (:class:`firmware_model.drive_node.DriveNode`)
and the plant node (:class:`plant.plant_node.PlantNode`) share: when the last wake-up of
:meth:`bus.cia301.slave.SlaveNode.step` left the service nothing to do, the io frames before the
service's deadline go through the transport's answer loop
(:class:`bus.bus_features.FrameAnswerer`; the hub client in C), each handed to the node's callback
and its answers written at once; whatever the loop hands back, :meth:`SlaveNode.step` takes as ever.
"""

from __future__ import annotations

from collections.abc import Callable

from bus.bus_features import AnswerEnd, FrameAnswer
from bus.cia301.slave import SlaveNode

__all__ = ["AnsweringNode"]


class AnsweringNode(SlaveNode):
    """A :class:`SlaveNode` whose plain io frames its transport may answer (module docstring).

    :ivar answered: io frames read and answered in the transport's loop (not counting one that
        its callback handled the Python way)
    """

    answered: int = 0

    def answering_now(self) -> bool:
        """The last wake-up left the service nothing to do and no fieldbus frame waits read ahead:
        the answer loop may wait (it returns at a fieldbus frame that comes)."""
        return self._settled and self._fds is not None and not self._fieldbus_pending()

    def step_answering(
        self,
        answer: Callable[..., tuple[int, AnswerEnd]],
        rx: tuple[int, int, int],
        on_frame: FrameAnswer,
        max_wait_s: float,
    ) -> int:
        """One :meth:`SlaveNode.step` after the frames ``rx`` = (first id, ids, data bytes) the loop
        ``answer`` handed to ``on_frame`` until the service's deadline (at most ``max_wait_s``
        [s]). After a frame ``on_frame`` handled itself (it returned None) the service looks at
        once, unless :meth:`stopped_plain` says that frame left it nothing to do.

        :return: frames received
        """
        assert self._fds is not None
        deadline = min(self._serve_by_s, self._clock() + max_wait_s)
        n, why = answer(*rx, on_frame, deadline, self._fds[0])
        self.ran_at(self._clock(), deadline)  # the loop runs its frames at once: only a stall makes it this late
        self.frames_in += n
        if why != AnswerEnd.STOPPED:
            self.answered += n
            return n + SlaveNode.step(self, max_wait_s)
        self.answered += n - 1  # the last one went the Python way
        if self.stopped_plain():
            return n
        return n + SlaveNode.step(self, 0.0)  # what waits, then the service

    def stopped_plain(self) -> bool:
        """After the loop stopped at a frame its callback handled itself: True when that frame left
        the service nothing to do (default: it always looks)."""
        return False
