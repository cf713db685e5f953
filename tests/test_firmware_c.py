"""The drive firmware in C (firmware_model/c/, the extension ``firmware_model._fwcore``) is bit-exact
with the Python reference model (the numba kernel :func:`firmware_model.control_law.control_tick`).

* the property test (the recipe of docs/firmware.md for one's own control law in C): random
  parameters within their EDS ranges (both loop structures, gains, torque limits, following-error
  window and time-out, control periods), random encoder counts including the int32 and int64
  extremes, random tables, table columns and recorder columns, parameter writes and trial starts
  between the ticks -- the two kernels give the same torque, status, state vector and recorder, bit
  for bit, over sequences of ticks;
* the C constants (indices, Q shifts) are the Python ones, the rounding helper is Python's, and so
  are the other integer steps of the period in C (CSP velocity reference, profile velocity in
  counts/s, torque actual 0x6077);
* the extension checks its arguments (no out-of-bounds write from Python);
* ``--firmware``: the choice, its one-line errors, and the reference digests of ``ilcrig sim`` with
  the C firmware (in-process, fast).  The rig and robot digests are in tests/test_firmware_c_rig.py
  (full tier).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_util import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_cli import REFERENCE_DIGESTS

from bus import fixedpoint as fp
from firmware_model import control_law as cl
from firmware_model.firmware_select import FIRMWARES, c_available, check_firmware, control_tick_for

pytestmark = pytest.mark.skipif(not c_available(), reason="the C firmware (firmware_model._fwcore) is not built")

if c_available():
    from firmware_model import _fwcore
else:  # pragma: no cover - skipped above
    _fwcore = None

I32 = (fp.INT32_MIN, fp.INT32_MAX)
I64 = (fp.INT64_MIN, fp.INT64_MAX)
U32_MAX = fp.UINT32_MAX

# ---------------------------------------------------------------- strategies


def _with_edges(lo: int, hi: int, *edges: int) -> st.SearchStrategy[int]:
    """Integers in [lo, hi], the range's ends and ``edges`` drawn often."""
    return st.one_of(st.sampled_from(sorted({lo, hi, *(e for e in edges if lo <= e <= hi)})), st.integers(lo, hi))


_gain = _with_edges(0, fp.INT32_MAX, 1, 1 << 16)  # 0x2110:1/2, 0x60FB:1, 0x60F9:1 (int32 >= 0, Q16)
_ff_gain = _with_edges(0, 131072, 65536)  # 0x60FB:2/3 (Q16, 0 .. 2.0)
_period_us = _with_edges(1, 100_000, 100, 1000)  # 0x2300 (EDS: 100 .. 100000; 1 µs: the largest rate)
_tlim = st.builds(fp.torque_limit_units, _with_edges(0, 3000, 1000), _with_edges(0, U32_MAX, 88200))  # 0x6072 · 0x6076
_fe_window = st.one_of(st.just(-1), _with_edges(0, U32_MAX - 1, 0, 1))  # 0x6065 (0xFFFFFFFF: off = -1)
_count = st.one_of(
    st.sampled_from([0, 1, -1, *I32, I32[0] - 1, I32[1] + 1, *I64, I64[0] + 1, I64[1] - 1]),
    st.integers(-(1 << 20), 1 << 20),
    st.integers(*I32),
    st.integers(*I64),
)


@st.composite
def _params(draw: st.DrawFn) -> dict[int, int]:
    """A parameter set as the drive's object callbacks write it (od_hooks)."""
    period = draw(_period_us)
    return {
        cl.P_LOOP: draw(st.sampled_from([cl.LOOP_PD, cl.LOOP_CASCADE])),
        cl.P_KP: draw(_gain),
        cl.P_KD: draw(_gain),
        cl.P_ALPHA: draw(_with_edges(1, fp.VEL_FILTER_ONE)),
        cl.P_RATE: fp.rate_q12_from_period_us(period),
        cl.P_TLIM: draw(_tlim),
        cl.P_FE_WINDOW: draw(_fe_window),
        cl.P_FE_TICKS: draw(_with_edges(0, 65535)) * 1000 // period,
        cl.P_KPP: draw(_gain),
        cl.P_KVFF: draw(_ff_gain),
        cl.P_KTFF: draw(_ff_gain),
        cl.P_KVP: draw(_gain),
        cl.P_KVI: fp.ki_per_tick_q16(draw(_gain), period),
    }


@st.composite
def _scenario(draw: st.DrawFn) -> dict[str, Any]:
    cols = draw(st.integers(1, 6))
    rec_cols = draw(st.integers(1, 6))
    tables = np.array(draw(st.lists(st.integers(*I32), min_size=3 * cols, max_size=3 * cols)), dtype=np.int32).reshape(3, cols)
    rec = np.array(draw(st.lists(st.integers(*I32), min_size=4 * rec_cols, max_size=4 * rec_cols)), dtype=np.int32)
    steps: list[tuple[Any, ...]] = []
    for _ in range(draw(st.integers(1, 25))):
        kind = draw(st.sampled_from(["tick", "tick", "tick", "tick", "params", "start"]))
        if kind == "tick":
            steps.append(("tick", draw(_count), draw(st.integers(0, cols - 1)), draw(st.integers(-1, rec_cols - 1))))
        elif kind == "params":
            steps.append(("params", draw(_params())))
        else:  # a trial starts (OperationMode.start_trial): the estimator starts afresh at an initial velocity
            steps.append(("start", draw(st.integers(*I32))))
    return {"params": draw(_params()), "tables": tables, "rec": rec.reshape(4, rec_cols), "steps": steps}


def _play(kernel: Any, sc: dict[str, Any]) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray]:
    state = cl.new_state()
    for k, v in sc["params"].items():
        state[k] = v
    tables, rec = sc["tables"].copy(), sc["rec"].copy()
    out: list[tuple[int, int]] = []
    for step in sc["steps"]:
        if step[0] == "tick":
            tau, status = kernel(step[1], step[2], step[3], state, tables, rec)
            out.append((int(tau), int(status)))
        elif step[0] == "params":
            for k, v in step[1].items():
                state[k] = v
        else:
            state[cl.S_HAVE_PREV] = 0
            state[cl.S_VF] = step[1] << fp.VEL_STATE_Q
            state[cl.S_VINT] = 0
    return out, state, rec


# ---------------------------------------------------------------- bit for bit


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(_scenario())
def test_c_kernel_is_the_python_kernel_bit_for_bit(sc: dict[str, Any]) -> None:
    py_out, py_st, py_rec = _play(cl.control_tick, sc)
    c_out, c_st, c_rec = _play(_fwcore.control_tick, sc)
    assert c_out == py_out
    assert c_st.tolist() == py_st.tolist()
    assert c_rec.tolist() == py_rec.tolist()


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.integers(*I64), st.sampled_from([*I64, -1, 0, 1, -(1 << 15), (1 << 15) - 1])), st.integers(0, 62))
def test_rounding_shift_is_pythons(x: int, q: int) -> None:
    assert _fwcore.rshift_round(x, q) == fp.rshift_round(x, q)


@settings(max_examples=300, deadline=None)
@given(st.integers(*I32), st.integers(*I32), _period_us)
def test_csp_velocity_reference_is_the_python_one(target: int, prev: int, period_us: int) -> None:
    rate = fp.rate_q12_from_period_us(period_us)
    python = fp.sat32(fp.rshift_round(fp.sat32(target - prev) * rate, fp.VEL_STATE_Q))  # as CspMode computes it
    assert _fwcore.csp_velocity_ref(target, prev, rate) == python


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.integers(-(1 << 46), 1 << 46), st.integers(-(1 << 62) + 1, (1 << 62) - 1)), _period_us)
def test_velocity_from_tick_is_the_python_one(v_q16: int, period_us: int) -> None:
    assert _fwcore.velocity_from_tick_q16(v_q16, period_us) == fp.velocity_from_tick_q16(v_q16, period_us)


@settings(max_examples=300, deadline=None)
@given(st.integers(-(1 << 61) + 1, (1 << 61) - 1), _with_edges(-1, U32_MAX, 0, 1, 88200))
def test_torque_actual_quantisation_is_the_python_one(tau: int, rated_mnm: int) -> None:
    assert _fwcore.torque_units_to_permille(tau, rated_mnm) == fp.torque_units_to_permille(tau, rated_mnm)


def test_constants_are_the_python_ones() -> None:
    names = [n for n in dir(cl) if n[:2] in ("P_", "S_") or n.startswith(("LOOP_", "ROW_", "REC_", "STATUS_"))]
    assert names and all(getattr(_fwcore, n) == getattr(cl, n) for n in names)
    assert _fwcore.N_STATE == cl.N_STATE
    for q in ("ACC_Q", "GAIN_Q", "VEL_FILTER_Q", "VEL_STATE_Q", "RATE_Q"):
        assert getattr(_fwcore, q) == getattr(fp, q), q


def test_the_extension_checks_its_arguments() -> None:
    state, tables, rec = cl.new_state(), cl.new_tables(2), cl.new_recorder(2)
    tick = _fwcore.control_tick
    assert tick(5, 2, 1, state, tables, rec) == cl.control_tick(5, 2, 1, cl.new_state(), cl.new_tables(2), cl.new_recorder(2))
    with pytest.raises(TypeError, match="st"):
        tick(0, 0, 0, state.astype(np.int32), tables, rec)
    with pytest.raises(ValueError, match="st must have shape"):
        tick(0, 0, 0, state[:5].copy(), tables, rec)
    with pytest.raises(TypeError, match="tables"):
        tick(0, 0, 0, state, tables.astype(np.int64), rec)
    with pytest.raises(TypeError, match="tables"):
        tick(0, 0, 0, state, np.asfortranarray(np.zeros((3, 4), dtype=np.int32)), rec)
    with pytest.raises(ValueError, match="rec must have 4 rows"):
        tick(0, 0, 0, state, tables, np.zeros((3, 2), dtype=np.int32))
    readonly = rec.copy()
    readonly.flags.writeable = False
    with pytest.raises(TypeError, match="rec"):
        tick(0, 0, 0, state, tables, readonly)
    with pytest.raises(IndexError):
        tick(0, 3, 0, state, tables, rec)
    with pytest.raises(IndexError):
        tick(0, -1, 0, state, tables, rec)
    with pytest.raises(IndexError):
        tick(0, 0, 2, state, tables, rec)
    with pytest.raises(OverflowError):
        tick(1 << 63, 0, 0, state, tables, rec)
    assert tick(np.int64(7), np.int64(0), -1, state, tables, rec)[1] == 0  # numpy integers as the numba kernel takes them


# ---------------------------------------------------------------- the choice


def test_firmware_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    assert FIRMWARES == ("python", "c", "pil")
    assert control_tick_for("python", 1) is cl.control_tick
    assert control_tick_for("c", 1) is _fwcore.control_tick
    assert check_firmware("c") == "c"
    import firmware_model.pil_build as pil_build

    monkeypatch.setattr(pil_build, "missing_tools", lambda: ["qemu-system-arm"])  # no QEMU here
    with pytest.raises(Exception, match="pil"):
        check_firmware("pil")


def test_the_period_steps_follow_the_firmware(monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``c`` the drive calls the C core's CSP velocity reference, profile velocity and 0x6077;
    with ``python`` their Python models; with ``pil`` the host build of the C (PIL: host-side)."""
    from firmware_model.drive import Drive
    from firmware_model.firmware_select import period_steps_for

    python, c = period_steps_for("python"), period_steps_for("c")
    assert (python.where, c.where, period_steps_for("pil").where) == ("python", "c", "c")
    assert python.csp_velocity_ref is cl.csp_velocity_ref and python.torque_units_to_permille is fp.torque_units_to_permille
    assert c.csp_velocity_ref is _fwcore.csp_velocity_ref and c.velocity_from_tick_q16 is _fwcore.velocity_from_tick_q16
    calls: list[tuple[int, int]] = []
    c_permille = _fwcore.torque_units_to_permille

    def permille(tau: int, rated: int) -> int:
        calls.append((tau, rated))
        return int(c_permille(tau, rated))

    monkeypatch.setattr(_fwcore, "torque_units_to_permille", permille)
    drive = Drive(1, firmware="c")
    assert drive.motion.steps.where == "c" and all(m.steps is drive.motion.steps for m in drive.motion.modes.values())
    drive.read_object(0x6077, 0)
    assert len(calls) == 1  # 0x6077 is the C function's
    assert Drive(1).motion.steps.where == "python"


def test_firmware_option_errors_are_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    code, _, err = run_cli(capsys, "sim", "--firmware", "rust", "--out", str(tmp_path / "a"))
    assert code == 2 and err.count("\n") == 1
    assert "--firmware" in err and "python, c, pil" in err
    import firmware_model.pil_build as pil_build

    monkeypatch.setattr(pil_build, "missing_tools", lambda: ["qemu-system-arm"])  # no QEMU here
    code, _, err = run_cli(capsys, "run", "--firmware", "pil", "--out", str(tmp_path / "b"))
    assert code == 2 and err.count("\n") == 1 and "pil" in err
    import firmware_model.firmware_select as sel

    monkeypatch.setattr(sel, "c_available", lambda: False)  # an installation without a C compiler
    for command in ("sim", "run", "robot"):
        code, _, err = run_cli(capsys, command, "--firmware", "c", "--out", str(tmp_path / command))
        assert code == 2 and err.count("\n") == 1 and "not built" in err, err
        assert not (tmp_path / command).exists()


@pytest.mark.parametrize("extra", sorted(REFERENCE_DIGESTS))
def test_sim_with_the_c_firmware_gives_the_reference_digest(
    extra: tuple[str, ...], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    digest, ticks = REFERENCE_DIGESTS[extra]
    code, out, err = run_cli(capsys, "sim", *extra, "--firmware", "c", "--out", str(tmp_path / "run"))
    assert code == 0, err
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["trace_sha256"] == digest and summary["ticks"] == ticks
    assert summary["bench"]["firmware"] == "c"
    assert f"trace_sha256 {digest[:16]}" in out


def test_api_takes_the_firmware() -> None:
    import ilcrig

    exp = ilcrig.Experiment(iterations=1, cycle_s=0.15, firmware="c")
    assert exp.firmware == "c" and exp.replace(iterations=2).firmware == "c"
    res = exp.run()
    ref = ilcrig.Experiment(iterations=1, cycle_s=0.15).run()
    assert res.summary["trace_sha256"] == ref.summary["trace_sha256"]
    assert res.summary["bench"]["firmware"] == "c"
    with pytest.raises(ilcrig.InputError, match="--firmware"):
        ilcrig.Experiment(firmware="rust")


def test_the_launchers_pass_the_firmware_on() -> None:
    from host.cli import build_parser
    from host.cli.robot import robot_options
    from host.cli.run import run_options
    from host.rig.role_commands import rig_role_args

    opts = run_options(build_parser().parse_args(["run", "--firmware", "c"]))
    assert opts.firmware == "c"
    host = build_parser().parse_args(["host", *rig_role_args(opts)])
    assert host.firmware == "c"  # the host role records it (summary bench.firmware)
    assert "--firmware" not in rig_role_args(run_options(build_parser().parse_args(["run"])))  # the default: unchanged
    assert robot_options(build_parser().parse_args(["robot", "--firmware", "c"])).firmware == "c"
    assert build_parser().parse_args(["drive", "--node", "1", "--firmware", "c"]).firmware == "c"
