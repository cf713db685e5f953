"""The bad inputs of a run are refused before anything starts: exit code 2,
one line ``ilcrig: error: …`` with the reason, no run folder written, no process started — a
transport this machine lacks, conflicting transport options, a hub address whose folder is
missing or not a loopback one, an ``--inject`` without ``@WHEN``, a cycle out of range; the same
for ``ilcrig robot``.

"Before anything starts" is asserted on events, not on the wall clock: spawning a process (a role,
the hub), creating the run folder and the expensive preparation of the experiment
(:func:`host.experiment.plan.prepare`) all fail the test if they are reached.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from cli_util import run_cli

from bus.transports.config import transport_from_name
from host.experiment import plan as plan_mod
from host.rig import launch_core, launcher, processes, robot_launcher


@pytest.fixture(autouse=True)
def _nothing_starts(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every way to start something or to write the run folder fails the test."""
    events: list[str] = []

    def refuse(what: str) -> Any:
        def boom(*args: object, **kwargs: object) -> None:
            events.append(what)
            raise AssertionError(f"{what} was reached: the input was not refused first")

        return boom

    monkeypatch.setattr(processes, "spawn", refuse("spawn"))
    monkeypatch.setattr(processes, "start_hub_process", refuse("start_hub_process"))
    monkeypatch.setattr(launch_core, "spawn", refuse("spawn"))
    monkeypatch.setattr(launch_core, "start_hub_process", refuse("start_hub_process"))
    for module in (launch_core, launcher, robot_launcher):
        monkeypatch.setattr(module, "make_run_folder", refuse("make_run_folder"))
    monkeypatch.setattr(plan_mod, "prepare", refuse("prepare"))
    return events


def _has_vcan() -> bool:
    try:
        transport_from_name("socketcan", None, False).check_usable(hub_given=False)
    except ValueError:
        return False
    return True


def _refused(capsys: pytest.CaptureFixture[str], out: Path, argv: list[str], *fragments: str) -> None:
    code, stdout, err = run_cli(capsys, *argv)
    lines = err.strip().splitlines()
    assert code == 2, (code, stdout, err)
    assert len(lines) == 1 and lines[0].startswith("ilcrig: error: ") and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert not out.exists(), "a run folder was written"


RUN_CASES = [
    pytest.param(["--hub", "unix:/nonexistent/dir/hub.sock"], ["/nonexistent/dir", "does not exist"], id="hub-folder-missing"),
    pytest.param(["--bus", "socketcan", "--hub", "unix:/tmp/x.sock"], ["--hub", "socketcan"], id="conflicting-hub"),
    pytest.param(["--inject", "kill:drive2"], ["kill:drive2", "@WHEN is missing"], id="inject-without-when"),
    pytest.param(["--bus", "frob"], ["--bus frob", "unknown transport"], id="unknown-transport"),
    pytest.param(["--hub", "tcp:10.1.2.3:5000"], ["non-loopback", "10.1.2.3"], id="non-loopback-hub"),
    pytest.param(["--cycle", "1e9"], ["--cycle", "table capacity"], id="cycle-out-of-range"),
]


@pytest.mark.parametrize(("argv", "fragments"), RUN_CASES)
def test_run_refuses_before_anything_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, _nothing_starts: list[str], argv: list[str], fragments: list[str]
) -> None:
    out = tmp_path / "run"
    _refused(capsys, out, ["run", "--iterations", "2", "--out", str(out), *argv], *fragments)
    assert _nothing_starts == []


def test_a_transport_this_machine_lacks(capsys: pytest.CaptureFixture[str], tmp_path: Path, _nothing_starts: list[str]) -> None:
    if _has_vcan():
        pytest.skip("this machine has vcan: --bus socketcan is usable here")
    out = tmp_path / "run"
    _refused(capsys, out, ["run", "--iterations", "2", "--out", str(out), "--bus", "socketcan"], "--bus socketcan", "vcan")
    assert _nothing_starts == []


def test_unknown_transport_lists_only_what_help_knows(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out = tmp_path / "run"
    code, _, err = run_cli(capsys, "run", "--out", str(out), "--bus", "frob")
    assert code == 2 and "virtual" not in err, err
    code, help_text, _ = run_cli(capsys, "run", "--help")
    assert code == 0
    listed = err.split("choose from", 1)[1].strip().split(", ")
    assert all(name in help_text for name in listed), (listed, help_text)


@pytest.mark.parametrize(
    ("argv", "fragments"),
    [
        pytest.param(["--hub", "unix:/nonexistent/dir/hub.sock"], ["/nonexistent/dir", "does not exist"], id="hub-missing"),
        pytest.param(["--bus", "frob"], ["--bus frob"], id="unknown-transport"),
    ],
)
def test_robot_refuses_before_anything_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, _nothing_starts: list[str], argv: list[str], fragments: list[str]
) -> None:
    out = tmp_path / "robot"
    _refused(capsys, out, ["robot", "--out", str(out), *argv], *fragments)
    assert _nothing_starts == []
