"""``python -P -m host.cli.janitor --out DIR --wait PID [--robot]``: the run folder's janitor process
(:func:`host.rig.janitor.run_janitor`), started by the launcher (:func:`host.rig.janitor.start_janitor`).

This module owns that process's command line (the launcher's internal helper, not an ``ilcrig``
subcommand).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``--out DIR --wait PID [--robot]`` and be the janitor."""
    from host.rig.janitor import run_janitor

    p = argparse.ArgumentParser(prog="python -m host.cli.janitor")
    p.add_argument("--out", required=True, help="the run folder")
    p.add_argument("--wait", type=int, required=True, help="the host's pid (with --robot: the plant's)")
    p.add_argument("--robot", action="store_true", help="the folder of an ilcrig robot session")
    args = p.parse_args(argv)
    return run_janitor(args.out, args.wait, robot=args.robot)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
