"""Timing of the clock master's ticks: real-time pacing and what it achieved.

This module owns :class:`TickPacer`, the bookkeeping of one trial's ticks on the wall clock of the
plant (the lockstep clock master, :mod:`plant.plant_node`): when tick n is due (t0 + n·Ts when paced),
how late each tick started, which ticks missed their deadline (completed after the start of the
next period: the first :data:`MISSES_KEPT` of them with their times), and the trial's duration.
It never reads a clock itself: the caller passes the times (s, any monotonic scale), so the
statistics are exact and testable with a scripted clock. Wall-clock time never enters the model:
pacing only delays when a tick's frames go out.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["TickPacer", "PacingResult", "MissedTick", "MISSES_KEPT"]

#: how many missed ticks a trial keeps with their times (the count goes on beyond): as many as 0x2441
#: lists (``bus.plant_objects.DEADLINE_MISSES_KEPT``; plant/ does not import bus/, a test keeps them equal)
MISSES_KEPT: int = 64


@dataclass(frozen=True)
class MissedTick:
    """One tick that missed its deadline (times in s on the pacer's clock).

    :ivar tick: the tick's index in the trial
    :ivar started_late_s: start(n) − (t0 + n·Ts): how late its frames went out
    :ivar overrun_s: completion − (t0 + (n + 1)·Ts): how far past its deadline it completed
    """

    tick: int
    started_late_s: float
    overrun_s: float


@dataclass(frozen=True)
class PacingResult:
    """What one trial achieved (times in s).

    :ivar paced: ticks were held back to t0 + n·Ts
    :ivar ticks: ticks completed
    :ivar duration_s: from t0 to the completion of the last tick
    :ivar deadline_misses: ticks completed after t0 + (n + 1)·Ts (paced only, else 0)
    :ivar lateness_p50_s, lateness_p99_s, lateness_max_s: of start(n) − (t0 + n·Ts) over the
        started ticks (paced only, else 0)
    :ivar t0_s: when tick 0 was due (paced) or started (on the pacer's clock)
    :ivar missed: the first :data:`MISSES_KEPT` deadline misses, in tick order
    """

    paced: bool
    ticks: int
    duration_s: float
    deadline_misses: int
    lateness_p50_s: float
    lateness_p99_s: float
    lateness_max_s: float
    t0_s: float = 0.0
    missed: tuple[MissedTick, ...] = ()


class TickPacer:
    """One trial's tick timing (see the module docstring).

    :param ts_s: control period, s
    :param n_ticks: ticks of the trial
    :param paced: hold tick n back until t0 + n·Ts (real-time mode)
    :param t0_s: the trial's start time, s (tick 0 is due then)
    """

    def __init__(self, ts_s: float, n_ticks: int, paced: bool, t0_s: float) -> None:
        if not ts_s > 0:
            raise ValueError(f"ts_s must be > 0, got {ts_s!r}")
        self.ts_s = float(ts_s)
        self.paced = bool(paced)
        self.t0_s = float(t0_s)
        self._lateness_s = np.zeros(max(int(n_ticks), 0), dtype=np.float64)
        self._started = 0
        self._completed = 0
        self._last_done_s = self.t0_s
        self.deadline_misses = 0
        self._missed: list[MissedTick] = []

    def due_s(self, n: int) -> float:
        """When tick ``n`` is due: t0 + n·Ts (when paced; the caller sends at once otherwise)."""
        return self.t0_s + n * self.ts_s

    def started(self, n: int, now_s: float) -> None:
        """Tick ``n``'s frames went out at ``now_s``."""
        if self.paced and n < len(self._lateness_s):
            self._lateness_s[n] = max(0.0, now_s - self.due_s(n))
        self._started = max(self._started, n + 1)

    def completed(self, n: int, now_s: float) -> None:
        """Tick ``n`` completed (all answers in, plant stepped) at ``now_s``."""
        if self.paced and now_s > self.due_s(n + 1):
            self.deadline_misses += 1
            if len(self._missed) < MISSES_KEPT:
                started_late = float(self._lateness_s[n]) if n < len(self._lateness_s) else 0.0
                self._missed.append(MissedTick(n, started_late, now_s - self.due_s(n + 1)))
        self._completed = max(self._completed, n + 1)
        self._last_done_s = now_s

    def result(self) -> PacingResult:
        """The statistics of the ticks so far."""
        late = self._lateness_s[: self._started] if self.paced else self._lateness_s[:0]
        p50, p99 = (float(v) for v in np.percentile(late, [50, 99])) if late.size else (0.0, 0.0)
        return PacingResult(
            paced=self.paced,
            ticks=self._completed,
            duration_s=max(0.0, self._last_done_s - self.t0_s),
            deadline_misses=self.deadline_misses,
            lateness_p50_s=p50,
            lateness_p99_s=p99,
            lateness_max_s=float(late.max()) if late.size else 0.0,
            t0_s=self.t0_s,
            missed=tuple(self._missed),
        )
