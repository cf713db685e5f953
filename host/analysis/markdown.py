"""How the reports write numbers, law names and tables (markdown).

Owns :func:`fmt` (significant digits, positional), :func:`paper_value` (a published number as
printed), :func:`md_table`, the joint numbers :data:`JOINTS` and the display names of the laws
:data:`LAW_LABEL`.  Used by the sweep report, the single-run report and the verdict texts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["JOINTS", "LAW_LABEL", "Floats", "fmt", "paper_value", "md_table", "jlist"]

JOINTS = (1, 2, 3, 4)
#: per-joint (or per-trial) values: a numpy array or a plain sequence such as a paper row
Floats = np.ndarray | Sequence[float]
#: display names of the learning laws, in the order the reports list them
LAW_LABEL = {
    "pd-ilc": "PD-ILC",
    "pd-ilc-q": "PD-ILC-Q",
    "d-ilc": "D-ILC",
    "q-ilc": "Q-ILC",
    "no-ilc": "NO-ILC",
    "no-ilc-id": "NO-ILC-ID",
    "pd-ol": "PD-OL",
    "p-ol": "P-OL",
    "cno-ilc": "CNO-ILC",
    "adjoint-ilc": "ADJOINT-ILC",
}


def fmt(v: float | None, digits: int = 3) -> str:
    """``digits`` significant digits, positional (0.0016, 0.00003), '—' for None/NaN."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    return np.format_float_positional(float(v), precision=digits, unique=True, fractional=False, trim="-")


def paper_value(v: float | None) -> str:
    """A published number as the paper prints it (all its digits), '—' for a value it does not give."""
    return "—" if v is None else np.format_float_positional(float(v), trim="-")


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """A markdown table as lines: header, separator, one line per row."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def jlist(idx: Sequence[int]) -> str:
    """Zero-based joint indices as 'j1, j3'."""
    return ", ".join(f"j{i + 1}" for i in idx)
