"""`ilcrig sim`: bad input is one line + exit 2; the run folder; determinism; the acceptance
numbers of the default experiment (PD-ILC against D-ILC, the best law against the encoder LSB).
The command line as a whole: only bad input is exit 2 (an internal error is exit 1, with or without
``--debug``), every command lives in host/cli/, and docs/usage.md lists every exit code."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_util import run_cli

from bus import units
from bus.exit_codes import EXIT_ERROR, EXIT_USAGE, ExitCode
from host.experiment.config import build_config
from host.experiment.plan import prepare
from host.experiment.trial_loop import run_experiment
from host.sim.inprocess import InProcessBench


def assert_one_line_error(code: int, err: str, fragment: str) -> None:
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("ilcrig: error: ")
    assert fragment in lines[0]
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["--path", "7"], "path"),
        (["--law", "x-ilc"], "unknown law 'x-ilc'"),
        (["--iterations", "0"], "iterations must be between 1 and 1000"),
        (["--iterations", "-3"], "iterations must be between 1 and 1000"),
        (["--iterations", "1001"], "iterations must be between 1 and 1000"),
        (["--cycle", "0.05"], "too short"),
        (["--cycle", "-1"], "cycle_s must be > 0"),
        (["--alpha", "nan"], "gains.alpha must be finite"),
        (["--profile", "trapezoid"], "unknown profile"),
        (["--disturbance", "wind"], "unknown disturbance"),
        (["--iterations", "ten"], "invalid int value"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path: Path, argv: list[str], fragment: str) -> None:
    code, _, err = run_cli(capsys, "sim", *argv, "--out", str(tmp_path / "run"))
    assert_one_line_error(code, err, fragment)
    assert not (tmp_path / "run" / "summary.json").exists()  # nothing moved


def test_debug_keeps_exit_code_2_for_bad_input(capsys, tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "--debug", "sim", "--iterations", "0", "--out", str(tmp_path / "run"))
    assert code == EXIT_USAGE and "ilcrig: error: iterations must be between 1 and 1000" in err
    code, _, err = run_cli(capsys, "--debug", "run", "--rt-priority", "5", "--out", str(tmp_path / "run2"))
    assert code == EXIT_USAGE and "ilcrig: error: --rt-priority 5" in err


@pytest.mark.parametrize("debug", [False, True])
def test_a_value_error_of_the_internals_is_an_internal_error(capsys, monkeypatch, debug: bool) -> None:
    """A ValueError that is no InputError is a bug: exit 1 and ``internal error``, never 2 — and the
    same code with ``--debug`` (which prints the traceback too)."""
    from host.learning import registry

    def broken() -> dict[str, str]:
        raise ValueError("an internal value went wrong")

    monkeypatch.setattr(registry, "law_descriptions", broken)
    code, _, err = run_cli(capsys, *(["--debug"] if debug else []), "laws")
    assert code == EXIT_ERROR
    assert "ilcrig: internal error: ValueError: an internal value went wrong" in err
    assert ("Traceback" in err) == debug


def test_laws_lists_every_law_of_the_registry(capsys) -> None:
    from host.learning.registry import law_names

    code, out, _ = run_cli(capsys, "laws")
    assert code == 0 and [line.split()[0] for line in out.splitlines()[:-1]] == list(law_names())


ROOT = Path(__file__).resolve().parent.parent


def test_argparse_lives_only_in_host_cli() -> None:
    """Below the command line typed options travel (dataclasses), never argparse or its Namespace;
    the ``python -m`` tools' parsers are in host/cli too (dbc, selfcheck, janitor)."""
    found = set()
    for top in ("bus", "firmware_model", "host", "plant", "ilcrig"):
        for path in (ROOT / top).rglob("*.py"):
            rel = path.relative_to(ROOT).as_posix()
            if not rel.startswith("host/cli/") and re.search(r"\bargparse\b|\bNamespace\b", path.read_text()):
                found.add(rel)
    assert not found, sorted(found)


def test_usage_lists_every_exit_code() -> None:
    usage = (ROOT / "docs" / "usage.md").read_text()
    table = usage[usage.index("## Exit codes") :]
    table = table[: table.index("\n## ")] if "\n## " in table else table
    rows = {int(m.group(1)): m.group(2) for m in re.finditer(r"^\| (\d+) \| `(\w+)` \|", table, re.MULTILINE)}
    assert rows == {int(code): code.name for code in ExitCode}, rows


def test_unknown_toml_key_and_nan_gain(capsys, tmp_path: Path) -> None:
    cfg = tmp_path / "exp.toml"
    cfg.write_text('law = "pd-ilc"\nspeed = 3\n')
    code, _, err = run_cli(capsys, "sim", "--config", str(cfg))
    assert_one_line_error(code, err, "unknown key(s): speed")
    cfg.write_text("[gains]\nld = nan\n")
    code, _, err = run_cli(capsys, "sim", "--config", str(cfg))
    assert_one_line_error(code, err, "gains.ld must be finite")
    cfg.write_text("[gains]\nwobble = 1\n")
    code, _, err = run_cli(capsys, "sim", "--config", str(cfg))
    assert_one_line_error(code, err, "unknown key(s) in [gains]: wobble")


def test_point_out_of_reach(capsys, tmp_path: Path) -> None:
    path = tmp_path / "far.toml"
    path.write_text('name = "far"\npick = [0.0, 0.0, -0.65]\nplace = [0.9, 0.0, -0.65]\nlift = 0.025\nrotation_deg = 0\n')
    code, _, err = run_cli(capsys, "sim", "--path", str(path), "--cycle", "0.5", "--profile", "poly5")
    assert_one_line_error(code, err, "cannot reach")


#: trace digests of known experiments (the arithmetic of the drives, the plant and the laws is fixed:
#: a change of any of them shows here): argv → (trace_sha256, ticks)
REFERENCE_DIGESTS: dict[tuple[str, ...], tuple[str, int]] = {
    (): ("8eabb5ecee2062bd4aaa407617991054312f4012feb959054a921b6d4a016aa3", 10 * 501),
    ("--law", "pd-ilc"): ("67c297ecf96bb3e56edb987d2752880a48d508a757f8362225a009f2cf14922c", 10 * 501),
    ("--ff-transport", "pdo"): ("3a99e01b8dc74f4ac2c62a6a5e57b7a783348f184186e7f0307cb3344e43cf72", 10 * 501),
}
#: the digest of the short experiment below with seed 7
SEED_7_DIGEST = "8304ecc7d761f584a0c374dbf0207843a6c0d0f65a58328fb14ae1b47f2d7b22"


def test_same_seed_same_digest_and_summary_schema(capsys, tmp_path: Path) -> None:
    args = ["sim", "--iterations", "2", "--disturbance", "both", "--seed", "7", "--cycle", "0.15"]
    digests = []
    for name in ("a", "b"):
        code, out, err = run_cli(capsys, *args, "--out", str(tmp_path / name))
        assert code == 0, err
        s = json.loads((tmp_path / name / "summary.json").read_text())
        digests.append(s["trace_sha256"])
    assert digests == [SEED_7_DIGEST, SEED_7_DIGEST]
    assert s["schema"] == "ilcrig.summary/1" and s["mode"] == "sim" and s["completed"] is True
    assert s["config"] | {"law": "no-ilc-id", "iterations": 2, "path": "1", "cycle_s": 0.15} == s["config"]
    assert (s["config"]["profile"], s["config"]["disturbance"], s["config"]["seed"], s["config"]["ts_s"]) == (
        "ruckig",
        "both",
        7,
        0.001,
    )
    assert [it["k"] for it in s["iterations"]] == [0, 1]
    for key in ("rmse_deg", "max_abs_deg", "mae_deg", "peak_torque_nm"):
        assert len(s["iterations"][0][key]) == 4
    assert set(s["convergence_check"]) >= {"rho_max", "ok"}
    assert s["encoder_lsb_deg"] == pytest.approx(360 / (10 * 2**20))
    assert s["ticks"] == 2 * 301  # iterations × N
    assert s["wall_s"] > 0 and s["ticks_per_s"] == pytest.approx(s["ticks"] / s["wall_s"])
    # what the console shows: the plan, the check, the header, one row per trial (its RMSE as in the
    # summary), the closing line with the summary's numbers
    lines = out.strip().splitlines()
    assert lines[0] == (
        "ilcrig sim: law no-ilc-id, path 1, cycle 0.15 s, profile ruckig, disturbance both, 2 iterations, N = 301 ticks/trial"
    )
    assert lines[1].startswith("convergence check: spectral radius ")
    assert lines[2].split()[:3] == ["iter", "RMSE", "j1"]
    assert len(lines) == 6
    for k, row in enumerate(lines[3:5]):
        fields = row.split()
        assert int(fields[0]) == k
        assert [float(x) for x in fields[1:5]] == pytest.approx(s["iterations"][k]["rmse_deg"], abs=5e-6)
    assert lines[5] == (
        f"602 ticks in {s['wall_s']:.2f} s ({s['ticks_per_s']:.0f} ticks/s); trace_sha256 {SEED_7_DIGEST[:16]}…; "
        f"summary: {tmp_path / 'b' / 'summary.json'}"
    )
    # another seed changes the non-repetitive disturbance and so the traces
    code, _, _ = run_cli(capsys, *args[:-4], "--cycle", "0.15", "--seed", "8", "--out", str(tmp_path / "c"))
    assert code == 0
    assert json.loads((tmp_path / "c" / "summary.json").read_text())["trace_sha256"] != SEED_7_DIGEST


@pytest.mark.slow
@pytest.mark.parametrize("argv", list(REFERENCE_DIGESTS), ids=lambda a: " ".join(a) or "defaults")
def test_reference_experiments_keep_their_digests(capsys, tmp_path: Path, argv: tuple[str, ...]) -> None:
    code, out, err = run_cli(capsys, "sim", *argv, "--out", str(tmp_path / "run"))
    assert code == 0, err
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    digest, ticks = REFERENCE_DIGESTS[argv]
    assert (s["trace_sha256"], s["ticks"], s["completed"]) == (digest, ticks, True)
    assert f"trace_sha256 {digest[:16]}…" in out.strip().splitlines()[-1]


def rmse(law: str, iterations: int = 10, **overrides) -> np.ndarray:
    cfg = build_config(None, {"law": law, "iterations": iterations, **overrides})
    res = run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim")
    assert res.fault is None
    return np.array([m.rmse_deg for m in res.metrics])


@pytest.mark.slow
def test_default_pd_ilc_learns_and_beats_d_ilc() -> None:
    pd = rmse("pd-ilc")
    d = rmse("d-ilc")
    assert np.all(np.diff(pd, axis=0) < 0), pd  # RMSE falls on every joint, every trial
    assert np.all(pd[-1, [0, 2]] <= 0.3 * pd[0, [0, 2]])
    assert np.all(pd[-1] < d[-1]), (pd[-1], d[-1])


@pytest.mark.slow
def test_best_law_reaches_encoder_lsb_level() -> None:
    r = rmse("no-ilc")
    assert np.all(r[-1] <= 20 * units.DEG_PER_COUNT), r[-1] / units.DEG_PER_COUNT


@pytest.mark.slow
def test_paper_literal_gains_are_flagged_and_fault_cleanly(tmp_path: Path) -> None:
    cfg = build_config(None, {"law": "pd-ilc", "iterations": 8, "gains": {"preset": "paper"}})
    plan = prepare(cfg)
    assert not plan.check.ok
    res = run_experiment(plan, InProcessBench(cfg), tmp_path, mode="sim")
    s = json.loads((tmp_path / "summary.json").read_text())
    if res.fault is not None:  # the following-error check removed torque: earlier trials are kept
        assert s["faults"] and s["faults"][0]["trial"] == len(s["iterations"])
        assert "0x8611" in s["faults"][0]["message"]
    else:
        r = np.array([it["rmse_deg"] for it in s["iterations"]])
        assert r[-1, 0] > r[0, 0]


#: ``ilcrig run`` in a fresh interpreter, signalled by itself (argv[1]) as its command modules are
#: imported: the moment a user's Ctrl-C or ``kill`` lands when it comes in the command's first
#: fraction of a second
_START_SIGNAL_SCRIPT = """
import os, signal, sys

class Hook:
    def find_spec(self, name, path=None, target=None):
        if name == "host.planning.task_plan":
            os.kill(os.getpid(), getattr(signal, sys.argv[1]))
        return None

sys.meta_path.insert(0, Hook())
from host.cli import main
sys.exit(main(["run", "--out", sys.argv[2]]))
"""


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_while_the_command_modules_are_imported_is_said_in_one_line(tmp_path: Path, signame: str) -> None:
    """main() holds SIGINT and SIGTERM from its first statement and imports the command modules
    after: a signal then is one line and exit 130 / 143 (it was Python's traceback for SIGINT, and
    for SIGTERM a death by the signal with nothing said); nothing was made."""
    proc = subprocess.run(
        [sys.executable, "-c", _START_SIGNAL_SCRIPT, signame, str(tmp_path / "run")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert (proc.returncode, proc.stdout, proc.stderr) == (
        128 + getattr(signal, signame),
        "",
        f"ilcrig: interrupted ({signame})\n",
    )
    assert not (tmp_path / "run").exists()


def test_the_console_script_runs_main_and_leaves_the_heap_out_of_the_final_collections() -> None:
    """``ilcrig`` (and ``python -m host.cli``) is :func:`host.cli.command`: main's exit code, with
    every object alive moved out of the cycle collector's reach before Python's finalization (its
    collections would traverse the heap of numpy, scipy and numba: a quarter of a second per process
    on the run's path to its end)."""
    import tomllib

    scripts = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"ilcrig": "host.cli:command"}
    code = (
        "import gc, sys; from host.cli import command; sys.argv = ['ilcrig', 'laws']; "
        "rc = command(); print(rc, gc.get_freeze_count() > 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "0 True"
    bad = subprocess.run(
        [sys.executable, "-m", "host.cli", "run", "--iterations", "-1"], capture_output=True, text=True, timeout=120
    )
    assert (bad.returncode, bad.stdout) == (EXIT_USAGE, "")
    assert bad.stderr.startswith("ilcrig: error: ") and bad.stderr.count("\n") == 1


THREAD_FAILS = """
import sys, threading
from host.cli import command
from host.learning import registry

real = registry.law_descriptions

def with_a_failing_thread():
    def fail():
        raise RuntimeError("a helper thread's bug\\nsecond line")
    t = threading.Thread(target=fail, name="helper")
    t.start()
    t.join()
    return real()

registry.law_descriptions = with_a_failing_thread
sys.argv = ["ilcrig", *sys.argv[1:]]
sys.exit(command())
"""


@pytest.mark.parametrize("debug", [False, True])
def test_a_thread_that_fails_is_one_line_on_a_users_terminal_never_a_traceback(debug: bool) -> None:
    """A thread of a user's command that ends with an exception is said like the main thread's bug
    (``ilcrig: internal error in thread …``, one line; the traceback only with ``--debug``); the
    command itself goes on (``laws`` lists the laws, exit 0)."""
    argv = [sys.executable, "-c", THREAD_FAILS, *(["--debug"] if debug else []), "laws"]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0 and "pd-ilc" in proc.stdout
    line = "ilcrig: internal error in thread helper: RuntimeError: a helper thread's bug (run with --debug for details)"
    if debug:
        assert "Traceback" in proc.stderr and "a helper thread's bug" in proc.stderr
    else:
        assert proc.stderr.strip() == line


def test_a_role_logs_a_failing_thread_with_its_traceback(monkeypatch: pytest.MonkeyPatch, caplog, capsys) -> None:
    import threading

    from host.cli import report_thread_errors

    monkeypatch.setattr(threading, "excepthook", threading.excepthook)  # restored after the test
    report_thread_errors(debug=False, role=True)

    def fail() -> None:
        raise RuntimeError("a role thread's bug")

    with caplog.at_level("ERROR", logger="host.cli"):
        t = threading.Thread(target=fail, name="role helper")
        t.start()
        t.join()
    (record,) = [r for r in caplog.records if r.name == "host.cli"]
    assert record.getMessage() == "thread role helper failed" and record.exc_info is not None
    assert "internal error" not in capsys.readouterr().err  # the role's log has it, with its traceback
