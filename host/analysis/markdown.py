"""How the reports write numbers, law names and tables (markdown).

Owns :func:`fmt` (significant digits, positional), :func:`md_table`, the joint numbers
:data:`JOINTS` and :data:`Floats` (per-joint values).  Used by the single-run report and the
studies' reports (:mod:`host.studies`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["JOINTS", "Floats", "fmt", "md_table"]

JOINTS = (1, 2, 3, 4)
#: per-joint (or per-trial) values: a numpy array or a plain sequence such as a paper row
Floats = np.ndarray | Sequence[float]


def fmt(v: float | None, digits: int = 3) -> str:
    """``digits`` significant digits, positional (0.0016, 0.00003), '—' for None/NaN."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    return np.format_float_positional(float(v), precision=digits, unique=True, fractional=False, trim="-")


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """A markdown table as lines: header, separator, one line per row."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines
