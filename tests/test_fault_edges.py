"""Faults at the edges of a run, without role processes: where a fault is placed (before the first
trial, in a trial, between trials, after the last trial) and what its one line says; the
``--inject`` forms of the edges and the injections refused before anything starts; latencies and
nodes the classification fills in; every SDO error an ``sdo_error`` through the one fault path; a
bench that reports a fault while it closes ends a completed run with exit code 3; a signal while
a trial's outputs are written is held back until they are."""

from __future__ import annotations

import io
import json
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bus.errors import SdoAbort
from bus.transports.fault_inject import FaultSpecError, check_specs, parse_spec
from host.experiment.faults import FaultKind, FaultRecord, Position, fault_line, position_of
from host.nodes.sdo_access import SdoTransportError, sdo_errors
from host.rig.fault_classify import DetectionTimes, EmcyFrame, emcy_fault, heartbeat_fault, host_stall_fault, sdo_fault

# ---------------------------------------------------------------------------------------
# positions and the one line
# ---------------------------------------------------------------------------------------


def test_positions_from_what_was_kept() -> None:
    assert position_of(0, 3, False) == (Position.BEFORE_FIRST_TRIAL, 0)
    assert position_of(0, 3, True) == (Position.IN_TRIAL, 0)
    assert position_of(2, 3, True) == (Position.IN_TRIAL, 2)
    assert position_of(1, 3, False) == (Position.BETWEEN_TRIALS, 1)
    assert position_of(3, 3, False) == (Position.AFTER_LAST_TRIAL, 2)  # the last trial, not a trial 3 of 3


@pytest.mark.parametrize(
    ("position", "trial", "tick", "where", "kept_text"),
    [
        (Position.IN_TRIAL, 1, 150, "drive2, trial 1, tick 150", "1 completed trial kept"),
        (Position.BEFORE_FIRST_TRIAL, 0, None, "drive2, before the first trial (trial 0 not started)", "0 completed trials kept"),
        (Position.BETWEEN_TRIALS, 1, None, "drive2, between trials 0 and 1 (trial 1 not started)", "1 completed trial kept"),
        (Position.AFTER_LAST_TRIAL, 2, None, "drive2, after the last trial (trial 2, kept)", "all 3 trials kept"),
    ],
)
def test_the_one_line_says_where(position: Position, trial: int, tick: int | None, where: str, kept_text: str) -> None:
    rec = FaultRecord(FaultKind.NODE_LOST, "heartbeat of drive2 lost", node="drive2", node_id=2, trial=trial, tick=tick)
    rec.position = str(position)
    kept = {Position.IN_TRIAL: 1, Position.BEFORE_FIRST_TRIAL: 0, Position.BETWEEN_TRIALS: 1, Position.AFTER_LAST_TRIAL: 3}
    line = fault_line(rec, kept[position], summary_path="s.json")
    assert line == (
        f"ilcrig: fault: heartbeat of drive2 lost [node_lost]: {where}; detected by host; torque removed, {kept_text}; "
        "summary: s.json"
    )
    again = FaultRecord.from_dict(json.loads(json.dumps(rec.as_dict())))
    assert again.position == position and again.where() == where


# ---------------------------------------------------------------------------------------
# --inject at the edges, and what cannot happen
# ---------------------------------------------------------------------------------------


def test_edge_forms_of_inject() -> None:
    assert (parse_spec("kill:drive2@before").when, parse_spec("stall:hub@after").when) == ("before", "after")
    sp = parse_spec("emcy:drive3@1:end,code=0x8611")
    assert (sp.when, sp.trial, sp.emcy_code) == ("end", 1, 0x8611)
    assert parse_spec("kill:plant@2:17").when == "tick"
    assert (parse_spec("diskfull@2").when, parse_spec("diskfull@2").trial) == ("end", 2)  # from trial 2's outputs on
    assert parse_spec("diskfull@0:40").when == "tick"  # in trial 0: the io log
    after = parse_spec("kill:hub@after").resolved(5)
    assert (after.when, after.trial) == ("end", 4)
    with pytest.raises(FaultSpecError, match="TRIAL:TICK .*TRIAL:end, before or after"):
        parse_spec("kill:drive1@soon")


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("stall:host@0:99999", "tick 99999 is beyond a trial of 301 ticks (0..300); after the trial is @0:end"),
        ("kill:drive1@0:301", "tick 301 is beyond a trial of 301 ticks"),
        ("kill:drive1@3:0", "trial 3 is beyond the run's 3 trials (0..2)"),
        ("emcy:drive1@3:end", "trial 3 is beyond the run's 3 trials"),
        ("diskfull@3", "trial 3 is beyond the run's 3 trials"),
        ("drop:io@before", "the io channel carries frames only during a trial"),
        ("corrupt:io@1:end", "the io channel carries frames only during a trial"),
        ("delay:io@after", "the io channel carries frames only during a trial"),
    ],
)
def test_injections_that_cannot_happen_are_refused(spec: str, message: str) -> None:
    with pytest.raises(FaultSpecError) as exc:
        check_specs([parse_spec(spec)], iterations=3, n_ticks=301, hub=True)
    assert str(exc.value) == f"--inject {spec}: {message}" or str(exc.value).startswith(f"--inject {spec}: {message}")


def test_injections_that_can_happen_pass() -> None:
    specs = [parse_spec(s) for s in ("kill:drive1@before", "stall:host@2:300", "corrupt:fieldbus@before", "emcy:plant@after")]
    check_specs(specs, iterations=3, n_ticks=301, hub=True)
    with pytest.raises(FaultSpecError, match="frame faults are done by the hub"):
        check_specs([parse_spec("corrupt:fieldbus@before")], iterations=3, n_ticks=301, hub=False)
    with pytest.raises(FaultSpecError, match="this transport has no hub"):
        check_specs([parse_spec("kill:hub@before")], iterations=3, n_ticks=301, hub=False)


def test_the_cli_refuses_them_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from host.cli import main

    monkeypatch.chdir(tmp_path)  # a refusal that regressed would write a run into the current folder
    out = tmp_path / "run"
    for argv, line in (
        (
            ["--inject", "stall:host@0:99999"],
            "ilcrig: error: --inject stall:host@0:99999: tick 99999 is beyond a trial of 301 ticks",
        ),
        (["--inject", "drop:io@after"], "ilcrig: error: --inject drop:io@after: the io channel carries frames only"),
    ):
        assert main(["run", "--iterations", "2", "--cycle", "0.15", "--out", str(out), *argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith(line), err
    assert main(["run", "--iterations", "2", "--out", ""]) == 2
    assert capsys.readouterr().err == "ilcrig: error: --out '': an empty path (give the run folder)\n"
    assert main(["sim", "--iterations", "1", "--out", ""]) == 2
    assert capsys.readouterr().err == "ilcrig: error: --out '': an empty path (give the run folder)\n"
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_pick_equal_to_place_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from host.cli import main

    path = tmp_path / "same.toml"
    path.write_text('name = "same"\npick = [0.01, 0.0, -0.65]\nplace = [0.01, 0.0, -0.65]\nlift = 0.02\nrotation_deg = 0\n')
    assert main(["sim", "--path", str(path), "--out", str(tmp_path / "run")]) == 2
    assert (
        capsys.readouterr().err
        == f"ilcrig: error: path file {path}: pick and place are the same point: there is nothing to carry\n"
    )
    assert not (tmp_path / "run").exists()


def test_no_room_says_how_many_trials_were_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    from host.experiment import outputs

    real = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(outputs.shutil, "disk_usage", lambda _: real._replace(free=4096))
    outputs.check_out_dir(tmp_path, create=False)  # the first, fast check: no experiment yet, no space asked
    with pytest.raises(outputs.OutFolderError) as exc:
        outputs.check_out_dir(tmp_path, iterations=1, n_ticks=301, create=False)
    need = outputs.reserve_bytes(1, 301) // 1024
    assert str(exc.value) == (
        f"--out {tmp_path}: only 4 KiB free on its filesystem; a run of 1 trial of 301 ticks needs at least {need} KiB "
        "for its final results"
    )


# ---------------------------------------------------------------------------------------
# what the classification fills in
# ---------------------------------------------------------------------------------------


def test_latencies_come_from_the_detectors_clock() -> None:
    times = DetectionTimes.scaled(2.0)  # ILCRIG_TIMEOUT_SCALE = 2: consumer 1000 ms, period 400 ms
    rec = emcy_fault(EmcyFrame(3, 0x8130, b"", 1.0, 2.0), times)
    assert (rec.kind, rec.node, rec.latency_ms, rec.latency_basis) == (
        FaultKind.HOST_LOST,
        "host",
        pytest.approx(600.0),
        "its next heartbeat was due",
    )
    assert emcy_fault(EmcyFrame(1, 0x8611, b"", 1.0, 2.0), times).latency_ms == 0.0
    rec = host_stall_fault(2.0, 10.0, DetectionTimes())
    assert (rec.kind, rec.detected_by, rec.latency_ms) == (FaultKind.HOST_LOST, "host", pytest.approx(1800.0))
    from bus.cia301.nmt import HeartbeatReport

    heard = dict.fromkeys((1, 2, 3, 4, 32), 9.0)
    rec = heartbeat_fault(HeartbeatReport(overdue=[1, 2, 3, 4, 32]), heard, 10.0, consumer_s=0.5, period_s=0.2, bus_name="hub")
    assert rec is not None and (rec.kind, rec.node, rec.latency_ms) == (FaultKind.BUS_SILENT, "hub", pytest.approx(800.0))


def test_an_sdo_error_is_an_sdo_error_with_its_wait() -> None:
    rec = sdo_fault(SdoTransportError("node 2: read failed", 2, elapsed_s=5.0), 1, 3.0)
    assert (rec.kind, rec.node, rec.latency_ms, rec.latency_basis) == (
        FaultKind.SDO_ERROR,
        "drive2",
        5000.0,
        "the SDO request (no answer)",
    )
    rec = sdo_fault(SdoAbort(0x06090011, "node 3 write"), 1, 3.0)
    assert (rec.kind, rec.node, rec.latency_ms) == (FaultKind.SDO_ERROR, "host", 0.0)


def test_canopens_own_sdo_errors_become_the_projects() -> None:
    from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

    with pytest.raises(SdoTransportError) as exc, sdo_errors(2, "heartbeat configuration"):
        raise SdoCommunicationError("No SDO response received")
    assert exc.value.node_id == 2 and exc.value.elapsed_s is not None
    assert str(exc.value) == "node 2: heartbeat configuration failed: No SDO response received"
    with pytest.raises(SdoAbort), sdo_errors(None, "bring-up"):
        raise SdoAbortedError(0x06020000)


# ---------------------------------------------------------------------------------------
# the trial loop's one fault path at the edges (a fake bench)
# ---------------------------------------------------------------------------------------


class FakeBench:
    """The in-process bench with faults at chosen moments."""

    def __init__(self, cfg: Any, *, fail_start: BaseException | None = None, closing: FaultRecord | None = None) -> None:
        from host.sim.inprocess import InProcessBench

        self.inner = InProcessBench(cfg)
        self.fail_start = fail_start
        self.closing = closing
        self.on_trial: Any = None

    @property
    def drives(self) -> Any:
        return self.inner.drives

    def start(self) -> None:
        if self.fail_start is not None:
            raise self.fail_start
        self.inner.start()

    def run_trial(self, *a: Any, **k: Any) -> Any:
        if self.on_trial is not None:
            self.on_trial()
        return self.inner.run_trial(*a, **k)

    def info(self) -> dict[str, Any]:
        return self.inner.info()

    def recover(self, trial: int) -> list[int]:
        return self.inner.recover(trial)

    def close(self) -> None:
        self.inner.close()

    def closing_fault(self) -> FaultRecord | None:
        return self.closing


def _session(tmp_path: Path, bench_kw: dict[str, Any], iterations: int = 2) -> tuple[Any, int, dict[str, Any], str]:
    from host.analysis.session import report_fault, run_session
    from host.experiment.config import build_config
    from host.experiment.plan import prepare

    cfg = build_config(None, {"iterations": iterations, "cycle_s": 0.15})
    out = tmp_path / "run"
    (out / "logs").mkdir(parents=True)
    bench = FakeBench(cfg, **bench_kw)
    res = run_session(prepare(cfg), bench, out, mode="sim", stream=io.StringIO())
    import contextlib

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = report_fault(res, out / "summary.json")
    return res, code, json.loads((out / "summary.json").read_text()), err.getvalue()


def test_an_sdo_error_before_the_first_trial(tmp_path: Path) -> None:
    res, code, s, err = _session(
        tmp_path, {"fail_start": SdoTransportError("node 1: read 0x1000:0 failed: timeout", 1, elapsed_s=5.0)}
    )
    f = s["faults"][0]
    assert code == 3 and err.startswith(
        "ilcrig: fault: node 1: read 0x1000:0 failed: timeout [sdo_error]: drive1, before the first trial"
    )
    assert (f["kind"], f["position"], f["trial"], f["tick"], f["latency_ms"]) == (
        "sdo_error",
        "before_first_trial",
        0,
        None,
        5000.0,
    )
    assert s["completed"] is False and s["iterations"] == []


def test_a_fault_while_the_bench_closes_ends_a_completed_run_with_3(tmp_path: Path) -> None:
    late = FaultRecord(FaultKind.NODE_LOST, "heartbeat of plant lost", node="plant", node_id=32, latency_ms=300.0)
    res, code, s, err = _session(tmp_path, {"closing": late})
    f = s["faults"][0]
    assert code == 3 and len(err.splitlines()) == 1
    assert "[node_lost]: plant (node 32), after the last trial (trial 1, kept)" in err and "all 2 trials kept" in err
    assert (f["position"], f["trial"], f["tick"]) == ("after_last_trial", 1, None)
    assert s["completed"] is True and len(s["iterations"]) == 2  # every trial was run and kept


def test_a_full_disk_after_the_last_trial_keeps_every_trial(tmp_path: Path) -> None:
    from host.analysis.session import report_fault, run_session
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.sim.inprocess import InProcessBench

    cfg = build_config(None, {"iterations": 2, "cycle_s": 0.15})
    out = tmp_path / "run"
    (out / "logs").mkdir(parents=True)
    res = run_session(prepare(cfg), InProcessBench(cfg), out, mode="sim", stream=io.StringIO(), fail_writes_from_trial=1)
    assert report_fault(res) == 3
    s = json.loads((out / "summary.json").read_text())
    f = s["faults"][0]
    assert (f["kind"], f["position"], f["trial"], f["node"]) == ("disk_full", "after_last_trial", 1, "host")
    assert s["completed"] is True and len(s["iterations"]) == 2
    assert s["recording"]["trials"] == [0, 1] and _recorded(out) == [0, 1]  # written again into the reserve's room


def _recorded(out: Path) -> list[int]:
    from fault_harness import recorded_trials

    return recorded_trials(out / "recording.rrd")


def test_a_signal_while_a_trials_outputs_are_written_waits_for_them(tmp_path: Path) -> None:
    """SIGTERM right after trial 0's summary entry is made: the recording and the summary file get
    trial 0 before the run ends as interrupted (143)."""
    from host.analysis.recording import RunRecorder
    from host.experiment.signal_shield import interrupt_on_signals

    real = RunRecorder.log_trial

    def log_trial(self: RunRecorder, k: int, *a: Any, **kw: Any) -> None:
        if k == 0:
            os.kill(os.getpid(), signal.SIGTERM)  # lands while the outputs of trial 0 are written
        real(self, k, *a, **kw)

    RunRecorder.log_trial = log_trial  # type: ignore[method-assign]
    try:
        with interrupt_on_signals():
            res, code, s, err = _session(tmp_path, {}, iterations=3)
    finally:
        RunRecorder.log_trial = real  # type: ignore[method-assign]
    assert code == 143 and err == ""
    assert len(s["iterations"]) == 1 and s["interrupted"]["signal"] == "SIGTERM"
    assert s["interrupted"]["position"] == "between_trials" and s["interrupted"]["trial"] == 1
    assert s["recording"]["trials"] == [0] and _recorded(tmp_path / "run") == [0]
    assert np.isfinite(s["iterations"][0]["rmse_deg"]).all()


def test_a_signal_held_while_outputs_fail_is_in_the_summary_as_in_the_exit_code(tmp_path: Path) -> None:
    """SIGTERM held while trial 0's outputs are written, whose write then fails (a full disk): the
    run ends through its fault path and the held signal is marked there — the final summary says
    ``interrupted`` (and the fault) and the exit code is 143; never a 143 whose summary is silent."""
    from host.analysis.recording import RunRecorder
    from host.analysis.session import report_fault, run_session
    from host.experiment.config import build_config
    from host.experiment.plan import prepare
    from host.experiment.signal_shield import interrupt_on_signals
    from host.sim.inprocess import InProcessBench

    real = RunRecorder.log_trial

    def log_trial(self: RunRecorder, k: int, *a: Any, **kw: Any) -> None:
        if k == 0:
            os.kill(os.getpid(), signal.SIGTERM)  # held: the outputs of trial 0 are being written
        real(self, k, *a, **kw)

    cfg = build_config(None, {"iterations": 3, "cycle_s": 0.15})
    out = tmp_path / "run"
    RunRecorder.log_trial = log_trial  # type: ignore[method-assign]
    try:
        with interrupt_on_signals():
            res = run_session(prepare(cfg), InProcessBench(cfg), out, mode="sim", stream=io.StringIO(), fail_writes_from_trial=0)
    finally:
        RunRecorder.log_trial = real  # type: ignore[method-assign]
    assert report_fault(res) == 143
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"]["signal"] == "SIGTERM" and s["end_reason"] == "interrupted"
    assert [f["kind"] for f in s["faults"]] == ["disk_full"] and s["completed"] is False
