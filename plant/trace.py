"""The robot's period trace: what the plant did in every control period, as a file.

This module owns the trace file of an ``ilcrig robot`` session (``RUN_DIR/trace.bin``): one
record per control period the robot stepped (:data:`TRACE_DTYPE`: the period, the joint angles q
at its end [rad], the four torques the drives sent for it [µN·m], the joints held by their brakes
and flags), after a one-line header that names the record layout and the control period.
:class:`TraceWriter` appends records in blocks of :attr:`TraceWriter.BLOCK` (a killed plant loses
at most the last block); :func:`read_trace` reads a file back (a partial last record is dropped)
and :func:`trace_digest` is the SHA-256 of the deterministic part (period, q, torque, brakes: the
same master script gives the same digest; the wall-clock flags are left out).

Header: ``ILCRIG-ROBOT-TRACE 1 {"ts_s": ..., "substeps": ..., "dtype": [...]}`` and a newline.
Imports numpy and the standard library only.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import IO

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["FLAG_FAULT", "FLAG_LATE", "TRACE_DTYPE", "Trace", "TraceWriter", "read_trace", "trace_digest"]

MAGIC = b"ILCRIG-ROBOT-TRACE 1 "
#: one record per period (little-endian, packed: 54 bytes)
TRACE_DTYPE = np.dtype([("period", "<u8"), ("q_rad", "<f8", (4,)), ("torque", "<i4", (4,)), ("held", "u1"), ("flags", "u1")])
#: flags: the period's SYNC came late (real time)
FLAG_LATE = 0x01
#: flags: a robot fault holds the robot (every joint braked)
FLAG_FAULT = 0x02


class Trace:
    """A trace read back: its header fields and records.

    :ivar ts_s: control period, s.  :ivar substeps: RK4 sub-steps per period.
    :ivar records: the periods (:data:`TRACE_DTYPE`).
    """

    def __init__(self, ts_s: float, substeps: int, records: np.ndarray) -> None:
        self.ts_s = ts_s
        self.substeps = substeps
        self.records = records

    @property
    def q_rad(self) -> np.ndarray:
        """(n, 4) joint angles at the end of every period, rad."""
        return np.asarray(self.records["q_rad"], dtype=np.float64)


class TraceWriter:
    """Appends period records to a trace file (see the module docstring).

    :param path: the file (created or truncated; its folder must exist).
    :param ts_s: control period, s.  :param substeps: RK4 sub-steps per period.
    :raises OSError: the file cannot be created.
    """

    #: records written per block
    BLOCK: int = 256

    def __init__(self, path: str | Path, ts_s: float, substeps: int) -> None:
        self.path = Path(path)
        self._file: IO[bytes] | None = open(self.path, "wb")  # noqa: SIM115 - closed by close()
        header = {"ts_s": float(ts_s), "substeps": int(substeps), "dtype": TRACE_DTYPE.descr}
        self._file.write(MAGIC + json.dumps(header).encode() + b"\n")
        # the block's records as Python tuples, made a record array when written: a period's
        # record costs a tuple, not five field writes of a structured array (docs/benchmarks.md)
        self._rows: list[tuple[int, list[float], list[int], int, int]] = []
        #: records added so far (written, buffered, or lost to a failed write)
        self.records = 0
        #: records in the file (written and flushed)
        self.written = 0
        #: why writing stopped (None while it works)
        self.error: str | None = None

    def add(self, period: int, q_rad: list[float] | np.ndarray, torque: np.ndarray, held_bits: int, flags: int) -> None:
        """One period's record (written when the block is full); ``q_rad`` as Python floats
        (:meth:`plant.simulator.Plant.q_list`) or an array."""
        rows = self._rows
        rows.append((period, q_rad if isinstance(q_rad, list) else q_rad.tolist(), torque.tolist(), held_bits, flags))
        self.records += 1
        if len(rows) == self.BLOCK:
            self.flush()

    def flush(self) -> None:
        """Write the buffered records.  A failing write (a full disk) stops the trace (:attr:`error`)
        and is logged once; the robot goes on."""
        f, rows = self._file, self._rows
        if f is None or not rows:
            rows.clear()
            return
        try:
            f.write(np.array(rows, dtype=TRACE_DTYPE).tobytes())
            f.flush()
            self.written += len(rows)
        except OSError as err:
            self.error = f"{err.strerror or err}"
            logger.error("robot trace %s stopped: %s", self.path, self.error)
            self._close_file()
        rows.clear()

    def close(self) -> None:
        """Write what is buffered and close the file (idempotent)."""
        self.flush()
        self._close_file()

    def _close_file(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()
            except OSError as err:
                logger.warning("closing the robot trace %s: %s", self.path, err)


def read_trace(path: str | Path) -> Trace:
    """Read a trace file (a partial last record, from a killed writer, is dropped).

    :raises ValueError: not a robot trace, or another record layout.
    """
    data = Path(path).read_bytes()
    if not data.startswith(MAGIC):
        raise ValueError(f"{path}: not an ilcrig robot trace")
    end = data.index(b"\n")
    header = json.loads(data[len(MAGIC) : end])
    if np.dtype([tuple(f) for f in header["dtype"]]) != TRACE_DTYPE:
        raise ValueError(f"{path}: record layout {header['dtype']} is not {TRACE_DTYPE.descr}")
    body = data[end + 1 :]
    n = len(body) // TRACE_DTYPE.itemsize
    records = np.frombuffer(body[: n * TRACE_DTYPE.itemsize], dtype=TRACE_DTYPE).copy()
    return Trace(float(header["ts_s"]), int(header["substeps"]), records)


def trace_digest(records: np.ndarray) -> str:
    """SHA-256 (hex) of the deterministic fields of ``records``: period, q, torque, brakes."""
    h = hashlib.sha256()
    for field in ("period", "q_rad", "torque", "held"):
        h.update(np.ascontiguousarray(records[field]).tobytes())
    return h.hexdigest()
