"""Test helper: :class:`ManualClock`, a node clock (``() -> float``, s) that only the test moves,
for nodes the test steps itself (heartbeats and timeouts fall due exactly when it says)."""

from __future__ import annotations


class ManualClock:
    """A node clock that only the test moves: ``now`` is the time it returns, s."""

    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now
