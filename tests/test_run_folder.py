"""One run, one folder: a run folder that holds another run is refused before anything starts
(``ilcrig sim``, ``ilcrig run``, ``ilcrig robot``, the API), with one line and exit code 2, and nothing in it changes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_util import run_cli

import ilcrig
from host.experiment.outputs import RUN_FOLDER_MARKERS

SHORT = ["--iterations", "2", "--cycle", "0.15"]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("command", ["sim", "run"])
def test_a_folder_holding_a_run_is_refused_and_left_as_it_was(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x"
    code, _, err = run_cli(capsys, "sim", *SHORT, "--out", str(out))
    assert code == 0, err
    before = _files(out)
    assert json.loads(before["summary.json"])["completed"] is True
    code, _, err = run_cli(capsys, command, "--iterations", "1", "--cycle", "0.15", "--out", str(out))
    assert code == 2
    held = "summary.json, trials, recording.rrd, report.md"
    assert err.splitlines() == [
        f"ilcrig: error: --out {out}: holds another run ({held}); give a new or an empty folder, or remove that run"
    ]
    assert _files(out) == before  # nothing of the second run, nothing of the first changed


def test_an_empty_or_new_folder_is_taken(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "empty", tmp_path / "new"):
        code, _, err = run_cli(capsys, "sim", "--iterations", "1", "--cycle", "0.15", "--out", str(out))
        assert code == 0, err


def test_the_api_refuses_a_folder_holding_a_run_too(tmp_path: Path) -> None:
    exp = ilcrig.Experiment(iterations=1, cycle_s=0.15)
    exp.run(out=tmp_path / "r")
    with pytest.raises(ilcrig.InputError, match="holds another run"):
        exp.run(out=tmp_path / "r")


@pytest.mark.parametrize("command", ["sim", "robot"])
@pytest.mark.parametrize("marker", RUN_FOLDER_MARKERS)
def test_any_output_of_a_run_marks_the_folder(
    marker: str, command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Of a run or of a robot session (``trace.bin``, ``plant.json``): ``ilcrig sim`` and ``ilcrig
    robot`` (which checks before any process starts) refuse the folder, exit 2, one line."""
    out = tmp_path / "x"
    out.mkdir()
    (out / marker).mkdir() if marker in ("trials", "logs") else (out / marker).write_text("")
    args = ["--iterations", "1", "--cycle", "0.15"] if command == "sim" else []
    code, _, err = run_cli(capsys, command, *args, "--out", str(out))
    assert code == 2 and err.splitlines() == [
        f"ilcrig: error: --out {out}: holds another run ({marker}); give a new or an empty folder, or remove that run"
    ]
    assert sorted(p.name for p in out.iterdir()) == [marker]


def test_a_run_nobody_named_gets_a_folder_of_its_own(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``runs/<kind>-<time>``: two commands of the same second (or a name taken earlier) get
    ``-2``, ``-3`` …, claimed atomically — never one folder for two runs."""
    from host.experiment.outputs import default_run_folder

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("time.strftime", lambda fmt: fmt.replace("%Y%m%d-%H%M%S", "20261206-120000"))
    named = default_run_folder("sim", claim=False)
    assert named == Path("runs/sim-20261206-120000") and not named.exists()
    claimed = [default_run_folder("sim", claim=True) for _ in range(3)]
    assert [p.name for p in claimed] == ["sim-20261206-120000", "sim-20261206-120000-2", "sim-20261206-120000-3"]
    assert all(p.is_dir() and not any(p.iterdir()) for p in claimed)
    assert default_run_folder("sim", claim=False).name == "sim-20261206-120000-4"


def test_two_sims_of_the_same_second_without_out_keep_two_folders(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("time.strftime", lambda fmt: fmt.replace("%Y%m%d-%H%M%S", "20261206-120000"))
    for _ in range(2):
        code, out, err = run_cli(capsys, "sim", "--iterations", "1", "--cycle", "0.15")
        assert code == 0, err
    runs = sorted(p.name for p in (tmp_path / "runs").iterdir())
    assert runs == ["sim-20261206-120000", "sim-20261206-120000-2"]
    assert all(json.loads((tmp_path / "runs" / r / "summary.json").read_text())["completed"] for r in runs)
    code, out, err = run_cli(capsys, "sim", "--iterations", "1", "--cycle", "1e9")  # bad input: no folder made
    assert code == 2 and sorted(p.name for p in (tmp_path / "runs").iterdir()) == runs
