"""Real time without privileges: what a real-time run asks of Linux's fair scheduler.

This module owns the scheduling of a real-time run (``ilcrig run --realtime``) when its lockstep
processes (the hub, the plant, the drives) cannot be put in ``SCHED_FIFO`` — every user without
``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO``, or ``--rt-priority 0``: :func:`apply_fair_scheduling`
(the lockstep processes), :func:`host_policy` (the host, which is no part of a tick in table
playback) and the helpers below. Everything here is what any process may do to its own user's
processes; nothing needs a capability, and a capability the caller happens to have (root) is not
used: a run as root with ``--rt-priority 0`` is scheduled as an ordinary user's would be.

A paced tick is a chain of wake-ups (plant → hub → four drives → hub → plant) that needs about half
of one CPU at 1 kHz (a quarter of this 2-core machine); what makes a tick late in normal scheduling is not a lack of CPU time
but a woken lockstep process waiting for the CPU its wake-up went to. The mechanisms, each named
in the run's scheduling record (``bench.timing.scheduling``):

``slice``
    Every thread of the lockstep processes gets a scheduler slice of :data:`LOCKSTEP_SLICE_NS`
    (``sched_setattr``: ``SCHED_OTHER`` with ``sched_runtime``, Linux >= 6.12, EEVDF). A woken task
    with a shorter slice than the one running preempts it at once (the kernel's
    ``PREEMPT_SHORT``) instead of waiting up to the running task's slice (0.7 ms × (1 + log2
    CPUs) by default) — the same CPU share, granted sooner. Threads started later inherit it.
``nice``
    The lockstep processes' nice value and the nice of their autogroup are lowered as far as
    ``RLIMIT_NICE`` permits (at most to :data:`LOCKSTEP_NICE`); with the usual limit 0 that is not
    at all, and the record says so.
``host``
    The host is started in ``SCHED_BATCH`` (:func:`host_policy`): the same CPU share, but its
    wake-ups (channel monitors, heartbeats, status polls) never preempt a lockstep process. Not
    with ``--ff-transport pdo``, where the host's SYNC producer is part of every tick.

Autogroups
    With ``CONFIG_SCHED_AUTOGROUP`` (most distributions) every session is a scheduling group of
    its own: the roles of ``ilcrig run`` are each a session, and nice values count only inside
    a group, while between groups the group's nice counts (``/proc/PID/autogroup``). Raising it
    (a lower share) is open to anyone, lowering it below 0 only within ``RLIMIT_NICE``; the kernel
    refuses a change less than 100 ms after the last one by an unprivileged process (system-wide),
    so :func:`set_autogroup_nice` retries for a while.

Leaving a mechanism out (diagnostics, ``benchmarks/rt_compare.py``): the environment variable
``ILCRIG_RT_WITHOUT`` lists the names to leave out, comma-separated
(:func:`bus.lockstep_process.mechanisms_left_out`: ``slice``, ``nice``, ``host`` here, and those
of :mod:`host.rig.idle_poll` and the roles).
"""

from __future__ import annotations

import ctypes
import errno
import logging
import os
import platform
import resource
import struct
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from bus.lockstep_process import WITHOUT_ENV

logger = logging.getLogger(__name__)

__all__ = [
    "LOCKSTEP_NICE",
    "LOCKSTEP_SLICE_NS",
    "apply_fair_scheduling",
    "host_policy",
    "lowest_nice_permitted",
    "set_autogroup_nice",
    "set_fair_slice",
    "threads",
]

#: the scheduler slice of the lockstep threads, ns (the kernel's minimum: 0.1 ms)
LOCKSTEP_SLICE_NS: int = 100_000
#: the nice value asked for the lockstep processes where RLIMIT_NICE permits it
LOCKSTEP_NICE: int = -10

#: sched_setattr system call numbers (Linux, per architecture; sched_getattr is the next one)
_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "arm64": 274, "riscv64": 274, "ppc64le": 355, "s390x": 345}
#: struct sched_attr (linux/sched/types.h), version 1: size, policy, flags, nice, priority, runtime,
#: deadline, period, util_min, util_max
_SCHED_ATTR = struct.Struct("IIQiIQQQII")
_SCHED_OTHER = 0
#: autogroup nice changes: retries after EAGAIN (the kernel's 100 ms rate limit), s
_AUTOGROUP_RETRY_S = 0.11
_AUTOGROUP_TRIES = 12


def threads(pid: int) -> list[int]:
    """The thread ids of process ``pid`` (just ``pid`` where /proc does not list them)."""
    try:
        return sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return [pid]


def _sched_setattr(tid: int, policy: int, nice: int, runtime_ns: int) -> None:
    """``sched_setattr(tid, {policy, nice, sched_runtime})``; raises OSError (ENOSYS where the
    system call is unknown here)."""
    number = _SYS_SCHED_SETATTR.get(platform.machine()) if sys.platform.startswith("linux") else None
    if number is None:
        raise OSError(errno.ENOSYS, "no sched_setattr on this system")
    libc = ctypes.CDLL(None, use_errno=True)
    attr = ctypes.create_string_buffer(
        _SCHED_ATTR.pack(_SCHED_ATTR.size, policy, 0, nice, 0, runtime_ns, 0, 0, 0, 0), _SCHED_ATTR.size
    )
    if libc.syscall(ctypes.c_long(number), ctypes.c_int(tid), attr, ctypes.c_uint(0)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def _sched_getattr_runtime(tid: int) -> int:
    """``sched_getattr(tid).sched_runtime``: a fair task's slice, ns (0 before Linux 6.12)."""
    number = _SYS_SCHED_SETATTR.get(platform.machine())
    if number is None or not sys.platform.startswith("linux"):
        raise OSError(errno.ENOSYS, "no sched_getattr on this system")
    libc = ctypes.CDLL(None, use_errno=True)
    attr = ctypes.create_string_buffer(_SCHED_ATTR.size)
    if libc.syscall(ctypes.c_long(number + 1), ctypes.c_int(tid), attr, ctypes.c_uint(_SCHED_ATTR.size), ctypes.c_uint(0)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))
    return int(_SCHED_ATTR.unpack(attr.raw)[5])


def set_fair_slice(tid: int, slice_ns: int, nice: int | None = None) -> None:
    """Thread ``tid`` in ``SCHED_OTHER`` with a scheduler slice of ``slice_ns`` (0: the kernel's
    default) and nice ``nice`` (None: unchanged). Raises OSError, also where the kernel accepts the
    call but keeps no slice for a fair task (before Linux 6.12: it reads back 0)."""
    if nice is None:
        nice = os.getpriority(os.PRIO_PROCESS, tid)
    _sched_setattr(tid, _SCHED_OTHER, nice, slice_ns)
    if slice_ns and _sched_getattr_runtime(tid) != slice_ns:
        raise OSError(errno.EOPNOTSUPP, "the kernel keeps no scheduler slice for a fair task")


def lowest_nice_permitted() -> int:
    """The lowest nice value ``RLIMIT_NICE`` lets this process set (20 − the soft limit; 20 with
    the usual limit 0: no value below the current one). Capabilities are not considered."""
    soft = resource.getrlimit(resource.RLIMIT_NICE)[0] if hasattr(resource, "RLIMIT_NICE") else 0
    if soft == resource.RLIM_INFINITY:
        return -20
    return max(-20, 20 - int(soft))


def autogroups_enabled() -> bool:
    """Whether the kernel groups the tasks of a session for scheduling (``sched_autogroup_enabled``)."""
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return False


def set_autogroup_nice(pid: int, nice: int) -> None:
    """The nice value of ``pid``'s autogroup (its session's scheduling group), retrying while the
    kernel's rate limit refuses it (EAGAIN). Raises OSError."""
    fd = os.open(f"/proc/{pid}/autogroup", os.O_WRONLY)
    try:
        for attempt in range(_AUTOGROUP_TRIES):
            try:
                os.write(fd, str(int(nice)).encode())
                return
            except BlockingIOError:
                if attempt + 1 == _AUTOGROUP_TRIES:
                    raise
                time.sleep(_AUTOGROUP_RETRY_S)
    finally:
        os.close(fd)


def apply_fair_scheduling(pids: Mapping[str, int], without: frozenset[str] = frozenset()) -> dict[str, Any]:
    """The lockstep processes ``pids`` (role -> pid) in normal scheduling made as prompt as an
    unprivileged process may make them (module docstring): ``slice`` and ``nice`` unless named in
    ``without``.

    :return: for the scheduling record: ``{"slice_us": …}`` (or ``"slice": why not``) and
        ``{"nice": n}`` (or ``"nice": why not``)
    """
    out: dict[str, Any] = {}
    floor = lowest_nice_permitted()
    nice: int | None = None
    if "nice" in without:
        out["nice"] = f"left out ({WITHOUT_ENV})"
    elif floor >= 0:
        out["nice"] = f"0 (RLIMIT_NICE {resource.getrlimit(resource.RLIMIT_NICE)[0]} permits no lower value)"
    else:
        nice = max(floor, LOCKSTEP_NICE)
    slice_ns = 0 if "slice" in without else LOCKSTEP_SLICE_NS
    failed: str | None = None
    for pid in pids.values():
        for tid in threads(pid):
            try:
                if slice_ns or nice is not None:
                    set_fair_slice(tid, slice_ns, nice)
            except ProcessLookupError:
                continue
            except OSError as err:
                failed = failed or err.strerror or str(err)
        if nice is not None and autogroups_enabled():
            try:
                set_autogroup_nice(pid, nice)
            except OSError as err:
                logger.warning("cannot set the autogroup nice of %d: %s", pid, err)
    if "slice" in without:
        out["slice"] = f"left out ({WITHOUT_ENV})"
    elif failed is not None:
        out["slice"] = f"not available ({failed}; needs Linux >= 6.12)"
    else:
        out["slice_us"] = slice_ns / 1000
    if nice is not None:
        out["nice"] = nice
    logger.info("lockstep processes %s in normal scheduling: %s", ", ".join(pids), out)
    return out


def host_policy(in_tick: bool, without: frozenset[str] = frozenset()) -> dict[str, Any]:
    """How the host is to be scheduled (module docstring, ``host``): ``{"policy": "SCHED_BATCH"}``
    (the launcher starts it so, :func:`host.rig.processes.spawn`), or ``{"policy": "normal",
    "reason": …}``.

    :param in_tick: the host is part of every tick (``--ff-transport pdo``: its SYNC producer)
    """
    if "host" in without:
        return {"policy": "normal", "reason": f"left out ({WITHOUT_ENV})"}
    if in_tick:
        return {"policy": "normal", "reason": "its SYNC producer is part of every tick"}
    if not hasattr(os, "SCHED_BATCH"):
        return {"policy": "normal", "reason": "this system has no SCHED_BATCH"}
    return {"policy": "SCHED_BATCH"}
