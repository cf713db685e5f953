"""What the launcher reads in the roles' logs: the lines of a drive's log that say whether its
torque came on and its safe-state records (:mod:`bus.safe_state`), for the summary's ``safe_state``
evidence (:meth:`host.rig.run_outcome.RunOutcome.drive_evidence`).

May import: ``bus``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["LOG_SEARCH_BYTES", "log_started", "safe_state_lines"]

#: how much of a drive's log is searched for its SAFE-STATE records (from the end), bytes
LOG_SEARCH_BYTES = 8 << 20


def safe_state_lines(path: Path | None) -> list[str]:
    """The lines of a role's log that carry a safe-state record or say torque came on, in order
    (the last :data:`LOG_SEARCH_BYTES` of it; a drive that faulted may log much after its record)."""
    from bus.safe_state import TAG, TORQUE_ON_TAG

    if path is None:
        return []
    try:
        with open(path, "rb") as fh:
            end = fh.seek(0, 2)
            fh.seek(max(0, end - LOG_SEARCH_BYTES))
            data = fh.read()
    except OSError:
        return []
    marks = (TAG.encode(), TORQUE_ON_TAG.encode())
    return [ln.decode(errors="replace") for ln in data.splitlines() if marks[0] in ln or marks[1] in ln]


def log_started(path: Path | None) -> bool:
    """The role's log holds lines (it ran and logged: its records, if any, would be there)."""
    try:
        return path is not None and path.stat().st_size > 0
    except OSError:
        return False
