"""Processor in the loop (``--firmware pil``): the C firmware on an emulated Cortex-M4.

* the protocol's numbers in firmware_model/pil_link.py are those of pil_protocol.h, and its integer
  coding round-trips (fast tier, no tools needed);
* without the cross compiler or QEMU, ``--firmware pil`` is one line naming the apt packages, exit 2,
  before anything starts (fast tier);
* marked ``pil`` (full tier; skipped where the tools are missing unless ``ILCRIG_REQUIRE_PIL=1``,
  as CI's PIL step sets, then they fail): the PIL kernel is the numba kernel bit for bit on random
  inputs and parameter writes; a QEMU that dies or stops answering is a PilError, not a hang;
  ``ilcrig run --firmware pil --iterations 2`` prints the digest of the Python firmware.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from firmware_model import control_law as cl
from firmware_model import pil_link
from firmware_model.pil_build import APT_PACKAGES, SOURCES, missing_tools
from tests.cli_util import ROOT, run_cli_process

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
    done = subprocess.run(
        [sys.executable, "-m", "host.cli", "run", "--firmware", "pil", "--iterations", "1", "--out", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert "--firmware" in done.stderr and f"apt-get install {' '.join(APT_PACKAGES)}" in done.stderr
    assert not out.exists()


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
        os.kill(silent.target.pid, signal.SIGSTOP)  # type: ignore[attr-defined]
        t0 = time.monotonic()
        with pytest.raises(PilError, match=r"node 2 PIL target: no reply within"):
            silent(1, 1, 1, st, tables, rec)  # type: ignore[operator]
        assert time.monotonic() - t0 < 10.0
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
