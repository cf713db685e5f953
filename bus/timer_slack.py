"""Fine timer slack: timed waits of this process wake when asked, not up to 50 µs later.

This module owns :func:`fine_timer_slack`, used by the processes that wait for a moment in time
rather than for a frame: the plant when it paces its ticks to the wall clock (``--realtime``) and
the hub when it delivers frames in bus time (``--bus-time``).
"""

from __future__ import annotations

import ctypes
import logging
import sys

logger = logging.getLogger(__name__)

__all__ = ["FINE_TIMER_SLACK_NS", "fine_timer_slack"]

#: prctl option: the process's timer slack, ns (Linux)
_PR_SET_TIMERSLACK = 29
#: the timer slack of a process that waits for a moment in time, ns
FINE_TIMER_SLACK_NS: int = 1000


def fine_timer_slack(slack_ns: int = FINE_TIMER_SLACK_NS) -> None:
    """Make the kernel wake this process's timed waits within ``slack_ns`` (default slack: 50 µs);
    nothing happens where prctl is unavailable."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) != 0:
            logger.debug("prctl(PR_SET_TIMERSLACK) failed: errno %d", ctypes.get_errno())
    except (OSError, AttributeError):
        logger.debug("no prctl: default timer slack")
