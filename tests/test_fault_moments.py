"""Outside signals at the edges of a run: a process killed while the host starts up
still leaves a summary.json (the launcher writes the one the host could not), with the fault's
kind, node and both detection times; a printed trial is never lost.

Each test runs the real multi-process rig (tests/fault_harness.py) and signals a process at a
moment it waits for on the launcher's stdout (the status line, the host's header line, a trial's
row) — never sleep-then-assert.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import threading
from pathlib import Path
from typing import Any

import pytest
from fault_harness import Outcome, host_pid, kill_session, recorded_trials, run_rig, sim_digest, status_pids

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


def _pids(line: str) -> dict[str, int]:
    return status_pids(line)


def _host_pid(out: Path) -> int:
    pid = host_pid(out)
    if pid is None:
        raise AssertionError("no host process")
    return pid


def _signal(pid: int, signum: int) -> None:
    """``signum`` to ``pid`` from a timer thread; a process already gone (the run ended) is no error."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signum)


def _stall_after(delay_s: float, pid: int, stall_s: float = 3.0) -> None:
    """In ``delay_s``: stop process ``pid`` (SIGSTOP) for ``stall_s`` (then SIGCONT); returns at once."""

    def stall() -> None:
        _signal(pid, signal.SIGSTOP)
        threading.Timer(stall_s, _signal, (pid, signal.SIGCONT)).start()

    threading.Timer(delay_s, stall).start()


def _check_launcher_summary(o: Outcome, node: str) -> dict[str, Any]:
    try:
        assert o.code == 3, o.stderr
        assert o.summary is not None, f"no summary.json: {sorted(p.name for p in o.out.iterdir())}"
        assert o.summary["written_by"] == "launcher" and o.summary["iterations"] == [] and not o.summary["completed"]
        assert o.summary["config"]["iterations"] == 2
        fault = o.fault
        assert fault is not None
        assert (fault["kind"], fault["node"], fault["position"], fault["trial"]) == (
            "process_died",
            node,
            "before_first_trial",
            0,
        )
        assert fault["t_detected_wall"] is not None and fault["t_detected_mono"] is not None
        assert (o.out / "report.md").exists()
        assert o.lines[-1].startswith("ilcrig: fault: ") and str(o.out / "summary.json") in o.lines[-1]
        assert not o.left
        return fault
    except AssertionError:
        kill_session(o)
        raise


def test_host_killed_while_it_starts_up_leaves_a_summary(tmp_path: Path) -> None:
    out = tmp_path / "run"

    def on_line(line: str, proc: Any) -> None:
        if line.startswith("ilcrig host:"):  # the host's header line: it is starting up
            host = _host_pid(out)
            threading.Timer(0.08, _signal, (host, signal.SIGKILL)).start()

    _check_launcher_summary(run_rig(out, on_line=on_line), "host")


def test_hub_killed_during_bring_up_leaves_a_summary(tmp_path: Path) -> None:
    out = tmp_path / "run"

    def on_line(line: str, proc: Any) -> None:
        if pids := _pids(line):  # every role started, the host about to: bring-up
            os.kill(pids["hub"], signal.SIGKILL)

    fault = _check_launcher_summary(run_rig(out, on_line=on_line), "hub")
    assert fault["process_ended"]["name"] == "hub"


@pytest.mark.parametrize("delay_s", [0.005, 0.03])
def test_a_printed_trial_is_kept_when_the_host_is_killed_after_its_row(tmp_path: Path, delay_s: float) -> None:
    out = tmp_path / "run"
    host: list[int] = []

    def on_line(line: str, proc: Any) -> None:
        if line.startswith("ilcrig host:"):
            host.append(_host_pid(out))
        elif re.match(r"\s+0\s+\d", line):  # trial 0's row: from now on trial 0 must be kept
            threading.Timer(delay_s, _signal, (host[0], signal.SIGKILL)).start()

    o = run_rig(out, iterations=3, on_line=on_line)
    try:
        assert o.code == 3, o.stderr
        assert o.summary is not None and o.kept >= 1, o.stderr
        fault = o.fault
        assert fault is not None and (fault["kind"], fault["node"]) == ("process_died", "host")
        assert fault["t_detected_wall"] is not None
        assert (o.out / "trials").is_dir() and any((o.out / "trials").iterdir())
        assert 0 in recorded_trials(o.out / "recording.rrd")
        assert not o.left
    finally:
        kill_session(o)


def test_an_emcy_of_the_plant_is_recorded_where_it_came(tmp_path: Path) -> None:
    o = run_rig(tmp_path / "run", "--inject", "emcy:plant@1:150,code=0x8611")
    try:
        assert o.code == 3, o.stderr
        fault = o.fault
        assert fault is not None and (fault["kind"], fault["node"], fault["trial"]) == ("emcy", "plant", 1), fault
        assert fault["position"] == "in_trial" and fault["tick"] is not None and fault["tick"] >= 150, fault
        assert fault["t_detected_wall"] is not None and fault["injected"]["spec"].startswith("emcy:plant@1:150")
        assert o.kept == 1 and not o.left
    finally:
        kill_session(o)


def test_a_hub_killed_between_trials_is_recorded_as_the_hub(tmp_path: Path) -> None:
    pids: dict[str, int] = {}

    def on_line(line: str, proc: Any) -> None:
        pids.update(_pids(line))
        if re.match(r"\s+0\s+\d", line):  # trial 0 kept: the host configures trial 1 (SDO traffic)
            os.kill(pids["hub"], signal.SIGKILL)

    o = run_rig(tmp_path / "run", iterations=3, on_line=on_line)
    try:
        assert o.code == 3, o.stderr
        fault = o.fault
        assert fault is not None and fault["node"] == "hub" and fault["kind"] in ("bus_lost", "bus_silent"), fault
        assert fault["t_detected_wall"] is not None and fault["t_detected_mono"] is not None
        assert o.kept >= 1 and not o.left
    finally:
        kill_session(o)


@pytest.mark.parametrize(("victim", "kind"), [("drive2", "node_lost"), ("hub", "bus_silent")])
def test_a_stall_after_the_last_row_is_a_fault(tmp_path: Path, victim: str, kind: str) -> None:
    """A 3 s stall 0.6 s after the last trial's row, while the host closes and writes its outputs,
    is never silent; which record it gets depends on when the launcher's heartbeat consumer notices
    it (its consumer time after the stall began) against the host's end, a race with the machine's
    speed: noticed while the host still ran (the results not yet safe), the run's fault (exit 3,
    ``after_last_trial``, detected by the launcher); noticed after, a liveness incident of the
    victim in the summary with an ``ilcrig: note:`` line, the run completed (exit 0). Either way
    every trial is kept and nothing is left."""
    pids: dict[str, int] = {}

    def on_line(line: str, proc: Any) -> None:
        pids.update(_pids(line))
        if re.match(r"\s+1\s+\d", line):  # the last trial's row: the host closes and writes its outputs
            _stall_after(0.6, pids[victim])

    o = run_rig(tmp_path / "run", on_line=on_line)
    try:
        assert o.code in (0, 3), o.stderr
        assert o.summary is not None and o.kept == 2 and o.summary["completed"] and not o.left
        if o.code == 3:
            fault = o.fault
            assert fault is not None and (fault["kind"], fault["node"], fault["detected_by"]) == (kind, victim, "launcher"), fault
            assert fault["position"] == "after_last_trial" and fault["t_detected_wall"] is not None
            assert o.lines[-1].startswith("ilcrig: fault: ")
        else:
            assert not o.summary["faults"]
            incidents = o.summary["liveness_incidents"]
            assert [i["node"] for i in incidents] == [victim], incidents
            assert "results safe already" in incidents[0]["what"] and incidents[0]["position"] == "after_last_trial"
            assert any(ln.startswith(f"ilcrig: note: {victim} ") for ln in o.lines), o.stderr
    finally:
        kill_session(o)


@pytest.mark.parametrize(
    ("moment", "victim", "kind", "position"),
    [
        ("header", "drive2", "node_lost", "before_first_trial"),
        ("header", "host", "host_lost", "before_first_trial"),
        ("last_row", "host", "host_lost", "after_last_trial"),
    ],
)
def test_a_stall_at_bring_up_or_of_the_host_at_the_end_is_a_fault(
    tmp_path: Path, moment: str, victim: str, kind: str, position: str
) -> None:
    out = tmp_path / "run"
    pids: dict[str, int] = {}

    def on_line(line: str, proc: Any) -> None:
        pids.update(_pids(line))
        if line.startswith("ilcrig host:"):
            pids["host"] = _host_pid(out)
            if moment == "header":  # the host brings the nodes up
                _stall_after(0.1, pids[victim])
        elif moment == "last_row" and re.match(r"\s+1\s+\d", line):
            _stall_after(0.6, pids[victim])

    o = run_rig(out, on_line=on_line)
    try:
        assert o.code == 3, o.stderr
        fault = o.fault
        assert fault is not None and (fault["kind"], fault["node"], fault["position"]) == (kind, victim, position), fault
        assert fault["t_detected_wall"] is not None and o.summary is not None
        assert o.lines[-1].startswith("ilcrig: fault: ") and not o.left
    finally:
        kill_session(o)


def test_a_role_that_cannot_be_started_leaves_a_summary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Exit 4 (a process of the run could not be started) ends with a summary too, naming it."""
    monkeypatch.setenv("ILCRIG_ROLE_CMD_DRIVE3", str(tmp_path / "no-such-program"))
    o = run_rig(tmp_path / "run")
    try:
        assert o.code == 4, o.stderr
        assert o.lines[-1].startswith("ilcrig: error: cannot start drive3"), o.stderr
        assert o.summary is not None and o.summary["written_by"] == "launcher" and o.summary["exit_code"] == 4
        fault = o.fault
        assert fault is not None and (fault["kind"], fault["node"], fault["position"]) == (
            "process_died",
            "drive3",
            "before_first_trial",
        )
        assert fault["t_detected_wall"] is not None and not o.left
    finally:
        kill_session(o)


@pytest.mark.parametrize("moment", ["status", "closing"])
def test_a_sigterm_to_the_launcher_is_in_the_summary_as_in_the_exit_code(tmp_path: Path, moment: str) -> None:
    """SIGTERM to ``ilcrig run`` at its status line (before the host: the launcher's summary):
    exit 143 and a summary that says ``interrupted`` with ``end_reason`` interrupted, as
    ``report.md`` does. At the host's closing line (the run completed, the processes not yet
    stopped): the run's records and exit code stand — exit 0, ``completed``, no marker — and one
    line says the run had completed before the signal; never a 143 whose summary says completed
    and nothing else."""
    out = tmp_path / "run"
    sent: list[str] = []

    def on_line(line: str, proc: Any) -> None:
        if sent:
            return
        if (moment == "status" and line.startswith("ilcrig run:")) or (moment == "closing" and "trace_sha256" in line):
            sent.append(line)
            _signal(proc.pid, signal.SIGTERM)

    o = run_rig(out, on_line=on_line)
    assert sent and o.summary is not None and o.left == [], (o.stdout, o.stderr)
    s = o.summary
    if moment == "closing":
        assert o.code == 0, o.stderr
        assert s["completed"] is True and "interrupted" not in s and s["end_reason"] == "completed" and len(s["iterations"]) == 2
        assert "interrupted" not in o.stderr or "the run had completed before SIGTERM: every trial kept" in o.stderr
        return
    assert o.code == 143, o.stderr
    assert s["interrupted"]["signal"] == "SIGTERM" and s["end_reason"] == "interrupted"
    assert s["iterations"] == [] and s["interrupted"]["position"] == "before_first_trial"
    assert "**Interrupted** by SIGTERM, before the first trial" in (out / "report.md").read_text()


def _run_tree(root: int) -> list[int]:
    """``root`` and every process below it (the role processes lead sessions of their own, but
    their parent is the launcher), from /proc."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(d.name))
    found, todo = [], [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo += children.get(pid, [])
    return found


def test_a_freeze_of_the_whole_machine_is_no_fault(tmp_path: Path) -> None:
    """Every process of the run stopped at once for 1.5 s -- what a virtual machine the hypervisor
    does not run looks like from inside -- longer than the heartbeat consumer time (0.5 s), the
    drives' SDO server timeout and the plant's tick deadline (1 s): each process that did not run
    itself judges the others from when it runs again, lockstep time stood still, so the run
    completes with the digest of the same experiment in process and says what happened in a note
    and in the summary."""
    frozen: list[int] = []

    def on_line(line: str, proc: Any) -> None:
        if not frozen and re.match(r"\s+0\s+\d", line):  # trial 0's row: the run goes on to trial 1
            frozen.extend(_run_tree(proc.pid))  # the launcher first, stopped first and continued last
            for pid in frozen:
                _signal(pid, signal.SIGSTOP)

            def thaw() -> None:
                for pid in reversed(frozen):
                    _signal(pid, signal.SIGCONT)

            threading.Timer(1.5, thaw).start()

    o = run_rig(tmp_path / "run", iterations=3, on_line=on_line)
    try:
        assert len(frozen) >= 7, frozen  # launcher, hub, plant, four drives, host
        assert o.code == 0, o.stderr
        assert o.summary is not None and o.summary["completed"] and not o.summary["faults"] and not o.left
        assert o.summary["trace_sha256"] == sim_digest(3)
        stalls = o.summary["bench"]["heartbeat"]["host_stalls"]
        assert len(stalls) == 1 and stalls[0]["gap_ms"] > 1000, stalls
        assert stalls[0]["what"].endswith("the nodes did not run either (the whole machine was stopped); not a fault")
        assert f"ilcrig: note: {stalls[0]['what']}; recorded in {o.out / 'summary.json'}" in o.stderr
    finally:
        kill_session(o)
