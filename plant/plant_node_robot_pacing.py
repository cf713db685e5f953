"""The robot's real-time schedule (:class:`RobotPacing`): when each period of the robot mode is due
on the wall clock, and what the schedule achieved (late SYNCs, missing SYNCs, deadline misses, the
lateness histogram).  Used by :class:`plant.plant_node_robot.RobotLoop`.

Real time (mode 2): periods are also paced to the wall clock — period n (counted from the first
SYNC, t0 its arrival) does not start before t0 + n·Ts (its encoder frames are held, as in a paced
trial); the schedule locks onto the master's phase as seen with the least transport delay, as a
drive locks onto SYNC (:class:`RobotPacing`: a SYNC up to Ts/4 early moves t0 to it; eight in a row
more than Ts/4 off on one side move it to the earliest of them); a SYNC later than
t0 + n·Ts + Ts/2 is late, one that comes a whole period or more after its time counts the periods
in between as missing (the robot waits for its drives: it does not move without a SYNC) and starts
the schedule afresh; a period that started late or completed after the next one's time is a late
period (0x2450:13).

May import: ``numpy`` only (a part of the plant node: it could import ``bus``, it needs nothing of it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["RobotPacing"]


class RobotPacing:
    """Real time: the schedule t0 + n·Ts of the robot's periods and what it achieved (times in s on
    the plant's monotonic clock, passed in by the caller: exact and testable with a scripted clock).

    The schedule locks onto the master's phase as its SYNCs are seen with the least transport
    delay: a SYNC up to :attr:`PHASE_S` of a period before its time moves t0 to it; one that comes
    a whole period or more after its time counts the periods in between as missing (the schedule
    goes on past them, its phase kept); and :attr:`RELOCK` SYNCs in a row more than :attr:`PHASE_S`
    off the schedule on the same side (the master's phase has moved: it paused and came back, or
    its clock stepped) move t0 to the earliest of them.  A period is *late* when it started more than Ts/2 after its time
    (its SYNC was late) or completed after the next period's time (a deadline miss); each late
    period counts once.  The lateness of every period's start goes into a histogram of
    :attr:`BIN_S` bins (its percentiles over the whole session)."""

    #: the lock window, a fraction of Ts on each side of the schedule
    PHASE_S = 0.25
    #: SYNCs in a row outside the lock window on one side that move the schedule
    RELOCK = 8
    #: times closer than this are the same (t0 + n·Ts is a sum of floats), s
    EPS_S = 1e-9
    #: lateness histogram: bin width, s, and bins (the last one holds everything beyond)
    BIN_S = 10e-6
    BINS = 2001

    def __init__(self, ts_s: float) -> None:
        self.ts_s = ts_s
        self.t0_s: float | None = None
        self.n = 0  # the period in progress (or the next one), counted from t0
        self.late = 0
        self.missing = 0
        self.deadline_misses = 0
        self.late_periods = 0
        self.relocks = 0
        self.lateness_max_s = 0.0
        self.lateness = np.zeros(self.BINS, dtype=np.int64)
        self.periods = 0
        self._late_start = False
        self._run_side = 0  # +1 later than the window, -1 earlier, 0 inside it
        self._run = 0
        self._run_min_s = 0.0

    def _due(self, n: int) -> float:
        assert self.t0_s is not None
        return self.t0_s + n * self.ts_s

    def schedule(self, arrival_s: float) -> tuple[float, bool]:
        """The next period's SYNC arrived at ``arrival_s``: (when the period is due, was it late)."""
        ts = self.ts_s
        t0 = arrival_s if self.t0_s is None else self.t0_s
        behind = arrival_s - (t0 + self.n * ts)
        if behind + self.EPS_S >= ts:  # whole periods without a SYNC: the schedule goes on past them
            skipped = int((behind + self.EPS_S) // ts)
            self.missing += skipped
            self.n += skipped
            behind -= skipped * ts
        window = self.PHASE_S * ts
        side = 1 if behind > window else -1 if behind < -window else 0
        if side == 0:
            self._run_side = self._run = 0
            if behind < 0.0:  # the master's phase, seen with less delay: follow it
                t0 += behind
                behind = 0.0
        else:
            if side != self._run_side:
                self._run_side, self._run, self._run_min_s = side, 0, behind
            self._run += 1
            self._run_min_s = min(self._run_min_s, behind)
            if self._run >= self.RELOCK:  # the master's phase has moved: lock onto it again
                t0 += self._run_min_s
                behind -= self._run_min_s
                self.relocks += 1
                self._run_side = self._run = 0
        self.t0_s = t0
        late = behind > 0.5 * ts
        if late:
            self.late += 1
        self._late_start = late
        return t0 + self.n * ts, late

    def started(self, now_s: float) -> None:
        if self.t0_s is None:
            return
        late = now_s - self._due(self.n)
        if late > 0.0:
            self.lateness_max_s = max(self.lateness_max_s, late)
            self.lateness[min(int(late / self.BIN_S), self.BINS - 1)] += 1
        else:
            self.lateness[0] += 1

    def completed(self, now_s: float) -> None:
        if self.t0_s is None:
            return
        missed = now_s > self._due(self.n + 1)
        if missed:
            self.deadline_misses += 1
        if missed or self._late_start:
            self.late_periods += 1
        self._late_start = False
        self.n += 1
        self.periods += 1

    def percentile_s(self, q: float) -> float:
        """The ``q``-th percentile of the periods' lateness, s (upper edge of its bin)."""
        total = int(self.lateness.sum())
        if not total:
            return 0.0
        k = int(np.searchsorted(np.cumsum(self.lateness), q / 100.0 * total))
        return min(k + 1, self.BINS) * self.BIN_S if k else 0.0

    def info(self) -> dict[str, Any]:
        """The real-time figures so far (lateness of a period's start after its time, µs)."""
        return {
            "late_syncs": self.late,
            "missing_syncs": self.missing,
            "deadline_misses": self.deadline_misses,
            "late_periods": self.late_periods,
            "relocks": self.relocks,
            "lateness_p50_us": 1e6 * self.percentile_s(50),
            "lateness_p99_us": 1e6 * self.percentile_s(99),
            "lateness_max_us": 1e6 * self.lateness_max_s,
        }
