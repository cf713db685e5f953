"""Running ``ilcrig`` in-process in tests: the exit code and what it printed."""

from __future__ import annotations

import pytest

from host.cli import main


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``main(argv)``; (exit code, stdout, stderr) — argparse's own errors exit by SystemExit."""
    try:
        code = main(list(argv))
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err
