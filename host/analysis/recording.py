"""Rerun recordings of a run (``recording.rrd``) and ``ilcrig view``.

This module owns the layout of ``recording.rrd`` (rerun is imported lazily here and in
:mod:`host.analysis.live_view`: importing this module does not import rerun).  :class:`RunRecorder`
implements the :class:`host.experiment.trials.TrialRecorder` protocol with a *non-global*
``rr.RecordingStream`` saved to a file (no viewer, no network), and with ``--view`` also to the
live stream of :class:`host.analysis.live_view.LiveView` (loopback only).

Layout (entity paths; timelines ``trial_time`` = t_n = n·Ts as a duration, ``iteration`` = k):

* ``/joint{j}/reference``  q_d of joint j (1..4), deg — one series (the same in every trial)
* ``/joint{j}/actual/iter{k}``     measured q (encoder) in trial k, deg
* ``/joint{j}/error/iter{k}``      e = q_d − q, deg
* ``/joint{j}/torque_ff/iter{k}``  feed-forward u_k sent to the drive, N·m
* ``/joint{j}/torque_fb/iter{k}``  feedback torque recorded by the drive, N·m
  All on ``trial_time`` with N rows (one per tick), one entity per iteration; the static
  ``SeriesLines`` name it ``<quantity> iter k [unit]`` (colour red = first → blue = last
  planned trial; reference grey), so the iterations overlay as K lines under
  ``/joint{j}/<quantity>``.
* ``/metrics/rmse_deg/joint{j}``, ``/metrics/maxe_deg/joint{j}``: one row per trial on the
  ``iteration`` sequence timeline (the values of the summary, deg).
* ``/robot`` (``ViewCoordinates.RIGHT_HAND_Z_UP``, base frame, m): static ``/robot/base``
  (motor-axis points A_i), ``/robot/base/motor_axes``, ``/robot/reference_path`` (reference TCP
  path); ``/robot/first/...`` (trial 0) and ``/robot/last/...`` (the last completed trial: logged
  again after every trial, the newest rows win), on ``trial_time`` every ``decimate_3d``-th
  sample, by forward kinematics from the MEASURED joint angles: ``arms`` (4 strips A_i → elbow
  B_i → ball-bar midpoint C_i: inner then outer arm), ``sub_platforms`` (upper bar C_1–C_3,
  lower bar C_2–C_4, screw shaft down to the tool with a 5 cm blade along θ), ``tool`` (TCP
  point) and a static ``tcp_path``.
* ``/run_info``: static text (configuration and how to read the recording).

The recording grows trial by trial: :meth:`RunRecorder.log_trial` sends the trial as a few
multi-entity Arrow record batches (``send_record_batch``: one column per entity, split by Rerun
into one chunk per entity, the same chunks ``send_columns`` makes).  Nothing is logged per sample.

Durability: the recording survives whatever the summary survives
    Rerun's stream goes to a :class:`rerun.BinaryStream`, not to a file sink: after each trial the
    encoded bytes — one complete Rerun stream (header, the trial's messages, end message, footer
    index and its 32-byte trailer) — are appended to ``recording.rrd`` by :class:`SegmentFile`, which
    owns every byte of the file.  The file is always a sequence of such segments whose last trailer
    is held back (written in front of the next segment): without a trailer at its end Rerun's
    readers (``RrdReader(...).stream()``, ``rerun rrd print``, the viewer) scan the segments one
    after the other, while a trailer at the end would make them trust that one segment's index.
    An append writes the new segment behind a 32-byte gap, then the previous trailer into the
    gap, then fsyncs: a write cut short by a kill leaves either the gap (readers stop cleanly at
    the last complete trial) or a partial last segment (readers drop it); a failing write (a full
    disk) is cut back at once and the trial's bytes are kept to be written again (after the run
    folder's reserve is given back).  :meth:`RunRecorder.committed` says how many bytes hold
    complete trials (the summary keeps it as ``summary["recording"]``), and :func:`cut_back` cuts a
    file back to that length — what a process that outlives a killed host does, so the file holds
    exactly the trials of the summary.  After a run that ended without a write failure,
    :meth:`RunRecorder.close` joins the segments into one stream with Rerun's footer index
    (``rerun rrd``-style: a temporary file renamed over the recording), which readers open without
    scanning; a recording that was not joined (a killed or faulted run) is read by a scan (``RrdReader``
    warns that it has no footer).  Before a trial is written its size is checked against the
    free space of the filesystem (the previous trial's growth, ×1.5): a full disk is one
    :class:`host.experiment.outputs.DiskFullError` before the disk is filled up.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from bus.exit_codes import EXIT_USAGE
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
from host.experiment.outputs import DiskFullError, OutputError, RunFolder, output_error
from host.learning.metrics import TrialMetrics
from host.planning.trajectory import JointReference

logger = logging.getLogger(__name__)

__all__ = [
    "RunRecorder",
    "RecordingError",
    "SegmentFile",
    "cut_back",
    "view_run",
    "viewer_command",
    "SERIES",
    "N_JOINTS",
]

#: per-joint time-series quantities (entity name, unit)
SERIES: tuple[tuple[str, str], ...] = (
    ("reference", "deg"),
    ("actual", "deg"),
    ("error", "deg"),
    ("torque_ff", "N·m"),
    ("torque_fb", "N·m"),
)


#: the fixed-size trailer at the end of every Rerun stream (footer offset and length, CRC, magic,
#: version) and its magic: rerun 0.41's RRD layout
TRAILER_BYTES = 32
FOOTER_MAGIC = b"RRF2FOOT"
STREAM_MAGIC = b"RRF2"


class RecordingError(ValueError):
    """Bad input to the recorder (shapes that do not match the reference)."""


class SegmentFile:
    """``recording.rrd`` as complete Rerun streams one after the other, the last one's trailer
    held back (see the module docstring: durability).

    :param path: the file (created, or emptied)
    :ivar committed: bytes of the file that hold complete segments (the last without its trailer)
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self.committed = 0
        self._trailer = b""

    @staticmethod
    def split(segment: bytes) -> tuple[bytes, bytes]:
        """A complete Rerun stream as (everything but its trailer, its trailer).

        :raises RecordingError: not the layout of rerun 0.41 (header magic, trailer magic)
        """
        if (
            len(segment) < len(STREAM_MAGIC) + TRAILER_BYTES
            or not segment.startswith(STREAM_MAGIC)
            or segment[-12:-4] != FOOTER_MAGIC
        ):
            raise RecordingError("Rerun's encoder did not return a complete stream (an unknown RRD layout?)")
        return segment[:-TRAILER_BYTES], segment[-TRAILER_BYTES:]

    def append(self, segment: bytes) -> None:
        """Append one complete stream: its body behind a gap for the held-back trailer, then that
        trailer, fsync. On failure the file is cut back to :attr:`committed` and the error raised.

        :raises OSError: the write failed (nothing of the segment stays in the file)
        """
        body, trailer = self.split(segment)
        start = self.committed
        end = start + len(self._trailer) + len(body)
        try:
            _pwrite_all(self.fd, body, start + len(self._trailer))
            if self._trailer:
                _pwrite_all(self.fd, self._trailer, start)
            os.ftruncate(self.fd, end)  # an earlier failed attempt may have left more behind
            os.fsync(self.fd)
        except OSError:
            try:
                os.ftruncate(self.fd, start)
            except OSError as err:  # pragma: no cover - a truncation frees space, it does not need it
                logger.error("recording %s: cannot cut back to %d bytes: %s", self.path, start, err)
            raise
        self.committed, self._trailer = end, trailer

    def close(self) -> None:
        """Close the file (its last trailer stays held back; idempotent)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


def cut_back(path: str | Path, committed_bytes: int) -> bool:
    """Cut a recording back to ``committed_bytes`` (``summary["recording"]["bytes"]``) when it is
    longer and still a sequence of segments (a joined recording, which ends with Rerun's trailer,
    is left as it is). Returns whether it was cut. Never raises (a failure is logged)."""
    p = Path(path)
    try:
        with open(p, "r+b") as fh:
            size = fh.seek(0, os.SEEK_END)
            if size <= committed_bytes or committed_bytes < 0:
                return False
            fh.seek(size - 12)
            if fh.read(8) == FOOTER_MAGIC:
                return False  # joined into one stream at the end of the run
            fh.truncate(committed_bytes)
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as err:
        logger.warning("cannot cut the recording %s back to %d bytes: %s", p, committed_bytes, err)
        return False
    logger.info("recording %s cut back from %d to %d bytes (the summary's trials)", p, size, committed_bytes)
    return True


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
    :class:`host.experiment.trials.TrialRecorder`.

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
        import pyarrow as pa

        # Rerun's Rust side logs to stderr by itself (e.g. its file sink on a full disk: an ERROR
        # line); the recorder reports its failures itself (``error``, a fault), so no stray line may
        # reach the terminal.  A RUST_LOG set by the user is kept.
        os.environ.setdefault("RUST_LOG", "off")
        rerun_environment()
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

        tmp = self.path.with_name(self.path.name + ".tmp")
        size = self._file.committed
        try:
            if shutil.disk_usage(self.path.parent).free < 2 * size + self.FIRST_TRIAL_BYTES:
                logger.info("recording %s: not joined (too little free space); its segments stay", self.path)
                return
            rec = self._rr.RecordingStream(self.application_id, recording_id=self.recording_id)
            rec.save(str(tmp), default_blueprint=default_blueprint())
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the segments have no footer: read by a scan
                rec.send_chunks(RrdReader(self.path).stream())
            rec.flush()
            rec.disconnect()
            with open(tmp, "rb+") as fh:
                end = fh.seek(0, os.SEEK_END)
                fh.seek(max(0, end - 12))
                if fh.read(8) != FOOTER_MAGIC:
                    raise OSError(f"the joined recording is incomplete ({end} bytes)")
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
            self._joined, self._joined_bytes = True, end
        except Exception as exc:  # noqa: BLE001 - the segments stay: a valid recording
            logger.info("recording %s: not joined (%s); its segments stay", self.path, exc)
            with contextlib.suppress(OSError):
                tmp.unlink()

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


def default_blueprint() -> Any:
    """The viewer layout: per-joint error / torque / position plots (tabs), the 3D robot, metrics."""
    rerun_environment()
    import rerun.blueprint as rrb

    def grid(kind: str, parts: Sequence[str], unit: str) -> Any:
        return rrb.Grid(
            *[
                rrb.TimeSeriesView(
                    origin=f"/joint{j}", contents=[f"+ /joint{j}/{p}/**" for p in parts], name=f"joint {j} {kind} [{unit}]"
                )
                for j in range(1, N_JOINTS + 1)
            ],
            name=kind,
        )

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(
                grid("error", ["error"], "deg"),
                grid("torque", ["torque_ff", "torque_fb"], "N·m"),
                grid("position", ["reference", "actual"], "deg"),
            ),
            rrb.Vertical(
                rrb.Tabs(
                    rrb.Spatial3DView(origin="/robot", name="robot: first (orange) vs last (blue) trial"),
                    rrb.TextDocumentView(origin="/run_info", name="run info"),
                ),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin="/metrics/rmse_deg", name="RMSE per iteration [deg]"),
                    rrb.TimeSeriesView(origin="/metrics/maxe_deg", name="MaxE per iteration [deg]"),
                ),
                row_shares=[3, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="trial_time"),
        collapse_panels=False,
    )


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
    out.write(
        f"ilcrig view: {why}; open the recording on a machine with a display:\n  rerun {rrd}\n  (viewer: pip install {pin})\n"
    )
    return 0
