"""The public API ``ilcrig``: experiments in-process (digest equal to the CLI's), stepping with a gain
change between trials, bad input as a typed exception with the CLI's message, the law protocol
(plug-ins by module:Class, registered classes, the "not checked" convergence check), the
constrained law against the torque limit, the model-free law's auxiliary rollouts, and one run on
the multi-process rig with the digest of sim."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_util import run_cli
from test_plugin import HalfP

import ilcrig
from bus import units

SHORT = {"iterations": 2, "cycle_s": 0.15}
#: the drives' joint torque limit, N·m (plant.params.TruePlantConfig)
LIMIT_NM = 264.6


def test_in_process_run_matches_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(
        capsys, "sim", "--law", "pd-ilc", "--iterations", "2", "--cycle", "0.15", "--out", str(tmp_path / "cli")
    )
    assert code == 0
    cli = json.loads((tmp_path / "cli" / "summary.json").read_text())
    res = ilcrig.Experiment(law="pd-ilc", **SHORT).run()
    assert res.digest == cli["trace_sha256"] and res.mode == "sim" and res.completed
    assert len(res) == 2 and res.rmse_deg.shape == (2, 4) and res.error_rad.shape == (2, 301, 4)
    np.testing.assert_allclose(res.rmse_deg, [it["rmse_deg"] for it in cli["iterations"]], rtol=0, atol=0)
    t = res[1]
    np.testing.assert_array_equal(t.error_rad, t.reference_rad - t.actual_rad)
    np.testing.assert_allclose(np.sqrt(np.mean(np.degrees(t.error_rad) ** 2, axis=0)), t.rmse_deg, rtol=1e-12)
    # the run folder of the CLI loads as the same results
    loaded = ilcrig.load(tmp_path / "cli")
    assert loaded.digest == res.digest
    np.testing.assert_array_equal(loaded.error_rad, res.error_rad)
    np.testing.assert_array_equal(loaded.feedforward_nm, res.feedforward_nm)
    np.testing.assert_array_equal(loaded.feedback_nm, res.feedback_nm)
    assert "rmse_deg j1" in res.table() and res.rows()[0]["trial"] == 0 and set(res.rows()[0]) >= {"rmse_deg_j4", "role"}


def test_outputs_on_request(tmp_path: Path) -> None:
    res = ilcrig.Experiment(law="pd-ol", iterations=2, cycle_s=0.15).run(out=tmp_path / "run")
    assert (tmp_path / "run" / "recording.rrd").is_file() and (tmp_path / "run" / "trials" / "trial-00001.npz").is_file()
    figs = res.figures(tmp_path / "figs")
    assert {p.name for p in figs} == {"report.md", "convergence.png", "tracking.png"}
    rrd = ilcrig.Experiment(law="pd-ol", iterations=1, cycle_s=0.15).run().recording(tmp_path / "mem.rrd")
    assert rrd.stat().st_size > 1000


def test_bad_input_is_a_typed_exception_with_the_cli_message(capsys: pytest.CaptureFixture[str]) -> None:
    for keys, argv in (
        ({"law": "x-ilc"}, ["--law", "x-ilc"]),
        ({"iterations": 0}, ["--iterations", "0"]),
        ({"cycle_s": 0.05}, ["--cycle", "0.05"]),
        ({"law_options": {"margin": 2.0}, "law": "cno-ilc"}, ["--law", "cno-ilc", "--law-options", "margin=2.0"]),
    ):
        code, _, err = run_cli(capsys, "sim", *argv, "--out", "/nonexistent-dir-for-the-test/x")
        assert code == 2
        with pytest.raises(ilcrig.InputError) as info:
            ilcrig.Experiment(**keys).plan  # noqa: B018
        assert err.strip() == f"ilcrig: error: {info.value}", (keys, err)
    with pytest.raises(ilcrig.InputError, match="mode must be 'sim' or 'rig'"):
        ilcrig.Experiment(**SHORT).run(mode="vm")


def test_toml_file_and_keywords(tmp_path: Path) -> None:
    f = tmp_path / "exp.toml"
    f.write_text('law = "pd-ol"\niterations = 3\ncycle_s = 0.15\n[gains]\nalpha = 4.0\n')
    exp = ilcrig.Experiment.from_toml(f, iterations=2)
    assert exp.config.law == "pd-ol" and exp.config.iterations == 2 and exp.config.gains.alpha == 4.0
    with pytest.raises(ilcrig.InputError, match=f"config file {f}: unknown key"):
        f.write_text("lawz = 1\n")
        ilcrig.Experiment(f)


def test_stepping_with_a_gain_change_between_trials() -> None:
    exp = ilcrig.Experiment(law="pd-ol", iterations=3, cycle_s=0.15)
    plain = exp.run()
    with exp.start() as session:
        first = session.step()
        assert first is not None and first.trial == 0
        kp0 = np.array(first.gains["kp_nm_per_rad"])
        session.set_gains(alpha=4.0)  # Kp = (alpha - 1) Lp: from 2 Lp to 3 Lp
        kp1 = session.plan.gains.kp
        np.testing.assert_allclose(kp1, 1.5 * kp0, rtol=1e-12)
        second = session.step()
        assert second is not None
        np.testing.assert_allclose(second.gains["kp_nm_per_rad"], kp1, rtol=1e-12)
        for j, drive in enumerate(session._sim.runner.bench.drives):  # the drive holds the new gain (Q16)
            assert drive.gains()[0] == pytest.approx(kp1[j], abs=2**-16)
        with pytest.raises(ilcrig.InputError, match=r"gains.alpha and gains.beta must be >= 1, got 0.5"):
            session.set_gains(alpha=0.5)
        rest = list(session)
    res = session.results
    assert [t.trial for t in res] == [0, 1, 2] and len(rest) == 1 and res.completed
    np.testing.assert_array_equal(res[0].error_rad, plain[0].error_rad)
    assert not np.array_equal(res[1].error_rad, plain[1].error_rad)  # stiffer feedback: another error
    assert res.summary["gain_changes"][0]["before_trial"] == 1


class FixedGainLaw(HalfP):
    """u_{k+1} = u_k + 0.5·Lp·e_k (shifted by one sample): a protocol law defined in this test module."""

    description = "half the learning P gain, one-sample lead"
    shift = 1


def test_protocol_laws_by_module_class_and_registration() -> None:
    by_path = ilcrig.Experiment(law=f"{__name__}:FixedGainLaw", **SHORT)
    assert not by_path.check.checked  # no iteration map: not checked, said plainly
    assert by_path.plan.check.as_dict()["ok"] is None
    res = by_path.run()
    assert res.check["checked"] is False and res.completed
    expected = res[0].feedforward_nm + 0.5 * by_path.plan.gains.lp * ilcrig.signals.lead(res[0].error_rad, 1)
    np.testing.assert_array_equal(res[1].feedforward_nm, expected)
    by_class = ilcrig.Experiment(law=FixedGainLaw, **SHORT)  # importable: module:Class
    assert by_class.config.law == f"{__name__}:FixedGainLaw" and by_class.run().digest == res.digest
    name = ilcrig.register_law(FixedGainLaw, "half-p-test")
    assert name in ilcrig.available_laws() and ilcrig.Experiment(law=name, **SHORT).run().digest == res.digest
    with pytest.raises(ilcrig.InputError, match="registered in this process only"):
        ilcrig.Experiment(law=name, **SHORT).run(mode="rig")


def _peaks(res: ilcrig.Results) -> tuple[float, float]:
    """Peak |u| and peak |u + feedback| (the demand before the drive's clamp) over all trials, N·m."""
    return float(np.abs(res.feedforward_nm).max()), float(np.abs(res.feedforward_nm + res.feedback_nm).max())


def test_constrained_law_respects_the_torque_limit() -> None:
    # 0.125 s with the 4-5-6-7 law: the unconstrained norm-optimal law winds its feed-forward up past
    # the drives' limit; the constrained one keeps u within (1 - margin) of it
    fast = {"cycle_s": 0.125, "profile": "poly4567", "iterations": 3}
    free = ilcrig.Experiment(law="no-ilc-id", **fast).run()
    cons = ilcrig.Experiment(law="cno-ilc", **fast).run()
    assert _peaks(free)[0] > LIMIT_NM
    assert _peaks(cons)[0] <= 0.98 * LIMIT_NM + 1e-6
    assert cons.final.rmse_deg.max() < free.final.rmse_deg.max()
    # --cycle 0.15 (the paper's Table 5 row) with a limit of the user's (law option)
    row = {"cycle_s": 0.15, "profile": "poly4567", "iterations": 3}
    free = ilcrig.Experiment(law="no-ilc-id", **row).run()
    cons = ilcrig.Experiment(law="cno-ilc", law_options={"torque_limit_nm": 185.0, "margin": 0.0}, **row).run()
    assert _peaks(free)[0] > 185.0 and _peaks(cons)[0] <= 185.0 + 1e-6
    assert cons.check["checked"] is True


def test_constrained_step_is_the_norm_optimal_step_when_no_limit_binds() -> None:
    from host.learning.laws.constrained import ConstrainedStep
    from host.learning.norm_optimal import NormOptimalStep

    plan = ilcrig.Experiment(law="no-ilc", cycle_s=0.15).plan
    model = plan.law.ctx.model
    step = NormOptimalStep(model, 1e-5)
    qp = ConstrainedStep(model, step.r, 1e6, None)
    e = np.random.default_rng(1).standard_normal((model.n, 4)) * 1e-3
    du_qp = qp(np.zeros_like(e), e, np.zeros_like(e))
    du_ref = step(e)
    assert qp.last_status == "solved"
    np.testing.assert_allclose(du_qp, du_ref, atol=1e-4 * np.abs(du_ref).max())


def test_model_free_law_counts_its_rollouts_as_trials() -> None:
    res = ilcrig.Experiment(law="adjoint-ilc", iterations=5, cycle_s=0.15).run()
    assert res.roles == ["learning", "auxiliary", "auxiliary", "learning", "learning"]
    assert [it.get("role", "learning") for it in res.summary["iterations"]] == res.roles
    assert res.summary["ticks"] == 5 * 301 and not res.check["checked"]
    # the last learning trial had no room for its rollouts: the feed-forward is kept
    np.testing.assert_array_equal(res[4].feedforward_nm, res[3].feedforward_nm)
    # the step learned: the error of trial 3 is below trial 0's; the rollouts perturbed u_0
    assert np.mean(res[3].rmse_deg) < np.mean(res[0].rmse_deg)
    for k in (1, 2):
        assert np.abs(res[k].feedforward_nm - res[0].feedforward_nm).max() == pytest.approx(5.0)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_api_on_the_rig_has_the_digest_of_sim(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(law="adjoint-ilc", iterations=4, cycle_s=0.15)
    sim = exp.run()
    seen = [(t.trial, t.role) for t in exp.trials(mode="rig", out=tmp_path / "rig", bus="hub", timeout_s=600)]
    assert seen == [(0, "learning"), (1, "auxiliary"), (2, "auxiliary"), (3, "learning")]
    rig = ilcrig.load(tmp_path / "rig")
    assert rig.mode == "rig" and rig.completed and rig.digest == sim.digest
    np.testing.assert_array_equal(rig.error_rad, sim.error_rad)
    np.testing.assert_array_equal(rig.feedforward_nm, sim.feedforward_nm)
    assert rig.roles == sim.roles and units.RAD_PER_COUNT > 0


def test_the_rig_imports_laws_from_this_processs_working_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``python -c`` / the REPL have '' on sys.path (the working folder): the rig's host gets that
    folder on its PYTHONPATH, so a law importable here by module:Class is importable there."""
    import ilcrig.rig

    class Spawned(Exception):
        pass

    seen: dict[str, str] = {}

    def fake_spawn(argv: list[str], **kw: Any) -> Any:
        seen.update(kw["env"])
        raise Spawned

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", ["", *sys.path])
    monkeypatch.setattr(ilcrig.rig, "spawn_process", fake_spawn)
    with pytest.raises(Spawned):
        ilcrig.RigRun(ilcrig.Experiment(law="pd-ol", iterations=1, cycle_s=0.15), tmp_path / "rig")
    assert str(tmp_path) in seen["PYTHONPATH"].split(os.pathsep)
