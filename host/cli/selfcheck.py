"""``python -m host.cli.selfcheck``: the plant's kernel timing and drive-train load check
(:func:`plant.selfcheck.report`), logged to the terminal.

This module owns that tool's command line (not an ``ilcrig`` subcommand: a developer's tool).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the check (``--help`` says what it measures)."""
    description = "the plant's kernel timing (µs per step) and drive-train load check (peak and RMS joint torques)"
    argparse.ArgumentParser(prog="python -m host.cli.selfcheck", description=description).parse_args(argv)
    from plant import selfcheck  # numba: after --help

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    selfcheck.report()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
