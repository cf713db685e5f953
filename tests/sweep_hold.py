"""``ilcrig reproduce`` with a hold point, for the interrupt test.

``python tests/sweep_hold.py reproduce [options…]`` runs the command line of ``ilcrig`` with one
change: every experiment whose id is listed (comma-separated) in ``$ILCRIG_TEST_HOLD`` does not
run; its worker writes ``<run folder>/held`` (its pid) and then waits until it is terminated.  So
a test can wait for the other experiments to finish and the held one to be holding, and then
interrupt a sweep that cannot have ended — whatever the machine's speed.
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path
from typing import Any

from host.analysis import sweep

HOLD_ENV = "ILCRIG_TEST_HOLD"
_RUN_ONE = sweep._run_one


def held_run_one(exp: Any, iterations: int, run_dir: str) -> dict[str, Any]:
    """The sweep's worker function, holding the experiments named in ``$ILCRIG_TEST_HOLD``."""
    if exp.id in os.environ.get(HOLD_ENV, "").split(","):
        d = Path(run_dir)
        d.mkdir(parents=True, exist_ok=True)
        (d / "held.tmp").write_text(f"{os.getpid()}\n")
        os.replace(d / "held.tmp", d / "held")
        while True:  # SIGTERM from the sweep ends the worker (default action)
            signal.pause()
    return _RUN_ONE(exp, iterations, run_dir)


def main(argv: list[str]) -> int:
    import sweep_hold  # this file under its module name, so the workers can import the function

    sweep._run_one = sweep_hold.held_run_one
    from host.cli import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
