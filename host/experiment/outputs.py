"""The run folder: checked before anything starts, space kept for the final results, failing writes.

This module owns

* :func:`check_out_dir` — ``--out`` refused before anything starts (one line naming the option):
  a path that exists and is not a folder, a folder that cannot be created or written, a filesystem
  without room for the final results;
* :class:`RunFolder` — the space reserve: a ballast file (``.ilcrig-reserve``,
  :func:`reserve_bytes` for the planned trials) taken when a run starts and given back when the
  disk is full (or at the end), so that ``summary.json`` with the fault and ``report.md`` can still
  be written after ``ENOSPC``;
* :class:`OutputError` / :class:`DiskFullError` — a failing write of the run's outputs as one
  fault (:func:`output_error`), and :func:`is_disk_full`;
* a test and fault-injection switch: :attr:`RunFolder.fail_writes_from_trial` makes the writes of
  the outputs fail with ``ENOSPC`` from that trial on (``--inject diskfull@K``).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import shutil
import time
from pathlib import Path

from bus.errors import IlcrigError

logger = logging.getLogger(__name__)

__all__ = [
    "DiskFullError",
    "OutputError",
    "OutFolderError",
    "RunFolder",
    "check_out_dir",
    "is_disk_full",
    "output_error",
    "reserve_bytes",
    "RESERVE_NAME",
]

#: the ballast file's name inside the run folder
RESERVE_NAME = ".ilcrig-reserve"
#: reserve for the final summary, report.md and convergence.png, bytes …
RESERVE_BASE_BYTES = 128 * 1024
#: … plus this much per planned trial (a trial's summary entry and report row)
RESERVE_PER_TRIAL_BYTES = 1536

_DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


class OutFolderError(ValueError):
    """``--out`` cannot be used (the CLI's exit code 2, nothing started)."""


class OutputError(IlcrigError):
    """Writing one of the run's outputs failed (a fault of the run)."""

    kind = "output_error"


class DiskFullError(OutputError):
    """The run folder's filesystem is full (``ENOSPC``/``EDQUOT``)."""

    kind = "disk_full"


def is_disk_full(err: BaseException) -> bool:
    """True for ``ENOSPC``, ``EDQUOT`` and ``EFBIG``."""
    return isinstance(err, OSError) and err.errno in _DISK_FULL_ERRNOS


def output_error(what: str, err: OSError) -> OutputError:
    """One :class:`OutputError` (a :class:`DiskFullError` for a full disk) for a failing write."""
    if is_disk_full(err):
        return DiskFullError(f"disk full: cannot write {what} ({err.strerror or err})")
    return OutputError(f"cannot write {what}: {err.strerror or err}")


def reserve_bytes(iterations: int) -> int:
    """The space kept back for the final results of a run of ``iterations`` trials, bytes."""
    return RESERVE_BASE_BYTES + RESERVE_PER_TRIAL_BYTES * max(int(iterations), 0)


def check_out_dir(path: str | Path, *, option: str = "--out", iterations: int = 0, create: bool = True) -> Path:
    """Refuse an unusable run folder before anything starts; create it if ``create``.

    Without ``create`` nothing is made: a missing folder is checked through its nearest existing
    parent (it must be a writable folder).

    :raises OutFolderError: one line naming ``option`` and what is wrong.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutFolderError(f"{option} {p}: exists and is not a folder (give a new or an existing folder)")
    if not create and not p.exists():
        parent = p.absolute().parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise OutFolderError(f"{option} {p}: {parent} is not a folder")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutFolderError(f"{option} {p}: cannot create the run folder: {parent} is not writable")
        _check_space(parent, p, option, iterations)
        return p
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutFolderError(f"{option} {p}: cannot create the run folder: {err.strerror or err}") from None
    probe = p / ".ilcrig-write-test"
    try:
        with open(probe, "wb") as fh:
            fh.write(b"x")
    except OSError as err:
        raise OutFolderError(f"{option} {p}: the run folder is not writable: {err.strerror or err}") from None
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()
    _check_space(p, p, option, iterations)
    return p


def _check_space(where: Path, p: Path, option: str, iterations: int) -> None:
    need = reserve_bytes(iterations)
    try:
        free = shutil.disk_usage(where).free
    except OSError:
        return
    existing = (p / RESERVE_NAME).stat().st_size if (p / RESERVE_NAME).is_file() else 0
    if free + existing < need:
        raise OutFolderError(
            f"{option} {p}: only {free // 1024} KiB free on its filesystem; a run of {iterations} "
            f"trials needs at least {need // 1024} KiB for its final results"
        )


class RunFolder:
    """A run folder's space reserve and write-failure switch (see the module docstring).

    :param path: the run folder (exists)
    :param iterations: planned trials (sizes the reserve)
    """

    def __init__(self, path: str | Path, iterations: int) -> None:
        self.path = Path(path)
        self.size = reserve_bytes(iterations)
        self.reserved = False
        self.released = False
        #: fault injection / tests: writes of the outputs fail with ENOSPC from this trial on, until
        #: the reserve is given back (the space the final results are written into)
        self.fail_writes_from_trial: int | None = None
        self._injected = False

    @property
    def reserve_path(self) -> Path:
        return self.path / RESERVE_NAME

    def reserve(self) -> bool:
        """Take the reserve (a ballast file of :attr:`size` bytes, really allocated). Returns
        whether it could be taken (a full disk leaves none: logged)."""
        try:
            with open(self.reserve_path, "wb") as fh:
                try:
                    os.posix_fallocate(fh.fileno(), 0, self.size)
                except (AttributeError, OSError) as err:
                    if is_disk_full(err):
                        raise
                    fh.write(b"\0" * self.size)  # filesystems without fallocate
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as err:
            logger.warning(
                "cannot reserve %d KiB in %s for the final results: %s", self.size // 1024, self.path, err.strerror or err
            )
            with contextlib.suppress(OSError):
                self.reserve_path.unlink()
            self.reserved = False
            return False
        self.reserved = True
        return True

    def release(self) -> None:
        """Give the reserve back (idempotent)."""
        with contextlib.suppress(FileNotFoundError):
            self.reserve_path.unlink()
        self.reserved = False
        self.released = True

    def _record_injection(self, trial: int) -> None:
        """The injection record (the format of :func:`bus.transports.fault_inject.write_record`)."""
        logs = self.path / "logs"
        if not logs.is_dir():
            return
        record = {
            "by": "host",
            "spec": f"diskfull@{self.fail_writes_from_trial}",
            "kind": "diskfull",
            "target": str(self.path),
            "trial": trial,
            "tick": None,
            "t_mono": time.monotonic(),
            "t_wall": time.time(),
        }
        with contextlib.suppress(OSError), open(logs / "injections-host.jsonl", "a", encoding="utf-8") as fh:
            fh.write(json.dumps(record) + "\n")

    def check_write(self, trial: int | None) -> None:
        """Raise the injected ``ENOSPC`` when writes must fail at ``trial`` (see
        :attr:`fail_writes_from_trial`)."""
        if (
            self.fail_writes_from_trial is not None
            and not self.released
            and trial is not None
            and trial >= self.fail_writes_from_trial
        ):
            if not self._injected:
                self._injected = True
                self._record_injection(trial)
            raise OSError(errno.ENOSPC, "No space left on device (injected)")
