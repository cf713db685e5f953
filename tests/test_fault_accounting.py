"""Every injection accounted for and a summary on every exit code, without processes: what
:func:`host.rig.injection_account.account_injections` makes of a run's injection records and fault
records (a fault, tolerated with what it hit, not injected), and the summary the launcher writes
when none was written (:meth:`host.rig.run_outcome.RunOutcome.ensure_summary`: exit 4, an
interrupt before the host started)."""

from __future__ import annotations

import json
from pathlib import Path

from bus.transports.fault_inject import parse_spec
from host.rig.injection_account import account_injections, describe_frame, note_lines
from host.rig.processes import LaunchError
from host.rig.run_outcome import RunOutcome


def _hub_record(spec: str, can_id: int, *, kept: int = 0, t_mono: float = 10.0) -> dict[str, object]:
    return {
        "by": "hub",
        "spec": spec,
        "kind": spec.split(":", 1)[0],
        "target": "fieldbus",
        "trial": -1,
        "tick": None,
        "in_trial": False,
        "kept": kept,
        "can_id": can_id,
        "t_mono": t_mono,
        "t_wall": 1000.0 + t_mono,
    }


def test_a_duplicated_sdo_request_is_tolerated_and_says_what_it_hit() -> None:
    spec = parse_spec("duplicate:fieldbus@before")
    [entry] = account_injections([spec], [_hub_record(spec.text, 0x602)], [], planned=2, ended_early=False)
    assert entry["effect"] == "tolerated" and entry["hits"] == 1
    assert "SDO request to drive2 (0x602)" in entry["what"] and "no fault followed" in entry["what"]
    assert (entry["position"], entry["trial"], entry["tick"]) == ("before_first_trial", 0, None)
    [line] = note_lines([entry], "runs/x/summary.json")
    assert line.startswith("ilcrig: note: --inject duplicate:fieldbus@before tolerated: duplicated an SDO request")


def test_a_late_heartbeat_between_trials_is_tolerated() -> None:
    spec = parse_spec("delay:fieldbus@0:end")
    [entry] = account_injections([spec], [_hub_record(spec.text, 0x77F, kept=1)], [], planned=2, ended_early=False)
    assert entry["effect"] == "tolerated" and "heartbeat of host" in entry["what"] and "consumer time" in entry["what"]
    assert (entry["position"], entry["trial"]) == ("between_trials", 1)


def test_the_injection_of_the_fault_is_the_fault() -> None:
    spec = parse_spec("kill:drive2@1:150")
    rec = {
        "by": "launcher",
        "spec": spec.text,
        "kind": "kill",
        "target": "drive2",
        "trial": 1,
        "tick": 150,
        "kept": 1,
        "when": "tick",
    }
    fault = {"kind": "node_lost", "node": "drive2", "message": "heartbeat of drive2 lost", "injected": {"spec": spec.text}}
    [entry] = account_injections([spec], [rec], [fault], planned=2, ended_early=True)
    assert entry["effect"] == "fault" and entry["what"].startswith("node_lost of drive2")
    assert (entry["position"], entry["trial"], entry["tick"]) == ("in_trial", 1, 150)


def test_an_injection_whose_moment_never_came() -> None:
    specs = [parse_spec("kill:drive2@1:150"), parse_spec("corrupt:fieldbus@after,id=0x7FF")]
    entries = account_injections(specs, [], [], planned=2, ended_early=True)
    assert [e["effect"] for e in entries] == ["not_injected", "not_injected"]
    [entry] = account_injections(specs[1:], [], [], planned=2, ended_early=False)
    assert "no COB-ID 0x7FF frame passed on the fieldbus" in entry["what"]


def test_frames_in_words() -> None:
    assert describe_frame("fieldbus", 0x582) == "an SDO answer of drive2 (0x582)"
    assert describe_frame("fieldbus", 0x720) == "the heartbeat of plant (0x720)"
    assert describe_frame("fieldbus", 0x081) == "an EMCY of drive1 (0x081)"
    assert describe_frame("io", 0x101) == "the encoder frame of joint 1 (0x101)"


def _outcome(tmp_path: Path, lines: list[str]) -> RunOutcome:
    (tmp_path / "logs").mkdir()
    return RunOutcome(
        tmp_path, [], lines.append, config=lambda: {"iterations": 2, "n_ticks": 301}, specs=[parse_spec("kill:drive2@1:150")]
    )


def test_a_process_that_could_not_start_leaves_a_summary(tmp_path: Path) -> None:
    outcome = _outcome(tmp_path, [])
    assert outcome.ensure_summary(
        4, LaunchError("cannot start drive3 (python -P -m host.cli …): [Errno 2] No such file", "drive3")
    )
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["written_by"] == "launcher" and s["exit_code"] == 4 and s["end_reason"] == "fault" and not s["completed"]
    [fault] = s["faults"]
    assert (fault["kind"], fault["node"], fault["position"], fault["trial"], fault["tick"]) == (
        "process_died",
        "drive3",
        "before_first_trial",
        0,
        None,
    )
    assert fault["t_detected_mono"] is not None and fault["t_detected_wall"] is not None
    assert s["injections"][0]["effect"] == "not_injected"
    assert (tmp_path / "report.md").exists()
    assert not outcome.ensure_summary(4)  # one summary: the one there is kept


def test_an_interrupt_before_the_host_started_leaves_a_summary(tmp_path: Path) -> None:
    assert _outcome(tmp_path, []).ensure_summary(143)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["end_reason"] == "interrupted" and s["faults"] == []


def test_bad_input_writes_no_summary(tmp_path: Path) -> None:
    assert not _outcome(tmp_path, []).ensure_summary(2)
    assert not (tmp_path / "summary.json").exists()


def test_a_launcher_that_failed_leaves_a_summary(tmp_path: Path) -> None:
    assert _outcome(tmp_path, []).ensure_summary(1)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["exit_code"] == 1 and s["faults"][0]["node"] == "launcher" and "exit code 1" in s["faults"][0]["message"]


def test_a_fault_of_another_node_is_not_the_injections() -> None:
    spec = parse_spec("stall:drive3@before,for=0.1")
    rec = {"by": "launcher", "spec": spec.text, "kind": "stall", "target": "drive3", "kept": 0, "when": "before", "t_mono": 1.0}
    fault = {"kind": "node_lost", "node": "drive1", "message": "heartbeat of drive1 lost", "injected": {"spec": spec.text}}
    [entry] = account_injections([spec], [rec], [fault], planned=2, ended_early=True)
    assert entry["effect"] == "tolerated" and "node_lost of drive1" in entry["what"] and "was not its" in entry["what"]


def test_a_fault_in_a_trial_is_not_placed_before_its_injection() -> None:
    from host.experiment.faults import FaultRecord
    from host.rig.run_outcome import not_before_injection

    record = FaultRecord("bus_lost", "the hub was killed", node="hub", position="in_trial", trial=1, tick=44)
    record.injected = {"spec": "kill:hub@1:92", "trial": 1, "tick": 92}
    assert not_before_injection(record, 301).tick == 92  # the host's io monitor was a round behind
    record.tick = 120
    assert not_before_injection(record, 301).tick == 120  # a later tick is the detector's own
    record.position, record.tick = "between_trials", None
    assert not_before_injection(record, 301).tick is None
    record.position, record.tick, record.injected = "in_trial", 301, None
    assert not_before_injection(record, 301).tick == 300  # never after the trial's last tick
