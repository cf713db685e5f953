"""The terminal streams of a user's command, and what happens when the reader goes away.

This module owns :class:`ConsoleStream` and :func:`hold_console`, which puts one in place of
``sys.stdout`` and ``sys.stderr`` for every command (:func:`host.cli.main`): a user's command, and
the roles, whose host writes the rows of ``ilcrig run`` to the terminal the launcher was started
on.

Why
    A run's console is a view of it; its records are the summary, the folder and the recording.
    When the reader of the console goes away — ``ilcrig sim | head`` once ``head`` has its lines,
    a pager quit early, a terminal whose window was closed or whose ssh connection dropped — a
    write raises (``BrokenPipeError``, ``OSError`` EIO). Uncaught, that ended the run at whatever
    print it hit as an "internal error", exit 1, with its summary unfinished (no end, no reason).
    Now the console is dropped instead: later writes go nowhere, the run goes on to its end and
    its records and exit code are those of the run. Ending on the terminal's hang-up is SIGHUP's
    job (:data:`host.experiment.signal_shield.RUN_SIGNALS`), which a closed terminal sends.
    Likewise a console whose encoding cannot show a character of a line (µ, ≥, the digest's …:
    ``PYTHONIOENCODING=ascii``, a Latin-1 locale) gets it escaped (``\\u2026``), not an error.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
from collections.abc import Iterator
from typing import TextIO

logger = logging.getLogger(__name__)

__all__ = ["ConsoleStream", "hold_console"]


class ConsoleStream(io.TextIOBase):
    """A text stream that writes to ``stream`` until a write or flush fails with an
    :class:`OSError` (the console went away), and from then on drops what it is given; what the
    stream's encoding cannot show is written escaped.

    The file descriptor under ``stream`` is pointed at ``/dev/null`` when that happens, so that what
    ``stream`` still buffers, and any other writer of the descriptor (a library, Python's own
    flush at exit), does not fail again.

    :ivar lost: the error that took the console away (None while it works)
    """

    def __init__(self, stream: TextIO, name: str) -> None:
        super().__init__()
        self.stream = stream
        self.name = name
        self.lost: OSError | None = None

    def write(self, text: str) -> int:
        if self.lost is None:
            try:
                try:
                    return self.stream.write(text)
                except UnicodeEncodeError:  # a console that cannot show µ, ≥ or …: escaped
                    encoding = self.stream.encoding or "ascii"
                    self.stream.write(text.encode(encoding, "backslashreplace").decode(encoding))
                    return len(text)
            except OSError as err:
                self._lose(err)
        return len(text)

    def flush(self) -> None:
        if self.lost is None:
            try:
                self.stream.flush()
            except OSError as err:
                self._lose(err)

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        return self.lost is None and self.stream.isatty()

    def fileno(self) -> int:
        return self.stream.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]  # TextIOBase's is a read-only attribute
        return self.stream.encoding

    @property
    def errors(self) -> str | None:  # type: ignore[override]
        return self.stream.errors

    def _lose(self, err: OSError) -> None:
        self.lost = err
        logger.debug("%s: the console went away (%s): its lines are dropped from now on", self.name, err)
        with contextlib.suppress(OSError, ValueError, io.UnsupportedOperation):
            null = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(null, self.stream.fileno())
            finally:
                os.close(null)


@contextlib.contextmanager
def hold_console() -> Iterator[tuple[ConsoleStream, ConsoleStream]]:
    """``sys.stdout`` and ``sys.stderr`` as :class:`ConsoleStream` while inside (the originals back
    after, each flushed by its :class:`ConsoleStream`); yields the two."""
    out, err = sys.stdout, sys.stderr
    held = ConsoleStream(out, "stdout"), ConsoleStream(err, "stderr")
    sys.stdout, sys.stderr = held
    try:
        yield held
    finally:
        for stream in held:
            stream.flush()
        sys.stdout, sys.stderr = out, err
