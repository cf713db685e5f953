"""docs/sweeps.md's examples run as documented, at a reduced size: the Monte Carlo sweep (§3), the
two tuning runs (§4: the starting point is the study's first trial, the best is never worse, best.toml
reproduces the best value, the study resumes) and the Python block (§6)."""

from __future__ import annotations

import math
import re
import shlex
import subprocess
from pathlib import Path

import pytest
from cli_util import run_cli_process

import ilcrig

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "sweeps.md"
#: the reduction: two short trials per experiment
SMALL = ["--set", "iterations=2", "--set", "cycle_s=0.15", "--workers", "2", "--no-progress"]
GUARD_S = 300.0


def _commands(prefix: str) -> list[list[str]]:
    """The documented commands starting with ``prefix`` (in fenced blocks, one per line)."""
    found, fence = [], None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fence = line[3:].strip() if fence is None else None
        elif fence == "" and line.startswith(prefix):
            found.append(shlex.split(line))
    return found


def _run(argv: list[str], out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """``argv`` (``ilcrig …``) with its ``--out`` in ``out`` and ``extra`` options."""
    args = list(argv[1:])
    args[args.index("--out") + 1] = str(out)
    return run_cli_process([*args, *extra], GUARD_S)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_monte_carlo_example(tmp_path: Path) -> None:
    cmd = _commands("ilcrig sweep --spec examples/montecarlo.toml")[0]  # §3 (§5 runs it on a cluster)
    assert cmd == shlex.split("ilcrig sweep --spec examples/montecarlo.toml --out runs/montecarlo")
    assert "samples = 100" in (ROOT / "examples" / "montecarlo.toml").read_text()
    out = tmp_path / "mc"
    p = _run(cmd, out, "--samples", "3", *SMALL)
    assert p.returncode == 0, p.stderr
    assert "6 run, 0 already finished" in p.stdout
    report = (out / "report.md").read_text()
    assert "## Monte Carlo: the final RMSE over 3 plants per grid point" in report
    assert "| pd-ilc | 3 | 0 |" in report and "| pd-ilc-q | 3 | 0 |" in report
    assert (out / "montecarlo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import pyarrow.parquet as pq

    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert len(rows) == 2 * 3 * 2 * 4  # laws × plants × trials × joints
    scales = {(r["law"], r["sample"]): r["plant.inertia_scale"] for r in rows}
    assert len(set(scales.values())) == 3  # the same three plants for both laws
    assert all(0.8 <= v <= 1.2 for v in scales.values())


def _study(out: Path):  # type: ignore[no-untyped-def]
    import optuna

    return optuna.load_study(study_name="ilcrig-tune", storage=f"sqlite:///{out / 'study.db'}")


@pytest.mark.slow
@pytest.mark.multiprocess
@pytest.mark.parametrize("example", ["tune_pd_ilc_q", "tune_pd_ilc"])
def test_tuning_examples(tmp_path: Path, example: str) -> None:
    from host.studies.spec import SweepSpec
    from host.studies.tune_params import Objective

    (cmd,) = _commands(f"ilcrig tune --spec examples/{example}.toml")
    out = tmp_path / "tune"
    p = _run(cmd, out, "--budget", "4", *SMALL)
    assert p.returncode == 0, p.stderr
    assert "best J = " in p.stdout and f"run them: ilcrig sim --config {out / 'best.toml'}" in p.stdout
    study = _study(out)
    trials = sorted(study.trials, key=lambda t: t.number)
    assert len(trials) == 4
    first = trials[0]
    spec = SweepSpec.from_toml(ROOT / "examples" / f"{example}.toml")
    spec.add_cli(["iterations=2", "cycle_s=0.15"])
    tuned = list(spec.extra["tune"])
    tuned.remove("budget")
    base = ilcrig.Experiment(**spec.base_options())
    start = {k: getattr(base.config.gains, k.split(".")[1]) for k in tuned}
    assert first.user_attrs.get("start") and first.params == start  # the hand-picked gains first
    obj = spec.extra["objective"]
    objective = Objective(settle_weight=obj["settle_weight"], require_check=obj["require_check"])
    assert base.check.ok  # the starting point is feasible and runs
    assert first.value == objective.of_summary(base.run().summary)  # the real objective
    assert math.isfinite(study.best_value) and study.best_value <= first.value
    # best.toml is an experiment file that gives the best value
    best = ilcrig.Experiment.from_toml(out / "best.toml")
    assert objective.of_summary(best.run().summary) == study.best_value
    assert "## Best against the starting point" in (out / "report.md").read_text()
    if example != "tune_pd_ilc_q":
        return
    # the study resumes up to a larger budget
    p = _run(cmd, out, "--budget", "5", *SMALL)
    assert p.returncode == 0, p.stderr
    assert "5 trials (4 in the study already)" in p.stderr
    assert len(_study(out).trials) == 5


@pytest.mark.slow
@pytest.mark.multiprocess
def test_python_block(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    (code,) = re.findall(r"^```python\n(.*?)^```", DOC.read_text(encoding="utf-8"), flags=re.S | re.M)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "docs/sweeps.md §6", "exec"), {"__name__": "__docs__"})  # noqa: S102 - the documentation's own code
    assert "2 points; the first one's labels: {'gains.alpha': 2}" in capsys.readouterr().out
    assert len(list((tmp_path / "runs" / "py-sweep" / "runs").iterdir())) == 2
