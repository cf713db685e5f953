"""The live view (``--view`` of ``ilcrig robot``, ``ilcrig run`` and ``ilcrig sim``): a Rerun stream
a viewer watches while the robot moves or the trials run.

This module owns

* :class:`LiveView` — where the live stream goes: a gRPC server of the Rerun SDK on a free port of
  the loopback interface (``rerun+http://127.0.0.1:PORT/proxy``; never another interface), which
  buffers what was logged for a viewer that connects later (up to :attr:`LiveView.MEMORY_LIMIT`;
  static data is kept).  With a display ($DISPLAY / $WAYLAND_DISPLAY) the Rerun viewer is
  started, connected to it (its own server bound to loopback too); without one, the one command
  that connects a viewer is printed.  A recording stream uses it through :meth:`LiveView.sink`.
* :class:`RobotLiveView` — the robot's stream, from the periods the launcher's io monitor sees
  (:class:`host.rig.robot_watch.PeriodSample`): per joint ``/joint{j}/reference`` (the target
  position the master sent, deg), ``/joint{j}/actual`` (deg) and ``/joint{j}/torque`` (N·m) on
  the timelines ``robot_time`` (period × Ts) and ``period``, and the 3D robot ``/robot/now/...``
  (inner and outer arms, sub-platforms, tool; forward kinematics of the joint angles, the layout of
  :mod:`host.analysis.recording`) every :attr:`RobotLiveView.DECIMATE_3D`-th period.  Samples are
  buffered and sent as columns by a thread of its own every :attr:`RobotLiveView.FLUSH_S`, so the
  view costs the lockstep processes nothing (it runs in the launcher, on frames it reads anyway).

The trials of ``ilcrig sim`` / ``ilcrig run`` go live through :class:`host.analysis.recording.RunRecorder`
(its ``live`` parameter: the same recording, to the file and to the live sink at once).
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import threading
from typing import Any

import numpy as np

from host.analysis.recording_layout import joint_grid
from host.analysis.recording_scene import Batch, rerun_environment, rgba_u32, skeleton_points
from host.analysis.viewer import display_available, viewer_command

logger = logging.getLogger(__name__)

__all__ = ["LiveView", "RobotLiveView", "free_loopback_port"]

N_JOINTS = 4


def free_loopback_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveView:
    """The live stream's server on loopback and, with a display, the viewer (module docstring).

    :param port: the server's port on 127.0.0.1 (default: a free one).
    :param spawn: start the viewer (default: when there is a display and a viewer is installed).
    """

    #: what the server keeps for viewers that connect later (the oldest data goes first)
    MEMORY_LIMIT: str = "256MiB"

    def __init__(self, port: int | None = None, *, spawn: bool | None = None) -> None:
        os.environ.setdefault("RUST_LOG", "off")
        self.port = int(port) if port is not None else free_loopback_port()
        self.url = f"rerun+http://127.0.0.1:{self.port}/proxy"
        cmd = viewer_command()
        self.viewer_cmd = cmd
        self.spawn = (cmd is not None and display_available()) if spawn is None else bool(spawn)
        self.viewer: subprocess.Popen[bytes] | None = None

    def sink(self) -> Any:
        """The Rerun sink of the server (``rr.GrpcServerSink`` on 127.0.0.1)."""
        import rerun as rr

        return rr.GrpcServerSink(bind_ip="127.0.0.1", port=self.port, server_memory_limit=self.MEMORY_LIMIT)

    def connect_command(self) -> str:
        """The command that connects a viewer to the stream."""
        return f"rerun {self.url}"

    def open_viewer(self) -> str:
        """Start the viewer if there is a display (after the server is up); the line to print."""
        if self.spawn and self.viewer_cmd is not None:
            argv = [*self.viewer_cmd, self.url, "--bind", "127.0.0.1", "--port", str(free_loopback_port())]
            try:
                self.viewer = subprocess.Popen(
                    argv,
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    start_new_session=True,
                    env={**os.environ, "RERUN_APP_ONLY": "true"},
                )
            except OSError as err:
                logger.warning("cannot start the viewer %s: %s", argv[0], err)
            else:
                return f"live view: opened the Rerun viewer on {self.url}"
        return f"live view: {self.url} (no display here; connect a viewer with: {self.connect_command()})"


class RobotLiveView:
    """The robot's live stream (see the module docstring).

    :param live: where it goes.
    :param ts_s: the control period, s (the ``robot_time`` timeline).
    """

    #: 3D frames every this many periods
    DECIMATE_3D: int = 5
    #: joint samples every this many periods
    DECIMATE_SERIES: int = 1
    #: the buffered samples go out at least this often, s
    FLUSH_S: float = 0.1

    def __init__(self, live: LiveView, ts_s: float) -> None:
        os.environ.setdefault("RUST_LOG", "off")
        rerun_environment()
        import pyarrow as pa
        import rerun as rr

        self._rr, self._pa = rr, pa
        self.live = live
        self.ts_s = float(ts_s)
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._rec = rr.RecordingStream("ilcrig-robot", recording_id=f"robot-{os.getpid()}")
        self._rec.set_sinks(live.sink(), default_blueprint=robot_blueprint())
        self._rows: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._targets: list[tuple[int, np.ndarray]] = []
        self._y_guess: np.ndarray | None = None
        self.samples = 0
        self._static_scene()
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="live view", daemon=True)
        self._flusher.start()

    def _flush_loop(self) -> None:
        """Send what is buffered every :attr:`FLUSH_S` (the samples come in the monitor's rounds)."""
        while not self._stop.wait(self.FLUSH_S):
            try:
                self.flush()
            except Exception:  # noqa: BLE001 - the view must never stop the robot
                logger.exception("the live view failed; it stops")
                return

    def _static_scene(self) -> None:
        from plant.params import Geometry

        rr, pa = self._rr, self._pa
        g = Geometry()
        phi = np.asarray(g.azimuths_rad)
        a = g.R * np.stack([np.cos(phi), np.sin(phi), np.zeros(4)], axis=1)
        self._rec.log("/robot", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        st = Batch(pa)
        grey = rgba_u32((90, 90, 90, 255))
        st.put("/robot/base", "Points3D:positions", a[None])
        st.put("/robot/base", "Points3D:radii", [[0.012]])
        st.put("/robot/base", "Points3D:colors", [[grey]])
        st.put("/robot/base", "Points3D:labels", [[f"M{i + 1}" for i in range(4)]])
        blue = [[rgba_u32((30, 144, 255, 255))]]
        for ent, radius in (("arms", 0.006), ("sub_platforms", 0.005)):
            st.put(f"/robot/now/{ent}", "LineStrips3D:radii", [[radius]])
            st.put(f"/robot/now/{ent}", "LineStrips3D:colors", blue)
        st.put("/robot/now/tool", "Points3D:radii", [[0.012]])
        st.put("/robot/now/tool", "Points3D:colors", blue)
        names = {"reference": "target [deg]", "actual": "actual [deg]", "torque": "torque [N·m]"}
        colors = {"reference": (150, 150, 150, 255), "actual": (30, 144, 255, 255), "torque": (220, 50, 47, 255)}
        for j in range(1, N_JOINTS + 1):
            for key, name in names.items():
                st.put(f"/joint{j}/{key}", "SeriesLines:names", [[f"joint {j} {name}"]])
                st.put(f"/joint{j}/{key}", "SeriesLines:colors", [[rgba_u32(colors[key])]])
        st.send(self._rec)

    def add(self, period: int, q_rad: np.ndarray, torque_nm: np.ndarray) -> None:
        """One period (the watch's thread); sent with the others at the next flush."""
        if period % self.DECIMATE_SERIES:
            return
        with self._lock:
            self._rows.append((period, q_rad, torque_nm))
            self.samples += 1

    def add_targets(self, period: int, target_rad: np.ndarray) -> None:
        """The target positions [rad] of ``period`` (NaN: none), as the master sent them."""
        if period % self.DECIMATE_SERIES:
            return
        with self._lock:
            self._targets.append((period, target_rad))

    def on_period(self, sample: Any) -> None:
        """:class:`host.rig.robot_watch.PeriodSample` in (the watch's listener)."""
        self.add(sample.period, sample.q_rad, sample.torque_nm)

    def flush(self) -> None:
        """Send the buffered periods (the flushing thread; :meth:`close`)."""
        with self._send_lock:
            with self._lock:
                rows, self._rows = self._rows, []
                targets, self._targets = self._targets, []
            if targets:
                self._send_targets(targets)
            if rows:
                self._send(rows)

    def _index(self, period: np.ndarray) -> list[Any]:
        rr = self._rr
        return [rr.TimeColumn("period", sequence=period), rr.TimeColumn("robot_time", duration=period * self.ts_s)]

    def _send_targets(self, targets: list[tuple[int, np.ndarray]]) -> None:
        period = np.array([t[0] for t in targets], dtype=np.int64)
        target = np.stack([t[1] for t in targets])
        for j in range(N_JOINTS):
            ok = np.isfinite(target[:, j])
            if ok.any():
                scalars = self._rr.Scalars.columns(scalars=np.degrees(target[ok, j]))
                self._rec.send_columns(f"/joint{j + 1}/reference", self._index(period[ok]), scalars)

    def _send(self, rows: list[tuple[int, np.ndarray, np.ndarray]]) -> None:
        rr = self._rr
        period = np.array([r[0] for r in rows], dtype=np.int64)
        q = np.stack([r[1] for r in rows])
        tau = np.stack([r[2] for r in rows])
        t_ns = np.rint(period * self.ts_s * 1e9).astype(np.int64)
        idx = self._index(period)
        for j in range(N_JOINTS):
            self._rec.send_columns(f"/joint{j + 1}/actual", idx, rr.Scalars.columns(scalars=np.degrees(q[:, j])))
            self._rec.send_columns(f"/joint{j + 1}/torque", idx, rr.Scalars.columns(scalars=tau[:, j]))
        sel = np.flatnonzero(period % self.DECIMATE_3D == 0)
        if len(sel):
            self._robot(q[sel], period[sel], t_ns[sel])

    def _robot(self, q: np.ndarray, period: np.ndarray, t_ns: np.ndarray) -> None:
        from plant.kinematics import KinematicsError, forward_kinematics

        pa = self._pa
        try:
            y = np.asarray(forward_kinematics(q, self._y_guess)).reshape(-1, 4)
        except KinematicsError as exc:
            logger.debug("live view: no 3D frame: %s", exc)
            return
        self._y_guess = y[-1].copy()
        pts = skeleton_points(q, y)
        m = q.shape[0]
        arms = np.stack([pts["A"], pts["B"], pts["C"]], axis=2).reshape(m, 4, 3, 3)
        c, pu, pl, tcp = pts["C"], pts["P_up"], pts["P_low"], pts["tcp"]
        upper = np.stack([c[:, 0], pu, c[:, 2], c[:, 2]], axis=1)
        lower = np.stack([c[:, 1], pl, c[:, 3], c[:, 3]], axis=1)
        shaft = np.stack([pu, pl, tcp, tcp + 0.05 * pts["tool_dir"]], axis=1)
        plat = np.stack([upper, lower, shaft], axis=1).reshape(m, 3, 4, 3)
        data = Batch(pa)
        data.put("/robot/now/arms", "LineStrips3D:strips", arms)
        data.put("/robot/now/sub_platforms", "LineStrips3D:strips", plat)
        data.put("/robot/now/tool", "Points3D:positions", tcp[:, None, :])
        data.send(self._rec, "period", pa.array(period, pa.int64()))

    def close(self) -> None:
        """Send what is buffered and end the stream (the server stops with it)."""
        self._stop.set()
        self._flusher.join(timeout=5.0)
        try:
            self.flush()
            self._rec.flush()
            self._rec.disconnect()
        except Exception:  # noqa: BLE001 - the view must never break the robot's shutdown
            logger.warning("closing the live view failed", exc_info=True)


def robot_blueprint() -> Any:
    """The robot view's layout: the 3D robot beside per-joint position and torque plots."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/robot", name="robot"),
            rrb.Tabs(joint_grid("position", ["reference", "actual"], "deg"), joint_grid("torque", ["torque"], "N·m")),
            column_shares=[2, 3],
        ),
        rrb.TimePanel(timeline="period"),
        collapse_panels=False,
    )
