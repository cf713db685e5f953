"""Idle CPUs that do not halt during a real-time session: a PM QoS CPU latency request.

This module owns :class:`CpuLatencyRequest` and :func:`request_cpu_latency`, which the launch core
(:mod:`host.rig.launch_core`) holds for the length of ``ilcrig run --realtime`` and ``ilcrig robot
--realtime``, in ``SCHED_FIFO`` and in normal scheduling alike.

Why
    A period of the rig or the robot is a chain of wake-ups, and between them every process sleeps;
    a CPU with nothing to run halts. In this VM (``haltpoll.guest_halt_poll_ns=0``) a halted CPU
    leaves the guest, and a process woken on it runs slower as well as later: the drive's code of
    one robot period (``benchmarks/wake_cost.py``: in one process, without sockets) takes ~25 µs
    in a loop that never sleeps and 74–90 µs when the process sleeps 2 ms before each period, but
    35–48 µs after the same sleeps with idle CPUs polling (docs/benchmarks.md, "What sleeping
    between periods costs").

How
    Linux's PM QoS interface (``Documentation/power/pm_qos_interface.rst``): a process that opens
    ``/dev/cpu_dma_latency`` and writes a 32-bit latency in µs has a request in force for as long as
    it holds the file open; 0 µs allows an idle CPU only the states that need no time to leave — the
    polling loop (cpuidle state ``POLL``). Linux drops the request when the file is closed, also
    when the process holding it dies by any signal: nothing outlives the session. It is what
    ``cyclictest`` of rt-tests does by default.

Who may
    The file is root's (mode 0600): an ordinary user does not get it, and the scheduling record
    says why (``cpu_latency.reason``). ``--no-idle-poll`` leaves it out, as it leaves out the
    ``SCHED_IDLE`` loops (:mod:`host.rig.idle_poll`), and so does ``ILCRIG_RT_WITHOUT=cpu-latency``.

Cost
    An idle CPU spins in the kernel for the session (power, heat; a hypervisor sees a busy virtual
    CPU). Unlike the ``SCHED_IDLE`` loops it is no task: the scheduler never weighs it against a
    woken process, so it is used beside normal scheduling too.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Set
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["CPU_LATENCY_PATH", "CpuLatencyRequest", "cpu_latency_target_us", "request_cpu_latency"]

#: Linux's PM QoS CPU latency device
CPU_LATENCY_PATH: str = "/dev/cpu_dma_latency"
#: the mechanism's name in ``ILCRIG_RT_WITHOUT`` (docs/timing.md §1)
WITHOUT_NAME: str = "cpu-latency"


class CpuLatencyRequest:
    """One PM QoS CPU latency request, in force while the file stays open (module docstring).

    :param latency_us: the longest wake-up latency allowed to an idle CPU, µs (0: polling only)
    :param path: the PM QoS device
    :raises OSError: the device cannot be opened or written (e.g. not root)
    """

    def __init__(self, latency_us: int = 0, path: str = CPU_LATENCY_PATH) -> None:
        if not 0 <= latency_us <= 0x7FFFFFFF:
            raise ValueError(f"latency_us must be 0..2**31-1, got {latency_us!r}")
        self.latency_us = latency_us
        self.path = path
        self._fd: int | None = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
        try:
            os.write(self._fd, struct.pack("=i", latency_us))  # the kernel's ABI: a native s32
        except OSError:
            self.release()
            raise
        logger.info("PM QoS: idle CPUs allowed %d µs of wake-up latency (%s held open)", latency_us, path)

    @property
    def held(self) -> bool:
        """True while the request is in force."""
        return self._fd is not None

    def release(self) -> None:
        """Withdraw the request (close the file); again does nothing."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def cpu_latency_target_us(path: str = CPU_LATENCY_PATH) -> int:
    """The CPU latency every request in force allows together, µs: the smallest of them, Linux's
    default 2,000,000,000 (2,000 s) when none is (read from the PM QoS device).

    :raises OSError: the device cannot be read (e.g. not root)
    """
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        return int(struct.unpack("=i", os.read(fd, 4))[0])
    finally:
        os.close(fd)


def request_cpu_latency(
    without: Set[str], no_idle_poll: bool, path: str = CPU_LATENCY_PATH
) -> tuple[CpuLatencyRequest | None, dict[str, Any]]:
    """The request of a real-time session, unless left out: (the request or None, the record for the
    summary's scheduling: ``{"latency_us": 0}`` or ``{"reason": ...}``)."""
    if no_idle_poll:
        return None, {"reason": "--no-idle-poll"}
    if WITHOUT_NAME in without:
        return None, {"reason": f"ILCRIG_RT_WITHOUT={WITHOUT_NAME}"}
    if not os.path.exists(path):
        return None, {"reason": f"this system has no {path}"}
    try:
        request = CpuLatencyRequest(0, path)
    except OSError as err:
        reason = "not permitted (root's)" if isinstance(err, PermissionError) else f"cannot write {path} ({err.strerror or err})"
        logger.info("no PM QoS request: %s", reason)
        return None, {"reason": reason}
    return request, {"latency_us": request.latency_us}
