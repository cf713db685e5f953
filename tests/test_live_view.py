"""The live view (``--view``, host/analysis/live_view.py): what a Rerun viewer receives while the
robot moves and while trials run.  Rerun's own command line is the viewer: ``rerun URL --save FILE``
connects to the stream served on 127.0.0.1 and writes what arrives, which the test reads back with
rerun's ``RrdReader`` (no display here, so ``--view`` serves and prints that URL; nothing of rerun is
mocked).  The reader runs with its own HOME (a fresh Rerun configuration) and binds its own server
to loopback.  Waits are for the data to arrive in the file, never for a time.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from robot_util import DRIVES, LockstepMaster, RobotProcess, counts_of

from bus import units
from host.analysis.live_view import free_loopback_port
from host.analysis.viewer import viewer_command
from host.rig.role_commands import rig_role_args
from plant.kinematics import inverse_kinematics
from plant.mechanics import HOME_POSE

pytestmark = [pytest.mark.slow]

URL = r"rerun\+http://127\.0\.0\.1:(\d+)/proxy"


class Reader:
    """``rerun URL --save FILE``: a viewer without a window, writing what it receives."""

    def __init__(self, url: str, tmp: Path) -> None:
        cmd = viewer_command()
        assert cmd is not None, "rerun-sdk installs the rerun command"
        self.path = tmp / "received.rrd"
        home = tmp / "rerun-home"
        home.mkdir()
        self.proc = subprocess.Popen(
            [*cmd, url, "--save", str(self.path), "--bind", "127.0.0.1", "--port", str(free_loopback_port())],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "HOME": str(home), "XDG_CONFIG_HOME": str(home), "RERUN_APP_ONLY": "true"},
        )

    def rows(self) -> dict[str, int]:
        """Rows per (non-static) entity received so far."""
        from rerun.chunk import RrdReader

        out: dict[str, int] = {}
        if not self.path.exists():
            return out
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for c in RrdReader(self.path).stream():
                    if not c.is_static:
                        out[c.entity_path] = out.get(c.entity_path, 0) + c.to_record_batch().num_rows
        except Exception:  # noqa: BLE001 - the file is being written: a partial message at its end
            pass
        return out

    def values(self, entity: str, index: str) -> tuple[np.ndarray, np.ndarray]:
        """(index values, scalars) of a Scalars entity, sorted by the index."""
        import pyarrow as pa
        from rerun.chunk import RrdReader

        t, v = [], []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for c in RrdReader(self.path).stream():
                if c.entity_path == entity and not c.is_static:
                    rb = c.to_record_batch()
                    col = next(n for n in rb.schema.names if n.endswith("Scalars:scalars"))
                    t.append(rb.column(index).cast(pa.int64()).to_numpy())
                    v.append(np.array([x[0] for x in rb.column(col).to_pylist()]))
        order = np.argsort(np.concatenate(t))
        return np.concatenate(t)[order], np.concatenate(v)[order]

    def wait(self, done: Callable[[dict[str, int]], bool], timeout_s: float = 120.0) -> dict[str, int]:
        """Until what arrived satisfies ``done`` (the reader's file grows as data comes)."""
        deadline = time.monotonic() + timeout_s
        rows = self.rows()
        while not done(rows):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise TimeoutError(f"received so far: {rows}")
            time.sleep(0.1)
            rows = self.rows()
        return rows

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def no_display(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


@pytest.mark.multiprocess
def test_robot_live_view_streams_the_moving_robot(tmp_path: Path, no_display: None) -> None:
    robot = RobotProcess(tmp_path / "robot", "--view", env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    reader: Reader | None = None
    master: LockstepMaster | None = None
    try:
        line = robot.wait_line(r"live view: " + URL)
        assert f"connect a viewer with: rerun rerun+http://127.0.0.1:{line.group(1)}/proxy" in line.string
        where = robot.ready()
        reader = Reader(line.group(0)[len("live view: ") :], tmp_path)
        master = LockstepMaster(interface=where["interface"], channel=where["channel"])
        master.configure()
        master.start()
        home = counts_of(inverse_kinematics(np.array(HOME_POSE)))
        master.enable(home)
        q_ref = inverse_kinematics(np.linspace(HOME_POSE, (0.04, 0.0, -0.69, 0.0), 300))
        last = {}
        for row in q_ref:
            last = master.cycle({n: (0x0F, round(float(row[n - 1]) / units.RAD_PER_COUNT)) for n in DRIVES})
        rows = reader.wait(
            lambda r: (
                r.get("/joint2/actual", 0) >= 300 and r.get("/joint2/reference", 0) >= 300 and r.get("/robot/now/arms", 0) >= 60
            )
        )
        assert rows.get("/joint2/torque", 0) >= 300
        # what the viewer got is what the robot did: the last actual angle, the targets the master sent
        period, actual = reader.values("/joint2/actual", "period")
        assert actual[-1] == pytest.approx(np.degrees(last[2][1] * units.RAD_PER_COUNT), abs=0.01)
        ref_period, target = reader.values("/joint2/reference", "period")
        assert target[-1] == pytest.approx(np.degrees(q_ref[-1][1]), abs=1e-3)
        assert ref_period[-1] == period[-1]  # the target of a period beside its actual angle
        assert np.all(np.diff(period) > 0)
    finally:
        if master is not None:
            master.close()
        if reader is not None:
            reader.close()
        robot.stop()
        robot.kill()


def test_sim_live_view_streams_each_trial_as_it_completes(tmp_path: Path, no_display: None) -> None:
    import ilcrig

    exp = ilcrig.Experiment(iterations=3, cycle_s=0.25)
    session = exp.start(tmp_path / "run", view=True)
    reader: Reader | None = None
    try:
        assert session.live_url is not None and re.fullmatch(URL, session.live_url)
        reader = Reader(session.live_url, tmp_path)
        first = session.step()
        second = session.step()
        assert first is not None and second is not None
        reader.wait(lambda r: r.get("/metrics/rmse_deg/joint1", 0) >= 2 and "/joint1/actual/iter1" in r)
        k, rmse = reader.values("/metrics/rmse_deg/joint1", "iteration")
        assert k.tolist() == [0, 1]
        np.testing.assert_allclose(rmse, [first.rmse_deg[0], second.rmse_deg[0]])
        while session.step() is not None:
            pass
    finally:
        session.close()
        if reader is not None:
            reader.close()
    assert (tmp_path / "run" / "recording.rrd").stat().st_size > 0  # the file as without --view


def test_run_passes_view_to_the_host_role() -> None:
    from host.cli import build_parser
    from host.cli.run import run_options

    assert "--view" in rig_role_args(run_options(build_parser().parse_args(["run", "--view"])))
    assert "--view" not in rig_role_args(run_options(build_parser().parse_args(["run"])))


def test_view_needs_a_run_folder_in_the_api() -> None:
    import ilcrig

    with pytest.raises(ilcrig.InputError, match="view"):
        ilcrig.Experiment(iterations=1).start(None, view=True)
