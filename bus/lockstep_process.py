"""What a process on the tick's critical path does for itself: its heap, and how it waits.

This module owns :func:`freeze_heap`, called by the plant and drive roles after their warm-up
(numba kernels compiled, models built), just before their select loop starts;
:func:`numba_without_blas`, the warm-up's first kernel load without numba's BLAS probe;
:func:`spin_in_this_class`, whether the plant spins the last stretch of a paced wait; and
:func:`mechanisms_left_out`, the diagnostic switch of the real-time mechanisms
(``ILCRIG_RT_WITHOUT``, read here because both the roles and the launcher honour it).

Why
    CPython's cycle collector runs a full collection now and then (when enough objects have
    survived two younger collections). It looks at every container object of the process: a role
    holds 60,000–100,000 of them after importing numpy, numba, scipy and python-can, and a full
    collection holds the process for 20–60 ms — twenty to sixty missed 1 ms ticks, in any
    scheduling class. :func:`gc.freeze` moves every object alive at that moment to a permanent
    generation the collector never scans: a full collection afterwards looks only at what was
    created since (per tick: a few frames, freed by reference counting anyway) and takes
    microseconds. The frozen objects live as long as the process, which they do anyway.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping

logger = logging.getLogger(__name__)

__all__ = [
    "LONG_COLLECTION_S",
    "WITHOUT_ENV",
    "freeze_heap",
    "in_realtime_class",
    "mechanisms_left_out",
    "numba_without_blas",
    "spin_in_this_class",
    "watch_collections",
]

#: environment variable: real-time mechanisms to leave out, comma-separated (diagnostics:
#: ``benchmarks/rt_compare.py``; names in docs/timing.md §1)
WITHOUT_ENV: str = "ILCRIG_RT_WITHOUT"
#: a garbage collection longer than this is logged, s
LONG_COLLECTION_S: float = 1e-3


def mechanisms_left_out(environ: Mapping[str, str] | None = None) -> frozenset[str]:
    """The mechanism names listed in ``ILCRIG_RT_WITHOUT`` (empty: every mechanism in force)."""
    text = (os.environ if environ is None else environ).get(WITHOUT_ENV, "")
    return frozenset(w.strip() for w in text.split(",") if w.strip())


#: the module numba imports to find a BLAS when its CPU target first loads
BLAS_PROBE_MODULE: str = "scipy.linalg"


@contextlib.contextmanager
def numba_without_blas(role: str) -> Iterator[None]:
    """Load numba's CPU target (the first compile or cache load of a kernel, inside the block)
    without its BLAS probe.

    When numba's CPU target loads, ``numba.np.arraymath`` checks for a BLAS (for ``np.dot`` and
    ``np.linalg`` in compiled code) by importing ``scipy.linalg``: 0.3 s of CPU in each process,
    paid by every drive and the plant of every rig run while all of them start on the same CPUs.
    Their kernels use no BLAS (the drive's control period is integer arithmetic, the plant solves
    its 4 × 4 mass matrix with its own LU, ``plant._kernels.lu4_solve``). Inside the block
    ``scipy.linalg`` is marked absent (``None`` in :data:`sys.modules`), so the probe fails at once
    and numba records that it has no BLAS; afterwards the mark is removed and ``scipy.linalg``
    imports as usual, but a kernel compiled later in this process cannot call a BLAS function (numba
    says so when it compiles it). If ``scipy.linalg`` is already imported, or the probe has run, the
    block changes nothing.
    ``role`` names the process in the log line that says which it was."""
    probed = "numba.np.arraymath" in sys.modules  # the module whose import probes
    marked = BLAS_PROBE_MODULE not in sys.modules and not probed
    if marked:
        sys.modules[BLAS_PROBE_MODULE] = None  # type: ignore[assignment]  # the import system's "absent"
    try:
        yield
    finally:
        if marked and sys.modules.get(BLAS_PROBE_MODULE, 0) is None:
            del sys.modules[BLAS_PROBE_MODULE]
    if not marked:
        logger.debug("%s: numba's BLAS probe left as it was (it had run, or %s was imported)", role, BLAS_PROBE_MODULE)
    elif "numba.np.arraymath" in sys.modules:
        logger.debug("%s: numba's kernels loaded without its BLAS probe (%s not imported)", role, BLAS_PROBE_MODULE)


def freeze_heap(role: str) -> bool:
    """Move every object alive now out of the cycle collector's reach (module docstring), unless
    ``gc`` is left out (``ILCRIG_RT_WITHOUT``), and log every collection from now on that holds the
    process longer than :data:`LONG_COLLECTION_S` (:func:`watch_collections`). Returns whether it froze."""
    watch_collections(role)
    if "gc" in mechanisms_left_out():
        logger.info("%s: heap not frozen (%s)", role, WITHOUT_ENV)
        return False
    gc.freeze()
    logger.info("%s: %d objects frozen out of the cycle collector's reach", role, gc.get_freeze_count())
    return True


def watch_collections(role: str, longer_than_s: float | None = None) -> Callable[[str, dict[str, int]], None]:
    """Log (INFO, in the role's log) every garbage collection of this process that takes longer than
    ``longer_than_s`` (default :data:`LONG_COLLECTION_S`): a stall of the process no scheduler trace
    names. Returns the callback (in :data:`gc.callbacks`)."""
    limit = LONG_COLLECTION_S if longer_than_s is None else longer_than_s
    started = [0.0]

    def callback(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
            return
        took = time.perf_counter() - started[0]
        if took > limit:
            logger.info(
                "%s: garbage collection of generation %d took %.1f ms (%d objects collected)",
                role,
                info.get("generation", -1),
                took * 1e3,
                info.get("collected", 0),
            )

    gc.callbacks.append(callback)
    return callback


def in_realtime_class() -> bool:
    """Whether this thread runs in a real-time scheduling class (``SCHED_FIFO``, ``SCHED_RR``)."""
    if not hasattr(os, "sched_getscheduler"):
        return False
    return os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)


def spin_in_this_class() -> bool:
    """Whether a process that waits for a moment should spin the last stretch of the wait: only in
    a real-time class (:func:`in_realtime_class`), where nothing of lower priority can take the
    CPU meanwhile and the spinning costs no share; in normal scheduling it sleeps until the moment
    (its 1 µs timer slack, :mod:`bus.timer_slack`), unless ``sleep-wait`` is left out
    (``ILCRIG_RT_WITHOUT``)."""
    return in_realtime_class() or "sleep-wait" in mechanisms_left_out()
