"""The Rerun recording of a run (``recording.rrd``): :class:`RunRecorder`, written trial by trial.

This module owns the recorder (rerun is imported lazily here and in :mod:`host.analysis.live_view`:
importing this module does not import rerun).  :class:`RunRecorder` implements the
:class:`host.experiment.bench.TrialRecorder` protocol with a *non-global* ``rr.RecordingStream``
saved to a file (no viewer, no network), and with ``--view`` also to the live stream of
:class:`host.analysis.live_view.LiveView` (loopback only).  What the recording holds is
:mod:`host.analysis.recording_layout` (entity paths, blueprint) and :mod:`host.analysis.recording_scene`
(Arrow batches, the 3D robot); how its bytes go to disk :mod:`host.analysis.recording_segments`
(durability: the recording survives whatever the summary survives); ``ilcrig view`` is
:mod:`host.analysis.viewer`.

The recording grows trial by trial: :meth:`RunRecorder.log_trial` sends the trial as a few
multi-entity Arrow record batches (``send_record_batch``: one column per entity, split by Rerun
into one chunk per entity, the same chunks ``send_columns`` makes).  Nothing is logged per sample.

May import: ``numpy``, ``rerun`` (lazily), :mod:`host.analysis`, :mod:`host.experiment.outputs`,
:mod:`host.learning.metrics`, :mod:`host.planning`.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bus.atomic import atomic_path
from host.analysis.recording_layout import SERIES, default_blueprint
from host.analysis.recording_scene import (
    COLOR_FIRST,
    COLOR_LAST,
    N_JOINTS,
    REFERENCE_GREY,
    Batch,
    add_robot,
    add_static_scene,
    components,
    iteration_color,
    rerun_environment,
    rgba_u32,
)
from host.analysis.recording_segments import FOOTER_MAGIC, RecordingError, SegmentFile
from host.experiment.outputs import DiskFullError, OutputError, RunFolder, output_error
from host.learning.metrics import TrialMetrics
from host.planning.joint_reference import JointReference

logger = logging.getLogger(__name__)

__all__ = ["RunRecorder"]


class _Tee:
    """Two recording streams as one: the file's (its binary stream taken already) and the live
    view's; ``log``, ``send_record_batch``, ``send_blueprint``, ``flush`` and ``disconnect`` go to both."""

    def __init__(self, file_rec: Any, live_rec: Any) -> None:
        self.file_rec, self.live_rec = file_rec, live_rec

    def _both(self, name: str, *args: Any, **kwargs: Any) -> None:
        getattr(self.file_rec, name)(*args, **kwargs)
        try:
            getattr(self.live_rec, name)(*args, **kwargs)
        except Exception:  # noqa: BLE001 - the live view must never break the recording
            logger.debug("live view: %s failed", name, exc_info=True)

    def log(self, *args: Any, **kwargs: Any) -> None:
        self._both("log", *args, **kwargs)

    def send_record_batch(self, *args: Any, **kwargs: Any) -> None:
        self._both("send_record_batch", *args, **kwargs)

    def send_blueprint(self, *args: Any, **kwargs: Any) -> None:
        self._both("send_blueprint", *args, **kwargs)

    def flush(self) -> None:
        self._both("flush")

    def disconnect(self) -> None:
        self._both("disconnect")


class RunRecorder:
    """Writes ``recording.rrd`` of one run, trial by trial; implements
    :class:`host.experiment.bench.TrialRecorder`.

    :meth:`log_trial` writes the trial (a few Arrow record batches: Rerun's cost is per entity and
    per call, not per value) and appends it to the file (module docstring: durability);
    :meth:`close` finishes it.  The stream and its file (with the default blueprint) are created
    by the constructor, so a bad path fails before the experiment starts.  :meth:`log_trial`
    raises :class:`host.experiment.outputs.OutputError` when the trial cannot be written (a full
    disk): the experiment makes that a fault, and a later :meth:`log_trial` of the same trial
    writes its kept bytes (a trial already in the file is not written twice); :meth:`close` never
    raises (a failure is logged and kept in :attr:`error`).

    :param path: the ``.rrd`` file to write (its folder is created).
    :param application_id: Rerun application id.
    :param recording_id: Rerun recording id (default: the run folder's name).
    :param config_summary: the run's configuration (shown as ``/run_info``; its ``iterations``
        sets the colour scale).
    :param decimate_3d: 3D frames every this many samples (≥ 1).
    :param folder: the run folder's write-failure switch (fault injection), if any.
    :param join: at a :meth:`close` after no failure, join the segments into one stream with
        Rerun's footer index.
    :param live: also stream the recording live (``--view``: :class:`host.analysis.live_view.LiveView`).
    """

    #: free space asked for before the first trial is written, bytes (later: the last trial's growth × 1.5)
    FIRST_TRIAL_BYTES: int = 512 * 1024

    def __init__(
        self,
        path: str | Path,
        *,
        application_id: str = "ilcrig",
        recording_id: str | None = None,
        config_summary: Mapping[str, Any] | None = None,
        decimate_3d: int = 5,
        folder: RunFolder | None = None,
        join: bool = True,
        live: Any = None,
    ) -> None:
        # Rerun's Rust side logs to stderr by itself (e.g. its file sink on a full disk: an ERROR
        # line); the recorder reports its failures itself (``error``, a fault), so no stray line may
        # reach the terminal.  A RUST_LOG set by the user is kept.
        os.environ.setdefault("RUST_LOG", "off")
        rerun_environment()
        import pyarrow as pa
        import rerun as rr
        import rerun.blueprint  # noqa: F401

        if isinstance(decimate_3d, bool) or int(decimate_3d) < 1:
            raise RecordingError(f"decimate_3d must be an integer >= 1, got {decimate_3d!r}")
        self._rr, self._pa = rr, pa
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.application_id = application_id
        self.recording_id = recording_id if recording_id is not None else self.path.parent.resolve().name
        self.config_summary: dict[str, Any] = dict(config_summary or {})
        self.decimate_3d = int(decimate_3d)
        self.folder = folder
        self.join = join
        self.error: str | None = None
        self._closed = False
        self._failed = False
        self._ref: JointReference | None = None
        self._k: list[int] = []
        self._trial_bytes = self.FIRST_TRIAL_BYTES
        self._joined = False
        self._joined_bytes = 0
        n_planned = self.config_summary.get("iterations")
        self._n_expected = int(n_planned) if isinstance(n_planned, int) else None
        self._unwritten: tuple[int, bytes] | None = None  # a trial encoded, its write failed
        self._rec: Any = rr.RecordingStream(application_id, recording_id=self.recording_id)
        self._stream = self._rec.binary_stream()  # type: ignore[misc]  # rerun's stub types it as a free function
        self._file = SegmentFile(self.path)
        self._rec.send_blueprint(default_blueprint(), make_active=False, make_default=True)
        try:
            self._append(self._encoded())
        except OSError as err:
            self._file.close()
            raise output_error(f"the recording {self.path}", err) from None
        if live is not None:
            # the live stream is a second recording stream with the same ids, on the live server's
            # sink: what is logged goes to both (the file's stream is a binary stream, which no
            # other sink can join)
            live_rec = rr.RecordingStream(application_id, recording_id=self.recording_id)
            live_rec.set_sinks(live.sink(), default_blueprint=default_blueprint())
            self._rec = _Tee(self._rec, live_rec)

    @property
    def trials(self) -> int:
        """Number of trials written so far."""
        return len(self._k)

    def committed(self) -> dict[str, Any]:
        """What the file holds durably: ``bytes`` (its length with complete segments; what
        :func:`cut_back` cuts a longer file back to), ``trials`` (their indices) and whether it was
        ``joined`` into one stream."""
        size = self._joined_bytes if self._joined else self._file.committed
        return {"file": self.path.name, "bytes": size, "trials": list(self._k), "joined": self._joined}

    def _encoded(self) -> bytes:
        """Everything logged since the last call, as one complete Rerun stream."""
        self._rec.flush()
        data = self._stream.read(flush=False)
        return bytes(data or b"")

    def _append(self, data: bytes) -> None:
        if data:
            self._file.append(data)

    # ---- TrialRecorder ------------------------------------------------------------------------

    def log_trial(
        self, k: int, ref: JointReference, traces: Sequence[Any], u: np.ndarray, error_rad: np.ndarray, metrics: TrialMetrics
    ) -> None:
        """Write trial ``k`` to the recording and flush it.

        :param traces: one DriveTrace per joint (``q_rad``, ``tau_fb_nm``).
        :param u: (N, 4) feed-forward of trial k, N·m.  :param error_rad: (N, 4) q_d − q, rad.
        :raises RecordingError: shapes that do not match the reference, or after :meth:`close`.
        :raises OutputError: the trial cannot be written (:class:`DiskFullError`: no room for it).
        """
        if self._closed:
            raise RecordingError("log_trial after close()")
        n = int(ref.t.shape[0])
        if self._ref is not None and self._ref.t.shape[0] != n:
            raise RecordingError(f"trial {k}: {n} samples, earlier trials had {self._ref.t.shape[0]}")
        u = np.array(u, dtype=np.float64)
        error_rad = np.array(error_rad, dtype=np.float64)
        if len(traces) != N_JOINTS or u.shape != (n, N_JOINTS) or error_rad.shape != (n, N_JOINTS):
            raise RecordingError(
                f"trial {k}: expected {N_JOINTS} traces and (N, 4) arrays with N = {n}, got "
                f"{len(traces)} traces, u {u.shape}, error {error_rad.shape}"
            )
        q_meas = np.stack([np.asarray(tr.q_rad, dtype=np.float64) for tr in traces], axis=1)
        tau_fb = np.stack([np.asarray(tr.tau_fb_nm, dtype=np.float64) for tr in traces], axis=1)
        if q_meas.shape != (n, N_JOINTS) or tau_fb.shape != (n, N_JOINTS):
            raise RecordingError(f"trial {k}: traces have {q_meas.shape[0]} samples, the reference {n}")
        if self._failed or int(k) in self._k:
            return  # the file is broken already (reported once), or the trial is in it
        if self.folder is None or not self.folder.released:
            self._check_space(k)  # after the reserve is given back: the final outputs are written into it
        if self._unwritten is not None and self._unwritten[0] == int(k):
            data = self._unwritten[1]  # encoded before, its write failed
        else:
            try:
                first = self._ref is None
                self._write_trial(ref, int(k), q_meas, error_rad, u, tau_fb, metrics, first)
                self._ref = ref
                data = self._encoded()
            except OutputError:
                raise
            except Exception as exc:  # noqa: BLE001 - rerun's own errors: one output fault
                self._failed = True
                self.error = f"{type(exc).__name__}: {exc}"
                raise OutputError(f"cannot write the recording {self.path}: {self.error}") from exc
        try:
            self._append(data)
        except OSError as err:
            self._unwritten = (int(k), data)
            raise output_error(f"trial {k} of the recording {self.path}", err) from None
        self._unwritten = None
        self._k.append(int(k))
        if len(data) > 0:
            self._trial_bytes = len(data)

    def close(self) -> None:
        """Update ``/run_info``, flush and finish the file (footer).  Idempotent; never raises (a
        failure is logged and kept in :attr:`error`)."""
        if self._closed:
            return
        self._closed = True
        clean = not self._failed and self._unwritten is None
        try:
            if not self._failed:
                static = Batch(self._pa)
                if self._ref is None:
                    self._write_static_scene(static)  # no trial: the scene and the run info only
                else:
                    self._add_run_info(static)
                    static.send(self._rec)
                self._append(self._encoded())
        except Exception as exc:  # noqa: BLE001 - the recording must never break the experiment
            clean = False
            self.error = self.error or f"{type(exc).__name__}: {exc}"
            logger.error("recording %s: writing failed: %s", self.path, self.error)
        finally:
            try:
                self._rec.flush()
                self._rec.disconnect()
            except Exception as exc:  # noqa: BLE001
                self.error = self.error or f"{type(exc).__name__}: {exc}"
                logger.error("recording %s: finalising failed: %s", self.path, exc)
            self._file.close()
        if clean and self.join:
            self._join()
        logger.debug("recording %s: %d trials", self.path, self.trials)

    def _join(self) -> None:
        """The segments as one Rerun stream with its footer index: written by Rerun's own file
        sink to a temporary file that replaces the recording once it is whole (on any failure the
        segments stay, which readers scan). Needs free space for a second copy."""
        import warnings

        from rerun.chunk import RrdReader

        size = self._file.committed
        if shutil.disk_usage(self.path.parent).free < 2 * size + self.FIRST_TRIAL_BYTES:
            logger.info("recording %s: not joined (too little free space); its segments stay", self.path)
            return
        try:
            with atomic_path(self.path, fsync=True, mkdir=False) as tmp:
                rec = self._rr.RecordingStream(self.application_id, recording_id=self.recording_id)
                rec.save(str(tmp), default_blueprint=default_blueprint())
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the segments have no footer: read by a scan
                    rec.send_chunks(RrdReader(self.path).stream())
                rec.flush()
                rec.disconnect()
                with open(tmp, "rb") as fh:
                    end = fh.seek(0, os.SEEK_END)
                    fh.seek(max(0, end - 12))
                    if fh.read(8) != FOOTER_MAGIC:
                        raise OSError(f"the joined recording is incomplete ({end} bytes)")
            self._joined, self._joined_bytes = True, end
        except Exception as exc:  # noqa: BLE001 - the segments stay: a valid recording
            logger.info("recording %s: not joined (%s); its segments stay", self.path, exc)

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- writing ------------------------------------------------------------------------------

    def _check_space(self, k: int) -> None:
        """Refuse to start writing trial ``k`` without room for it (:class:`DiskFullError`)."""
        need = int(1.5 * self._trial_bytes)
        try:
            if self.folder is not None:
                self.folder.check_write(k)
            free = shutil.disk_usage(self.path.parent).free
        except OSError as err:
            raise output_error(f"the recording {self.path}", err) from None
        if free < need:
            raise DiskFullError(
                f"disk full: {free // 1024} KiB free, trial {k} of the recording {self.path} needs about {need // 1024} KiB"
            )

    def _write_trial(
        self,
        ref: JointReference,
        k: int,
        q: np.ndarray,
        e: np.ndarray,
        u: np.ndarray,
        fb: np.ndarray,
        metrics: TrialMetrics,
        first: bool,
    ) -> None:
        pa, rec = self._pa, self._rec
        n = int(ref.t.shape[0])
        t_ns = pa.array(np.rint(np.asarray(ref.t, dtype=np.float64) * 1e9).astype(np.int64), pa.duration("ns"))
        comp = components()
        scal = comp["Scalars:scalars"][0]
        sl = {c: comp[c][0] for c in ("SeriesLines:names", "SeriesLines:colors")}
        static = Batch(pa)
        series = Batch(pa)
        str_list, u32_list = pa.list_(pa.utf8()), pa.list_(pa.uint32())
        off_1 = pa.array(np.arange(n + 1, dtype=np.int32))
        values = {"actual": np.degrees(q), "error": np.degrees(e), "torque_ff": u, "torque_fb": fb}
        if first:
            ref_deg = np.degrees(np.asarray(ref.q, dtype=np.float64))
            for j in range(N_JOINTS):
                ent = f"/joint{j + 1}/reference"
                series.add_array(ent, scal, pa.ListArray.from_arrays(off_1, pa.array(np.ascontiguousarray(ref_deg[:, j]))))
                static.add_array(ent, sl["SeriesLines:names"], pa.array([["reference [deg]"]], str_list))
                static.add_array(ent, sl["SeriesLines:colors"], pa.array([[rgba_u32(REFERENCE_GREY)]], u32_list))
        # names and colours of every planned iteration's lines go out once, with the first trial
        named = range(max(self._n_expected or 0, k + 1)) if first else ([] if k < (self._n_expected or 0) else [k])
        for j in range(N_JOINTS):
            for name, unit in SERIES[1:]:
                ent = f"/joint{j + 1}/{name}/iter{k}"
                col = np.ascontiguousarray(values[name][:, j])
                series.add_array(ent, scal, pa.ListArray.from_arrays(off_1, pa.array(col)))
                for i in named:
                    ent_i = f"/joint{j + 1}/{name}/iter{i}"
                    color = rgba_u32(iteration_color(i, self._n_expected))
                    static.add_array(ent_i, sl["SeriesLines:names"], pa.array([[f"{name} iter {i} [{unit}]"]], str_list))
                    static.add_array(ent_i, sl["SeriesLines:colors"], pa.array([[color]], u32_list))
        series.send(rec, "trial_time", t_ns)

        met = Batch(pa)
        f64_list = pa.list_(pa.float64())
        for key, vals in (("rmse_deg", metrics.rmse_deg), ("maxe_deg", metrics.max_abs_deg)):
            for j in range(N_JOINTS):
                met.add_array(f"/metrics/{key}/joint{j + 1}", scal, pa.array([[float(vals[j])]], f64_list))
        met.send(rec, "iteration", pa.array([k], pa.int64()))

        idx = np.unique(np.r_[np.arange(0, n, self.decimate_3d), n - 1])
        y_guess = None
        if ref.task is not None:
            from plant.kinematics import subplatform_from_task

            y_guess = subplatform_from_task(ref.task.X[0])
        robot = Batch(pa)
        views = (("first", COLOR_FIRST), ("last", COLOR_LAST)) if first else (("last", COLOR_LAST),)
        for which, c in views:
            add_robot(robot, static, which, q[idx], y_guess, c)
        if robot.fields:
            robot.send(rec, "trial_time", t_ns.take(pa.array(idx)))
        if first:
            self._write_static_scene(static, ref)
        else:
            static.send(rec)

    def _add_run_info(self, st: Batch) -> None:
        text = (
            "# ilcrig run\n\n"
            f"{self.trials} trials recorded.\n\n"
            "* joint plots: timeline **trial_time**; one line per iteration (red = first, blue = last), "
            "reference grey.\n"
            "* metrics (RMSE, MaxE per joint, deg): select the timeline **iteration**.\n"
            "* 3D: orange = first trial, blue = last trial, grey = reference TCP path; "
            "from the measured joint angles by forward kinematics.\n\n"
            "```json\n" + json.dumps(self.config_summary, indent=2, default=str) + "\n```\n"
        )
        st.put("/run_info", "TextDocument:text", [[text]])
        st.put("/run_info", "TextDocument:media_type", [["text/markdown"]])

    def _write_static_scene(self, static: Batch | None, ref: JointReference | None = None) -> None:
        st = static if static is not None else Batch(self._pa)
        self._rec.log("/robot", self._rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._add_run_info(st)
        add_static_scene(st, ref if ref is not None else self._ref, self.decimate_3d)
        st.send(self._rec)
