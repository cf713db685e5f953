"""A signal at a random moment of ``ilcrig sim`` leaves every record true.

The run is :func:`host.sim.session.run_sim` in this process; SIGTERM comes from a timer thread at
a random delay over the whole command (its start-up, its trials, its end), as from ``kill``. Before
the command installs its handlers and after it gives them back the test's own handler stands for
the default action (the process dies there): it ends the command with :class:`_Died`.

After each example:

* died before the handlers: nothing was made; died after them: the records are final;
* exit 0: every trial kept, ``completed``, no ``interrupted`` marker;
* exit 143: ``interrupted`` SIGTERM, ``end_reason`` interrupted, placed ``after_last_trial``
  exactly when every trial was kept (held while the last trial's outputs were written);
* ``completed`` exactly when every trial was run and kept, whatever the exit code;
* always: the summary's trials = the console's rows = the trials' arrays = the recording's
  trials, and ``report.md`` is there when a trial was kept or the run was interrupted.
"""

from __future__ import annotations

import io
import itertools
import json
import os
import signal
import threading
from pathlib import Path
from types import FrameType

import pytest
from fault_harness import recorded_trials
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytestmark = [pytest.mark.slow]

ITERATIONS = 3
#: the delays drawn, s: the command in this process takes about 1 s (warm)
MAX_DELAY_S = 1.6
_RUNS = itertools.count()


class _Died(BaseException):
    """SIGTERM while the command had no handler of its own: the process would be gone."""


def _default_action(signum: int, _frame: FrameType | None) -> None:
    raise _Died(signum)


@pytest.fixture(scope="module", autouse=True)
def _imports_made(tmp_path_factory: pytest.TempPathFactory) -> None:
    """One run without a signal first: the stand-in for the process's death (:class:`_Died`) may
    land inside an import, which a dead process would never use again, but this interpreter does."""
    from host.experiment.config import build_config
    from host.sim.session import SimOptions, run_sim

    out = tmp_path_factory.mktemp("warm") / "run"
    assert run_sim(SimOptions(build_config(None, {"iterations": 2, "cycle_s": 0.15}), out), io.StringIO()) == 0


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(delay_s=st.floats(0.0, MAX_DELAY_S))
def test_at_random_a_signal_over_ilcrig_sim_leaves_every_record_true(tmp_path: Path, delay_s: float) -> None:
    from host.experiment.config import build_config
    from host.sim.session import SimOptions, run_sim

    out = tmp_path / f"run{next(_RUNS)}"
    console = io.StringIO()
    old = signal.signal(signal.SIGTERM, _default_action)
    timer = threading.Timer(delay_s, os.kill, (os.getpid(), signal.SIGTERM))
    died = False
    try:
        cfg = build_config(None, {"iterations": ITERATIONS, "cycle_s": 0.15})
        timer.start()
        try:
            code = run_sim(SimOptions(cfg, out), console)
        except _Died:
            died, code = True, 143
        timer.join()  # a signal not yet sent lands here: the command has ended
    except _Died:
        died, code = True, 143
    finally:
        timer.cancel()
        signal.signal(signal.SIGTERM, old)
    if died and not (out / "summary.json").exists():
        assert not out.exists() or not any(out.iterdir()), sorted(p.name for p in out.iterdir())
        return
    s = json.loads((out / "summary.json").read_text())
    kept = len(s["iterations"])
    assert "end_reason" in s, "a summary that is not final"
    if not died:
        assert code in (0, 143)
        if code == 0:
            assert s["completed"] is True and kept == ITERATIONS and "interrupted" not in s
        else:
            assert s["interrupted"]["signal"] == "SIGTERM" and s["end_reason"] == "interrupted"
            assert (s["interrupted"]["position"] == "after_last_trial") == (kept == ITERATIONS), s["interrupted"]
    assert s["completed"] is (kept == ITERATIONS), (kept, s.get("interrupted"))  # completed: every trial run and kept
    rows = [ln for ln in console.getvalue().splitlines() if len(ln.split()) == 9 and ln.split()[0].isdigit()]
    assert len(rows) == kept, console.getvalue()
    assert len(list((out / "trials").glob("trial-*.npz"))) == kept
    assert recorded_trials(out / "recording.rrd") == list(range(kept))
    if kept or "interrupted" in s:
        assert (out / "report.md").is_file()
