"""The fault matrix: every fault kind injected into a real multi-process ``ilcrig run``
(hub, plant, four drives, host) with ``--inject``, during trial 1 of 2 (short trials), ends the same
way — exit code 3, one terminal line ``ilcrig: fault: …``, ``summary.json`` with the completed
trial (its digest equal to ``ilcrig sim --iterations 1``), ``completed: false`` and a ``faults``
entry naming the kind, node, trial and tick and who detected it, every drive torque-free (on the
bus or in its log), ``report.md``, a recording with exactly the summary's trials, and no process,
temp folder or temporary file left.  An interrupt keeps 143 and an ``interrupted`` marker.

The edges of the run: every kind once more at one of the positions outside a trial — before the
first trial, between trials, after the last trial (a position chosen per kind, the three spread
over the kinds; ``benchmarks/fault_matrix.py`` draws all of them at random) — ends the same way,
with its ``position`` in the record and the line, no field null that can be known, and after the
last trial ``completed: true`` (every trial was run and kept).  ``ilcrig robot`` (no host; a
python-canopen master holding the enabled robot in CSP) ends the same way when one of its processes
dies: exit code 3, one line ``ilcrig: fault: <process> …``, ``summary.json`` saying which, and no
process left.  The faults a foreign master causes on the robot (its heartbeat, NMT STOP, its RPDOs
or SYNCs stopping, an end stop): tests/test_robot_faults.py, and the ``robot-master-*`` kinds of
``benchmarks/fault_matrix.py``.

Runs one rig at a time (they are timing-sensitive on 2 cores); each waits for the launcher to end.
Marker ``faultmatrix`` (the normal ``pytest`` command runs it; ``-m "not faultmatrix"`` skips it).
Latency goals are measured by ``benchmarks/fault_matrix.py``, not asserted here.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from fault_harness import Outcome, kill_session, recorded_trials, run_rig, sim_digest
from robot_util import robot_fault_run

from bus.transports.hub.wire import BULK_HOLD_S

pytestmark = [pytest.mark.faultmatrix, pytest.mark.multiprocess, pytest.mark.slow]

TICK = 120

# (id, spec, kinds the fault may be reported as, the node it names, who may have detected it)
CASES = [
    ("kill-drive", f"kill:drive2@1:{TICK}", {"node_lost"}, "drive2", {"host"}),
    ("kill-plant", f"kill:plant@1:{TICK}", {"node_lost"}, "plant", {"host"}),
    ("kill-hub", f"kill:hub@1:{TICK}", {"bus_lost", "bus_silent"}, "hub", {"host"}),
    ("kill-host", f"kill:host@1:{TICK}", {"process_died"}, "host", {"launcher"}),
    ("stall-drive", f"stall:drive3@1:{TICK},for=2", {"node_lost"}, "drive3", {"host"}),
    ("stall-plant", f"stall:plant@1:{TICK},for=2", {"node_lost"}, "plant", {"host"}),
    ("stall-hub", f"stall:hub@1:{TICK},for=2", {"bus_silent"}, "hub", {"host"}),
    ("stall-host", f"stall:host@1:{TICK},for=2", {"host_lost"}, "host", {"drive1", "drive2", "drive3", "drive4", "plant"}),
    ("drop-io", f"drop:io@1:{TICK}", {"frame_lost"}, None, {"plant"}),
    ("corrupt-io", f"corrupt:io@1:{TICK}", {"frame_error"}, None, {"host", "plant"}),
    # every receiver lost the frame and says so at once: a drive, the plant or the host's io monitor
    ("overflow-io", f"overflow:io@1:{TICK}", {"frame_lost"}, None, {"host", "plant", "drive1", "drive2", "drive3", "drive4"}),
    ("duplicate-io", f"duplicate:io@1:{TICK}", {"frame_sequence"}, None, {"drive1", "drive2", "drive3", "drive4", "plant"}),
    ("delay-io", f"delay:io@1:{TICK}", {"frame_lost"}, None, {"plant"}),
    ("emcy", f"emcy:drive2@1:{TICK},code=0x8611", {"emcy"}, "drive2", {"drive2"}),
]


def check_common(o: Outcome, kept: int) -> dict:
    """What every faulted run must show; returns the fault entry."""
    assert o.code == 3, (o.stdout[-1500:], o.stderr)
    assert o.left == [], f"processes left: {o.left}"
    assert o.hub_dir is not None and not os.path.exists(o.hub_dir), "the hub's temp folder is left"
    assert "Traceback" not in o.stderr and "Traceback" not in o.stdout
    assert len(o.lines) == 1 and o.lines[0].startswith("ilcrig: fault: "), o.stderr
    s = o.summary
    assert s is not None
    assert o.kept == kept, (o.fault, o.lines)
    assert s["trace_sha256"] == sim_digest(kept)  # the kept trials are exactly `ilcrig sim --iterations k`'s
    f = o.fault
    assert f is not None
    assert s["completed"] is (f["position"] == "after_last_trial")  # then every trial was run and kept
    for key in ("kind", "node", "trial", "position", "detected_by", "latency_ms", "message"):
        assert f.get(key) is not None, key  # never null where it can be known
    assert (f["tick"] is not None) == (f["position"] == "in_trial")  # a tick only in a trial
    # one line: what, which node, where in the run
    assert f"trial {f['trial']}" in o.lines[0] and f"[{f['kind']}]" in o.lines[0]
    assert recorded_trials(o.out / "recording.rrd") == list(range(kept)) == s["recording"]["trials"]
    names = {p.name for p in o.out.rglob("*")}
    assert not {n for n in names if n.endswith(".tmp") or "reserve" in n}, names
    drives = {e["node"]: e for e in s["safe_state"] if str(e["node"]).startswith("drive")}
    assert sorted(drives) == ["drive1", "drive2", "drive3", "drive4"]
    for e in drives.values():
        assert e["torque"] == "off", e
    report = (o.out / "report.md").read_text()
    assert "**Fault**" in report and (o.out / "convergence.png").exists() == (kept > 0)  # a plot of the trials kept
    return f


@pytest.mark.parametrize(("spec", "kinds", "node", "detectors"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_injected_fault_ends_the_run_the_one_way(
    tmp_path: Path, spec: str, kinds: set[str], node: str | None, detectors: set[str]
) -> None:
    o = run_rig(tmp_path / "run", "--inject", spec)
    try:
        f = check_common(o, kept=1)
        assert f["kind"] in kinds, f
        assert f["detected_by"] in detectors, f
        if node is not None:
            assert f["node"] == node, f
        assert f["trial"] == 1
        if f["kind"] not in ("bus_lost",):
            # at (or just after) the injection, as the detector saw the io channel: a frame in flight
            # when the hub stalls may never reach it (one tick earlier); the host's io monitor gets
            # its frames in bulk, up to BULK_HOLD_S late, so a stalled hub keeps those ticks from it
            # (20 ms: 20 ticks at real time, 80 at 4x; the bound allows 5x)
            lag = 1 + (round(5 * BULK_HOLD_S / 1e-3) if spec.startswith("stall:hub") else 0)
            assert f["tick"] is not None and TICK - lag <= f["tick"], f
        assert f["injected"]["spec"] == spec and f["latency_basis"] == "injection"
        if spec.startswith("kill:host"):
            # the host died: the launcher recorded it; the drives saw the host's heartbeat stop
            assert recorded_trials(o.out / "recording.rrd") == [0]  # the recording kept the completed trial
            reasons = {e["evidence"] for e in o.summary["safe_state"] if str(e["node"]).startswith("drive")}
            assert all("heartbeat-of-node-127-lost" in r for r in reasons), reasons
        if spec.startswith(("kill:drive", "kill:plant", "kill:hub")):
            assert f["process_ended"]["name"] == spec.split(":")[1].split("@")[0]
    finally:
        kill_session(o)


# (id, spec, kinds, node, detectors, trials kept, positions it may be detected at) — two trials
EDGE_CASES = [
    ("kill-drive@before", "kill:drive2@before", {"node_lost"}, "drive2", {"host"}, 0, {"before_first_trial", "in_trial"}),
    ("kill-plant@between", "kill:plant@0:end", {"node_lost"}, "plant", {"host"}, 1, {"between_trials", "in_trial"}),
    ("kill-hub@after", "kill:hub@after", {"bus_lost", "bus_silent"}, "hub", {"host"}, 2, {"after_last_trial"}),
    ("kill-host@between", "kill:host@0:end", {"process_died"}, "host", {"launcher"}, 1, {"between_trials"}),
    ("stall-drive@after", "stall:drive3@after,for=2", {"node_lost"}, "drive3", {"host"}, 2, {"after_last_trial"}),
    ("stall-plant@before", "stall:plant@before,for=2", {"node_lost"}, "plant", {"host"}, 0, {"before_first_trial", "in_trial"}),
    ("stall-hub@between", "stall:hub@0:end,for=2", {"bus_silent"}, "hub", {"host"}, 1, {"between_trials", "in_trial"}),
    (
        "stall-host@after",
        "stall:host@after,for=2",
        {"host_lost"},
        "host",
        {"host", "drive1", "drive2", "drive3", "drive4", "plant"},
        2,
        {"after_last_trial"},
    ),
    # the launcher's EMCY goes out when the summary holds trial 0; the host does not wait for it and
    # may have begun trial 1 (its round before a trial saw no EMCY yet): then it is trial 1's fault
    ("emcy@between", "emcy:drive1@0:end,code=0x8611", {"emcy"}, "drive1", {"drive1"}, 1, {"between_trials", "in_trial"}),
    ("corrupt-fieldbus@before", "corrupt:fieldbus@before", {"frame_error"}, "fieldbus", {"host"}, 0, {"before_first_trial"}),
    ("diskfull@before", "diskfull@before", {"disk_full"}, "host", {"host"}, 0, {"before_first_trial"}),
    ("diskfull@in-trial", "diskfull@1:100", {"disk_full"}, "host", {"host"}, 1, {"in_trial"}),
    ("diskfull@after", "diskfull@after", {"disk_full"}, "host", {"host"}, 2, {"after_last_trial"}),
]


@pytest.mark.parametrize(
    ("spec", "kinds", "node", "detectors", "kept", "positions"), [c[1:] for c in EDGE_CASES], ids=[c[0] for c in EDGE_CASES]
)
def test_a_fault_at_the_edges_of_the_run_ends_it_the_one_way(
    tmp_path: Path, spec: str, kinds: set[str], node: str, detectors: set[str], kept: int, positions: set[str]
) -> None:
    o = run_rig(tmp_path / "run", "--inject", spec)
    try:
        f = check_common(o, kept=kept)
        assert f["kind"] in kinds and f["node"] == node and f["detected_by"] in detectors, f
        assert f["position"] in positions, f
        position_words = {
            "before_first_trial": "before the first trial",
            "between_trials": f"between trials {f['trial'] - 1} and {f['trial']}",
            "after_last_trial": "after the last trial (trial 1, kept)",
            "in_trial": f"trial {f['trial']}, tick {f['tick']}",
        }
        assert position_words[f["position"]] in o.lines[0], o.lines[0]
        assert f["injected"]["spec"] == spec and f["latency_basis"] == "injection"
    finally:
        kill_session(o)


def test_full_disk_is_a_fault_with_the_results_kept(tmp_path: Path) -> None:
    """The run folder's writes fail with ENOSPC from trial 1 on (injected in the host): the space
    reserve lets the final summary and report be written with both completed trials."""
    o = run_rig(tmp_path / "run", "--inject", "diskfull@1", iterations=3)
    try:
        f = check_common(o, kept=2)
        assert f["kind"] == "disk_full" and f["detected_by"] == "host"
        assert not (o.out / "summary.json.tmp").exists() and not (o.out / ".ilcrig-reserve").exists()
    finally:
        kill_session(o)


def test_sigterm_keeps_143_and_marks_the_summary(tmp_path: Path) -> None:
    def on_line(line: str, proc) -> None:  # type: ignore[no-untyped-def]
        if line.split()[:1] == ["0"]:  # the row of trial 0: interrupt during trial 1
            os.kill(proc.pid, signal.SIGTERM)

    o = run_rig(tmp_path / "run", on_line=on_line)
    try:
        assert o.code == 143, o.stderr
        assert o.left == []
        assert o.lines == ["ilcrig: interrupted (SIGTERM); stopping 7 processes"]
        s = o.summary
        assert s is not None and s["completed"] is False and s["faults"] == []
        assert s["interrupted"]["signal"] == "SIGTERM" and s["interrupted"]["trial"] == 1
        assert o.kept == 1 and s["trace_sha256"] == sim_digest(1)
        assert all(e["torque"] == "off" for e in s["safe_state"])
    finally:
        kill_session(o)


# the master's receiving thread (python canopen's notifier) ends with an error when the hub dies
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
@pytest.mark.parametrize("victim", ["drive2", "plant", "hub"])
def test_a_killed_process_of_the_robot_ends_it_with_one_line(tmp_path: Path, victim: str) -> None:
    r = robot_fault_run(tmp_path / "robot", victim)
    assert r["code"] == 3, r["stderr"]
    assert len(r["stderr"]) == 1, r["stderr"]
    assert r["stderr"][0].startswith(f"ilcrig: fault: {victim} (pid {r['pids'][victim]}) was killed by SIGKILL")
    assert r["left"] == [], f"processes left: {r['left']}"
    s = r["summary"]
    assert s is not None and s["exit_code"] == 3 and s["end"]["process"] == victim
