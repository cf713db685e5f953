"""``ilcrig view``: a run's ``recording.rrd`` opened in the Rerun viewer, or the command to open it
printed (no display, no viewer installed).  :func:`view_run` takes typed arguments (no argparse);
:func:`viewer_command` and :func:`display_available` are shared with the live view
(:mod:`host.analysis.live_view`).  Imports no rerun.

May import: ``bus`` (exit codes).
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import TextIO

from bus.exit_codes import EXIT_USAGE

logger = logging.getLogger(__name__)

__all__ = ["display_available", "view_run", "viewer_command"]


def _rerun_version() -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rerun-sdk")
    except PackageNotFoundError:
        return None


def viewer_command() -> list[str] | None:
    """The command that starts the Rerun viewer here: ``rerun`` on PATH, the one next to this
    Python, or ``python -m rerun``; None if rerun-sdk is not installed."""
    exe = shutil.which("rerun")
    if exe:
        return [exe]
    sibling = Path(sys.executable).parent / "rerun"
    if sibling.is_file() and os.access(sibling, os.X_OK):
        return [str(sibling)]
    from importlib.util import find_spec

    if find_spec("rerun_cli") is not None or find_spec("rerun") is not None:
        return [sys.executable, "-m", "rerun"]
    return None


def display_available() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view_run(run_dir: str | Path, *, stdout: TextIO | None = None, stderr: TextIO | None = None) -> int:
    """``ilcrig view RUN_DIR``: open ``RUN_DIR/recording.rrd`` in the viewer, or say how to.

    :returns: 0 (viewer spawned, or the command printed), 2 if there is no recording.
    """
    out = stdout if stdout is not None else sys.stdout
    err = stderr if stderr is not None else sys.stderr
    p = Path(run_dir)
    rrd = p if p.suffix == ".rrd" else p / "recording.rrd"
    if not rrd.is_file():
        err.write(f"ilcrig: error: no recording at {rrd}\n")
        return EXIT_USAGE
    rrd = rrd.resolve()
    cmd = viewer_command()
    if cmd is not None and display_available():
        try:
            subprocess.Popen([*cmd, str(rrd)], stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as exc:
            logger.warning("cannot start the viewer %s: %s", cmd[0], exc)
        else:
            out.write(f"ilcrig view: opened {rrd} in the Rerun viewer ({' '.join(cmd)})\n")
            return 0
    ver = _rerun_version()
    pin = f"rerun-sdk=={ver}" if ver else "rerun-sdk"
    why = "no display ($DISPLAY / $WAYLAND_DISPLAY unset)" if cmd is not None else "no Rerun viewer installed"
    out.write(
        f"ilcrig view: {why}; open the recording on a machine with a display:\n  rerun {rrd}\n  (viewer: pip install {pin})\n"
    )
    return 0
