"""Atomic file writes: the one home of write-a-temporary-file-then-rename.

This module owns :func:`atomic_path` (a context manager that yields a temporary path beside the
target, for writers that want a path or an open file: ``np.savez``, ``pyarrow``, matplotlib) and
:func:`atomic_write` (bytes or text).  Either the whole new file is in place under its name, or the
previous file (or none) is, and no temporary file is left behind — also when the writer raises.
With ``fsync=True`` the data is on the disk before the rename (summary.json, trial files).

May import: the standard library only.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from pathlib import Path

logger = logging.getLogger(__name__)

__all__ = ["atomic_path", "atomic_write", "TMP_SUFFIX"]

#: the suffix of the temporary file beside the target (``summary.json.tmp``)
TMP_SUFFIX = ".tmp"


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, fsync: bool = False, mkdir: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends without an exception the file
    written there replaces ``path`` in one rename.  On an exception the temporary file is removed
    and the exception propagates; ``path`` is untouched.

    :param fsync: flush the file to the disk before the rename
    :param mkdir: create the parent folder first
    """
    target = Path(path)
    tmp = target.with_name(target.name + TMP_SUFFIX)
    try:
        if mkdir:
            target.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        if fsync:
            _fsync(tmp)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def atomic_write(path: str | os.PathLike[str], data: bytes | str, *, fsync: bool = False, encoding: str = "utf-8") -> Path:
    """Write ``data`` (bytes, or text in ``encoding``) to ``path`` atomically (:func:`atomic_path`);
    return the path."""
    target = Path(path)
    raw = data.encode(encoding) if isinstance(data, str) else data
    with atomic_path(target, fsync=fsync) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(raw)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
    return target
