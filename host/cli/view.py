"""``ilcrig view``: a run's ``recording.rrd`` in the Rerun viewer.

This module owns the ``view`` subcommand, :class:`ViewOptions` and :func:`cmd_view`
(:func:`host.analysis.viewer.view_run`).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["ViewOptions", "add_parser", "cmd_view", "run_view"]


@dataclass(frozen=True)
class ViewOptions:
    """``ilcrig view RUN_DIR``."""

    run_dir: Path


def add_parser(sub: Any) -> None:
    """``view`` on the subcommands ``sub``."""
    vp = sub.add_parser("view", help="open a run's recording.rrd in the Rerun viewer (or print how to)")
    vp.add_argument("run_dir", help="a run folder (with recording.rrd)")
    vp.set_defaults(func=cmd_view)


def cmd_view(args: argparse.Namespace) -> int:
    return run_view(ViewOptions(Path(args.run_dir)))


def run_view(opts: ViewOptions) -> int:
    """Open the recording of ``opts.run_dir``; returns the exit code."""
    from host.analysis.viewer import view_run

    return int(view_run(opts.run_dir))
