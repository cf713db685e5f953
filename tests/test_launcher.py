"""Tests of the launcher of `ilcrig run` (host/rig/launcher.py, role_commands.py, processes.py,
supervisor.py, run_outcome.py): it starts every role and leaves no process behind.

Fake roles (tests/fake_role.py) stand in for the host and the plant (and for a failing drive);
the other drives are real `ilcrig drive` processes on a private hub. "No process left" is checked
without psutil: /proc/<pid>/stat missing, or the process is a zombie (state Z/X; in a container
PID 1 may not reap orphans, and a zombie holds no resources or sockets).
"""

from __future__ import annotations

import io
import logging
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_util import pid_alive, wait_gone

from bus.exit_codes import EXIT_CHILD_FAILED, EXIT_FAULT
from bus.units import timeout_scale
from host.cli import build_parser
from host.cli.options import experiment_options
from host.cli.run import run_options
from host.rig import role_commands
from host.rig.launcher import RigLauncher
from host.rig.options import RunOptions
from host.rig.role_commands import child_argv, host_role_args, role_command
from host.rig.supervisor import UNHEARD_GRACE_S

pytestmark = pytest.mark.multiprocess

FAKE = str(Path(__file__).with_name("fake_role.py"))
ROOT = str(Path(__file__).resolve().parents[1])


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------


def fake(role: str, *opts: str) -> list[str]:
    return [sys.executable, FAKE, role, *opts]


def fake_env(role_key: str, *opts: str) -> str:
    return " ".join([sys.executable, FAKE, role_key.rstrip("0123456789"), *opts])


def run_args(out: Path, *extra: str) -> RunOptions:
    return run_options(build_parser().parse_args(["run", "--iterations", "2", "--out", str(out), "--bus", "hub", *extra]))


def fake_pids(piddir: Path) -> dict[str, int]:
    """name → pid of every fake role that started (from their pid files)."""
    found = {}
    for f in piddir.iterdir():
        name, _, pid = f.name.rpartition(".")
        if name and not name.startswith(".") and pid.isdigit():
            found[name] = int(pid)
    return found


def fake_argv(piddir: Path, name: str) -> list[str]:
    f = next(f for f in piddir.iterdir() if f.name.startswith(name + "."))
    return f.read_text().split()


def kill_leftovers(pids: list[int]) -> None:
    for pid in pids:
        if pid_alive(pid):
            try:
                os.killpg(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass


@pytest.fixture
def piddir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """FAKE_ROLE_DIR for the fake roles; kills whatever a failing test left behind."""
    d = tmp_path / "pids"
    d.mkdir()
    monkeypatch.setenv("FAKE_ROLE_DIR", str(d))
    for key in [k for k in os.environ if k.startswith(role_commands.ROLE_ENV_PREFIX)]:
        monkeypatch.delenv(key)
    yield d
    kill_leftovers(list(fake_pids(d).values()))


@pytest.fixture
def roles(monkeypatch: pytest.MonkeyPatch) -> dict[str, list[str]]:
    """The launcher's ROLE_COMMAND hook, emptied after the test."""
    table: dict[str, list[str]] = {}
    monkeypatch.setattr(role_commands, "ROLE_COMMAND", table)
    return table


def run_launcher(rl: RigLauncher) -> int:
    try:
        return rl.run()
    finally:  # belt and braces: the launcher must have done this already
        kill_leftovers([c.pid for c in rl.children])
        if rl.hub is not None:
            rl.hub.stop()


def assert_all_gone(rl: RigLauncher, hub_pid: int | None = None) -> None:
    for c in rl.children:
        assert c.proc.returncode is not None, f"{c.name} not reaped"
    pids = [c.pid for c in rl.children] + ([hub_pid] if hub_pid else [])
    assert wait_gone(pids, 0.5) == []
    for c in rl.children:
        with pytest.raises(ProcessLookupError):
            os.kill(c.pid, 0)
    assert rl.hub is None


class Spy(threading.Thread):
    """Watches a running launcher from a thread: records its hub pid, runs ``action`` once
    the child ``name`` is running (its fake role wrote ``<name>.<pid>`` into ``piddir``)."""

    def __init__(self, rl: RigLauncher, name: str, piddir: Path, action) -> None:
        super().__init__(daemon=True)
        self.rl, self.name, self.piddir, self.action = rl, name, piddir, action
        self.hub_pid: int | None = None
        self.result: object = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                if self.rl.hub is not None:
                    self.hub_pid = self.rl.hub.pid
                child = next((c for c in self.rl.children if c.name == self.name), None)
                if child is not None and (self.piddir / f"{self.name}.{child.pid}").exists():
                    self.result = self.action(self.rl, child)
                    return
                time.sleep(0.01)
        except BaseException as err:  # noqa: BLE001 - reported by the test
            self.error = err


# ---------------------------------------------------------------------------------------
# command lines
# ---------------------------------------------------------------------------------------


def test_host_args_round_trip_through_the_host_parser(tmp_path: Path) -> None:
    args = build_parser().parse_args(
        [
            "run",
            "--law",
            "d-ilc",
            "--iterations",
            "3",
            "--path",
            "2",
            "--cycle",
            "0.30000000000000004",
            "--profile",
            "quintic",
            "--disturbance",
            "repetitive",
            "--seed",
            "7",
            "--ff0",
            "zero",
            "--gains",
            "paper",
            "--alpha",
            "1.1",
            "--ld",
            "230",
            "--lead",
            "2",
            "--config",
            "x.toml",
            "--out",
            str(tmp_path),
            "--bus",
            "hub",
        ]
    )
    argv = host_role_args(experiment_options(args))
    assert "--out" not in argv and "--bus" not in argv and "--hub" not in argv
    assert argv[argv.index("--cycle") + 1] == "0.30000000000000004"
    host = build_parser().parse_args(["host", *argv, "--out", str(tmp_path), "--bus", "hub"])
    assert experiment_options(host) == experiment_options(args)
    assert experiment_options(args).gains == {"alpha": 1.1, "ld": 230.0, "lead": 2}
    assert (host.out, host.bus) == (args.out, args.bus)
    # options not given stay absent (the host's defaults apply)
    assert host_role_args(experiment_options(build_parser().parse_args(["run"]))) == []


def test_role_command_hooks(monkeypatch: pytest.MonkeyPatch, roles: dict[str, list[str]]) -> None:
    for key in [k for k in os.environ if k.startswith(role_commands.ROLE_ENV_PREFIX)]:
        monkeypatch.delenv(key)
    # safe-path mode: the folder `ilcrig run` was started in is not on a role's import path
    assert role_command("drive", 3) == [sys.executable, "-P", "-m", "host.cli", "drive"]
    assert role_command("host", debug=True) == [sys.executable, "-P", "-m", "host.cli", "--debug", "host"]
    roles["drive"] = ["x", "drive"]
    assert role_command("drive", 3) == ["x", "drive"]
    monkeypatch.setenv("ILCRIG_ROLE_CMD_DRIVE3", "/bin/echo 'a b'")
    assert role_command("drive", 3) == ["/bin/echo", "a b"]
    assert role_command("drive", 2) == ["x", "drive"]
    assert child_argv("drive", ["--bus", "hub"], node=2) == ["x", "drive", "--node", "2", "--bus", "hub"]


def test_virtual_transport_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="virtual"):
        RigLauncher(run_options(build_parser().parse_args(["run", "--out", str(tmp_path), "--bus", "virtual"]))).run()


# ---------------------------------------------------------------------------------------
# exit paths, in process (real drives on a private hub, fake host and plant)
# ---------------------------------------------------------------------------------------


def test_success_returns_host_code_and_reaps_everything(tmp_path: Path, piddir: Path, roles: dict[str, list[str]]) -> None:
    roles["host"] = fake("host", "--wait-drives", "4", "--sleep", "0.3", "--exit", "3")
    roles["plant"] = fake("plant")
    out, err = io.StringIO(), io.StringIO()
    rl = RigLauncher(run_args(tmp_path / "run"), stdout=out, stderr=err)
    code = run_launcher(rl)
    assert code == 3, err.getvalue()
    # a host that ends with a fault but wrote no summary: one line naming its log and the summary the
    # launcher wrote in its place (a summary always)
    run = tmp_path / "run"
    assert err.getvalue().splitlines() == [
        "ilcrig: fault: the host ended the run with exit code 3 [trial_fault]: host, before the first trial (trial 0 not "
        f"started); detected by host; torque removed, 0 completed trials kept; its log: {run / 'logs' / 'host.log'}; "
        f"summary: {run / 'summary.json'}"
    ]
    # four real drives met on both buses of the hub and talk (boot-up, heartbeats); the plant is fake;
    # the launcher follows the io channel too (the trial and tick of a process's end) and consumes
    # every node's heartbeat on the fieldbus (host/rig/liveness.py)
    fb_clients, io_clients, fb_frames = map(int, (piddir / "hub_stats").read_text().split())
    assert (fb_clients, io_clients) == (5, 5) and fb_frames >= 4
    hub_pid = int(re.search(r"processes: hub (\d+), ", out.getvalue()).group(1))  # type: ignore[union-attr]
    assert_all_gone(rl, hub_pid)
    assert [c.name for c in rl.children] == ["plant", "drive1", "drive2", "drive3", "drive4", "host"]
    # the status line names the transport and every pid started before the host
    line = out.getvalue()
    assert line.startswith(f"ilcrig run: transport hub ({rl.hub_address}); processes: hub {hub_pid}, ")
    for c in rl.children[:-1]:
        assert f"{c.name} {c.pid}" in line
    # the host got the experiment options and the same bus; the hub socket is gone
    host_argv = fake_argv(piddir, "host")
    assert host_argv[host_argv.index("--iterations") + 1] == "2"
    assert host_argv[host_argv.index("--out") + 1] == str(tmp_path / "run")
    assert host_argv[-4:] == ["--bus", "hub", "--hub", rl.hub_address]
    assert not os.path.exists(rl.hub_address.removeprefix("unix:"))
    assert (tmp_path / "run" / "logs" / "drive4.log").exists()


def test_drive_exiting_early_ends_the_run(tmp_path: Path, piddir: Path, roles: dict[str, list[str]]) -> None:
    roles["host"] = fake("host")  # would run forever
    roles["plant"] = fake("plant")
    roles["drive2"] = fake("drive", "--sleep", "0.3", "--exit", "1")
    err = io.StringIO()
    # the (fake) host never notices: after its grace period the launcher stops it and records the fault
    rl = RigLauncher(run_args(tmp_path), stdout=io.StringIO(), stderr=err, host_grace_s=0.5)
    code = run_launcher(rl)
    assert code == EXIT_FAULT
    lines = err.getvalue().splitlines()
    assert len(lines) == 1, lines
    assert re.fullmatch(
        r"ilcrig: fault: drive2 \(pid \d+\) exited with code 1 \[process_died\]: drive2, before the first trial "
        r"\(trial 0 not started\); detected by launcher after \d+ ms; torque removed, 0 completed trials kept; "
        r"its log: .*drive2\.log; summary: .*summary\.json",
        lines[0],
    ), lines[0]
    assert [d.name for d in rl.deaths] == ["drive2"]
    assert_all_gone(rl)


def test_a_node_dead_before_its_heartbeat_is_heard_does_not_wait_out_the_hosts_grace(
    tmp_path: Path, piddir: Path, roles: dict[str, list[str]], caplog: pytest.LogCaptureFixture
) -> None:
    """A drive that dies before the host configured its heartbeat (it never booted) cannot be
    noticed by the host, which awaits its boot-up: the launcher gives the host the short grace of
    an unheard node, not the whole grace period (here 600 s) in silence."""
    roles["host"] = fake("host")  # would run forever
    roles["plant"] = fake("plant")
    roles["drive3"] = fake("drive", "--sleep", "0.2", "--exit", "1")  # the fake roles send no heartbeat
    err = io.StringIO()
    rl = RigLauncher(run_args(tmp_path), stdout=io.StringIO(), stderr=err, host_grace_s=600.0)
    with caplog.at_level(logging.INFO, logger="host.rig.supervisor"):
        code = run_launcher(rl)
    assert code == EXIT_FAULT
    assert err.getvalue().startswith("ilcrig: fault: drive3 (pid ") and len(err.getvalue().splitlines()) == 1
    grace = UNHEARD_GRACE_S * timeout_scale()
    assert any(
        r.getMessage().endswith(f"its heartbeat was not heard yet; the host gets {grace:.1f} s to notice")
        and r.getMessage().startswith("drive3 (pid ")
        for r in caplog.records
    ), [r.getMessage() for r in caplog.records]
    assert any(f"the host did not end within {grace:.1f} s of drive3" in r.getMessage() for r in caplog.records)
    assert_all_gone(rl)


def test_child_killed_during_the_run(tmp_path: Path, piddir: Path, roles: dict[str, list[str]]) -> None:
    roles["host"] = fake("host")
    roles["plant"] = fake("plant")
    err = io.StringIO()
    rl = RigLauncher(run_args(tmp_path), stdout=io.StringIO(), stderr=err, host_grace_s=0.5)
    spy = Spy(rl, "host", piddir, lambda rl, _: os.kill(next(c.pid for c in rl.children if c.name == "drive3"), signal.SIGKILL))
    spy.start()
    code = run_launcher(rl)
    spy.join(5)
    assert spy.error is None
    assert code == EXIT_FAULT
    drive3 = next(c for c in rl.children if c.name == "drive3")
    assert err.getvalue().startswith(f"ilcrig: fault: drive3 (pid {drive3.pid}) was killed by SIGKILL [process_died]")
    assert len(err.getvalue().splitlines()) == 1
    assert_all_gone(rl, spy.hub_pid)


def test_crash_is_one_line_naming_the_log(tmp_path: Path, piddir: Path, roles: dict[str, list[str]]) -> None:
    roles["host"] = fake("host")
    roles["plant"] = fake("plant", "--sleep", "0.2", "--crash")
    roles["drive"] = fake("drive")
    err = io.StringIO()
    rl = RigLauncher(run_args(tmp_path), stdout=io.StringIO(), stderr=err, host_grace_s=0.5)
    assert run_launcher(rl) == EXIT_FAULT
    lines = err.getvalue().splitlines()
    assert len(lines) == 1 and "Traceback" not in err.getvalue()  # no traceback on the terminal
    assert lines[0].startswith("ilcrig: fault: plant (pid ") and "exited with code 1" in lines[0]
    assert lines[0].endswith(f"its log: {tmp_path / 'logs' / 'plant.log'}; summary: {tmp_path / 'summary.json'}")
    log = (tmp_path / "logs" / "plant.log").read_text()
    assert "Traceback" in log and "RuntimeError: fake plant crashed on purpose" in log  # it is in the log
    assert_all_gone(rl)


def test_child_ignoring_sigterm_is_killed(tmp_path: Path, piddir: Path, roles: dict[str, list[str]]) -> None:
    roles["host"] = fake("host", "--sleep", "0.5", "--exit", "0")
    roles["plant"] = fake("plant", "--ignore-term")
    roles["drive"] = fake("drive")
    rl = RigLauncher(run_args(tmp_path), stdout=io.StringIO(), stderr=io.StringIO(), grace_s=0.5)
    assert run_launcher(rl) == 0
    plant = rl.children[0]
    assert plant.name == "plant" and plant.proc.returncode == -signal.SIGKILL
    assert [c.proc.returncode for c in rl.children[1:5]] == [-signal.SIGTERM] * 4
    assert_all_gone(rl)


def test_host_that_cannot_start(tmp_path: Path, piddir: Path, roles: dict[str, list[str]]) -> None:
    roles["host"] = [str(tmp_path / "no-such-program")]
    roles["plant"] = fake("plant")
    roles["drive"] = fake("drive")
    err = io.StringIO()
    rl = RigLauncher(run_args(tmp_path), stdout=io.StringIO(), stderr=err)
    assert run_launcher(rl) == EXIT_CHILD_FAILED
    assert err.getvalue().startswith("ilcrig: error: cannot start host (")
    assert len(rl.children) == 5
    assert_all_gone(rl)


# ---------------------------------------------------------------------------------------
# the launcher as a process: SIGINT and SIGKILL
# ---------------------------------------------------------------------------------------


def start_cli_run(tmp_path: Path, piddir: Path) -> tuple[subprocess.Popen[bytes], str, dict[str, int]]:
    """`python -m host.cli run` with fake roles; returns (proc, status line, pids incl. host)."""
    env = dict(os.environ)
    env.update(
        {
            "ILCRIG_ROLE_CMD_HOST": fake_env("host"),
            "ILCRIG_ROLE_CMD_PLANT": fake_env("plant"),
            "ILCRIG_ROLE_CMD_DRIVE": fake_env("drive"),
            "PYTHONPATH": ROOT + os.pathsep + env.get("PYTHONPATH", ""),
        }
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "host.cli", "run", "--iterations", "2", "--out", str(tmp_path / "run"), "--bus", "hub"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        env=env,
        cwd=ROOT,
        start_new_session=True,
    )  # its own process group, like a shell's foreground job
    assert proc.stdout is not None
    buf, deadline = b"", time.monotonic() + 20
    while b"starting host\n" not in buf:
        assert time.monotonic() < deadline, f"no status line: {buf!r}"
        if select.select([proc.stdout], [], [], 0.1)[0]:
            chunk = os.read(proc.stdout.fileno(), 4096)
            assert chunk, f"launcher ended: {buf!r} {proc.stderr.read() if proc.stderr else ''}"
            buf += chunk
    line = next(ln for ln in buf.decode().splitlines() if ln.startswith("ilcrig run:"))
    while "host" not in fake_pids(piddir):
        assert time.monotonic() < deadline, "fake host did not start"
        time.sleep(0.02)
    pids = {name: int(pid) for name, pid in re.findall(r"(hub|plant|drive\d) (\d+)", line)}
    pids["host"] = fake_pids(piddir)["host"]
    assert sorted(pids) == ["drive1", "drive2", "drive3", "drive4", "host", "hub", "plant"]
    return proc, line, pids


def test_sigint_to_the_launcher(tmp_path: Path, piddir: Path) -> None:
    proc = None
    pids: dict[str, int] = {}
    try:
        proc, line, pids = start_cli_run(tmp_path, piddir)
        sock = re.search(r"\(unix:(\S+)\)", line).group(1)  # type: ignore[union-attr]
        assert os.path.exists(sock)
        # the hub, like every child, is a session of its own (bus.processes): a terminal's Ctrl-C
        # (the launcher's process group) does not close the bus under the roles
        assert os.getsid(pids["hub"]) == pids["hub"] != os.getpgid(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
        _, stderr = proc.communicate(timeout=10)
        assert proc.returncode == 130, stderr
        assert b"ilcrig: interrupted (SIGINT); stopping 7 processes" in stderr
        assert wait_gone(list(pids.values()), 0.5) == []
        assert not os.path.exists(sock) and not os.path.exists(os.path.dirname(sock))
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        kill_leftovers(list(pids.values()))


def test_sigkill_to_the_launcher_takes_the_children_down(tmp_path: Path, piddir: Path) -> None:
    proc = None
    pids: dict[str, int] = {}
    sockdir = None
    try:
        proc, line, pids = start_cli_run(tmp_path, piddir)
        sock = re.search(r"\(unix:(\S+)\)", line).group(1)  # type: ignore[union-attr]
        sockdir = os.path.dirname(sock)
        proc.kill()
        proc.wait()
        left = wait_gone(list(pids.values()), 10.0)
        assert left == [], {n: p for n, p in pids.items() if p in left}
        # the hub removes its socket and its private temp folder when its stdin closes: nothing left
        deadline = time.monotonic() + 10.0
        while os.path.exists(sockdir) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not os.path.exists(sock) and not os.path.exists(sockdir)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        kill_leftovers(list(pids.values()))
        if sockdir:
            shutil.rmtree(sockdir, ignore_errors=True)  # only if the test failed
