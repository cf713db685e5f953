"""Rerun recordings of a run (``recording.rrd``) and ``ilcrig view``.

This module owns the layout of ``recording.rrd`` and the only ``import rerun`` of the project
(lazy: importing this module does not import rerun).  :class:`RunRecorder` implements the
:class:`host.experiment.TrialRecorder` protocol with a *non-global* ``rr.RecordingStream`` saved
to a file (no viewer, no network).

Layout (entity paths; timelines ``trial_time`` = t_n = n·Ts as a duration, ``iteration`` = k):

* ``/joint{j}/reference/iter{k:02d}``  q_d of joint j (1..4), deg       (trial_time)
* ``/joint{j}/actual/iter{k:02d}``     measured q (encoder), deg         (trial_time)
* ``/joint{j}/error/iter{k:02d}``      e = q_d − q, deg                  (trial_time)
* ``/joint{j}/torque_ff/iter{k:02d}``  feed-forward u_k sent to the drive, N·m  (trial_time)
* ``/joint{j}/torque_fb/iter{k:02d}``  feedback torque recorded by the drive, N·m (trial_time)
  One entity per iteration, so the iterations overlay on ``trial_time``; each carries a static
  ``SeriesLines`` (name ``iter k``, colour from early = red to late = blue; references grey).
* ``/metrics/rmse_deg/joint{j}``, ``/metrics/maxe_deg/joint{j}``: one row per trial on the
  ``iteration`` sequence timeline (the values of the summary, deg).
* ``/robot`` (``ViewCoordinates.RIGHT_HAND_Z_UP``, base frame, m):
  static ``/robot/base`` (motor-axis points A_i), ``/robot/base/motor_axes``,
  ``/robot/reference_path`` (reference TCP path);
  ``/robot/first/...`` (trial 0) and ``/robot/last/...`` (the last completed trial), each on
  ``trial_time`` every ``decimate_3d``-th sample, computed by forward kinematics from the
  MEASURED joint angles: ``inner_arms`` (A_i → elbow B_i), ``outer_arms`` (B_i → ball-bar
  midpoint C_i), ``sub_platforms`` (upper bar C_1–C_3, lower bar C_2–C_4, screw shaft to the
  tool), ``tool`` (TCP point), ``tool_angle`` (arrow along θ) and a static ``tcp_path``.
* ``/run_info``: static text (configuration and how to read the recording).

Cost: the time series of one trial go out as ONE Arrow record batch (one column per entity,
Rerun splits it into one chunk per entity), the metrics as another; the 3D frames of the first
and last trials as a few columnar ``send_columns`` calls.  Nothing is logged per sample.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence, TextIO

import numpy as np

from host.metrics import TrialMetrics
from host.trajectory import JointReference

logger = logging.getLogger(__name__)

__all__ = ["RunRecorder", "RecordingError", "view_run", "viewer_command", "SERIES", "N_JOINTS"]

N_JOINTS = 4
#: per-joint time-series quantities (entity name, unit)
SERIES: tuple[tuple[str, str], ...] = (
    ("reference", "deg"), ("actual", "deg"), ("error", "deg"), ("torque_ff", "N·m"), ("torque_fb", "N·m"))
EXIT_USAGE = 2

_COLOR_FIRST = (255, 140, 0, 255)
_COLOR_LAST = (30, 144, 255, 255)
_REFERENCE_GREY = (150, 150, 150, 255)


class RecordingError(ValueError):
    """Bad input to the recorder (shapes that do not match the reference)."""


def _rgba_u32(c: Sequence[int]) -> int:
    r, g, b, a = (int(v) & 0xFF for v in c)
    return (r << 24) | (g << 16) | (b << 8) | a


def _iteration_color(k: int, n_expected: int | None) -> tuple[int, int, int, int]:
    """Red (first trial) → blue (last expected trial); beyond the expected count: blue."""
    n = max(int(n_expected or 10), 2)
    f = min(max(k / (n - 1), 0.0), 1.0)
    a, b = np.array([220, 50, 47]), np.array([38, 139, 210])
    r, g, bl = (a + f * (b - a)).round().astype(int)
    return int(r), int(g), int(bl), 255


class _Templates:
    """Arrow field types and Rerun metadata of the components we write, taken from rerun itself
    (a one-row chunk per archetype), so the hand-built multi-entity batches are identical to what
    ``send_columns`` / ``log`` would produce."""

    def __init__(self, rr: Any) -> None:
        from rerun.chunk import Chunk

        def fields(cols: Any, static: bool) -> dict[str, Any]:
            idx = [] if static else [rr.TimeColumn("iteration", sequence=[0])]
            schema = Chunk.from_columns("/template", indexes=idx, columns=cols).to_record_batch().schema
            return {f.name: f for f in schema if (f.metadata or {}).get(b"rerun:kind") == b"data"}

        self.scalars = fields(rr.Scalars.columns(scalars=[0.0]), static=False)["Scalars:scalars"]
        self.series_lines = fields(rr.SeriesLines.columns(names=["x"], colors=[0xFF0000FF], widths=[1.0]),
                                   static=True)
        self.series_points = fields(rr.SeriesPoints.columns(names=["x"], colors=[0xFF0000FF],
                                                            marker_sizes=[3.0]), static=True)


class _Batch:
    """Columns for many entities that share one index (or are static), sent as one record batch."""

    def __init__(self, pa: Any) -> None:
        self._pa = pa
        self.fields: list[Any] = []
        self.arrays: list[Any] = []

    def add(self, entity: str, template: Any, array: Any) -> None:
        md = dict(template.metadata or {})
        md[b"rerun:entity_path"] = entity.encode()
        self.fields.append(self._pa.field(f"{entity}:{template.name}", template.type, metadata=md))
        self.arrays.append(array)

    def send(self, rec: Any, index_name: str | None = None, index_array: Any = None) -> None:
        pa = self._pa
        if not self.fields:
            return
        fields, arrays = list(self.fields), list(self.arrays)
        if index_name is not None:
            fields.insert(0, pa.field(index_name, index_array.type, metadata={
                "rerun:index_name": index_name, "rerun:kind": "index", "rerun:is_sorted": "true"}))
            arrays.insert(0, index_array)
        rb = pa.RecordBatch.from_arrays(arrays, schema=pa.schema(fields))
        rec.send_record_batch(rb, index=index_name)
        self.fields.clear()
        self.arrays.clear()


class RunRecorder:
    """Writes ``recording.rrd`` of one run; implements :class:`host.experiment.TrialRecorder`.

    :param path: the ``.rrd`` file to write (its folder is created).
    :param application_id: Rerun application id.
    :param recording_id: Rerun recording id (default: the run folder's name).
    :param config_summary: the run's configuration (shown as ``/run_info``; ``iterations``
        sets the colour ramp of the iterations).
    :param decimate_3d: 3D frames every this many samples (≥ 1).
    """

    def __init__(self, path: str | Path, *, application_id: str = "ilcrig", recording_id: str | None = None,
                 config_summary: Mapping[str, Any] | None = None, decimate_3d: int = 5) -> None:
        import pyarrow as pa
        import rerun as rr

        if int(decimate_3d) < 1:
            raise RecordingError(f"decimate_3d must be >= 1, got {decimate_3d}")
        self._rr, self._pa = rr, pa
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.recording_id = recording_id if recording_id is not None else self.path.parent.resolve().name
        self.config_summary: dict[str, Any] = dict(config_summary or {})
        self.decimate_3d = int(decimate_3d)
        self._expected = self.config_summary.get("iterations")
        self._tpl = _Templates(rr)
        self._rec = rr.RecordingStream(application_id, recording_id=self.recording_id)
        self._rec.save(str(self.path), default_blueprint=default_blueprint())
        self._closed = False
        self.trials = 0
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None  # (t_s, q_rad, Y_guess)
        self._log_static_scene()

    # ---- TrialRecorder ------------------------------------------------------------------------

    def log_trial(self, k: int, ref: JointReference, traces: Sequence[Any], u: np.ndarray,
                  error_rad: np.ndarray, metrics: TrialMetrics) -> None:
        """Log trial ``k``: the per-joint series, its metrics and (first trial) the 3D robot.

        :param traces: one DriveTrace per joint (``q_rad``, ``tau_fb_nm``).
        :param u: (N, 4) feed-forward of trial k, N·m.  :param error_rad: (N, 4) q_d − q, rad.
        """
        if self._closed:
            raise RecordingError("log_trial after close()")
        pa = self._pa
        n = int(ref.t.shape[0])
        if len(traces) != N_JOINTS or u.shape != (n, N_JOINTS) or error_rad.shape != (n, N_JOINTS):
            raise RecordingError(f"trial {k}: expected {N_JOINTS} traces and (N, 4) arrays with N = {n}, got "
                                 f"{len(traces)} traces, u {u.shape}, error {error_rad.shape}")
        q_meas = np.stack([np.asarray(tr.q_rad, dtype=np.float64)[:n] for tr in traces], axis=1)
        tau_fb = np.stack([np.asarray(tr.tau_fb_nm, dtype=np.float64)[:n] for tr in traces], axis=1)
        if q_meas.shape != (n, N_JOINTS):
            raise RecordingError(f"trial {k}: traces have {q_meas.shape[0]} samples, the reference {n}")
        values = {
            "reference": np.degrees(ref.q),
            "actual": np.degrees(q_meas),
            "error": np.degrees(np.asarray(error_rad, dtype=np.float64)),
            "torque_ff": np.asarray(u, dtype=np.float64),
            "torque_fb": tau_fb,
        }
        t_ns = np.rint(np.asarray(ref.t, dtype=np.float64) * 1e9).astype(np.int64)
        offsets = pa.array(np.arange(n + 1, dtype=np.int32))
        data, style = _Batch(pa), _Batch(pa)
        tl = self._tpl.series_lines
        color = _rgba_u32(_iteration_color(k, self._expected))
        for j in range(N_JOINTS):
            for name, unit in SERIES:
                entity = f"/joint{j + 1}/{name}/iter{k:02d}"
                col = np.ascontiguousarray(values[name][:, j])
                data.add(entity, self._tpl.scalars, pa.ListArray.from_arrays(offsets, pa.array(col)))
                c = _rgba_u32(_REFERENCE_GREY) if name == "reference" else color
                style.add(entity, tl["SeriesLines:names"], pa.array([[f"{name} iter {k} [{unit}]"]],
                                                                    tl["SeriesLines:names"].type))
                style.add(entity, tl["SeriesLines:colors"], pa.array([[c]], tl["SeriesLines:colors"].type))
                style.add(entity, tl["SeriesLines:widths"], pa.array([[1.5]], tl["SeriesLines:widths"].type))
        style.send(self._rec)
        data.send(self._rec, "trial_time", pa.array(t_ns, pa.duration("ns")))

        met = _Batch(pa)
        for j in range(N_JOINTS):
            for key, vals in (("rmse_deg", metrics.rmse_deg), ("maxe_deg", metrics.max_abs_deg)):
                met.add(f"/metrics/{key}/joint{j + 1}", self._tpl.scalars,
                        pa.array([[float(vals[j])]], self._tpl.scalars.type))
        met.send(self._rec, "iteration", pa.array([int(k)], pa.int64()))

        step = self.decimate_3d
        idx = np.unique(np.r_[np.arange(0, n, step), n - 1])
        y_guess = None
        if ref.task is not None:
            from plant.kinematics import subplatform_from_task

            y_guess = subplatform_from_task(ref.task.X[0])
        if self.trials == 0:
            self._log_reference_path(ref)
            self._log_robot("first", ref.t[idx], q_meas[idx], y_guess, _COLOR_FIRST)
        self._last = (np.asarray(ref.t[idx], dtype=np.float64), q_meas[idx].copy(), y_guess)
        self.trials += 1

    def close(self) -> None:
        """Log the last trial's 3D robot, flush and finalise the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._last is not None:
                t, q, y_guess = self._last
                self._log_robot("last", t, q, y_guess, _COLOR_LAST)
        finally:
            self._rec.flush()
            self._rec.disconnect()
        logger.debug("recording %s: %d trials", self.path, self.trials)

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- 3D ------------------------------------------------------------------------------------

    def _log_static_scene(self) -> None:
        rr, rec = self._rr, self._rec
        from plant.params import Geometry

        g = Geometry()
        phi = np.asarray(g.azimuths_rad)
        e = np.stack([np.cos(phi), np.sin(phi), np.zeros(4)], axis=1)
        u_axis = np.stack([-np.sin(phi), np.cos(phi), np.zeros(4)], axis=1)
        A = g.R * e
        rec.log("/robot", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("/robot/base", rr.Points3D(A, radii=0.012, colors=[(90, 90, 90)],
                                           labels=[f"M{i + 1}" for i in range(4)]), static=True)
        rec.log("/robot/base/motor_axes", rr.LineStrips3D(np.stack([A - 0.04 * u_axis, A + 0.04 * u_axis], axis=1),
                                                          radii=0.006, colors=[(90, 90, 90)]), static=True)
        text = ("# ilcrig run\n\n"
                "* joint plots: timeline **trial_time**; one line per iteration (red = first, blue = last).\n"
                "* metrics (RMSE, MaxE per joint, deg): select the timeline **iteration**.\n"
                "* 3D: orange = first trial, blue = last trial, grey = reference TCP path; "
                "from the measured joint angles by forward kinematics.\n\n"
                "```json\n" + json.dumps(self.config_summary, indent=2, default=str) + "\n```\n")
        rec.log("/run_info", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        tpl_l, tpl_p, pa = self._tpl.series_lines, self._tpl.series_points, self._pa
        style = _Batch(pa)
        for key, label in (("rmse_deg", "RMSE"), ("maxe_deg", "MaxE")):
            for j in range(N_JOINTS):
                c = _rgba_u32(((228, 26, 28), (55, 126, 184), (77, 175, 74), (152, 78, 163))[j] + (255,))
                ent = f"/metrics/{key}/joint{j + 1}"
                name = f"{label} joint {j + 1} [deg]"
                style.add(ent, tpl_l["SeriesLines:names"], pa.array([[name]], tpl_l["SeriesLines:names"].type))
                style.add(ent, tpl_l["SeriesLines:colors"], pa.array([[c]], tpl_l["SeriesLines:colors"].type))
                style.add(ent, tpl_p["SeriesPoints:names"], pa.array([[name]], tpl_p["SeriesPoints:names"].type))
                style.add(ent, tpl_p["SeriesPoints:colors"], pa.array([[c]], tpl_p["SeriesPoints:colors"].type))
                style.add(ent, tpl_p["SeriesPoints:marker_sizes"],
                          pa.array([[4.0]], tpl_p["SeriesPoints:marker_sizes"].type))
        style.send(self._rec)

    def _log_reference_path(self, ref: JointReference) -> None:
        rr = self._rr
        if ref.task is not None:
            xyz = np.asarray(ref.task.X[:, :3], dtype=np.float64)
        else:
            from plant.kinematics import KinematicsError, forward_kinematics, task_from_subplatform

            try:
                xyz = task_from_subplatform(forward_kinematics(ref.q[:: self.decimate_3d]))[:, :3]
            except KinematicsError as exc:
                logger.warning("recording: no reference path in 3D: %s", exc)
                return
        self._rec.log("/robot/reference_path", rr.LineStrips3D([xyz], radii=0.0015, colors=[_REFERENCE_GREY]),
                      static=True)

    def _log_robot(self, which: str, t_s: np.ndarray, q: np.ndarray, y_guess: np.ndarray | None,
                   color: tuple[int, int, int, int]) -> None:
        """The robot skeleton at every (decimated) sample of one trial under ``/robot/{which}``."""
        from plant.kinematics import KinematicsError, forward_kinematics

        try:
            Y = forward_kinematics(q, y_guess)
        except KinematicsError as exc:
            logger.warning("recording: no 3D view of the %s trial: %s", which, exc)
            return
        rr, rec = self._rr, self._rec
        pts = skeleton_points(q, Y)
        m = q.shape[0]
        base = f"/robot/{which}"
        times = [rr.TimeColumn("trial_time", duration=np.rint(t_s * 1e9).astype(np.int64).astype("timedelta64[ns]"))]
        inner = np.stack([pts["A"], pts["B"]], axis=2).reshape(m * 4, 2, 3)
        outer = np.stack([pts["B"], pts["C"]], axis=2).reshape(m * 4, 2, 3)
        C, pu, pl, tcp = pts["C"], pts["P_up"], pts["P_low"], pts["tcp"]
        upper = np.stack([C[:, 0], pu, C[:, 2]], axis=1)
        lower = np.stack([C[:, 1], pl, C[:, 3]], axis=1)
        shaft = np.stack([pu, pl, tcp], axis=1)
        plat = np.stack([upper, lower, shaft], axis=1).reshape(m * 3, 3, 3)
        rec.send_columns(f"{base}/inner_arms", indexes=times,
                         columns=rr.LineStrips3D.columns(strips=inner).partition([4] * m))
        rec.send_columns(f"{base}/outer_arms", indexes=times,
                         columns=rr.LineStrips3D.columns(strips=outer).partition([4] * m))
        rec.send_columns(f"{base}/sub_platforms", indexes=times,
                         columns=rr.LineStrips3D.columns(strips=plat).partition([3] * m))
        rec.send_columns(f"{base}/tool", indexes=times,
                         columns=rr.Points3D.columns(positions=tcp).partition([1] * m))
        rec.send_columns(f"{base}/tool_angle", indexes=times,
                         columns=rr.Arrows3D.columns(vectors=pts["tool_dir"] * 0.05, origins=tcp).partition([1] * m))
        rec.log(f"{base}/inner_arms", rr.LineStrips3D.from_fields(radii=0.008, colors=[color]), static=True)
        rec.log(f"{base}/outer_arms", rr.LineStrips3D.from_fields(radii=0.004, colors=[color]), static=True)
        rec.log(f"{base}/sub_platforms", rr.LineStrips3D.from_fields(radii=0.006, colors=[color]), static=True)
        rec.log(f"{base}/tool", rr.Points3D.from_fields(radii=0.012, colors=[color]), static=True)
        rec.log(f"{base}/tool_angle", rr.Arrows3D.from_fields(radii=0.003, colors=[color]), static=True)
        rec.log(f"{base}/tcp_path", rr.LineStrips3D([tcp], radii=0.001, colors=[color]), static=True)


def skeleton_points(q: np.ndarray, Y: np.ndarray, geometry: Any | None = None) -> dict[str, np.ndarray]:
    """Points of the robot's skeleton (robot.md §3.1), base frame, m.

    :param q: (M, 4) joint angles, rad.  :param Y: (M, 4) sub-platform coordinates (x, y, z_u, z_l).
    :returns: ``A`` (M, 4, 3) motor-axis points, ``B`` elbows, ``C`` ball-bar midpoints, ``P_up`` /
        ``P_low`` (M, 3) sub-platform centres, ``tcp`` (M, 3), ``tool_dir`` (M, 3) unit vector at θ.
    """
    from plant.kinematics import task_from_subplatform
    from plant.params import LIMB_ON_UPPER, Geometry

    g = geometry if geometry is not None else Geometry()
    q = np.asarray(q, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    m = q.shape[0]
    phi = np.asarray(g.azimuths_rad)
    e = np.stack([np.cos(phi), np.sin(phi), np.zeros(4)], axis=1)  # (4, 3)
    k = np.array([0.0, 0.0, 1.0])
    A = np.broadcast_to(g.R * e, (m, 4, 3))
    B = A + g.l_a * (np.cos(q)[..., None] * e - np.sin(q)[..., None] * k)
    p_up = np.stack([Y[:, 0], Y[:, 1], Y[:, 2]], axis=1)
    p_low = np.stack([Y[:, 0], Y[:, 1], Y[:, 3]], axis=1)
    centre = np.where(np.asarray(LIMB_ON_UPPER)[None, :, None], p_up[:, None, :], p_low[:, None, :])
    C = centre + g.r * e
    X = task_from_subplatform(Y, g)
    tcp = X[:, :3]
    tool_dir = np.stack([np.cos(X[:, 3]), np.sin(X[:, 3]), np.zeros(m)], axis=1)
    return {"A": np.array(A), "B": B, "C": C, "P_up": p_up, "P_low": p_low, "tcp": tcp, "tool_dir": tool_dir}


def default_blueprint() -> Any:
    """The viewer layout: per-joint error / torque / position plots (tabs), the 3D robot, metrics."""
    import rerun.blueprint as rrb

    def grid(kind: str, parts: Sequence[str], unit: str) -> Any:
        return rrb.Grid(*[rrb.TimeSeriesView(origin=f"/joint{j}", contents=[f"+ /joint{j}/{p}/**" for p in parts],
                                             name=f"joint {j} {kind} [{unit}]")
                          for j in range(1, N_JOINTS + 1)], name=kind)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(grid("error", ["error"], "deg"), grid("torque", ["torque_ff", "torque_fb"], "N·m"),
                     grid("position", ["reference", "actual"], "deg")),
            rrb.Vertical(
                rrb.Tabs(rrb.Spatial3DView(origin="/robot", name="robot: first (orange) vs last (blue) trial"),
                         rrb.TextDocumentView(origin="/run_info", name="run info")),
                rrb.Horizontal(rrb.TimeSeriesView(origin="/metrics/rmse_deg", name="RMSE per iteration [deg]"),
                               rrb.TimeSeriesView(origin="/metrics/maxe_deg", name="MaxE per iteration [deg]")),
                row_shares=[3, 2]),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="trial_time"),
        collapse_panels=False)


# ---- ilcrig view ---------------------------------------------------------------------------------


def _rerun_version() -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rerun-sdk")
    except PackageNotFoundError:
        return None


def viewer_command() -> list[str] | None:
    """The command that starts the Rerun viewer here: ``rerun`` on PATH, the one next to this
    Python, or ``python -m rerun``; None if rerun-sdk is not installed."""
    exe = shutil.which("rerun")
    if exe:
        return [exe]
    sibling = Path(sys.executable).parent / "rerun"
    if sibling.is_file() and os.access(sibling, os.X_OK):
        return [str(sibling)]
    from importlib.util import find_spec

    if find_spec("rerun_cli") is not None or find_spec("rerun") is not None:
        return [sys.executable, "-m", "rerun"]
    return None


def _display_available() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view_run(run_dir: str | Path, *, stdout: TextIO | None = None, stderr: TextIO | None = None) -> int:
    """``ilcrig view RUN_DIR``: open ``RUN_DIR/recording.rrd`` in the viewer, or say how to.

    :returns: 0 (viewer spawned, or the command printed), 2 if there is no recording.
    """
    out = stdout if stdout is not None else sys.stdout
    err = stderr if stderr is not None else sys.stderr
    p = Path(run_dir)
    rrd = p if p.suffix == ".rrd" else p / "recording.rrd"
    if not rrd.is_file():
        err.write(f"ilcrig: error: no recording at {rrd}\n")
        return EXIT_USAGE
    rrd = rrd.resolve()
    cmd = viewer_command()
    if cmd is not None and _display_available():
        try:
            subprocess.Popen([*cmd, str(rrd)], stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as exc:
            logger.warning("cannot start the viewer %s: %s", cmd[0], exc)
        else:
            out.write(f"ilcrig view: opened {rrd} in the Rerun viewer ({' '.join(cmd)})\n")
            return 0
    ver = _rerun_version()
    pin = f"rerun-sdk=={ver}" if ver else "rerun-sdk"
    why = "no display ($DISPLAY / $WAYLAND_DISPLAY unset)" if cmd is not None else "no Rerun viewer installed"
    out.write(f"ilcrig view: {why}; open the recording on a machine with a display:\n"
              f"  rerun {rrd}\n"
              f"  (viewer: pip install {pin})\n")
    return 0
