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

from host.analysis.markdown import fmt
from host.analysis.run_report import write_run_report
from host.learning.names import LAWS
from host.studies.paper import paper_data
from host.studies.paper.claims import paper_self_check
from host.studies.paper.convergence_verdicts import verdict_disturbance, verdict_long_bounded, verdict_rise, verdict_settle
from host.studies.paper.plan import (
    GROUPS,
    PLUGIN_LAWS,
    Experiment,
    ReproduceError,
    all_experiments,
    experiment_list,
    limit_experiments,
    run_dir_of,
    table_rows,
)
from host.studies.paper.verdicts import (
    Verdict,
    verdict_beats,
    verdict_cycles,
    verdict_floor_raised,
    verdict_paths,
    verdict_profiles_order,
    verdict_profiles_similar,
)
from host.studies.point import is_finished
from host.studies.settling import (
    settle_iteration,
    settle_iterations,
    settled_floor,
    settled_windows,
    split_repeatable,
)

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
    summary = {
        "iterations": [{}, {}, {}],
        "completed": True,
        "faults": [],
        "config": cfg.as_dict() | {"n_ticks": 501, "trial_s": 0.5},
    }
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


#: RMSE per trial of `pd-ilc` on path 1, 0.25 s, 4-5-6-7 law, no disturbance (deg; `ilcrig sim`)
PD_ILC_RMSE = np.array(
    [
        [0.210185, 0.0817, 0.138093, 0.089311],
        [0.114469, 0.043937, 0.067899, 0.047659],
        [0.062837, 0.023765, 0.034802, 0.025583],
        [0.034351, 0.013057, 0.020243, 0.013788],
        [0.017048, 0.006891, 0.013074, 0.007273],
        [0.007412, 0.003618, 0.008239, 0.003833],
        [0.004336, 0.002537, 0.005085, 0.002658],
        [0.003102, 0.00225, 0.003805, 0.002325],
        [0.001975, 0.001593, 0.002222, 0.001579],
        [0.001634, 0.001517, 0.001862, 0.001543],
    ]
)


def test_settle_iteration_within_2x_of_final() -> None:
    r = [1.0, 0.5, 0.25, 0.12, 0.06, 0.03, 0.02, 0.015, 0.012, 0.01]
    # band [0.005, 0.02] around the final 0.01: r[6] = 0.02 is inside, r[5] = 0.03 is not
    assert settle_iteration(r) == 6
    assert settle_iteration([0.2, 0.2]) == 0
    assert settle_iteration([0.3]) == 0
    # entering the band from below counts as outside: 0.01 < 0.3 / 2
    assert settle_iteration([1.0, 0.1, 0.01, 0.3, 0.3]) == 3
    assert settle_iteration([1.0, 0.0, 0.0]) == 1  # a final 0 is reached only by 0
    # every joint: j1 settles at 7, j2 at 6, j3 at 8 (0.003805 > 2 × 0.001862), j4 at 6
    assert settle_iterations(PD_ILC_RMSE) == [7, 6, 8, 6]
    assert settle_iteration(PD_ILC_RMSE) == 8
    with pytest.raises(ValueError):
        settle_iteration([])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(1e-6, 10.0, allow_nan=False), min_size=1, max_size=30))
def test_settle_iteration_property(r: list[float]) -> None:
    k = settle_iteration(r)
    assert 0 <= k <= len(r) - 1
    f = r[-1]
    assert all(f / 2 <= x <= 2 * f for x in r[k:])
    if k > 0:
        assert not f / 2 <= r[k - 1] <= 2 * f


def test_settled_floor_and_windows() -> None:
    r = [1.0, 0.5, 0.25, 0.12, 0.06, 0.03, 0.02, 0.015, 0.012, 0.01]
    fl = settled_floor(r)
    assert (fl.settle, fl.trials) == (6, 4)
    assert fl.floor_deg == pytest.approx([0.01425])
    fl = settled_floor(r, settle=8)  # a disturbed run takes the settle iteration of its run without
    assert (fl.settle, fl.trials) == (8, 2) and fl.floor_deg == pytest.approx([0.011])
    assert settled_floor(r, settle=20).settle == 9  # clamped to the last trial
    long = np.concatenate([np.full(10, 1.0), np.full(10, 0.1), np.full(30, 0.2)])
    w = settled_windows(long, 10, settle=5)
    assert (w.settle, w.best_start) == (5, 10)
    assert w.best_mean_deg == pytest.approx(0.1) and w.last_mean_deg == pytest.approx(0.2)
    w = settled_windows(long, 10, settle=45)  # fewer than 10 trials after settling
    assert w.best_start is None and np.isnan(w.best_mean_deg)


def test_verdict_settle_states_criterion_and_values() -> None:
    v = verdict_settle(PD_ILC_RMSE)
    assert v.holds is False
    assert "settles at k = 8 (j1 7, j2 6, j3 8, j4 6; of 10 trials)" in v.detail
    assert "j1 0.00741 (4.5× the final 0.00163)" in v.detail and "not settled at k = 5" in v.detail
    assert "within 2× of its final (last-trial) RMSE" in v.criterion and "k ≤ 5" in v.criterion
    assert v.line().endswith(f"*Criterion:* {v.criterion}.")
    fast = np.tile([[1.0], [0.1], [0.011], [0.0105], [0.0102], [0.0101], [0.01], [0.01]], (1, 4))
    v = verdict_settle(fast)
    assert v.holds is True and v.detail == "settles at k = 2 (j1 2, j2 2, j3 2, j4 2; of 8 trials)"
    assert verdict_settle(fast[:6]).holds is None  # too few trials to judge k ≤ 5


def test_verdict_rise() -> None:
    v = verdict_rise(np.array([[0.3, 0.1], [0.2, 0.12], [0.1, 0.05]]))
    assert v.holds is True and v.detail.startswith("first rise at k = 1 on j2 (0.1 → 0.12 deg)")
    v = verdict_rise(np.array([[0.3, 0.1], [0.2, 0.08], [0.1, 0.05]]))
    assert v.holds is False and "monotonically" in v.detail and "1%" in v.criterion


def test_verdict_disturbance_floors_after_settling() -> None:
    none = np.tile(np.array([[0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.004, 0.004, 0.002, 0.002]]).T, (1, 4))
    # scatter of 3× between trials: the disturbed run settles only at its last trial on its own
    dist = np.tile(np.array([[0.25, 0.12, 0.06, 0.03, 0.02, 0.015, 0.01, 0.03, 0.01, 0.03]]).T, (1, 4))
    assert settle_iteration(none) == 6 and settle_iteration(dist) == 9
    v = verdict_disturbance(none, dist)
    assert v.holds is True
    # both floors over k = 6..9 (the run without disturbance settles at 6): 0.003 and 0.02
    assert "floor without → with disturbance: j1 0.003 → 0.02, j2 0.003 → 0.02" in v.detail
    assert "settle iteration 6: floors over k = 6..9" in v.detail
    assert "growth of the last 4 trials over the 4 before: j1 0.64×" in v.detail
    assert v.criterion.startswith("floor = the mean RMSE per joint over the trials from the settle iteration on")
    lower = dist.copy()
    lower[:, 2] = none[:, 2] * 0.9  # j3 learns even better with the disturbance
    v = verdict_disturbance(none, lower)
    assert v.holds is False and "not raised on j3" in v.detail
    growing = dist.copy()
    growing[6:, 1] = [0.05, 0.08, 0.12, 0.15]  # grows again after learning
    v = verdict_disturbance(none, growing)
    assert v.holds is False and "the error grows on j2" in v.detail
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
    assert all(v.holds for v in paper_self_check().values())


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


def _fake_run(out: Path, e: Experiment, iterations: int, rmse: np.ndarray, fault: str | None = None) -> None:
    """A finished run of ``e`` in sweep folder ``out`` with the given RMSE history (deg), or one
    ended by ``fault``."""
    d = run_dir_of(out, e)
    d.mkdir(parents=True)
    cfg = e.config(iterations)
    its = [{"k": k, "rmse_deg": list(r), "max_abs_deg": list(3 * r), "mae_deg": list(0.8 * r)} for k, r in enumerate(rmse)]
    summary = {
        "completed": fault is None,
        "faults": [] if fault is None else [{"trial": len(rmse), "message": fault}],
        "config": cfg.as_dict() | {"n_ticks": 5, "trial_s": 0.005},
        "iterations": its,
        "wall_s": 1.0,
        "convergence_check": {"rho_max": 0.9, "ok": True, "norm2": 1.0, "long_bounded": True},
    }
    (d / "summary.json").write_text(json.dumps(summary))
    np.save(d / "errors.npy", np.zeros((len(rmse), 5, 4), np.float32))


def test_sweep_report_judges_with_settled_floors_and_windows(tmp_path: Path) -> None:
    """The report on a sweep folder: the disturbed run's floor starts at the settle iteration of the
    run without disturbance; a long run's best window starts at the settle iteration over the first
    ``iterations`` trials; every verdict line states its criterion."""
    from host.studies.paper.report import write_sweep_report

    none = np.tile(np.array([[0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.004, 0.004, 0.002, 0.002]]).T, (1, 4))
    dist = np.tile(np.array([[0.25, 0.12, 0.06, 0.03, 0.02, 0.015, 0.01, 0.03, 0.01, 0.03]]).T, (1, 4))
    _fake_run(tmp_path, Experiment("pd-ilc"), 10, none)
    _fake_run(tmp_path, Experiment("pd-ilc", disturbance="both"), 10, dist)
    # long runs: the first 10 trials as above, then flat; the disturbed one dips at k = 10..29
    long_none = np.concatenate([none, np.full((190, 4), 0.002)])
    long_dist = np.concatenate([dist, np.full((20, 4), 0.005), np.full((170, 4), 0.02)])
    _fake_run(tmp_path, Experiment("pd-ilc", trials=200), 10, long_none)
    _fake_run(tmp_path, Experiment("pd-ilc", disturbance="both", trials=200), 10, long_dist)
    _fake_run(tmp_path, Experiment("d-ilc"), 10, np.zeros((0, 4)), fault="EMCY 0x8611 on node 2")  # no trial
    text = write_sweep_report(tmp_path, 10).read_text()
    verdict_lines = [line for line in text.splitlines() if line.startswith("- **")]
    lines = {key: next(line for line in verdict_lines if claim in line) for key, claim in paper_data.CLAIMS.items()}
    settle = lines["fig8_settle"]
    assert settle.startswith("- **does not hold**") and "settles at k = 6 (j1 6, j2 6, j3 6, j4 6; of 10 trials)" in settle
    assert "*Criterion:* settle iteration = the first trial k (k = 0: before learning)" in settle
    t3 = lines["table3"]
    assert t3.startswith("- **holds**") and "j1 0.003 → 0.02" in t3 and "floors over k = 6..9" in t3
    assert "*Criterion:* floor = the mean RMSE per joint over the trials from the settle iteration on" in t3
    ln = lines["long_none"]
    assert ln.startswith("- **holds**") and "settle iteration k = 6;" in ln
    ld = lines["long_dist"]
    # the dip k = 10..29 lies after settling (k = 6): last 20 (0.02) is 4× the best (0.005)
    assert ld.startswith("- **does not hold**") and "best 20 trials after settling k = 10..29 0.005 deg" in ld
    assert "| PD-ILC | both | 0.03 | 6 | 0.005 (k = 10..29) | 0.02 | 4 | does not hold | bounded | 1 |" in text
    missing_line = lines["table2"]  # D-ILC ended before its first trial: nothing to judge
    assert missing_line.startswith("- **not evaluated**") and "*Criterion:*" in missing_line
    assert "| d-ilc_p1_250ms_poly4567_none | fault: EMCY 0x8611 on node 2 |" in text
    assert (tmp_path / "fig8.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


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
    t2 = next(line for line in report.splitlines() if line.startswith("- **") and paper_data.CLAIMS["table2"] in line)
    assert t2.endswith("*Criterion:* PD-ILC's MaxE and mean error after learning are both smaller than D-ILC's on every joint.")
    settle = next(line for line in report.splitlines() if paper_data.CLAIMS["fig8_settle"] in line)
    assert settle.startswith("- **not evaluated**") and "too few trials to judge (2)" in settle
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
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_stops_cleanly_and_keeps_finished(tmp_path: Path, signum: int) -> None:
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) or SIGTERM to the command
    alone (as ``kill`` sends it) while one experiment is finished and another one is held
    (tests/sweep_hold.py): the sweep cannot end before the interrupt, whatever the machine's
    speed; one line, no traceback from anyone, exit 130 / 143 (SIGTERM was 130); the local
    cluster's workers end with it; running again resumes."""
    out = tmp_path / "sweep"
    done, held = Experiment("pd-ilc"), Experiment("d-ilc")
    proc = subprocess.Popen(
        [sys.executable, "tests/sweep_hold.py", "reproduce", "--out", str(out), "--iterations", "2", "--only", "table2"]
        + ["--jobs", "2"],
        cwd=ROOT,
        env=os.environ | {"ILCRIG_TEST_HOLD": held.id},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 300  # a guard against a hang, not a timing assumption
        while not (is_finished(run_dir_of(out, done), done.config(2)) and (run_dir_of(out, held) / "held").is_file()):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the sweep neither finished one experiment nor held the other"
            time.sleep(0.1)
        held_pid = int((run_dir_of(out, held) / "held").read_text())
        if signum == signal.SIGINT:
            os.killpg(proc.pid, signal.SIGINT)  # as Ctrl-C on a terminal: the whole process group
        else:
            proc.send_signal(signal.SIGTERM)  # as kill: the command alone
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signum, err
    assert "ilcrig: interrupted;" in err and "run again to resume" in err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err  # from no one: the workers ignore SIGINT
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # no process of the sweep is left in its session/group
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail("worker processes survived the interrupt")
    with pytest.raises(ProcessLookupError):
        os.kill(held_pid, 0)
    assert is_finished(run_dir_of(out, done), done.config(2))  # the finished experiment is kept
    assert not (run_dir_of(out, held) / "summary.json").exists()  # the held one never ran
    sweep = json.loads((out / "sweep.json").read_text())
    assert [h["interrupted"] for h in sweep["history"]] == [True]
    assert not (out / "report.md").exists()
    # resume: only the held experiment runs
    p = _cli("reproduce", "--out", str(out), "--iterations", "2", "--only", "table2", "--jobs", "2", "--no-progress")
    assert p.returncode == 0, p.stderr
    assert "1 run, 1 already finished" in p.stdout
    assert is_finished(run_dir_of(out, held), held.config(2)) and (out / "report.md").is_file()
    assert [h["ran"] for h in json.loads((out / "sweep.json").read_text())["history"]] == [1, 1]


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_signal_once_the_experiments_ran_leaves_the_records_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM while ``ilcrig reproduce`` writes its report after every experiment ran (the process
    died there, with sweep.json and no report, or no sweep.json at all): the report, the table and
    sweep.json are written, exit 0, one warning saying the signal came while the records were
    finished."""
    import host.studies.paper.reproduce as reproduce_mod
    from host.cli import main

    write = reproduce_mod.write_sweep_report
    sent: list[int] = []

    def signalled(out: Path, iterations: int) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        sent.append(1)
        write(out, iterations)

    monkeypatch.setattr(reproduce_mod, "write_sweep_report", signalled)
    out = tmp_path / "sweep"
    argv = ["reproduce", "--out", str(out), "--iterations", "2", "--only", "table2", "--jobs", "1", "--no-progress"]
    assert main([*argv, "--no-dashboard"]) == 0 and sent == [1]
    assert (out / "report.md").is_file() and (out / "results.parquet").is_file()
    assert [h["interrupted"] for h in json.loads((out / "sweep.json").read_text())["history"]] == [False]


def test_near_misses_are_flagged_as_ties() -> None:
    v = verdict_cycles({0.15: [3.0], 0.25: [2.0], 0.5: [2.04]}, {0.15: [3.0], 0.25: [2.0], 0.5: [1.0]})
    assert v.holds is False and "effectively a tie" in v.detail
    v = verdict_cycles({0.15: [3.0], 0.25: [2.0], 0.5: [2.5]}, {0.15: [3.0], 0.25: [2.0], 0.5: [1.0]})
    assert v.holds is False and "tie" not in v.detail
    assert "effectively a tie" in verdict_profiles_order([0.102], [0.1]).detail


def test_verdict_long_bounded() -> None:
    settled = np.array([[0.2 * 0.9**k + 0.001] * 4 for k in range(200)])
    # over the paper's horizon (10 trials) the final is 0.2·0.9^9 + 0.001 = 0.0785: k = 3 is within 2×
    assert settle_iteration(settled[:10]) == 3
    v = verdict_long_bounded(settled, settle=3)
    assert v.holds is True
    # the RMSE falls monotonically: the best window after settling is the last one
    assert "best 20 trials after settling k = 180..199 0.001 deg, last 20 trials 0.001 deg (1× the best)" in v.detail
    assert v.detail.startswith("settle iteration k = 3;") and v.detail.endswith("over 200 trials")
    assert "best 20-trial mean after settling" in v.criterion
    diverging = settled.copy()
    diverging[100:] *= np.geomspace(1, 100, 100)[:, None]
    v = verdict_long_bounded(diverging, settle=3)
    assert v.holds is False and v.detail.startswith("the error grows again: the 20-trial mean exceeds 2× the best")
    w = settled_windows(diverging, 20, settle=3)
    assert 80 <= w.best_start <= 100 and w.best_mean_deg == pytest.approx(0.00102, rel=0.02)
    assert w.last_mean_deg / w.best_mean_deg > 50
    # a window before settling does not count as the best: the early dip at k = 0..19 is skipped
    dip = np.full((200, 4), 0.03)
    dip[:20] = 0.01
    v = verdict_long_bounded(dip, settle=0)
    assert v.holds is False and "best 20 trials after settling k = 0..19 0.01 deg" in v.detail
    v = verdict_long_bounded(dip, settle=20)
    assert v.holds is True and "best 20 trials after settling k = 20..39 0.03 deg" in v.detail
    assert verdict_long_bounded(settled[:30], settle=3).holds is None  # fewer than two blocks of 20
    assert verdict_long_bounded(settled, settle=190).holds is None  # fewer than 20 trials after settling
