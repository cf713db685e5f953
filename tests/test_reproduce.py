"""``ilcrig reproduce``: the paper's numbers, the experiment list, verdict logic, the single-run
report, and (slow) a tiny sweep with resume and a clean Ctrl-C."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.analysis import paper_data
from host.analysis.report import (
    Verdict,
    fmt,
    settle_iteration,
    settle_iteration_final,
    split_repeatable,
    verdict_beats,
    verdict_cycles,
    verdict_disturbance,
    verdict_floor_raised,
    verdict_long_bounded,
    verdict_paths,
    verdict_profiles_order,
    verdict_profiles_similar,
    verdict_rise,
    verdict_settle,
)
from host.analysis.run_report import write_run_report
from host.analysis.sweep_plan import (
    GROUPS,
    PLUGIN_LAWS,
    Experiment,
    ReproduceError,
    all_experiments,
    experiment_list,
    is_finished,
    limit_experiments,
    run_dir_of,
    table_rows,
)
from host.learning.names import LAWS

ROOT = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------------------------- paper data


def test_paper_data_spot_values() -> None:
    t2 = paper_data.TABLES["table2"]
    assert t2.rows["PD-ILC"].max_err_deg[0] == 0.71
    assert t2.rows["D-ILC"].max_err_deg == (0.94, 0.0035, 0.81, 0.0026)
    assert t2.rows["PD-ILC"].mean_err_deg == (0.27, 0.0004, 0.24, 0.0003)
    assert paper_data.TABLE3.rows["both"].mean_err_deg[3] == 0.057
    assert paper_data.TABLE4.rows["3"].mean_err_deg == (0.069, 0.0006, 0.19, 0.0003)
    assert paper_data.TABLE4.rows["2"].mean_err_deg[1] == 0.00003
    assert paper_data.TABLE5.rows["0.15"].max_err_deg == (0.78, 0.0039, 0.68, 0.0021)
    assert paper_data.TABLE5.rows["0.50"].max_err_deg[3] == 0.00025
    assert paper_data.TABLE6.rows["poly5"].max_err_deg[0] == 0.6854
    assert paper_data.TABLE6.rows["poly4567"].mean_err_deg[2] == 0.2404
    assert paper_data.FIG8_RMSE_DEG["D-ILC"]["final"] == (0.5180, 0.0021, 0.4597, 0.0013)
    assert paper_data.FIG8_RMSE_DEG["PD-ILC"]["initial"][1] == 0.0556
    assert paper_data.DOI == "10.20517/ir.2022.02" and "Li, Liu, Cui, Wu" in paper_data.SOURCE
    # path 1 / 0.25 s / 4567 rows are the same experiment in Tables 2-5
    for key, row in (("table3", "none"), ("table4", "1"), ("table5", "0.25")):
        assert paper_data.TABLES[key].rows[row].max_err_deg == t2.rows["PD-ILC"].max_err_deg


# -------------------------------------------------------------------------------- experiment list


def test_table2_configs() -> None:
    exps = experiment_list("table2")
    assert {e.law for e in exps} == {"pd-ilc", "d-ilc"}
    for e in exps:
        cfg = e.config(7)
        assert (cfg.path, cfg.cycle_s, cfg.profile, cfg.disturbance, cfg.iterations) == ("1", 0.25, "poly4567", "none", 7)
        assert cfg.law == e.law


def test_each_table_varies_one_thing() -> None:
    assert [(e.law, e.disturbance) for e in (r.experiment for r in table_rows("table3"))] == [
        ("pd-ilc", "none"),
        ("pd-ilc", "both"),
    ]
    assert [r.experiment.path for r in table_rows("table4")] == ["1", "2", "3", "4"]
    assert [r.experiment.cycle_s for r in table_rows("table5")] == [0.25, 0.15, 0.50]
    assert [r.experiment.profile for r in table_rows("table6")] == ["poly4567", "poly5"]
    assert all(r.paper_key is not None for t in ("table2", "table3", "table4", "table5", "table6") for r in table_rows(t))
    beyond = table_rows("table5", ("q-ilc", "no-ilc"))
    assert {r.law for r in beyond} == {"q-ilc", "no-ilc"} and all(r.paper_key is None for r in beyond)
    figs = {(e.law, e.disturbance) for e in experiment_list("figs")}
    assert figs == {("pd-ilc", "none"), ("pd-ilc", "both"), ("d-ilc", "none"), ("d-ilc", "both")}


def test_full_list_is_deduplicated_and_covers_beyond() -> None:
    exps = all_experiments()
    ids = [e.id for e in exps]
    assert len(ids) == len(set(ids)) == 85
    long = [e for e in exps if e.trials is not None]
    assert len(long) == 2 * (len(LAWS) + len(PLUGIN_LAWS)) == 20 and all(e.trials == 200 and e.id.endswith("_k200") for e in long)
    assert long[0].config(10).iterations == 200
    assert "pd-ilc_p1_250ms_poly4567_none" in ids
    assert {e.law for e in exps} == set(LAWS) | set(PLUGIN_LAWS)
    assert {(e.law, e.cycle_s) for e in limit_experiments()} <= {(e.law, e.cycle_s) for e in exps}
    for law in ("pd-ilc-q", "q-ilc", "no-ilc", "no-ilc-id", *PLUGIN_LAWS):  # Tables 2-5 rows beyond the paper
        for e in (
            Experiment(law),
            Experiment(law, disturbance="both"),
            Experiment(law, path="3"),
            Experiment(law, cycle_s=0.15),
            Experiment(law, cycle_s=0.5),
        ):
            assert e.id in ids
    assert experiment_list(",".join(GROUPS)) == exps


def test_bad_only_is_a_value_error() -> None:
    with pytest.raises(ReproduceError, match="unknown --only group.*table9"):
        experiment_list("table2,table9")
    with pytest.raises(ValueError):
        experiment_list(" , ")


def test_cli_rejects_bad_arguments(tmp_path: Path) -> None:
    from host.cli import main

    assert main(["reproduce", "--out", str(tmp_path / "x"), "--only", "table7"]) == 2
    assert main(["reproduce", "--out", str(tmp_path / "x"), "--jobs", "0"]) == 2
    assert main(["reproduce", "--out", str(tmp_path / "x"), "--iterations", "0"]) == 2
    assert not (tmp_path / "x").exists()  # nothing started


def test_is_finished_requires_same_config_and_errors(tmp_path: Path) -> None:
    e = Experiment("pd-ilc")
    d = run_dir_of(tmp_path, e)
    d.mkdir(parents=True)
    cfg = e.config(3)
    summary = {"completed": True, "faults": [], "config": cfg.as_dict() | {"n_ticks": 501, "trial_s": 0.5}}
    (d / "summary.json").write_text(json.dumps(summary))
    assert not is_finished(d, cfg)  # no errors.npy yet
    np.save(d / "errors.npy", np.zeros((3, 5, 4), np.float32))
    assert is_finished(d, cfg)
    assert not is_finished(d, e.config(4))  # other iteration count = other experiment
    summary["completed"] = False
    (d / "summary.json").write_text(json.dumps(summary))
    assert not is_finished(d, cfg)  # interrupted run is redone
    summary["faults"] = [{"trial": 1, "message": "EMCY"}]
    (d / "summary.json").write_text(json.dumps(summary))
    assert is_finished(d, cfg)  # a fault is a (deterministic) result
    (d / "summary.json").write_text("{trunc")
    assert not is_finished(d, cfg)


# -------------------------------------------------------------------------------------- verdicts


def test_verdict_beats_holds_and_fails_with_reason() -> None:
    v = verdict_beats([0.1, 0.01, 0.1, 0.01], [0.05, 0.005, 0.05, 0.005], [0.2, 0.02, 0.2, 0.02], [0.1, 0.01, 0.1, 0.01])
    assert v.holds is True and "j1 2×" in v.detail
    assert v.line().startswith("- **holds** — PD-ILC gives smaller")
    v = verdict_beats([0.1, 0.03, 0.1, 0.01], [0.05, 0.005, 0.05, 0.005], [0.2, 0.02, 0.2, 0.02], [0.1, 0.01, 0.1, 0.01])
    assert v.holds is False
    assert "MaxE of PD-ILC not smaller on j2 (0.03 vs 0.02 deg)" in v.detail
    assert "**does not hold**" in v.line() and "reason:" in v.line()


def test_settle_definitions() -> None:
    r = [1.0, 0.5, 0.25, 0.12, 0.06, 0.03, 0.02, 0.015, 0.012, 0.01]
    # band 0.1 * 0.99 = 0.099: r[4] = 0.06 is within, r[3] = 0.12 is not
    assert settle_iteration(r) == 4
    # within 10 % of 0.01: only the last value
    assert settle_iteration_final(r) == 9
    assert settle_iteration([0.2, 0.2]) == 0
    hist = np.array([r, r, r, r]).T
    assert verdict_settle(hist).holds is True
    slow = np.array([[0.9**k] * 4 for k in range(10)])
    v = verdict_settle(slow)
    assert v.holds is False and "still changing after k = 5" in v.detail
    assert verdict_settle(hist[:3]).holds is None  # too few trials


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 10.0, allow_nan=False), min_size=1, max_size=30))
def test_settle_iteration_property(r: list[float]) -> None:
    k = settle_iteration(r)
    assert 0 <= k <= len(r) - 1
    band = 0.1 * abs(r[0] - r[-1])
    assert all(abs(x - r[-1]) <= band for x in r[k:])
    if k > 0:
        assert abs(r[k - 1] - r[-1]) > band


def test_verdict_rise() -> None:
    assert verdict_rise(np.array([[0.3, 0.1], [0.2, 0.12], [0.1, 0.05]])).holds is True
    v = verdict_rise(np.array([[0.3, 0.1], [0.2, 0.08], [0.1, 0.05]]))
    assert v.holds is False and "monotonically" in v.detail


def test_verdict_disturbance_raised_bounded_and_growing() -> None:
    none = np.array([[0.2 * 0.5**k] * 4 for k in range(10)])
    dist = none + 0.01
    v = verdict_disturbance(none, dist)
    assert v.holds is True and "bounded" in v.detail
    lower = dist.copy()
    lower[:, 2] = none[:, 2] * 0.9  # j3 learns even better with the disturbance
    v = verdict_disturbance(none, lower)
    assert v.holds is False and "not raised on j3" in v.detail
    growing = dist.copy()
    growing[6:, 1] = [0.05, 0.08, 0.12, 0.15]  # grows again after learning
    v = verdict_disturbance(none, growing)
    assert v.holds is False and "grows on j2" in v.detail
    assert verdict_floor_raised([0.1, 0.1], [0.2, 0.05]).holds is False


def test_verdict_paths_cycles_profiles() -> None:
    maxe = {"1": [0.7, 0.002, 0.6, 0.002], "2": [0.6, 0.001, 0.65, 0.001]}
    mae = {"1": [0.27, 0.0004, 0.24, 0.0003], "2": [0.22, 0.00003, 0.24, 0.00004]}
    assert verdict_paths(maxe, mae).holds is True
    maxe["3"], mae["3"] = [0.1, 0.001, 0.2, 0.001], [0.05, 0.0001, 0.05, 0.0001]
    v = verdict_paths(maxe, mae)
    assert v.holds is False and "path 1 vs 3" in v.detail
    good = {0.15: [3.0, 3.0], 0.25: [2.0, 2.0], 0.5: [1.0, 1.0]}
    assert verdict_cycles(good, good).holds is True
    bad = {0.15: [3.0, 3.0], 0.25: [2.0, 4.0], 0.5: [1.0, 1.0]}
    v = verdict_cycles(good, bad)
    assert v.holds is False and "mean error j2: 0.15 s 3, 0.25 s 4, 0.5 s 1" in v.detail
    assert verdict_profiles_similar([0.7, 0.1], [0.3, 0.1], [0.68, 0.1], [0.31, 0.1]).holds is True
    assert verdict_profiles_similar([0.7, 0.1], [0.3, 0.1], [0.2, 0.1], [0.31, 0.1]).holds is False
    assert verdict_profiles_order([0.2, 0.1], [0.3, 0.2]).holds is True
    v = verdict_profiles_order([0.2, 0.3], [0.3, 0.2])
    assert v.holds is False and "not smaller on j2" in v.detail


def test_paper_numbers_satisfy_the_criteria() -> None:
    from host.analysis.report import _paper_self_check

    assert all(v.holds for v in _paper_self_check().values())


def test_split_repeatable() -> None:
    rng = np.random.default_rng(0)
    n = 2000
    common = np.radians(0.1) * np.sin(np.linspace(0, 6, n))[:, None] * np.ones(4)
    noise = np.radians(0.02) * rng.standard_normal((4, n, 4))
    rep, nonrep = split_repeatable(np.concatenate([np.zeros((3, n, 4)), common + noise]))
    assert np.allclose(rep, 0.1 * np.sqrt(np.mean(np.sin(np.linspace(0, 6, n)) ** 2)), rtol=0.03)
    assert np.allclose(nonrep, 0.02, rtol=0.05)
    with pytest.raises(ValueError):
        split_repeatable(np.zeros((0, 3, 4)))


def test_fmt() -> None:
    assert fmt(0.0016) == "0.0016"
    assert fmt(0.00003) == "0.00003"
    assert fmt(0.123456) == "0.123"
    assert fmt(None) == "—" and fmt(float("nan")) == "—"
    assert Verdict("c", None, "x").line() == "- **not evaluated** — c: x"


def test_write_run_report(tmp_path: Path) -> None:
    its = [
        {
            "k": k,
            "rmse_deg": [0.2 / (k + 1)] * 4,
            "max_abs_deg": [0.5 / (k + 1)] * 4,
            "mae_deg": [0.1 / (k + 1)] * 4,
            "peak_torque_nm": [1.0] * 4,
        }
        for k in range(3)
    ]
    summary = {
        "mode": "sim",
        "config": {
            "law": "pd-ilc",
            "path": "1",
            "cycle_s": 0.25,
            "profile": "ruckig",
            "disturbance": "none",
            "iterations": 3,
            "n_ticks": 501,
        },
        "iterations": its,
        "completed": True,
        "faults": [],
        "trace_sha256": "ab" * 32,
        "convergence_check": {"rho_max": 0.95, "ok": True, "norm2": 1.2},
    }
    path = write_run_report(tmp_path / "run", summary)
    text = path.read_text()
    assert "| 2 | 0.0667 | 0.0667 | 0.0667 | 0.0667 | 0.167 |" in text
    assert "spectral radius 0.95 (ok)" in text
    png = tmp_path / "run" / "convergence.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------------------------------ sweeps


def _cli(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "host.cli", *args], cwd=ROOT, capture_output=True, text=True, timeout=300, **kw)


@pytest.mark.slow
def test_tiny_sweep_report_and_resume(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    p = _cli("reproduce", "--out", str(out), "--iterations", "2", "--only", "table2", "--jobs", "2")
    assert p.returncode == 0, p.stderr
    assert "2 run, 0 already finished" in p.stdout
    report = (out / "report.md").read_text()
    assert "## Table 2" in report
    assert "| PD-ILC | paper | 0.71 | 0.0021 | 0.61 | 0.0016 | 0.27 | 0.0004 | 0.24 | 0.0003 |" in report
    assert "| PD-ILC | ilcrig |" in report and "| D-ILC | ilcrig |" in report
    assert "PD-ILC gives smaller MaxE and mean error than D-ILC on every joint (Table 2)" in report
    assert any(w in report for w in ("- **holds** —", "- **does not hold** —"))
    assert (out / "fig8.png").is_file()
    for law in ("pd-ilc", "d-ilc"):
        s = json.loads((out / "runs" / f"{law}_p1_250ms_poly4567_none" / "summary.json").read_text())
        assert s["completed"] and len(s["iterations"]) == 2 and s["config"]["profile"] == "poly4567"
    mtimes = {f: f.stat().st_mtime_ns for f in (out / "runs").rglob("*") if f.is_file()}
    p = _cli("reproduce", "--out", str(out), "--iterations", "2", "--only", "table2", "--jobs", "2")
    assert p.returncode == 0, p.stderr
    assert "0 run, 2 already finished" in p.stdout
    assert mtimes == {f: f.stat().st_mtime_ns for f in (out / "runs").rglob("*") if f.is_file()}
    sweep = json.loads((out / "sweep.json").read_text())
    assert [h["ran"] for h in sweep["history"]] == [2, 0]


@pytest.mark.slow
@pytest.mark.multiprocess
def test_ctrl_c_stops_cleanly_and_keeps_finished(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "host.cli",
            "reproduce",
            "--out",
            str(out),
            "--iterations",
            "3",
            "--only",
            "table4,table5",
            "--jobs",
            "2",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not list((out / "runs").glob("*/errors.npy")) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.1)
        finished = {f.parent.name for f in (out / "runs").glob("*/errors.npy")}
        assert finished
        proc.send_signal(signal.SIGINT)  # the parent only: it must stop its workers itself
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # no process of the sweep is left in its session/group
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail("worker processes survived the interrupt")
    for name in finished:
        e = next(x for x in all_experiments() if x.id == name)
        assert is_finished(out / "runs" / name, e.config(3))


def test_near_misses_are_flagged_as_ties() -> None:
    v = verdict_cycles({0.15: [3.0], 0.25: [2.0], 0.5: [2.04]}, {0.15: [3.0], 0.25: [2.0], 0.5: [1.0]})
    assert v.holds is False and "effectively a tie" in v.detail
    v = verdict_cycles({0.15: [3.0], 0.25: [2.0], 0.5: [2.5]}, {0.15: [3.0], 0.25: [2.0], 0.5: [1.0]})
    assert v.holds is False and "tie" not in v.detail
    assert "effectively a tie" in verdict_profiles_order([0.102], [0.1]).detail


def test_verdict_long_bounded() -> None:
    settled = np.array([[0.2 * 0.5**k + 0.001] * 4 for k in range(200)])
    v = verdict_long_bounded(settled)
    assert v.holds is True and "over 200 trials" in v.detail and "best 20 trials" in v.detail
    diverging = settled.copy()
    diverging[100:] *= np.geomspace(1, 100, 100)[:, None]
    v = verdict_long_bounded(diverging)
    assert v.holds is False and "grows again" in v.detail
    assert verdict_long_bounded(settled[:30]).holds is None  # fewer than two blocks of 20
