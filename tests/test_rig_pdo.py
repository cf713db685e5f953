"""``ilcrig run --ff-transport pdo`` as separate processes over the hub: the trace digest equals
``ilcrig sim --ff-transport pdo``; cantools (the DBC files, the stock ``cantools decode`` command)
reads the run's io.log and fieldbus.log and finds there exactly the values the drives recorded;
the bus-fit check refuses a configuration that does not fit, before anything starts."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cantools
import numpy as np
import pytest
from cantools.logreader import Parser

from bus import fixedpoint as fp
from bus import io_frames
from bus.cyclic import rpdo_cob_id, tpdo_cob_id
from bus.dbc import FIELDBUS_DBC_PATH, IO_DBC_PATH
from bus.objects import RATED_TORQUE_MNM
from host.experiment.config import build_config
from host.experiment.loop_state import ExperimentResult
from host.experiment.plan import prepare
from host.experiment.trial_loop import run_experiment
from host.sim.inprocess import InProcessBench
from tests.cli_util import run_cli_process

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

REPO = Path(__file__).resolve().parent.parent
EXP = ["--iterations", "2", "--cycle", "0.15", "--disturbance", "both", "--seed", "3", "--ff-transport", "pdo"]
EXP_CFG = {"iterations": 2, "cycle_s": 0.15, "disturbance": "both", "seed": 3, "ff_transport": "pdo"}
N = 301


@pytest.fixture(scope="module")
def sim() -> ExperimentResult:
    cfg = build_config(None, EXP_CFG)
    return run_experiment(prepare(cfg), InProcessBench(cfg), None, mode="sim", keep_traces=True)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[subprocess.CompletedProcess[str], Path]]:
    out = tmp_path_factory.mktemp("rigpdo") / "run"
    cmd = [sys.executable, "-m", "host.cli", "run", *EXP, "--bus", "hub", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, cwd=REPO)
    try:
        so, se = proc.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        so, se = proc.communicate()
        pytest.fail(f"rig timed out:\n{so}\n{se}")
    yield subprocess.CompletedProcess(cmd, proc.returncode, so, se), out


def test_pdo_rig_digest_equals_sim(rig: tuple[subprocess.CompletedProcess[str], Path], sim: ExperimentResult) -> None:
    res, out = rig
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] and s["config"]["ff_transport"] == "pdo" and s["faults"] == []
    assert s["ticks"] == 2 * N and [it["k"] for it in s["iterations"]] == [0, 1]
    assert s["bench"]["timing"]["ticks"] == 2 * N
    assert s["trace_sha256"] == sim.summary["trace_sha256"]
    assert s["bus_fit"]["fits"] and s["bus_fit"]["bits_worst_case"] == 975
    assert s["bench"]["pdo_frames"] == {"sync": 2 * N, "rpdo": 2 * 4 * N, "tpdo": 2 * 4 * N}
    assert "SYNC + 4 RPDO (6 B) + 4 TPDO (6 B)" in res.stdout


def _decoded(db: cantools.database.Database, log: Path) -> list[tuple[int, dict[str, int]]]:
    """(frame id, raw signal values) of every frame of a candump log that the DBC describes."""
    ids = {m.frame_id for m in db.messages}
    out = []
    with open(log) as fh:
        for frame in Parser(fh):
            if frame.frame_id not in ids:
                continue
            out.append((frame.frame_id, db.decode_message(frame.frame_id, frame.data, scaling=False, decode_choices=False)))
    return out


def test_cantools_finds_the_recorded_values_in_the_logs(
    rig: tuple[subprocess.CompletedProcess[str], Path], sim: ExperimentResult
) -> None:
    res, out = rig
    assert res.returncode == 0, res.stderr[-3000:]
    traces = sim.traces[0]  # trial 0: what each drive's recorder holds (the rig's digest is the same)
    io = _decoded(cantools.database.load_file(str(IO_DBC_PATH)), out / "io.log")
    starts = [k for k, (fid, sig) in enumerate(io) if fid == io_frames.CONTROL_COB_ID and sig["command"] == 1]
    assert len(starts) == 2
    trial0 = io[starts[0] : starts[1]]
    fb = _decoded(cantools.database.load_file(str(FIELDBUS_DBC_PATH)), out / "fieldbus.log")
    assert sum(1 for fid, _ in fb if fid == 0x080) == 2 * N  # one SYNC per tick
    for j, tr in enumerate(traces):
        enc = [sig["position"] for fid, sig in trial0 if fid == io_frames.encoder_cob_id(j)]
        tq = [sig["torque"] for fid, sig in trial0 if fid == io_frames.torque_cob_id(j)]
        assert enc == tr.position_counts.tolist()
        assert tq == tr.torque_units.tolist()
        tpdo = [sig for fid, sig in fb if fid == tpdo_cob_id(j + 1)][:N]
        assert [s["position_actual"] for s in tpdo] == tr.position_counts.tolist()
        assert [s["torque_actual"] for s in tpdo] == [
            fp.torque_units_to_permille(int(t), RATED_TORQUE_MNM) for t in tr.torque_units
        ]
        rpdo = [sig for fid, sig in fb if fid == rpdo_cob_id(j + 1)][:N]
        ff_permille = np.rint(sim.feedforward[0][:, j] * 1e6 / RATED_TORQUE_MNM).astype(int)
        assert [s["torque_offset"] for s in rpdo] == ff_permille.tolist()


def test_stock_cantools_decode_command_reads_io_log(
    rig: tuple[subprocess.CompletedProcess[str], Path], sim: ExperimentResult
) -> None:
    _, out = rig
    with open(out / "io.log") as fh:
        res = subprocess.run(
            [sys.executable, "-m", "cantools", "decode", str(IO_DBC_PATH)], stdin=fh, capture_output=True, text=True, timeout=300
        )
    assert res.returncode == 0, res.stderr[-2000:]
    first = int(sim.traces[0][0].position_counts[0])
    assert f"IO_ENCODER_J1(\n    position: {first} counts,\n    wire_tick: 0 tick\n)" in res.stdout


def test_a_configuration_that_does_not_fit_is_refused_before_anything_starts(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = run_cli_process(["run", "--ff-transport", "pdo", "--fieldbus-bitrate", "500000", "--out", str(out)], 300)
    assert res.returncode == 2
    assert res.stderr.startswith("ilcrig: error: the cyclic PDO exchange does not fit the fieldbus")
    assert "195.0 %" in res.stderr and "--force-bus-fit" in res.stderr
    assert not out.exists()
