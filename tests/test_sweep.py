"""``ilcrig sweep`` on Dask distributed: the spec (grid, ranges, Monte Carlo draws), the plant
uncertainty factors, a sweep on a 2-worker local cluster with resume and the digests of
``ilcrig sim``, the same sweep on a scheduler and two workers started as separate processes
(results equal, every socket on loopback), and a worker killed while it holds a point."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from cli_util import run_cli_process

import ilcrig
from host.studies.spec import Point, SweepSpec, parse_assignment
from plant.params import PlantScales, default_true_plant, scaled_true_plant

ROOT = Path(__file__).resolve().parent.parent
#: a tiny experiment: short cycle, 2 trials
TINY = ["--set", "iterations=2", "--set", "cycle_s=0.15"]
DASK = Path(sys.executable).parent / "dask"
#: a guard against a hang, not a timing assumption
GUARD_S = 300.0


# --------------------------------------------------------------------------------------- the spec


def test_vary_is_the_product_and_points_are_validated() -> None:
    spec = SweepSpec()
    spec.add_cli(["law=pd-ilc-q", "iterations=2"], ["gains.alpha=2,3", "path=1,3"])
    pts = spec.points()
    assert [(p.labels["gains.alpha"], p.labels["path"]) for p in pts] == [(2, 1), (2, 3), (3, 1), (3, 3)]
    assert all(p.config.law == "pd-ilc-q" and p.config.iterations == 2 for p in pts)
    assert [p.config.gains.alpha for p in pts] == [2.0, 2.0, 3.0, 3.0] and pts[1].config.path == "3"
    # a point's id is its configuration's: the same in any sweep, whatever else is varied
    again = SweepSpec()
    again.add_cli(["iterations=2"], ["path=3", "gains.alpha=2", "law=pd-ilc-q"])
    assert again.points()[0].id == pts[1].id == Point.config_id(pts[1].config)
    assert parse_assignment("law_options.torque_limit_nm=200,250") == ("law_options.torque_limit_nm", [200, 250])


def test_spec_file_ranges_and_draws(tmp_path: Path) -> None:
    f = tmp_path / "s.toml"
    f.write_text(
        """
[base]
law = "pd-ilc-q"
iterations = 2
[base.gains]
beta = 2.5
[vary]
cycle_s = { start = 0.15, stop = 0.25, step = 0.05 }
"gains.lp_norm" = { start = 1e-4, stop = 1e-2, num = 3, log = true }
[monte_carlo]
samples = 4
seed = 7
[monte_carlo.draw]
"plant.mass_scale" = { uniform = [0.9, 1.1] }
"plant.friction_scale" = { lognormal = [0.0, 0.3] }
seed = { integers = [0, 1000] }
"""
    )
    spec = SweepSpec.from_toml(f)
    assert spec.vary["cycle_s"] == [0.15, 0.2, 0.25]
    assert np.allclose(spec.vary["gains.lp_norm"], [1e-4, 1e-3, 1e-2])
    pts = spec.points()
    assert len(pts) == spec.n_points == 3 * 3 * 4
    assert all(p.config.gains.beta == 2.5 for p in pts)
    # the draws of a sample depend on the seed and the sample index only: the same at every grid point
    d = [spec.draw(s) for s in range(4)]
    assert [p.labels["plant.mass_scale"] for p in pts[:4]] == [x["plant.mass_scale"] for x in d]
    assert [p.labels["sample"] for p in pts[4:8]] == [0, 1, 2, 3] and pts[4].labels["seed"] == d[0]["seed"]
    assert all(0.9 <= x["plant.mass_scale"] <= 1.1 and isinstance(x["seed"], int) for x in d)
    assert pts[5].config.plant.mass_scale == d[1]["plant.mass_scale"] and pts[5].config.seed == d[1]["seed"]
    more = SweepSpec.from_toml(f)
    more.samples = 6  # more samples keep the earlier ones
    assert [more.draw(s) for s in range(4)] == d


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[vary]\nalpha = [1, 2]\n", "unknown option 'alpha'"),
        ("[vary]\n'gains.alpha' = { start = 1, stop = 2 }\n", "a range is {start, stop, step}"),
        ("[vary]\n'plant.mass' = [1]\n", "unknown plant factor 'mass'"),
        ("[monte_carlo]\nsamples = 2\n[monte_carlo.draw]\nseed = { poisson = [3] }\n", "unknown distribution 'poisson'"),
        ("[monte_carlo.draw]\n'plant.mass_scale' = { uniform = [1, 2] }\n", "draws need samples >= 1"),
        ("[vary]\n'gains.alpha' = [0.5]\n", "gains.alpha and gains.beta must be >= 1, got 0.5, 3.0 (point gains.alpha = 0.5)"),
        ("[sweep]\n", "unknown section(s) sweep"),
    ],
)
def test_bad_specs_are_one_line_errors(tmp_path: Path, text: str, message: str) -> None:
    f = tmp_path / "s.toml"
    f.write_text(text)
    with pytest.raises(ilcrig.InputError) as err:
        SweepSpec.from_toml(f).points()
    assert message in str(err.value) and "\n" not in str(err.value)


def test_cli_refuses_bad_input_before_anything_starts(tmp_path: Path) -> None:
    from host.cli import main

    out = tmp_path / "x"
    assert main(["sweep", "--out", str(out), "--vary", "gains.alpha"]) == 2
    assert main(["sweep", "--out", str(out), "--vary", "gains.alpha=2", "--set", "gains.alpha=3"]) == 2
    assert main(["sweep", "--out", str(out), "--vary", "law=nope"]) == 2
    assert main(["sweep", "--out", str(out), "--workers", "0"]) == 2
    assert main(["sweep", "--out", str(out), "--dashboard", "0.0.0.0:8787"]) == 2
    assert not out.exists()


# ------------------------------------------------------------------------------ plant uncertainty


def test_plant_scales_change_the_emulated_robot_only() -> None:
    base = default_true_plant()
    assert scaled_true_plant(base, PlantScales()) is base
    s = scaled_true_plant(base, PlantScales(inertia_scale=1.2, mass_scale=0.9, friction_scale=0.5, payload_scale=2.0))
    assert s.mass.I_a == pytest.approx(1.2 * base.mass.I_a) and s.mass.J_m == pytest.approx(1.2 * base.mass.J_m)
    assert s.mass.m_low == pytest.approx(0.9 * base.mass.m_low) and s.mass.payload == pytest.approx(2 * base.mass.payload)
    assert s.coulomb_nm == pytest.approx(tuple(0.5 * c for c in base.coulomb_nm))
    assert s.joint_torque_limit_nm == base.joint_torque_limit_nm
    with pytest.raises(ValueError, match="plant.mass_scale must be > 0"):
        PlantScales(mass_scale=0.0)
    plain = ilcrig.Experiment(law="pd-ilc", iterations=2, cycle_s=0.15)
    same = ilcrig.Experiment(law="pd-ilc", iterations=2, cycle_s=0.15, plant={"mass_scale": 1.0})
    assert "plant" not in same.config.as_dict()  # the robot as built: summaries unchanged
    heavy = ilcrig.Experiment(law="pd-ilc", iterations=2, cycle_s=0.15, plant={"mass_scale": 1.3})
    assert heavy.config.as_dict()["plant"]["mass_scale"] == 1.3
    a, b, c = plain.run(), same.run(), heavy.run()
    assert a.digest == b.digest != c.digest
    assert heavy.check.rho_max == plain.check.rho_max  # the plan (nominal model) is the same


@pytest.mark.slow
@pytest.mark.multiprocess
def test_plant_factors_on_the_rig_give_the_digest_of_sim(tmp_path: Path) -> None:
    """The factors reach the plant node (0x2400:6..9) as exact float64: the rig's digest is sim's."""
    exp = ilcrig.Experiment(law="pd-ilc", iterations=1, cycle_s=0.15, plant={"inertia_scale": 1.15, "friction_scale": 0.7})
    sim = exp.run()
    rig = exp.run(mode="rig", out=tmp_path / "rig", bus="hub", timeout_s=600)
    assert rig.completed and rig.config["plant"]["inertia_scale"] == 1.15
    assert rig.digest == sim.digest != ilcrig.Experiment(law="pd-ilc", iterations=1, cycle_s=0.15).run().digest


# ------------------------------------------------------------------------------------- processes


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``ilcrig ARGS`` in its own session; returns once it and every process it started ended."""
    return run_cli_process(list(args), GUARD_S)


def _table(out: Path) -> dict[tuple[str, int, int], tuple]:
    """results.parquet as {(point, trial, joint): (digest, rmse, maxe, mae, peak torque)}."""
    import pyarrow.parquet as pq

    t = pq.read_table(out / "results.parquet").to_pylist()
    return {
        (r["point"], r["trial"], r["joint"]): (r["digest"], r["rmse_deg"], r["max_abs_deg"], r["mae_deg"], r["peak_torque_nm"])
        for r in t
    }


GRID_SETS = ["law=pd-ilc-q", "iterations=2", "cycle_s=0.15"]
GRID_VARY = ["gains.alpha=2,4", "plant.friction_scale=0.5,1.5"]
GRID = [*(x for s in GRID_SETS for x in ("--set", s)), *(x for v in GRID_VARY for x in ("--vary", v))]


def _grid_points() -> list[Point]:
    spec = SweepSpec()
    spec.add_cli(GRID_SETS, GRID_VARY)
    return spec.points()


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The grid swept in this process on a 2-worker local cluster (:class:`Engine`): every socket of
    the cluster on loopback, and its worker processes gone once the engine is closed."""
    from host.studies.engine import Engine, run_points

    out = tmp_path_factory.mktemp("local") / "grid"
    with Engine(workers=2, dashboard=True) as engine:
        assert engine.n_workers == 2 and engine.describe() == "a local cluster of 2 worker process(es) on 127.0.0.1"
        pids = list(engine.client.run(os.getpid).values())
        sockets = _listening([os.getpid()])
        assert {pid for pid, _, _ in sockets} >= set(pids)  # the workers serve too
        assert sockets and all(ip == "127.0.0.1" for _, ip, _ in sockets), sockets
        if engine.dashboard is not None:  # bokeh installed
            assert engine.dashboard.startswith("http://127.0.0.1:")
        outcome = run_points(engine, out, _grid_points(), progress=False)
    assert len(outcome.ran) == 4 and not outcome.errors and not outcome.interrupted
    deadline = time.monotonic() + GUARD_S
    while any(_alive(pid) for pid in pids):
        assert time.monotonic() < deadline, "worker processes survived the engine"
        time.sleep(0.1)
    return out


@pytest.mark.slow
@pytest.mark.multiprocess
def test_local_sweep_table_report_resume_and_sim_digests(local_sweep: Path, tmp_path: Path) -> None:
    out = local_sweep
    mtimes = {f: f.stat().st_mtime_ns for f in (out / "runs").rglob("*") if f.is_file()}
    p = _cli("sweep", "--out", str(out), "--workers", "2", "--no-progress", *GRID)  # resume: nothing to run
    assert p.returncode == 0, p.stderr
    assert "0 run, 4 already finished" in p.stdout and "4 point(s) (gains.alpha, plant.friction_scale)" in p.stderr
    assert mtimes == {f: f.stat().st_mtime_ns for f in (out / "runs").rglob("*") if f.is_file()}
    assert [h["ran"] for h in json.loads((out / "sweep.json").read_text())["history"]] == [0]
    rows = _table(out)
    assert len(rows) == 4 * 2 * 4  # points × trials × joints
    import pyarrow.parquet as pq

    cols = pq.read_table(out / "results.parquet").column_names
    for c in ("point", "law", "cycle_s", "gains.alpha", "plant.friction_scale", "trial", "joint", "rmse_deg", "digest", "final"):
        assert c in cols
    report = (out / "report.md").read_text()
    assert "## Final RMSE across the grid" in report and "![final RMSE across the grid](grid.png)" in report
    assert (out / "grid.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a point's digest is the one of `ilcrig sim` with the same options
    target = next(pt for pt in _grid_points() if pt.labels == {"gains.alpha": 4, "plant.friction_scale": 0.5})
    sim = _cli(
        "sim",
        "--law",
        "pd-ilc-q",
        "--iterations",
        "2",
        "--cycle",
        "0.15",
        "--alpha",
        "4",
        "--friction-scale",
        "0.5",
        "--out",
        str(tmp_path / "sim"),
    )
    assert sim.returncode == 0, sim.stderr
    digest = json.loads((tmp_path / "sim" / "summary.json").read_text())["trace_sha256"]
    assert rows[(target.id, 1, 3)][0] == digest
    assert ilcrig.Experiment(**target.options).run().digest == digest
    assert json.loads((out / "runs" / target.id / "point.json").read_text())["labels"] == target.labels


def _listening(pids: list[int]) -> list[tuple[int, str, int]]:
    """The listening TCP sockets of ``pids`` and their descendants: (pid, address, port)."""
    import psutil

    procs = []
    for pid in pids:
        with _suppress_gone():
            p = psutil.Process(pid)
            procs += [p, *p.children(recursive=True)]
    found = []
    for p in procs:
        with _suppress_gone():
            for c in p.net_connections(kind="inet"):
                if c.status == psutil.CONN_LISTEN:
                    found.append((p.pid, c.laddr.ip, c.laddr.port))
    return found


class _suppress_gone:
    def __enter__(self) -> None:
        return None

    def __exit__(self, typ: object, value: object, tb: object) -> bool:
        import psutil

        return isinstance(value, psutil.NoSuchProcess)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie child of this process is gone for good once reaped
        wpid, _ = os.waitpid(pid, os.WNOHANG)
        return wpid == 0
    except ChildProcessError:
        return True


# ------------------------------------------------------------------- a cluster of separate processes


def _start(cmd: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(cmd, cwd=ROOT, stdout=log.open("wb"), stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    """End every process group started here (SIGTERM, then SIGKILL) and reap them."""
    for p in procs:
        with _suppress_lookup():
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            with _suppress_lookup():
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    for p in procs:  # the group is empty: nothing of the cluster is left
        deadline = time.monotonic() + GUARD_S
        while True:
            try:
                os.killpg(p.pid, 0)
            except ProcessLookupError:
                break
            if time.monotonic() > deadline:
                os.killpg(p.pid, signal.SIGKILL)
                pytest.fail(f"processes of group {p.pid} survived")
            time.sleep(0.1)


class _suppress_lookup:
    def __enter__(self) -> None:
        return None

    def __exit__(self, typ: object, value: object, tb: object) -> bool:
        return isinstance(value, ProcessLookupError)


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[tuple[str, list[subprocess.Popen[bytes]], Path]]:
    """``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1, started with the ``dask``
    CLI; the workers can import tests/sweep_hold.py and hold its points once.  Yields (address,
    processes, hold folder)."""
    from distributed import Client

    hold = tmp_path / "hold"
    env = os.environ | {"PYTHONPATH": str(ROOT / "tests"), "ILCRIG_TEST_HOLD_DIR": str(hold)}
    env["ILCRIG_TEST_HOLD"] = HELD.id
    sfile = tmp_path / "scheduler.json"
    procs = [
        _start(
            [
                str(DASK),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--dashboard-address",
                "127.0.0.1:0",
                "--scheduler-file",
                str(sfile),
            ],
            tmp_path / "scheduler.log",
            env,
        )
    ]
    try:
        deadline = time.monotonic() + GUARD_S
        address = None
        while address is None:  # the scheduler writes its file once it listens
            assert procs[0].poll() is None, (tmp_path / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "the scheduler did not start"
            try:
                address = json.loads(sfile.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.1)
        for i in (1, 2):
            procs.append(
                _start(
                    [
                        str(DASK),
                        "worker",
                        address,
                        "--nthreads",
                        "1",
                        "--host",
                        "127.0.0.1",
                        "--dashboard-address",
                        "127.0.0.1:0",
                        "--name",
                        f"w{i}",
                    ],
                    tmp_path / f"worker{i}.log",
                    env,
                )
            )
        with Client(address, timeout=GUARD_S) as client:
            client.wait_for_workers(2, timeout=GUARD_S)
        yield address, procs, hold
    finally:
        _stop(procs)


#: the point the held sweep holds (and whose worker the test kills)
HELD_SPEC = ["law=pd-ilc", "iterations=2", "cycle_s=0.15"]


def _held_spec() -> SweepSpec:
    s = SweepSpec()
    s.add_cli(HELD_SPEC, ["gains.alpha=2,3,4"])
    return s


HELD = _held_spec().points()[1]


@pytest.mark.slow
@pytest.mark.multiprocess
def test_scheduler_and_workers_as_processes_same_results_loopback_and_a_killed_worker(
    tmp_path: Path, local_sweep: Path, dask_cluster: tuple[str, list[subprocess.Popen[bytes]], Path]
) -> None:
    address, procs, hold = dask_cluster
    # everything the cluster's processes listen on is on loopback
    sockets = _listening([p.pid for p in procs])
    assert len({pid for pid, _, _ in sockets}) >= 3 and all(ip == "127.0.0.1" for _, ip, _ in sockets), sockets
    # the same sweep locally and on the cluster: the same table
    remote = tmp_path / "remote"
    p = _cli("sweep", "--out", str(remote), "--scheduler", address, "--no-progress", *GRID)
    assert p.returncode == 0, p.stderr
    assert f"on the cluster at {address} (2 workers)" in p.stderr
    from host.studies.table import write_table

    write_table(local_sweep, _grid_points())  # the local run's table (the resume test may not have run)
    assert _table(local_sweep) == _table(remote)
    # a worker killed while it holds a point: the point runs elsewhere and the sweep completes
    out = tmp_path / "held"
    args = ["sweep", "--out", str(out), "--scheduler", address, "--no-progress", "--set", HELD_SPEC[0], "--set", HELD_SPEC[1]]
    args += ["--set", HELD_SPEC[2], "--vary", "gains.alpha=2,3,4"]
    client = subprocess.Popen(
        [sys.executable, "tests/sweep_hold.py", *args],
        cwd=ROOT,
        env=os.environ | {"ILCRIG_TEST_HOLD": HELD.id, "ILCRIG_TEST_HOLD_DIR": str(hold)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        held = hold / HELD.id / "held"
        deadline = time.monotonic() + GUARD_S
        while not held.is_file():
            assert client.poll() is None, client.communicate()
            assert time.monotonic() < deadline, "no worker held the point"
            time.sleep(0.1)
        victim = int(held.read_text())
        assert victim in [c.pid for p in procs[1:] for c in _children(p.pid)]
        os.kill(victim, signal.SIGKILL)
        stdout, stderr = client.communicate(timeout=GUARD_S)
    finally:
        if client.poll() is None:
            os.killpg(client.pid, signal.SIGKILL)
            client.wait()
    assert client.returncode == 0, stderr
    assert "3 run, 0 already finished" in stdout
    doc = json.loads((out / "runs" / HELD.id / "point.json").read_text())
    assert doc["error"] is None and not doc["worker"].endswith(f":{victim}")
    rows = _table(out)
    assert len(rows) == 3 * 2 * 4 and all(r[0] for r in rows.values())
    assert rows[(HELD.id, 1, 1)][0] == ilcrig.Experiment(**HELD.options).run().digest


def _children(pid: int) -> list[object]:
    import psutil

    return psutil.Process(pid).children(recursive=True)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_tune_over_monte_carlo_plants(tmp_path: Path) -> None:
    """A trial's value is the mean of J over its plants (the spec's draws), each plant a point."""
    import optuna

    from host.studies.tune_params import Objective

    spec = tmp_path / "t.toml"
    spec.write_text(
        '[base]\nlaw = "pd-ilc-q"\niterations = 2\ncycle_s = 0.15\n'
        '[tune]\n"gains.alpha" = { low = 2.0, high = 4.0 }\n'
        "[objective]\nplants = 2\n"
        '[monte_carlo]\nseed = 3\n[monte_carlo.draw]\n"plant.mass_scale" = { uniform = [0.9, 1.1] }\n'
    )
    out = tmp_path / "tune"
    p = _cli("tune", "--spec", str(spec), "--out", str(out), "--budget", "2", "--workers", "2", "--no-progress")
    assert p.returncode == 0, p.stderr
    study = optuna.load_study(study_name="ilcrig-tune", storage=f"sqlite:///{out / 'study.db'}")
    first = min(study.trials, key=lambda t: t.number)
    assert first.params == {"gains.alpha": 3.0} and len(first.user_attrs["points"]) == 2
    draws = SweepSpec.from_toml(spec)
    js = [
        Objective().of_summary(
            ilcrig.Experiment(law="pd-ilc-q", iterations=2, cycle_s=0.15, plant={"mass_scale": draws.draw(s)["plant.mass_scale"]})
            .run()
            .summary
        )
        for s in (0, 1)
    ]
    assert first.value == pytest.approx(float(np.mean(js)), rel=1e-12)
    assert len(list((out / "runs").iterdir())) == 4  # two trials × two plants


#: ``ilcrig sweep`` in a fresh interpreter that sends itself SIGINT as its local cluster is made,
#: inside the moment the worker processes are spawned with SIGINT ignored (host.studies.dask_quiet)
_CLUSTER_SIGINT_SCRIPT = """
import importlib.abc, importlib.machinery, os, signal, sys

class After(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name != "host.studies.dask_quiet":
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            made = module.NoHttpLocalCluster.__init__

            def init(self, *args, **kwargs):
                assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # inside the window
                os.kill(os.getpid(), signal.SIGINT)
                return made(self, *args, **kwargs)

            module.NoHttpLocalCluster.__init__ = init

        spec.loader.exec_module = exec_module
        return spec

sys.meta_path.insert(0, After())
from host.cli import main
out = ["--out", sys.argv[1]] if sys.argv[1] else []  # "": the default folder, runs/sweep-<time>
sys.exit(main(["sweep", *out, "--vary", "gains.alpha=2,3", "--set", "iterations=2",
               "--workers", "1", "--no-progress", "--no-dashboard"]))
"""


@pytest.mark.slow
@pytest.mark.multiprocess
@pytest.mark.parametrize("named", [True, False], ids=["out", "default-folder"])
def test_a_ctrl_c_while_the_workers_are_spawned_is_not_lost(tmp_path: Path, named: bool) -> None:
    """The workers are spawned while this process ignores SIGINT (they inherit it: no traceback
    from them); a Ctrl-C then is held, not dropped, and ends the sweep once the cluster is made
    (it was dropped: the sweep ran to its end with exit 0). Without ``--out`` the folder it claimed
    is given back: nothing was written into it (an empty ``runs/sweep-<time>`` was left)."""
    out = tmp_path / "sweep"
    proc = subprocess.run(
        [sys.executable, "-c", _CLUSTER_SIGINT_SCRIPT, str(out) if named else ""],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 130, (proc.stdout, proc.stderr)
    assert proc.stderr.splitlines()[-1] == "ilcrig: interrupted (SIGINT)", proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert not (out / "results.parquet").exists()
    assert not out.exists()  # interrupted before its first point: no folder claims a sweep
    assert list(tmp_path.glob("runs/*")) == []  # nor an empty default folder


def test_an_interrupted_call_is_recorded_with_its_signal(tmp_path: Path) -> None:
    """``sweep.json``'s history says which signal ended a call, beside what it ran."""
    from host.studies.engine import SweepOutcome
    from host.studies.sweep_record import record_call

    record_call(tmp_path, {"spec": {}}, {"command": "sweep"}, {"on": "here"}, SweepOutcome(ran=["a"], signum=signal.SIGTERM))
    record_call(tmp_path, {"spec": {}}, {"command": "sweep"}, {"on": "here"}, SweepOutcome(ran=["b"]))
    first, second = json.loads((tmp_path / "sweep.json").read_text())["history"]
    assert (first["interrupted"], first["signal"], first["ran"]) == (True, "SIGTERM", 1)
    assert (second["interrupted"], second["signal"], second["ran"]) == (False, None, 1)
