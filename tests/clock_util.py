"""Test helpers of time: :class:`ManualClock`, a node clock (``() -> float``, s) that only the test
moves, for nodes the test steps itself (heartbeats and timeouts fall due exactly when it says);
:func:`wait_for`, polling a condition on the real clock until it holds or a timeout passes;
:data:`SDO_RESPONSE_S`, the SDO wait of the tests' masters."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from bus.units import timeout_scale

#: how long a python-canopen master of the tests waits for an SDO answer, s (canopen's own 0.3 s
#: is a real-time bound no lockstep node promises on a busy machine: the wait is an event's)
SDO_RESPONSE_S = 5.0 * timeout_scale()


class ManualClock:
    """A node clock that only the test moves: ``now`` is the time it returns, s."""

    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def wait_for(predicate: Callable[[], Any], timeout_s: float = 10.0) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` passed (the caller asserts the result)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return bool(predicate())
