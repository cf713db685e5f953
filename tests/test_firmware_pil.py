"""Processor in the loop (``--firmware pil``): the C firmware on an emulated Cortex-M4.

* the protocol's numbers in firmware_model/pil_link.py are those of pil_protocol.h, and its integer
  coding round-trips (fast tier, no tools needed);
* without the cross compiler or QEMU, ``--firmware pil`` is one line naming the apt packages, exit 2,
  before anything starts (fast tier);
* marked ``pil`` (full tier; skipped where the tools are missing unless ``ILCRIG_REQUIRE_PIL=1``,
  as CI's PIL step sets, then they fail): the PIL kernel is the numba kernel bit for bit on random
  inputs and parameter writes; a QEMU that dies or stops answering is a PilError, not a hang;
  ``ilcrig run --firmware pil --iterations 2`` prints the digest of the Python firmware;
* a PIL target that fails is a drive fault, not the end of the drive process: torque off, CiA 402
  Fault, EMCY 0x6100 with cause 9, what happened and the trial tick, the run ends with exit 3 and a
  true summary -- in the fast tier with a stand-in kernel that raises the link's error, in the
  ``pil`` tier with a QEMU killed, or SIGSTOPed, mid-trial (in ``ilcrig sim`` and in the rig).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from firmware_model import control_law as cl
from firmware_model import pil_link
from firmware_model.pil_build import APT_PACKAGES, SOURCES, missing_tools
from tests.cli_util import ROOT, run_cli, run_cli_process

REQUIRE_ENV = "ILCRIG_REQUIRE_PIL"
PROTOCOL_H = Path(pil_link.__file__).resolve().parent / "c" / "pil" / "pil_protocol.h"


def _require() -> None:
    missing = missing_tools()
    if not missing:
        return
    message = f"processor in the loop needs {', '.join(missing)} (apt-get install {' '.join(APT_PACKAGES)})"
    if os.environ.get(REQUIRE_ENV, "").strip().lower() in ("1", "true", "yes"):
        pytest.fail(f"{REQUIRE_ENV}=1: {message}")
    pytest.skip(message)


@pytest.fixture(scope="module")
def kernel() -> Iterator[object]:
    _require()
    from firmware_model.pil import pil_control_tick

    k = pil_control_tick(1)
    yield k
    k.close()


# ---------------------------------------------------------------- no tools needed


def test_protocol_numbers_are_the_headers() -> None:
    defines = dict(re.findall(r"^#define (PIL_\w+) (\S+)", PROTOCOL_H.read_text(), re.M))
    as_int = {k: int(v.rstrip("u"), 0) if not v.startswith("'") else ord(v[1]) for k, v in defines.items()}
    for name in ("PROTOCOL_VERSION", "SYNC", "MAX_PAYLOAD", "TABLE_COLS", "REC_COLS", "HELLO", "TICK", "ERROR", "FAULT"):
        assert getattr(pil_link, name) == as_int[f"PIL_{name}"], name
    assert pil_link.HELLO_REPLY == as_int["PIL_HELLO_REPLY"] and pil_link.TICK_REPLY == as_int["PIL_TICK_REPLY"]
    assert pil_link.TICK_COLUMN == as_int["PIL_TICK_COLUMN"]
    errors = {v: k for k, v in as_int.items() if k.startswith("PIL_ERR_")}
    assert set(errors) == set(pil_link.ERRORS)
    assert all(path.is_file() for path in SOURCES)


def test_integer_coding_round_trips() -> None:
    values = [0, 1, -1, 63, -64, 64, 2**31 - 1, -(2**31), 2**63 - 1, -(2**63), 123456789, -987654321]
    out = bytearray()
    for v in values:
        pil_link.put_s(out, v)
    pos = 0
    for v in values:
        got, pos = pil_link.get_s(out, pos)
        assert got == v
    assert pos == len(out)
    assert pil_link.wrap64(2**63) == -(2**63) and pil_link.wrap64(-(2**63) - 1) == 2**63 - 1
    f = pil_link.frame(pil_link.TICK, b"\x01\x02")
    assert f[0] == pil_link.SYNC and f[-1] == (pil_link.TICK + 2 + 1 + 2) & 0xFF


def test_missing_tools_are_one_line_before_anything_starts(tmp_path: Path) -> None:
    bare = tmp_path / "bin"
    bare.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PATH"} | {"PATH": str(bare)}
    out = tmp_path / "run"
    done = run_cli_process(["run", "--firmware", "pil", "--iterations", "1", "--out", str(out)], 120, env=env)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert "--firmware" in done.stderr and f"apt-get install {' '.join(APT_PACKAGES)}" in done.stderr
    assert not out.exists()


# ---------------------------------------------------------------- a failed target is a drive fault

SHORT = ["--iterations", "2", "--cycle", "0.15"]
FAIL_TICK = 60  # node 2's target fails at trial 1, tick 60


def _failing_kernels(monkeypatch: pytest.MonkeyPatch, act: Callable[[object], None]) -> None:
    """Node 2's kernel runs ``act(kernel)`` before its period of trial 1, tick FAIL_TICK (the
    second call with that table column); the others are left alone."""
    import firmware_model.drive as drive_mod
    from firmware_model.firmware_select import control_tick_for

    def kernel_for(firmware: str, node_id: int) -> object:
        kernel = control_tick_for(firmware, node_id)
        if node_id != 2:
            return kernel
        seen = [0]

        def tick(*args: object) -> object:
            if args[1] == FAIL_TICK and args[2] == FAIL_TICK:
                seen[0] += 1
                if seen[0] == 2:
                    act(kernel)
            return kernel(*args)  # type: ignore[operator]

        return tick

    monkeypatch.setattr(drive_mod, "control_tick_for", kernel_for)


def _check_drive_fault(code: int, err: str, out: Path) -> dict[str, object]:
    """The run ended in the fault of drive 2 at trial 1, tick FAIL_TICK, with trial 0 kept."""
    assert code == 3, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["end_reason"] == "fault" and len(summary["iterations"]) == 1
    (fault,) = summary["faults"]
    assert (fault["kind"], fault["node"], fault["trial"], fault["tick"]) == ("emcy", "drive2", 1, FAIL_TICK), fault
    assert fault["message"].startswith("node 2: PIL target: ") and fault["message"].endswith("EMCY 0x6100"), fault
    return dict(fault)


@pytest.mark.slow
def test_a_failed_pil_target_is_a_drive_fault_not_the_end_of_the_drive(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No tools needed: node 2's kernel raises the link's error as a dead QEMU makes it."""
    from bus.pil_fault import PilFailure

    def die(kernel: object) -> None:
        raise pil_link.PilError("node 2 PIL target: QEMU closed the serial line (QEMU pid 1, exit status -9)", PilFailure.EXITED)

    _failing_kernels(monkeypatch, die)
    code, _, err = run_cli(capsys, "sim", *SHORT, "--out", str(tmp_path / "run"))
    _check_drive_fault(code, err, tmp_path / "run")


def test_the_drive_reacts_to_a_failed_target_like_to_an_internal_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """The power stage's reaction: Fault, torque off, 0x1001/0x603F/0x1003, the trial in FAULT
    with cause 9, EMCY 0x6100 with cause, what happened and the tick (U24; none outside a trial)."""
    from bus.cia301.nmt import NmtState
    from bus.objects import Cia402State, FaultCause, TrialState
    from bus.pil_fault import PIL_NO_TICK, PilFailure
    from firmware_model.drive import Drive

    drive = Drive(2)
    drive.nmt_state = NmtState.OPERATIONAL
    for cw in (0x06, 0x07, 0x0F):
        drive.power.controlword(cw)
    assert drive.power.on
    drive.trial.state = TrialState.RUNNING
    drive.trial.next_tick = 700
    drive.pop_emcy()

    def dead(*args: object) -> tuple[int, int]:
        raise pil_link.PilError("node 2 PIL target: no reply within 5 s", PilFailure.NO_ANSWER)

    drive.motion.mode.control_tick = dead
    assert drive.io_tick(700, 1234) == 0
    assert drive.power.state == Cia402State.FAULT and not drive.power.on
    assert drive.trial.state == TrialState.FAULT and drive.trial.fault_cause == FaultCause.PIL_TARGET
    assert drive.power.error_code == 0x6100 and drive.power.error_register == 0x81
    ((code, register, mfr),) = drive.pop_emcy()
    assert (code, register) == (0x6100, 0x81)
    assert mfr == bytes((9, 2)) + (700).to_bytes(3, "little")
    assert drive.io_tick(701, 1234) == 0  # torque is off: no period runs any more
    # outside a trial: no tick
    drive.power.target_failed(PilFailure.CORE_FAULT, "node 2 PIL target: HardFault")
    (emcy,) = drive.pop_emcy()
    assert emcy[2] == bytes((9, 3)) + PIL_NO_TICK.to_bytes(3, "little")


def test_the_hosts_record_of_a_pil_target_emcy() -> None:
    from host.rig.fault_classify import EmcyFrame, emcy_fault

    frame = EmcyFrame(node_id=3, code=0x6100, data=bytes((9, 1)) + (60).to_bytes(3, "little"), t_mono=1.0, t_wall=2.0)
    record = emcy_fault(frame)
    assert (record.node, record.tick) == ("drive3", 60)
    assert record.message.startswith("PIL target: the emulator exited") and "EMCY 0x6100" in record.message
    outside = emcy_fault(EmcyFrame(3, 0x6100, bytes((9, 2, 0xFF, 0xFF, 0xFF)), 1.0, 2.0))
    assert outside.tick is None and outside.message.startswith("PIL target: no answer within the reply time")


# ---------------------------------------------------------------- on the emulated Cortex-M4


@pytest.mark.pil
def test_pil_kernel_is_the_numba_kernel_bit_for_bit(kernel: object) -> None:
    rng = np.random.default_rng(20261128)
    cap = 40
    st_py = cl.new_state()
    st_pil = st_py.copy()
    tables = cl.new_tables(cap)
    tables[:] = rng.integers(-(2**31), 2**31, size=tables.shape, dtype=np.int64).astype(np.int32)
    setpoint = cl.new_tables(0)
    rec_py = cl.new_recorder(cap)
    rec_pil = rec_py.copy()
    for n in range(240):
        if n % 30 == 0:  # parameter writes within bus/fixedpoint.py's ranges, both loop structures
            params = {
                cl.P_KP: rng.integers(0, 2**31),
                cl.P_KD: rng.integers(0, 2**31),
                cl.P_ALPHA: rng.integers(1, 2**15 + 1),
                cl.P_RATE: rng.integers(1, 2**32),
                cl.P_TLIM: rng.integers(0, 2**31),
                cl.P_FE_WINDOW: rng.integers(-1, 5000),
                cl.P_LOOP: n // 30 % 2,
                cl.P_KPP: rng.integers(0, 2**31),
                cl.P_KVFF: rng.integers(0, 2**31),
                cl.P_KTFF: rng.integers(0, 2**31),
                cl.P_KVP: rng.integers(0, 2**31),
                cl.P_KVI: rng.integers(0, 2**31),
                cl.P_FE_TICKS: rng.integers(0, 4),
            }
            for slot, value in params.items():
                st_py[slot] = st_pil[slot] = int(value)
            if n % 60 == 0:  # the Python side's own resets of loop state (torque on, trial start)
                st_py[cl.S_HAVE_PREV] = st_pil[cl.S_HAVE_PREV] = 0
                st_py[cl.S_VINT] = st_pil[cl.S_VINT] = 0
            tables[:, rng.integers(0, cap + 1)] = rng.integers(-(2**31), 2**31, size=3, dtype=np.int64)
        count = int(rng.integers(-(2**33), 2**33)) if n % 9 == 0 else int(rng.integers(-(2**20), 2**20))
        if n % 5 == 0:  # a cyclic mode's one-column set-point table
            setpoint[:, 0] = rng.integers(-(2**31), 2**31, size=3, dtype=np.int64)
            tab, idx = setpoint, 0
        else:
            tab, idx = tables, int(rng.integers(0, cap + 1))
        rec_idx = int(rng.integers(-1, cap))
        want = cl.control_tick(count, idx, rec_idx, st_py, tab, rec_py)
        got = kernel(count, idx, rec_idx, st_pil, tab, rec_pil)  # type: ignore[operator]
        assert tuple(int(v) for v in want) == tuple(got), n
        assert np.array_equal(st_py, st_pil), n
        assert np.array_equal(rec_py, rec_pil), n
    stats = kernel.stats  # type: ignore[attr-defined]
    assert set(stats) == {"pd", "cascade"} and all(0 < s.mean <= s.largest < 2000 for s in stats.values())


@pytest.mark.pil
def test_a_dead_or_silent_qemu_is_a_pil_error_not_a_hang(monkeypatch: pytest.MonkeyPatch) -> None:
    _require()
    from firmware_model.pil import PilError, pil_control_tick

    st, tables, rec = cl.new_state(), cl.new_tables(4), cl.new_recorder(4)
    silent = pil_control_tick(2)
    try:
        silent(0, 0, 0, st, tables, rec)  # type: ignore[operator]
        monkeypatch.setattr(pil_link, "REPLY_TIMEOUT_S", 0.5)
        waits: list[float] = []  # the drive process keeps its heartbeat going from this hook
        monkeypatch.setattr(pil_link, "on_wait", lambda: waits.append(time.monotonic()))
        os.kill(silent.target.pid, signal.SIGSTOP)  # type: ignore[attr-defined]
        t0 = time.monotonic()
        with pytest.raises(PilError, match=r"node 2 PIL target: no reply within"):
            silent(1, 1, 1, st, tables, rec)  # type: ignore[operator]
        assert time.monotonic() - t0 < 10.0
        assert waits, "the wait for the silent target never let the process serve its heartbeat"
    finally:
        silent.close()  # type: ignore[attr-defined]
    dead = pil_control_tick(3)
    try:
        os.kill(dead.target.pid, signal.SIGKILL)  # type: ignore[attr-defined]
        with pytest.raises(PilError, match=r"node 3 PIL target: .*(closed the serial line|could not send).*exit status"):
            dead(0, 0, 0, st, tables, rec)  # type: ignore[operator]
    finally:
        dead.close()  # type: ignore[attr-defined]


def _digest(run_dir: Path) -> str:
    return str(json.loads((run_dir / "summary.json").read_text())["trace_sha256"])


@pytest.mark.pil
@pytest.mark.slow
@pytest.mark.multiprocess
def test_rig_with_pil_firmware_prints_the_python_digest(tmp_path: Path) -> None:
    """The acceptance run of CI's PIL step: ``ilcrig run --firmware pil --iterations 2`` against
    ``ilcrig sim --iterations 2`` with the Python firmware (sim and run are bit-exact)."""
    _require()
    ref = run_cli_process(["sim", "--iterations", "2", "--out", str(tmp_path / "py")], guard_s=300)
    assert ref.returncode == 0, ref.stderr
    pil = run_cli_process(["run", "--firmware", "pil", "--iterations", "2", "--out", str(tmp_path / "pil")], guard_s=900)
    assert pil.returncode == 0, pil.stderr[-3000:]
    digest = _digest(tmp_path / "py")
    assert _digest(tmp_path / "pil") == digest
    assert f"trace_sha256 {digest[:16]}" in pil.stdout


# ---------------------------------------------------------------- a target that fails mid-trial


def _stop_and_wait(pid: int) -> None:
    """SIGSTOP ``pid`` and return once the kernel says it is stopped (state T)."""
    os.kill(pid, signal.SIGSTOP)
    deadline = time.monotonic() + 30.0
    while Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("T", "t"):
        assert time.monotonic() < deadline, "QEMU did not stop"
        time.sleep(0.005)


@pytest.mark.pil
@pytest.mark.slow
@pytest.mark.parametrize("how", ["killed", "stopped"])
def test_a_qemu_killed_or_stopped_mid_trial_is_a_drive_fault(
    how: str,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``ilcrig sim --firmware pil``: node 2's QEMU is killed (the event: it has exited) or stopped
    (the event: its state is T) just before its period of trial 1, tick FAIL_TICK; the drive
    faults (a stopped one after the bounded reply time), the run ends with exit 3."""
    _require()
    from firmware_model import pil

    targets: list[pil_link.PilTarget] = []

    def fail(kernel: object) -> None:
        target = kernel.target  # type: ignore[attr-defined]
        targets.append(target)
        if how == "killed":
            os.kill(target.pid, signal.SIGKILL)
            target._proc.wait(30.0)
        else:
            _stop_and_wait(target.pid)

    _failing_kernels(monkeypatch, fail)
    t0 = time.monotonic()
    try:
        code, _, err = run_cli(capsys, "sim", "--firmware", "pil", *SHORT, "--out", str(tmp_path / "run"))
    finally:
        pil._close_all()
    fault = _check_drive_fault(code, err, tmp_path / "run")
    assert targets and targets[0]._proc.poll() is not None  # the failed target is gone, never left stopped
    assert time.monotonic() - t0 < 300.0
    said = (
        r"node 2 PIL target: (QEMU closed the serial line|could not send)"
        if how == "killed"
        else r"node 2 PIL target: no reply within [0-9.]+ s"
    )
    assert re.search(said + r".*exit status -9.*\(tick " + str(FAIL_TICK) + r"\): torque off", caplog.text), caplog.text
    assert "EMCY 0x6100" in str(fault["message"])


def _ancestors(pid: int) -> Iterator[int]:
    while pid > 1:
        try:
            pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            return
        yield pid


def _qemu_of_drive(root: int, node: int) -> int | None:
    """The pid of drive ``node``'s QEMU among the descendants of ``root`` (None: not yet)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            if not argv[0].endswith(b"qemu-system-arm"):
                continue
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            drive = Path(f"/proc/{parent}/cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
        if b"--node" in drive and drive[drive.index(b"--node") + 1] == str(node).encode() and root in _ancestors(parent):
            return int(entry.name)
    return None


def _rchar(pid: int) -> int:
    """Bytes ``pid`` has read so far (/proc/PID/io): QEMU reads the drive's requests."""
    for line in Path(f"/proc/{pid}/io").read_text().splitlines():
        if line.startswith("rchar:"):
            return int(line.split()[1])
    raise AssertionError("no rchar")


@pytest.mark.pil
@pytest.mark.slow
@pytest.mark.multiprocess
@pytest.mark.parametrize("how", ["killed", "stopped"])
def test_rig_a_qemu_killed_or_stopped_mid_trial_is_a_drive_fault(how: str, tmp_path: Path) -> None:
    """``ilcrig run --firmware pil --iterations 2``: once trial 0's row is printed and drive 2's
    QEMU has read some 40 more periods' requests (trial 1 runs), it is killed or stopped; the
    host's fault record names drive 2, trial 1, a tick and ``PIL target: <what happened>`` (a
    stopped one: after the bounded reply time, before the drive's heartbeat is missed); exit 3."""
    _require()
    import queue
    import threading

    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "host.cli", "run", "--firmware", "pil", "--iterations", "2", "--out", str(out)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stdout is not None
    stdout = proc.stdout
    threading.Thread(target=lambda: [lines.put(line) for line in stdout], daemon=True).start()
    deadline = time.monotonic() + 900.0
    try:
        while not re.match(r"^\s+0\s+\d", lines.get(timeout=max(deadline - time.monotonic(), 0.1))):
            pass  # the event: trial 0's row (trial 1 comes next)
        qemu = _qemu_of_drive(proc.pid, 2)
        assert qemu is not None, "drive 2 has no QEMU"
        start = _rchar(qemu)
        while _rchar(qemu) < start + 600:  # the event: trial 1's periods reach the target
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.002)
        os.kill(qemu, signal.SIGKILL if how == "killed" else signal.SIGSTOP)
        code = proc.wait(max(deadline - time.monotonic(), 1.0))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    err = proc.stderr.read() if proc.stderr else ""
    assert code == 3, err[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["end_reason"] == "fault" and len(summary["iterations"]) == 1
    fault = summary["faults"][0]
    assert (fault["node"], fault["trial"]) == ("drive2", 1), fault
    assert fault["tick"] is not None and 0 < fault["tick"] < 501, fault
    what = "the emulator exited" if how == "killed" else "no answer within the reply time"
    assert fault["message"].startswith(f"PIL target: {what}"), fault
    said = r"(QEMU closed the serial line|could not send)" if how == "killed" else r"no reply within"
    assert re.search(r"PIL target: " + said, (out / "logs" / "drive2.log").read_text())
