"""The ``ilcrig`` command line with hold points, for the interrupt and lost-worker tests.

``python tests/sweep_hold.py COMMAND [options…]`` runs ``ilcrig COMMAND`` with one change: a
point whose id is listed (comma-separated) in ``$ILCRIG_TEST_HOLD`` does not run the first time
a worker gets it: the worker writes ``$ILCRIG_TEST_HOLD_DIR/<point id>/held`` (its pid; the
default folder is ``runs`` of the ``--out`` folder) and waits until its process is ended.  When the
point runs again (a retry on another worker after the held one was killed), the ``held`` file
exists and the point runs normally.  So a test can wait for the other points to finish and the held
one to be holding, and then interrupt the sweep or kill the worker — whatever the machine's speed.
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path
from typing import Any

from host.studies import engine, point

HOLD_ENV = "ILCRIG_TEST_HOLD"
HOLD_DIR_ENV = "ILCRIG_TEST_HOLD_DIR"


def held_run_point(point_id: str, options: dict[str, Any], save_errors: bool) -> dict[str, Any]:
    """The sweep's point function, holding the points named in ``$ILCRIG_TEST_HOLD`` once."""
    if point_id in os.environ.get(HOLD_ENV, "").split(","):
        d = Path(os.environ[HOLD_DIR_ENV]) / point_id
        d.mkdir(parents=True, exist_ok=True)
        if not (d / "held").exists():
            (d / "held.tmp").write_text(f"{os.getpid()}\n")
            os.replace(d / "held.tmp", d / "held")
            while True:  # the end of the worker process ends the hold
                signal.pause()
    return point.run_point(point_id, options, save_errors)


def main(argv: list[str]) -> int:
    import sweep_hold  # this file under its module name, so the workers can import the function

    if HOLD_DIR_ENV not in os.environ and "--out" in argv:
        os.environ[HOLD_DIR_ENV] = str(Path(argv[argv.index("--out") + 1]).resolve() / "runs")
    engine.POINT_FUNCTION = sweep_hold.held_run_point
    from host.cli import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
