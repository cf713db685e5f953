"""The run summary, ``summary.json`` (schema ``ilcrig.summary/1``).

This module owns the summary's schema name, its skeleton before the first trial, the per-trial
update, the conversion of results to JSON-safe values, and the atomic write (temporary file,
fsync, rename) so that a failing write or a fault never leaves a corrupt or partial summary.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["SCHEMA", "jsonable", "write_summary"]

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


def write_summary(out_dir: Path, summary: dict[str, Any]) -> None:
    """Replace ``out_dir/summary.json`` atomically: write a temporary file, fsync, rename."""
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / "summary.json.tmp"
    data = json.dumps(summary, indent=2, allow_nan=False)
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, out_dir / "summary.json")
