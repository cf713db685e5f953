"""Every bad input is refused before anything starts: one line ``ilcrig: error: …`` naming the
option or file and what is allowed, exit code 2, nothing written, no process started.  The
refusals come before the expensive part of the preparation (checked by what a fresh interpreter
has imported, not by wall-clock time).  The memory check is driven through its documented input,
``$ILCRIG_AVAILABLE_MEMORY``."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from cli_util import run_cli

from host.experiment import plan as plan_mod
from host.experiment.config import MAX_ITERATIONS, build_config
from host.rig import launcher


def assert_refused(code: int, err: str, *fragments: str) -> str:
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("ilcrig: error: ") and "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


@pytest.fixture(autouse=True)
def _no_launch(monkeypatch: pytest.MonkeyPatch) -> None:
    """`ilcrig run` must refuse before it launches anything: launching is an error here."""

    def boom(self: object) -> int:
        raise AssertionError("a process was launched")

    monkeypatch.setattr(launcher.RigLauncher, "run", boom)


@pytest.mark.parametrize(
    ("argv", "fragments"),
    [
        (["--iterations", "100000000"], [f"iterations must be between 1 and {MAX_ITERATIONS}"]),
        (["--lead", "600"], ["--lead 600", "less than N = 501"]),
        (["--lead", "1000000"], ["--lead 1000000", "(0..500)"]),
        (["--cycle", "40"], ["--cycle 40", "table capacity of 60000 samples"]),
        (["--cycle", "nan"], ["cycle_s must be finite"]),
        (["--cycle", "inf"], ["cycle_s must be finite"]),
        (["--lp", "nan"], ["gains.lp must be finite"]),
        (["--alpha", "inf"], ["gains.alpha must be finite"]),
        (["--lp", "30000"], ["Kp of joint 1 = 60000", "fixed-point range 0..54685"]),
        (["--lp", "1e12"], ["Kp of joint 1 = 2e+12"]),
        (["--seed", "5000000000"], ["seed must be 0..4294967295"]),
    ],
)
@pytest.mark.parametrize("command", ["sim", "run"])
def test_bad_option(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, command: str, argv: list[str], fragments: list[str]
) -> None:
    code, _, err = run_cli(capsys, command, *argv, "--out", str(tmp_path / "run"))
    assert_refused(code, err, *fragments)
    assert not (tmp_path / "run").exists()  # nothing written


def test_a_run_that_needs_more_memory_than_the_machine_has(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(plan_mod.MEMORY_ENV, "800M")
    need = plan_mod.run_memory_bytes(20001, 100, "no-ilc-id")
    assert 800 * 1024**2 < need < 1024**3  # what the message shows in MiB
    code, _, err = run_cli(capsys, "sim", "--cycle", "10", "--iterations", "100", "--out", str(tmp_path / "run"))
    line = assert_refused(
        code,
        err,
        "--cycle 10, --iterations 100",
        "N = 20001",
        "law no-ilc-id",
        f"needs about {need / 1024**2:.0f} MiB of memory",
        "800 MiB available (ILCRIG_AVAILABLE_MEMORY)",
    )
    # the largest cycle that fits with 100 trials, as the model gives it
    n_fit = (800 * 1024**2 / plan_mod.MEMORY_MARGIN - plan_mod.RUN_BASE_BYTES) // (
        plan_mod.SAMPLE_BYTES["no-ilc-id"] + 100 * plan_mod.TRIAL_SAMPLE_BYTES
    )
    assert f"use a cycle of at most about {(n_fit - 1) // 2 * 0.001:.2f} s or fewer trials" in line
    assert not (tmp_path / "run").exists()


def test_a_machine_without_room_for_any_run(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(plan_mod.MEMORY_ENV, "100M")
    code, _, err = run_cli(capsys, "sim")
    fixed = plan_mod.MEMORY_MARGIN * plan_mod.RUN_BASE_BYTES
    assert_refused(code, err, "100 MiB available", f"not even the fixed part of about {fixed / 1024**2:.0f} MiB fits")


@pytest.mark.parametrize("value", ["lots", "-1G", "nan", "2X"])
def test_a_bad_memory_size_in_the_environment_is_named(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setenv(plan_mod.MEMORY_ENV, value)
    code, _, err = run_cli(capsys, "sim")
    assert_refused(code, err, f"ILCRIG_AVAILABLE_MEMORY={value!r}: must be a size in bytes")


@pytest.mark.parametrize(("value", "size"), [("2G", 2 * 1024**3), ("512MiB", 512 * 1024**2), ("1.5k", 1536), ("1000", 1000)])
def test_memory_sizes_in_the_environment(monkeypatch: pytest.MonkeyPatch, value: str, size: int) -> None:
    monkeypatch.setenv(plan_mod.MEMORY_ENV, value)
    assert plan_mod.available_memory_bytes() == size


def test_the_rig_counts_its_other_processes(monkeypatch: pytest.MonkeyPatch) -> None:
    """``ilcrig run`` needs the memory of seven processes: refused where ``ilcrig sim`` fits."""
    cfg = build_config(None, {"cycle_s": 10.0, "iterations": 2})
    sim_need = plan_mod.run_memory_bytes(20001, 2, cfg.law)
    rig_need = plan_mod.run_memory_bytes(20001, 2, cfg.law, rig=True)
    rig_part = plan_mod.RIG_EXTRA_BYTES + 20001 * plan_mod.RIG_SAMPLE_BYTES
    assert rig_need == pytest.approx(sim_need + plan_mod.MEMORY_MARGIN * rig_part, abs=2)
    monkeypatch.setenv(plan_mod.MEMORY_ENV, str(sim_need))
    assert plan_mod.check_config_limits(cfg) == 20001
    with pytest.raises(plan_mod.PlanError, match=f"the rig's processes need about {rig_need / 1024**3:.1f} GiB of memory"):
        plan_mod.check_config_limits(cfg, rig=True)


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("[gains]\nlp = 1e12\n", ["Kp of joint 1 = 2e+12"]),
        ("[gains]\nlp = 30000\n", ["Kp of joint 1 = 60000"]),
        ("gains = 5\n", ["exp.toml: gains must be a table", "got 5"]),
        ('gains = "abc"\n', ["exp.toml: gains must be a table", "got 'abc'"]),
        ("law = 3\n", ["exp.toml: law must be a string, got 3"]),
        ("cycle_s = nan\n", ["exp.toml: cycle_s must be finite"]),
        ("[gains]\nalpha = inf\n", ["exp.toml: gains.alpha must be finite"]),
        ("iterations = 5000\n", ["exp.toml: iterations must be between 1 and 1000"]),
        ("path = [1, 2]\n", ["exp.toml: path must be 1-4 or a path file name"]),
        ("law = \n", ["exp.toml is not valid TOML"]),
    ],
)
@pytest.mark.parametrize("command", ["sim", "run"])
def test_bad_config_file(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, command: str, text: str, fragments: list[str]
) -> None:
    cfg = tmp_path / "exp.toml"
    cfg.write_text(text)
    code, _, err = run_cli(capsys, command, "--config", str(cfg), "--out", str(tmp_path / "run"))
    assert_refused(code, err, *fragments)


def test_binary_or_unreadable_config_file_is_named(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    binary = tmp_path / "bin.toml"
    binary.write_bytes(bytes(range(256)) * 4)
    code, _, err = run_cli(capsys, "sim", "--config", str(binary), "--out", str(tmp_path / "run"))
    assert_refused(code, err, f"config file {binary} is not a text (UTF-8) TOML file")
    code, _, err = run_cli(capsys, "run", "--config", str(tmp_path), "--out", str(tmp_path / "run"))
    assert_refused(code, err, f"config file {tmp_path} is a folder")
    code, _, err = run_cli(capsys, "sim", "--config", str(tmp_path / "nope.toml"))
    assert_refused(code, err, "config file not found", "nope.toml")


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_config_file_without_read_permission(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    cfg = tmp_path / "secret.toml"
    cfg.write_text("iterations = 2\n")
    cfg.chmod(0)
    code, _, err = run_cli(capsys, "sim", "--config", str(cfg))
    assert_refused(code, err, f"cannot read config file {cfg}")


@pytest.mark.parametrize("command", ["sim", "run"])
def test_out_is_an_existing_file(capsys: pytest.CaptureFixture[str], tmp_path: Path, command: str) -> None:
    f = tmp_path / "taken"
    f.write_text("x")
    code, _, err = run_cli(capsys, command, "--out", str(f))
    assert_refused(code, err, f"--out {f}: exists and is not a folder")


def _read_only_folder(tmp_path: Path) -> Path | None:
    """A folder nobody can write into: chmod for a normal user, a read-only tmpfs for root."""
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:
        ro.chmod(0o555)
        return ro
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)], capture_output=True)
    return ro if res.returncode == 0 else None


@pytest.mark.parametrize("command", ["sim", "run"])
def test_out_in_a_read_only_folder(capsys: pytest.CaptureFixture[str], tmp_path: Path, command: str) -> None:
    ro = _read_only_folder(tmp_path)
    if ro is None:
        pytest.skip("no read-only folder available (root without mount)")
    try:
        code, _, err = run_cli(capsys, command, "--out", str(ro / "run"))
        assert_refused(code, err, f"--out {ro / 'run'}: cannot create the run folder")
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", str(ro)], capture_output=True)


def test_bad_inject_specs(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    for spec, fragment in (
        ("kill:drive9@1:10", "kill needs a role"),
        ("drop:io@99:0", "trial 99 is beyond"),
        ("shake:io@1:1", "unknown action 'shake'"),
        ("drop:io@1:2,rate=2", "rate must be in (0, 1]"),
        ("stall:host@x:1", "@WHEN must be TRIAL:TICK (two integers >= 0"),
        ("stall:host@0:99999", "tick 99999 is beyond a trial of 501 ticks (0..500); after the trial is @0:end"),
        ("drop:io@after", "the io channel carries frames only during a trial"),
    ):
        code, _, err = run_cli(capsys, "run", "--iterations", "2", "--inject", spec, "--out", str(tmp_path / "r"))
        assert_refused(code, err, f"--inject {spec}", fragment)


def test_relative_path_in_a_config_is_relative_to_the_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg_dir = tmp_path / "cfg"
    cfg_dir.mkdir()
    (cfg_dir / "exp.toml").write_text('path = "mine.toml"\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    cfg = build_config(cfg_dir / "exp.toml")
    assert cfg.path == str(cfg_dir.resolve() / "mine.toml")
    # built-in paths stay built-in; a command-line path is the user's (relative to the working directory)
    (cfg_dir / "exp.toml").write_text('path = "2"\n')
    assert build_config(cfg_dir / "exp.toml").path == "2"
    assert build_config(cfg_dir / "exp.toml", {"path": "here.toml"}).path == "here.toml"


def test_command_line_gains_merge_over_the_file_table(tmp_path: Path) -> None:
    (tmp_path / "exp.toml").write_text("[gains]\nalpha = 2.0\nld_norm = 0.1\n")
    cfg = build_config(tmp_path / "exp.toml", {"gains": {"lp_norm": 0.002}})
    assert (cfg.gains.alpha, cfg.gains.ld_norm, cfg.gains.lp_norm) == (2.0, 0.1, 0.002)


@pytest.mark.parametrize(
    "argv",
    [
        ["--lead", "600"],
        ["--lp", "1e12"],
        ["--cycle", "40"],
        ["--cycle", "10", "--iterations", "1000"],
        ["--path", "/nonexistent.toml"],
    ],
)
def test_cheap_refusals_come_before_planning(tmp_path: Path, argv: list[str]) -> None:
    """These are refused before the trajectory is planned and the learning law is built: in a
    fresh interpreter scipy.signal (about 1 s to import, needed by the laws) was never imported.
    (The memory refusal: with 1 GiB available.)"""
    import sys

    code = (
        "import sys\n"
        "from host.cli import main\n"
        f"code = main({['sim', *argv, '--out', str(tmp_path / 'o')]!r})\n"
        "print(code, 'scipy.signal' in sys.modules)\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parent.parent,
        env=dict(os.environ, **{plan_mod.MEMORY_ENV: "1G"}),
    )
    assert res.stdout.split() == ["2", "False"], (res.stdout, res.stderr)
    assert res.stderr.startswith("ilcrig: error: ") and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_rt_priority_range_and_needs_realtime(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "run", "--realtime", "--rt-priority", "100", "--out", str(tmp_path / "run"))
    assert_refused(code, err, "--rt-priority", "0..99")
    code, _, err = run_cli(capsys, "run", "--rt-priority", "5", "--out", str(tmp_path / "run"))
    assert_refused(code, err, "--rt-priority 5", "add --realtime")
    assert not (tmp_path / "run").exists()


def test_bus_time_needs_the_hub(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "run", "--bus-time", "--bus", "udp_multicast", "--out", str(tmp_path / "run"))
    assert_refused(code, err, "--bus-time", "use --bus hub")
    assert not (tmp_path / "run").exists()


def test_no_idle_poll_needs_realtime(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "run", "--no-idle-poll", "--out", str(tmp_path / "run"))
    assert_refused(code, err, "--no-idle-poll", "add --realtime")
