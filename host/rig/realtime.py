"""Wall-clock timing of the rig's trials as the plant measured them: real-time statistics.

This module owns how the per-trial timing of the test-bench node (0x2440,
:class:`bus.bench_objects.TrialTiming`) becomes the run's figures in ``summary.json``
(:func:`timing_summary`) and on the console (:func:`timing_line`): in real-time mode
(``ilcrig run --realtime``) the deadline misses, the tick lateness p50 / p99 / max and the
achieved rate, and whether the run kept up; in lockstep mode the emulator throughput (ticks per
second of wall time inside the trials). Wall-clock figures are diagnostics: they depend on the
machine and never on or in the model.
"""

from __future__ import annotations

import logging
import statistics
from collections.abc import Sequence
from typing import Any

from bus.bench_objects import TrialTiming

logger = logging.getLogger(__name__)

__all__ = ["timing_summary", "timing_line"]


def timing_summary(timings: Sequence[TrialTiming], ts_s: float, realtime: bool) -> dict[str, Any]:
    """The run's timing figures from the trials' :class:`TrialTiming` (see the module docstring).

    Over several trials: lateness p50 is the median of the trials' medians, p99 the worst trial's
    p99, max the worst tick; the achieved rate is all ticks over the sum of the trials' durations.
    """
    ticks = sum(t.ticks for t in timings)
    duration_s = sum(t.duration_us for t in timings) * 1e-6
    rate = ticks / duration_s if duration_s > 0 else 0.0
    out: dict[str, Any] = {
        "mode": "realtime" if realtime else "lockstep",
        "basis": "wall clock of the plant (the clock master), from the start of a trial to its last tick; "
                 "diagnostics: depends on the machine, never on the model",
        "control_period_s": ts_s,
        "trials": len(timings),
        "ticks": ticks,
        "duration_s": duration_s,
        "achieved_ticks_per_s": rate,
        "real_time_factor": rate * ts_s,
        "per_trial": [
            {"ticks": t.ticks, "duration_s": t.duration_us * 1e-6, "ticks_per_s": t.ticks_per_s,
             "deadline_misses": t.deadline_misses, "lateness_p50_s": t.lateness_p50_us * 1e-6,
             "lateness_p99_s": t.lateness_p99_us * 1e-6, "lateness_max_s": t.lateness_max_us * 1e-6}
            for t in timings
        ],
    }
    if realtime:
        misses = sum(t.deadline_misses for t in timings)
        late_max_s = max((t.lateness_max_us for t in timings), default=0) * 1e-6
        out |= {
            "deadline_misses": misses,
            "deadline_miss_percent": 100.0 * misses / ticks if ticks else 0.0,
            "lateness_p50_s": statistics.median(t.lateness_p50_us for t in timings) * 1e-6 if timings else 0.0,
            "lateness_p99_s": max((t.lateness_p99_us for t in timings), default=0) * 1e-6,
            "lateness_max_s": late_max_s,
            "kept_up": bool(timings) and misses == 0 and late_max_s < ts_s,
        }
    return out


def timing_line(timing: dict[str, Any]) -> str:
    """One console line of :func:`timing_summary`'s figures."""
    rate = timing["achieved_ticks_per_s"]
    ts_ms = timing["control_period_s"] * 1e3
    if timing["mode"] != "realtime":
        return (f"emulator throughput (lockstep, wall clock): {rate:,.0f} ticks/s inside the trials "
                f"({timing['real_time_factor']:.2f}x real time at Ts = {ts_ms:g} ms)")
    late = (f"tick lateness p50 {timing['lateness_p50_s'] * 1e3:.3f} ms, p99 {timing['lateness_p99_s'] * 1e3:.3f} ms, "
            f"max {timing['lateness_max_s'] * 1e3:.3f} ms")
    if timing["kept_up"]:
        return (f"real time: kept up, {timing['ticks']} ticks paced at Ts = {ts_ms:g} ms, 0 deadline misses, {late} "
                f"(no tick later than one period); achieved {rate:,.1f} ticks/s")
    return (f"real time: could NOT keep up at Ts = {ts_ms:g} ms: {timing['deadline_misses']} of {timing['ticks']} ticks "
            f"missed their deadline ({timing['deadline_miss_percent']:.1f} %), {late}; the rig held "
            f"{rate:,.1f} ticks/s ({timing['real_time_factor']:.2f}x real time)")
