"""``python -m host.cli.dbc [--check]``: rewrite the DBC files of the rig's cyclic frames, or check
that they are current (:mod:`bus.dbc` generates them).

This module owns that tool's command line (not an ``ilcrig`` subcommand: a developer's tool).

May import: what ``host.cli`` may.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from bus.dbc import stale_dbc_files, write_dbc_files

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite both DBC files; with ``--check``, exit 1 when one differs from the generated text."""
    parser = argparse.ArgumentParser(prog="python -m host.cli.dbc", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when a file differs from the generated text")
    if parser.parse_args(argv).check:
        return 1 if stale_dbc_files() else 0
    write_dbc_files()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
