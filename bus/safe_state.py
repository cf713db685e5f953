"""The safe-state record: one log line a node writes when its torque goes off, and its parser.

This module owns the format both sides agree on: a drive (or the plant node) logs a
``SAFE-STATE`` line whenever it removes torque (a fault reaction, a lost host or bus, NMT stop,
CiA 402 disable, the process stopping); the launcher of ``ilcrig run`` reads those lines back
from the roles' logs as evidence of the safe state when the host cannot report it (the host or the
bus is gone).

Format (one line, ``key=value`` pairs without spaces)::

    SAFE-STATE node=drive2 torque=off reason=host-heartbeat-lost cia402=FAULT nmt=OPERATIONAL tick=150 t_mono=1234.567890

``t_mono`` is ``time.monotonic()`` of the writing process (CLOCK_MONOTONIC: one clock for every
process of the machine), so reaction latencies can be computed across processes.
"""

from __future__ import annotations

import logging
import time
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["TAG", "TORQUE_ON_TAG", "format_safe_state", "parse_safe_state", "last_state_in_log"]

#: first word of a safe-state record
TAG = "SAFE-STATE"
#: first word of the line a drive logs when its torque comes on (a later SAFE-STATE supersedes it)
TORQUE_ON_TAG = "TORQUE-ON"


def _clean(value: Any) -> str:
    text = f"{value:.6f}" if isinstance(value, float) else str(value)
    return "-".join(text.split()) or "-"


def format_safe_state(node: str, reason: str, **fields: Any) -> str:
    """The record of ``node`` (e.g. ``drive2``) removing torque because of ``reason``; further
    fields (``cia402``, ``nmt``, ``tick`` …) follow; ``t_mono`` is added."""
    parts = [TAG, f"node={_clean(node)}", "torque=off", f"reason={_clean(reason)}"]
    parts += [f"{k}={_clean(v)}" for k, v in fields.items()]
    parts.append(f"t_mono={time.monotonic():.6f}")
    return " ".join(parts)


def parse_safe_state(line: str) -> dict[str, str] | None:
    """The fields of a safe-state record found anywhere in ``line`` (a log line with a prefix),
    or None if the line holds none."""
    at = line.find(TAG + " ")
    if at < 0:
        return None
    out: dict[str, str] = {}
    for part in line[at + len(TAG) + 1 :].split():
        key, sep, value = part.partition("=")
        if sep:
            out[key] = value
    return out if "node" in out else None


def last_state_in_log(lines: list[str], node: str) -> tuple[dict[str, str] | None, bool]:
    """``(last SAFE-STATE record of node, torque came on again after it)`` in a role's log lines."""
    last: dict[str, str] | None = None
    on_after = False
    marker = f"{TORQUE_ON_TAG} node={node}"
    for line in lines:
        rec = parse_safe_state(line)
        if rec is not None and rec.get("node") == node:
            last, on_after = rec, False
        elif marker in line:
            on_after = True
    return last, on_after
