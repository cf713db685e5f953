"""A learning law for the rig's interrupt/failure tests (tests/test_api_rig_interrupts.py), imported by
the rig's host process as ``rig_scripted_law:RigScriptedLaw`` (the API puts this folder on its
``PYTHONPATH``).  It is told what to do by the environment variable :data:`SCRIPT_ENV` (JSON:
``kind``, ``at``, ``dir``), inherited from the test through the launcher:

* ``law_error``: its update after trial ``at`` raises ``ZeroDivisionError("scripted")``;
* ``update_signal``: its update after trial ``at`` writes ``<dir>/update-<at>`` and then waits (up to
  :data:`HOLD_S`) for the signal the test sends on seeing that file, so the signal falls inside the
  update;
* ``busy``: every update runs a pure-Python busy loop of ``seconds`` (holding the GIL but for the
  interpreter's switch interval) before it returns;
* ``gil_call``: every update makes one C call that holds the GIL throughout (``sum(range(n))``).

Otherwise a P-type update ``u + 0.5·40·e[n+1]`` (the same in-process and on the rig).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from host.learning.protocol import TrialData
from host.learning.signals import lead

#: the environment variable with the script (JSON)
SCRIPT_ENV = "ILCRIG_TEST_RIG_SCRIPT"
#: the longest an ``update_signal`` update waits for its signal, s
HOLD_S = 120.0


class RigScriptedLaw:
    """The scripted law (module docstring)."""

    name = "rig-scripted-p"

    def __init__(self, ctx: Any = None) -> None:
        self.script: dict[str, Any] = json.loads(os.environ.get(SCRIPT_ENV, "{}"))

    def update(self, trial: TrialData) -> Any:
        kind, at = self.script.get("kind"), self.script.get("at")
        if kind == "busy":
            t0 = time.perf_counter()
            x = 0
            while time.perf_counter() - t0 < float(self.script["seconds"]):
                x += 1  # pure Python: the interpreter lets other threads run every switch interval
        elif kind == "gil_call":
            sum(range(int(self.script["n"])))  # one C call: the interpreter cannot switch threads
        elif trial.trial == at and kind == "law_error":
            raise ZeroDivisionError("scripted")
        elif trial.trial == at and kind == "update_signal":
            Path(self.script["dir"], f"update-{at}").write_text(str(os.getpid()))
            t0 = time.monotonic()
            while time.monotonic() - t0 < HOLD_S:
                time.sleep(0.01)  # the test's signal ends the run here
        lp = 0.5 * np.full(trial.error_rad.shape[1], 40.0)
        return trial.feedforward_nm + lp * lead(trial.error_rad, 1)
