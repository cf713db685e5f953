"""Which process wrote a record, and whether that process still runs.

This module owns :func:`process_identity` (a record's ``writer``: pid, the process's start time in
clock ticks since boot, the boot's id, the host name) and :func:`identity_alive`.  A pid alone is
not an identity: pids are reused, and a machine that rebooted has none of the old processes; the
start time (``/proc/<pid>/stat`` field 22) and the boot id (``/proc/sys/kernel/random/boot_id``)
make it one, on the machine that wrote it.

A run's ``summary.json`` carries its writer (:func:`host.experiment.loop_state.new_summary`): a
summary whose ``end_reason`` is still empty and whose writer is gone was left by a process killed
with nobody to say so (SIGKILL, the OOM killer, a crash) — readers report it as ``writer_lost``
(:attr:`ilcrig.Results.end_reason`), not as a run still going.

May import: the standard library only.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

__all__ = ["identity_alive", "process_identity"]

_BOOT_ID = Path("/proc/sys/kernel/random/boot_id")


def _start_ticks(pid: int) -> int | None:
    """Process ``pid``'s start time, clock ticks after boot (None: no such process, or no /proc)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    try:
        return int(fields[19])  # field 22 of stat(5); fields[0] is field 3
    except (IndexError, ValueError):
        return None


def _boot_id() -> str | None:
    try:
        return _BOOT_ID.read_text().strip()
    except OSError:
        return None


def process_identity(pid: int | None = None) -> dict[str, Any]:
    """The identity of process ``pid`` (default: this one): ``pid``, ``start_ticks``, ``boot_id``,
    ``host`` (the last three None where the system does not tell)."""
    pid = os.getpid() if pid is None else pid
    return {"pid": pid, "start_ticks": _start_ticks(pid), "boot_id": _boot_id(), "host": socket.gethostname()}


def identity_alive(identity: Any) -> bool | None:
    """Whether the process ``identity`` (a :func:`process_identity` record) still runs: False when it
    is gone (this machine rebooted since, or no process has its pid and start time), True when it
    runs, None when this machine cannot tell (another host, no /proc, not a record)."""
    if not isinstance(identity, dict) or not isinstance(identity.get("pid"), int):
        return None
    if identity.get("host") != socket.gethostname():
        return None
    boot, then = _boot_id(), identity.get("boot_id")
    if boot is None or then is None or identity.get("start_ticks") is None:
        return None
    if boot != then:
        return False
    state = _state(identity["pid"])
    if state is None or state in ("Z", "X"):
        return False  # gone, or ended and not yet reaped
    return _start_ticks(identity["pid"]) == identity["start_ticks"]


def _state(pid: int) -> str | None:
    """The state letter of process ``pid`` (``R``, ``S``, ``Z`` …; None: no such process)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None
