"""A law may take as long as it needs on the rig, up to a documented limit (docs/api.md §5): a
5-second pure-Python update after every trial completes with the digest of the same run in
process, and so does one call that holds the GIL for seconds (the host's heartbeat is written by a
thread of C on the hub); past the limit (``ILCRIG_LAW_UPDATE_LIMIT_S``) the run ends with a fault
naming the law; where a Python thread sends the heartbeat (the hub's C core switched off), a call
that holds the GIL longer than the heartbeat consumer time ends it as ``host_lost`` with the law
named.  Full tier: each test starts a rig (scripted law: tests/rig_scripted_law.py)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from rig_scripted_law import SCRIPT_ENV

import ilcrig
from bus.transports.hub.core import HUB_CORE_ENV
from host.experiment.law_watch import LAW_LIMIT_ENV

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

LAW = "rig_scripted_law:RigScriptedLaw"


@contextmanager
def environment(**values: str) -> Iterator[None]:
    """``values`` in this process's environment (the rig's processes inherit it) for a while."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def test_a_five_second_update_completes_on_the_rig(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law=LAW, iterations=2, cycle_s=0.15)
    with environment(**{SCRIPT_ENV: json.dumps({"kind": "busy", "seconds": 5.0})}):
        rig = exp.run(mode="rig", out=tmp_path / "rig", bus="hub", timeout_s=600)
        sim = exp.run()
    assert rig.completed and rig.end_reason == "completed" and not rig.summary["faults"]
    assert rig.digest == sim.digest


def test_past_the_limit_the_run_ends_with_a_fault_naming_the_law(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law=LAW, iterations=2, cycle_s=0.15)
    with environment(**{SCRIPT_ENV: json.dumps({"kind": "busy", "seconds": 8.0}), LAW_LIMIT_ENV: "2"}):
        rig = exp.run(mode="rig", out=tmp_path / "rig", bus="hub", timeout_s=600)
    assert rig.end_reason == "law_error" and len(rig) == 1
    message = rig.summary["faults"][0]["message"]
    assert "law rig-scripted-p did not return from its update after trial 0 within the limit on the rig (2 s" in message
    assert "in update" in (tmp_path / "rig" / "logs" / "law-error.log").read_text()  # where the law's code was
    err = (tmp_path / "rig" / "console.err").read_text()  # the launcher's fault line points to it
    assert f"the law's traceback: {tmp_path / 'rig' / 'logs' / 'law-error.log'}" in err


def test_a_call_holding_the_gil_for_seconds_completes_on_the_rig(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law=LAW, iterations=2, cycle_s=0.15)
    with environment(**{SCRIPT_ENV: json.dumps({"kind": "gil_call", "n": 300_000_000})}):
        rig = exp.run(mode="rig", out=tmp_path / "rig", bus="hub", timeout_s=600)
        sim = exp.run()
    assert rig.completed and rig.end_reason == "completed" and not rig.summary["faults"]
    assert rig.digest == sim.digest
    # the call did hold the host's interpreter longer than the nodes' consumer time (the law watch's warning)
    assert "the host's threads did not run for" in (tmp_path / "rig" / "logs" / "host.log").read_text()


def test_without_the_c_writer_a_call_holding_the_gil_is_named_as_the_cause_of_the_lost_host(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law=LAW, iterations=2, cycle_s=0.15)
    script = json.dumps({"kind": "gil_call", "n": 100_000_000})
    with environment(**{SCRIPT_ENV: script, HUB_CORE_ENV: "python"}):  # a Python thread sends the heartbeat
        rig = exp.run(mode="rig", out=tmp_path / "rig", bus="hub", timeout_s=600)
    assert rig.end_reason == "law_error" and len(rig) == 1
    fault = rig.summary["faults"][0]
    assert fault["kind"] == "host_lost"
    assert "during law rig-scripted-p's update after trial 0 the host's threads did not run for" in fault["message"]
    assert "a call of the law that holds the GIL" in fault["message"]
