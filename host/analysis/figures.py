"""The Agg canvas helpers of the reports: a figure and its axes (:func:`figure`), written as PNG
atomically (:func:`save_png`); used by the single-run report and the studies' reports.

Figures are drawn with matplotlib's Agg canvas directly (no pyplot, no global backend change) and
written atomically (a temporary file, then a rename).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from bus.atomic import atomic_path

logger = logging.getLogger(__name__)

__all__ = ["figure", "save_png"]


def figure(nrows: int, ncols: int, w: float, h: float) -> tuple[Any, Any]:
    """A matplotlib Figure on an Agg canvas (w × h inches) and its (nrows, ncols) axes array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def save_png(fig: Any, path: Path) -> Path:
    """Lay out ``fig`` and write it to ``path`` as PNG, atomically."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
