"""``recording.rrd`` on disk: complete Rerun streams one after the other (:class:`SegmentFile`),
the cut back to the summary's trials (:func:`cut_back`) and the recorder's input error
(:class:`RecordingError`).  Imports no rerun.

Durability: the recording survives whatever the summary survives
    Rerun's stream goes to a :class:`rerun.BinaryStream`, not to a file sink: after each trial the
    encoded bytes — one complete Rerun stream (header, the trial's messages, end message, footer
    index and its 32-byte trailer) — are appended to ``recording.rrd`` by :class:`SegmentFile`, which
    owns every byte of the file.  The file is always a sequence of such segments whose last trailer
    is held back (written in front of the next segment): without a trailer at its end Rerun's
    readers (``RrdReader(...).stream()``, ``rerun rrd print``, the viewer) scan the segments one
    after the other, while a trailer at the end would make them trust that one segment's index.
    An append writes the new segment behind a 32-byte gap, then the previous trailer into the
    gap, then fsyncs: a write cut short by a kill leaves either the gap (readers stop cleanly at
    the last complete trial) or a partial last segment (readers drop it); a failing write (a full
    disk) is cut back at once and the trial's bytes are kept to be written again (after the run
    folder's reserve is given back).  :meth:`RunRecorder.committed` says how many bytes hold
    complete trials (the summary keeps it as ``summary["recording"]``), and :func:`cut_back` cuts a
    file back to that length — what a process that outlives a killed host does, so the file holds
    exactly the trials of the summary.  After a run that ended without a write failure,
    :meth:`RunRecorder.close` joins the segments into one stream with Rerun's footer index
    (``rerun rrd``-style: a temporary file renamed over the recording), which readers open without
    scanning; a recording that was not joined (a killed or faulted run) is read by a scan (``RrdReader``
    warns that it has no footer).  Before a trial is written its size is checked against the
    free space of the filesystem (the previous trial's growth, ×1.5): a full disk is one
    :class:`host.experiment.outputs.DiskFullError` before the disk is filled up.

May import: the standard library only.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

logger = logging.getLogger(__name__)

__all__ = ["FOOTER_MAGIC", "STREAM_MAGIC", "TRAILER_BYTES", "RecordingError", "SegmentFile", "cut_back"]


#: the fixed-size trailer at the end of every Rerun stream (footer offset and length, CRC, magic,
#: version) and its magic: rerun 0.41's RRD layout
TRAILER_BYTES = 32
FOOTER_MAGIC = b"RRF2FOOT"
STREAM_MAGIC = b"RRF2"


class RecordingError(ValueError):
    """Bad input to the recorder (shapes that do not match the reference)."""


class SegmentFile:
    """``recording.rrd`` as complete Rerun streams one after the other, the last one's trailer
    held back (see the module docstring: durability).

    :param path: the file (created, or emptied)
    :ivar committed: bytes of the file that hold complete segments (the last without its trailer)
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self.committed = 0
        self._trailer = b""

    @staticmethod
    def split(segment: bytes) -> tuple[bytes, bytes]:
        """A complete Rerun stream as (everything but its trailer, its trailer).

        :raises RecordingError: not the layout of rerun 0.41 (header magic, trailer magic)
        """
        if (
            len(segment) < len(STREAM_MAGIC) + TRAILER_BYTES
            or not segment.startswith(STREAM_MAGIC)
            or segment[-12:-4] != FOOTER_MAGIC
        ):
            raise RecordingError("Rerun's encoder did not return a complete stream (an unknown RRD layout?)")
        return segment[:-TRAILER_BYTES], segment[-TRAILER_BYTES:]

    def append(self, segment: bytes) -> None:
        """Append one complete stream: its body behind a gap for the held-back trailer, then that
        trailer, fsync. On failure the file is cut back to :attr:`committed` and the error raised.

        :raises OSError: the write failed (nothing of the segment stays in the file)
        """
        body, trailer = self.split(segment)
        start = self.committed
        end = start + len(self._trailer) + len(body)
        try:
            _pwrite_all(self.fd, body, start + len(self._trailer))
            if self._trailer:
                _pwrite_all(self.fd, self._trailer, start)
            os.ftruncate(self.fd, end)  # an earlier failed attempt may have left more behind
            os.fsync(self.fd)
        except OSError:
            try:
                os.ftruncate(self.fd, start)
            except OSError as err:  # pragma: no cover - a truncation frees space, it does not need it
                logger.error("recording %s: cannot cut back to %d bytes: %s", self.path, start, err)
            raise
        self.committed, self._trailer = end, trailer

    def close(self) -> None:
        """Close the file (its last trailer stays held back; idempotent)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


def cut_back(path: str | Path, committed_bytes: int) -> bool:
    """Cut a recording back to ``committed_bytes`` (``summary["recording"]["bytes"]``) when it is
    longer and still a sequence of segments (a joined recording, which ends with Rerun's trailer,
    is left as it is). Returns whether it was cut. Never raises (a failure is logged)."""
    p = Path(path)
    try:
        with open(p, "r+b") as fh:
            size = fh.seek(0, os.SEEK_END)
            if size <= committed_bytes or committed_bytes < 0:
                return False
            fh.seek(size - 12)
            if fh.read(8) == FOOTER_MAGIC:
                return False  # joined into one stream at the end of the run
            fh.truncate(committed_bytes)
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as err:
        logger.warning("cannot cut the recording %s back to %d bytes: %s", p, committed_bytes, err)
        return False
    logger.info("recording %s cut back from %d to %d bytes (the summary's trials)", p, size, committed_bytes)
    return True
