"""The run folder: checked before anything starts, space kept for the final results, failing writes.

This module owns

* :func:`check_out_dir` — ``--out`` refused before anything starts (one line naming the option):
  an empty path, a path that exists and is not a folder, a folder that cannot be created or
  written, a filesystem without room for the final results;
* :class:`RunFolder` — the space reserve: room for the final results (:func:`reserve_bytes` for the
  planned trials and ticks: the final summary and report, and one trial's recording and arrays)
  taken when a run starts and given back at the end — before the final outputs are written, so
  that ``summary.json`` with the fault, the last trial's recording and ``report.md`` can still be
  written after ``ENOSPC``; a small part of it (:meth:`RunFolder.release_last`, room for the
  summary once more) is kept until the report is written, so a disk filled by someone else even
  then still lets the summary say so.  The reserve is made of files without a name (``O_TMPFILE``;
  where the filesystem has none, a file unlinked right after it is made) whose space the process
  holds through open descriptors: it never outlives the process, whatever ends it (SIGKILL
  included);
* :func:`default_run_folder` — the one naming (and making) of a run folder nobody named;
  :func:`release_unused_folder` gives one back that nothing was written into;
* :func:`summary_of` / :func:`read_summary` — the one reading of a folder's ``summary.json`` (a
  dict with its list of ``iterations``, else not a summary); :func:`end_reason_of` — how its run
  ended, ``writer_lost`` for a summary left unfinished by a process that is gone;
* :func:`remove_leftovers` — what a run that was killed may leave in its folder (temporary files of
  atomic writes, trial arrays the summary does not hold), removed by whoever outlives it;
* :class:`OutputError` / :class:`DiskFullError` — a failing write of the run's outputs as one
  fault (:func:`output_error`), and :func:`is_disk_full`;
* a test and fault-injection switch: :attr:`RunFolder.fail_writes_from_trial` makes the writes of
  the outputs fail with ``ENOSPC`` from that trial's outputs on (``--inject diskfull@K``; −1: from
  the summary written before the first trial on, ``diskfull@before``).
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
from typing import Any

from bus.errors import IlcrigError, InputError
from bus.process_identity import identity_alive

logger = logging.getLogger(__name__)

__all__ = [
    "DiskFullError",
    "default_run_folder",
    "release_unused_folder",
    "end_reason_of",
    "RUNS_DIR",
    "OutputError",
    "OutFolderError",
    "RunFolder",
    "check_out_dir",
    "RUN_FOLDER_MARKERS",
    "is_disk_full",
    "output_error",
    "read_summary",
    "remove_leftovers",
    "reserve_bytes",
    "RESERVE_NAME",
    "SUMMARY_NAME",
    "summary_of",
]

#: the reserve's name while it is made, where the filesystem cannot make a file without a name
RESERVE_NAME = ".ilcrig-reserve"
#: reserve for the final summary, report.md and convergence.png, bytes …
RESERVE_BASE_BYTES = 128 * 1024
#: … plus this much per planned trial (a trial's summary entry and report row) …
RESERVE_PER_TRIAL_BYTES = 1536
#: … plus one trial's outputs (written again after a full disk): the first trial's recording
#: segment (the 3D scene with it: 240 KB + 530 B per tick measured with rerun 0.41), its arrays and
#: the reference (200 B per tick), with a margin of 1.25
RESERVE_TRIAL_BASE_BYTES = 320 * 1024
RESERVE_PER_TICK_BYTES = 1000
#: the part of the reserve kept for a last summary write (after a failing report): the summary
#: before the trials and one entry per trial
RESERVE_LAST_WORD_BASE_BYTES = 32 * 1024
#: temporary files of the run's atomic writes (removed by :func:`remove_leftovers`)
LEFTOVER_GLOBS = (
    "summary.json.tmp",
    "recording.rrd.tmp",
    "report.md.tmp",
    "convergence.tmp.png",  # the name of earlier versions
    "convergence.png.tmp",
    "trials/*.tmp",
    RESERVE_NAME,
    ".ilcrig-write-test",
)

_DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


class OutFolderError(InputError):
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


def reserve_bytes(iterations: int, n_ticks: int = 0) -> int:
    """The space kept back for the final results of a run of ``iterations`` trials of ``n_ticks``
    ticks, bytes."""
    trial = RESERVE_TRIAL_BASE_BYTES + RESERVE_PER_TICK_BYTES * max(int(n_ticks), 0) if n_ticks > 0 else 0
    return RESERVE_BASE_BYTES + RESERVE_PER_TRIAL_BYTES * max(int(iterations), 0) + trial


#: the run's summary in its folder (:mod:`host.experiment.summary` writes it)
SUMMARY_NAME = "summary.json"

#: what a run leaves in its folder: a folder holding one of them holds a run
RUN_FOLDER_MARKERS: tuple[str, ...] = (
    SUMMARY_NAME,
    "trials",
    "recording.rrd",
    "report.md",
    "logs",
    "fieldbus.log",
    "io.log",
    "trace.bin",  # an ilcrig robot session's
    "plant.json",
)


def summary_of(folder: str | Path) -> dict[str, Any]:
    """``folder/summary.json`` as written by the run.

    :raises OSError: absent or unreadable
    :raises ValueError: not JSON, or not a run's summary (no list of ``iterations``)
    """
    doc = json.loads((Path(folder) / SUMMARY_NAME).read_text(encoding="utf-8"))
    if not isinstance(doc, dict) or not isinstance(doc.get("iterations"), list):
        raise ValueError("not a run's summary (no list of iterations)")
    return doc


def read_summary(folder: str | Path) -> dict[str, Any] | None:
    """``folder/summary.json`` (:func:`summary_of`), or None when there is none to read."""
    try:
        return summary_of(folder)
    except (OSError, ValueError):
        return None


#: where the commands put a run folder the user did not name
RUNS_DIR = Path("runs")


def default_run_folder(kind: str, *, claim: bool) -> Path:
    """The run folder of a command the user gave no ``--out``: ``runs/<kind>-<local time>``, or
    with ``-2``, ``-3`` … where that name is taken — by an earlier run, or by another command
    started in the same second, which would otherwise write a second run into the same folder.

    :param claim: make it (atomically: of two commands racing for a name, one gets the next); else
        only name the first one not there now (for checks before anything is made)
    :raises OutFolderError: ``runs`` cannot hold it (one line)
    """
    base = RUNS_DIR / time.strftime(f"{kind}-%Y%m%d-%H%M%S")
    for n in range(1, 10_000):
        path = base if n == 1 else base.with_name(f"{base.name}-{n}")
        if not claim:
            if not path.exists():
                return path
            continue
        try:
            path.mkdir(parents=True)
        except FileExistsError:
            continue
        except OSError as err:
            raise OutFolderError(f"--out {path}: cannot create the run folder: {err.strerror or err}") from None
        return path
    raise OutFolderError(f"--out {base}: every name of this second is taken; give a run folder")


def release_unused_folder(path: Path) -> bool:
    """Remove ``path`` — a folder :func:`default_run_folder` claimed — when nothing was written into
    it: a command that ended before its first record (interrupted while a cluster started) leaves
    no empty folder that looks like a run or a study. True when it was removed."""
    try:
        path.rmdir()  # only an empty folder
    except OSError:
        return False
    return True


def end_reason_of(summary: dict[str, Any]) -> str | None:
    """How the run of ``summary`` ended: its ``end_reason``; while that is empty, ``writer_lost``
    when the process that writes the summary (``writer``, :mod:`bus.process_identity`) is gone —
    killed with nobody left to say so —, else None (the run is still going, or this machine cannot
    tell: a summary written on another host)."""
    reason = summary.get("end_reason")
    if reason is not None:
        return str(reason)
    return "writer_lost" if identity_alive(summary.get("writer")) is False else None


def check_out_dir(
    path: str | Path,
    *,
    option: str = "--out",
    iterations: int | None = None,
    n_ticks: int = 0,
    create: bool = True,
    new_run: bool = False,
) -> Path:
    """Refuse an unusable run folder before anything starts; create it if ``create``.

    With ``new_run`` (a run about to start in it, as the user named it) a folder that already holds
    a run (:data:`RUN_FOLDER_MARKERS`) is refused: one run, one folder, never two runs mixed.

    Without ``create`` nothing is made: a missing folder is checked through its nearest existing
    parent (it must be a writable folder).  The free space is checked against the reserve of
    ``iterations`` trials of ``n_ticks`` ticks (None: not checked yet, the experiment is not known).

    :raises OutFolderError: one line naming ``option`` and what is wrong.
    """
    if str(path).strip() == "":
        raise OutFolderError(f"{option} {str(path)!r}: an empty path (give the run folder)")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutFolderError(f"{option} {p}: exists and is not a folder (give a new or an empty folder)")
    if new_run and p.is_dir():
        held = [m for m in RUN_FOLDER_MARKERS if (p / m).exists()]
        if held:
            raise OutFolderError(
                f"{option} {p}: holds another run ({', '.join(held)}); give a new or an empty folder, or remove that run"
            )
    if not create and not p.exists():
        parent = p.absolute().parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise OutFolderError(f"{option} {p}: {parent} is not a folder")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutFolderError(f"{option} {p}: cannot create the run folder: {parent} is not writable")
        if iterations is not None:
            _check_space(parent, p, option, iterations, n_ticks)
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
    if iterations is not None:
        _check_space(p, p, option, iterations, n_ticks)
    return p


def _check_space(where: Path, p: Path, option: str, iterations: int, n_ticks: int) -> None:
    need = reserve_bytes(iterations, n_ticks)
    try:
        free = shutil.disk_usage(where).free
    except OSError:
        return
    if free < need:
        ticks = f" of {n_ticks} ticks" if n_ticks > 0 else ""
        raise OutFolderError(
            f"{option} {p}: only {free // 1024} KiB free on its filesystem; a run of {iterations} "
            f"trial{'s' if iterations != 1 else ''}{ticks} needs at least {need // 1024} KiB for its final results"
        )


class RunFolder:
    """A run folder's space reserve and write-failure switch (see the module docstring).

    :param path: the run folder (exists)
    :param iterations: planned trials (sizes the reserve)
    :param n_ticks: ticks per trial (sizes the reserve)
    """

    def __init__(self, path: str | Path, iterations: int, n_ticks: int = 0) -> None:
        self.path = Path(path)
        self.size = reserve_bytes(iterations, n_ticks)
        #: of it, kept until :meth:`release_last` (room for one more summary write), bytes
        self.last_word = min(self.size // 2, RESERVE_LAST_WORD_BASE_BYTES + RESERVE_PER_TRIAL_BYTES * max(int(iterations), 0))
        self.reserved = False
        self.released = False
        self._fd = -1
        self._fd_last = -1
        #: fault injection / tests: writes of the outputs fail with ENOSPC from this trial's on (−1:
        #: from the summary before the first trial), until the reserve is given back (the space the
        #: final results are written into); :attr:`fail_spec`: the ``--inject`` spec that asked for it
        self.fail_writes_from_trial: int | None = None
        self.fail_spec: str | None = None
        self._injected = False

    @property
    def reserve_path(self) -> Path:
        """The name the reserve has for a moment where no file without a name can be made."""
        return self.path / RESERVE_NAME

    def _open_nameless(self) -> int:
        """A new file without a name in the run folder (``O_TMPFILE``), else one unlinked at once."""
        try:
            return os.open(self.path, os.O_TMPFILE | os.O_RDWR | os.O_CLOEXEC, 0o600)
        except (AttributeError, OSError) as err:
            if isinstance(err, OSError) and is_disk_full(err):
                raise
        fd = os.open(self.reserve_path, os.O_CREAT | os.O_EXCL | os.O_RDWR | os.O_CLOEXEC, 0o600)
        with contextlib.suppress(OSError):
            os.unlink(self.reserve_path)
        return fd

    def _allocate(self, size: int) -> int:
        """A file without a name holding ``size`` bytes, really allocated; its descriptor.

        :raises OSError: no room (or no file)
        """
        fd = self._open_nameless()
        try:
            try:
                os.posix_fallocate(fd, 0, size)
            except OSError as err:
                if is_disk_full(err):
                    raise
                os.pwrite(fd, b"\0" * size, 0)  # filesystems without fallocate
            os.fsync(fd)
        except BaseException:
            os.close(fd)
            raise
        return fd

    def reserve(self) -> bool:
        """Take the reserve (:attr:`size` bytes, really allocated, held by open descriptors of
        files without a name). Returns whether it could be taken (a full disk leaves none: logged)."""
        if self._fd >= 0:
            return True
        try:
            self._fd_last = self._allocate(self.last_word)
            self._fd = self._allocate(self.size - self.last_word)
        except OSError as err:
            logger.warning(
                "cannot reserve %d KiB in %s for the final results: %s", self.size // 1024, self.path, err.strerror or err
            )
            self.release_last()
            self.reserved = self.released = False
            return False
        self.reserved = True
        return True

    def release(self) -> None:
        """Give the reserve back but its last part (:meth:`release_last`): close its descriptor,
        the filesystem frees its space (idempotent)."""
        if self._fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = -1
        self.reserved = False
        self.released = True

    def release_last(self) -> None:
        """Give back the last part too (room for a last summary write; idempotent)."""
        self.release()
        if self._fd_last >= 0:
            with contextlib.suppress(OSError):
                os.close(self._fd_last)
            self._fd_last = -1

    def _record_injection(self, trial: int) -> None:
        """The injection record (the format of :func:`bus.transports.fault_inject.write_record`)."""
        logs = self.path / "logs"
        if not logs.is_dir():
            return
        record = {
            "by": "host",
            "spec": self.fail_spec or f"diskfull@{self.fail_writes_from_trial}",
            "kind": "diskfull",
            "target": str(self.path),
            "trial": max(trial, 0),
            "tick": None,
            "kept": trial + 1 if trial >= 0 else 0,  # the write after trial k: k + 1 trials kept
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


def remove_leftovers(run_dir: str | Path, kept: int | None = None) -> list[Path]:
    """Remove what a killed run may leave in ``run_dir``: the temporary files of its atomic writes
    (:data:`LEFTOVER_GLOBS`) and, with ``kept`` (the trials in its summary), trial arrays of later
    trials (``trials/trial-KKKKK.npz`` written before the process died, not in the summary).
    Returns what was removed; never raises (a failure is logged)."""
    d = Path(run_dir)
    found = [p for pattern in LEFTOVER_GLOBS for p in d.glob(pattern)]
    if kept is not None:
        for p in d.glob("trials/trial-*.npz"):
            number = p.stem.removeprefix("trial-")
            if number.isdigit() and int(number) >= kept:
                found.append(p)
    removed = []
    for p in found:
        try:
            p.unlink()
            removed.append(p)
        except FileNotFoundError:
            pass
        except OSError as err:
            logger.warning("cannot remove %s: %s", p, err)
    return removed
