"""The run summary, ``summary.json`` (schema ``ilcrig.summary/1``).

This module owns the summary's schema name, its skeleton before the first trial, the per-trial
update, the conversion of results to JSON-safe values (a non-finite number becomes ``null``, with a
warning: a NaN never reaches the file), and the atomic write (temporary file, fsync, rename) so
that a failing write or a fault never leaves a corrupt or partial summary: when the write fails
the previous ``summary.json`` stays as it was, the temporary file is removed and one
:class:`host.experiment.outputs.OutputError` is raised.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from bus.atomic import atomic_write
from host.experiment.outputs import SUMMARY_NAME, OutputError, RunFolder, output_error

logger = logging.getLogger(__name__)

__all__ = ["SCHEMA", "finite", "jsonable", "write_summary"]

#: the summary's schema name and version
SCHEMA = "ilcrig.summary/1"


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON types (dataclasses, ``as_dict()``, numpy arrays and scalars)."""
    if hasattr(obj, "as_dict"):
        return jsonable(obj.as_dict())
    if dataclass_fields := getattr(obj, "__dataclass_fields__", None):
        return {k: jsonable(getattr(obj, k)) for k in dataclass_fields}
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def finite(obj: Any, where: str = "summary") -> Any:
    """``obj`` with every non-finite float replaced by None (logged with its place)."""
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        logger.warning("%s: non-finite value %r written as null", where, obj)
        return None
    if isinstance(obj, dict):
        return {k: finite(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    return obj


def write_summary(out_dir: Path, summary: dict[str, Any], *, folder: RunFolder | None = None, trial: int | None = None) -> None:
    """Replace ``out_dir/summary.json`` atomically: write a temporary file, fsync, rename.

    :param folder: the run folder's reserve / write-failure switch (fault injection)
    :param trial: the trial this write belongs to (for the injected failure)
    :raises OutputError: the write failed (a :class:`~host.experiment.outputs.DiskFullError` on a
        full disk); the previous summary is untouched and no temporary file is left.
    """
    data = json.dumps(finite(jsonable(summary)), indent=2, allow_nan=False)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        if folder is not None:
            folder.check_write(trial)
        atomic_write(out_dir / SUMMARY_NAME, data, fsync=True)
    except OSError as err:
        raise output_error(str(out_dir / SUMMARY_NAME), err) from None


__all__ += ["OutputError"]
