"""Results of an experiment as numpy arrays, whatever ran it.

This module owns :class:`TrialResult` (one trial: reference, actual, error, feed-forward, feedback
and total torque per joint and sample, units in the names, and its metrics), :class:`Results` (all
trials, the metrics as (K, 4) arrays and as a plain table, the run's digest, fault and convergence
check, the recording and the figures on request) and :func:`load` (the results of a run folder of
``ilcrig sim`` or ``ilcrig run``: ``summary.json`` and ``trials/``, :mod:`host.experiment.arrays`).

Sign and units (docs/learning-laws.md §1): e = q_d − q in rad; torques in N·m; the total torque is
what the drive applied (after its clamp at the torque limit), the feedback Kp·e + Kd·ė as the drive
recorded it.  Metrics in degrees (RMSE, MaxE, MAE) and N·m (peak total torque), as the summary.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import numpy.typing as npt

from bus import units
from bus.errors import InputError
from host.experiment.arrays import load_reference, load_trial
from host.experiment.outputs import end_reason_of, summary_of
from host.learning.protocol import AUXILIARY, LEARNING

logger = logging.getLogger(__name__)

__all__ = ["TrialResult", "Results", "load", "METRICS"]

Array = npt.NDArray[np.float64]

#: the per-trial metrics (per joint): RMSE, MaxE, MAE in deg, peak total torque in N·m
METRICS: tuple[str, ...] = ("rmse_deg", "max_abs_deg", "mae_deg", "peak_torque_nm")


@dataclass(frozen=True)
class TrialResult:
    """One trial (N samples, 4 joints).

    :ivar trial: its index in the run (every rollout counts)
    :ivar role: ``learning``, or ``auxiliary`` for an extra rollout a law asked for
    :ivar time_s: (N,) t_n = n·Ts
    :ivar reference_rad: (N, 4) q_d
    :ivar actual_rad: (N, 4) q from the encoders
    :ivar error_rad: (N, 4) e = q_d − q
    :ivar feedforward_nm: (N, 4) the feed-forward table played
    :ivar feedback_nm: (N, 4) the drives' feedback torque
    :ivar torque_nm: (N, 4) the total torque applied (after the drive's clamp)
    :ivar rmse_deg, max_abs_deg, mae_deg: (4,) metrics, deg
    :ivar peak_torque_nm: (4,) peak total torque, N·m
    :ivar gains: the gains the trial ran with (Kp, Kd, Lp, Ld per joint …), or empty when unknown
    """

    trial: int
    role: str
    time_s: Array
    reference_rad: Array
    actual_rad: Array
    error_rad: Array
    feedforward_nm: Array
    feedback_nm: Array
    torque_nm: Array
    rmse_deg: Array
    max_abs_deg: Array
    mae_deg: Array
    peak_torque_nm: Array
    gains: Mapping[str, Any] = field(default_factory=dict)

    @property
    def auxiliary(self) -> bool:
        """True for an auxiliary rollout."""
        return self.role == AUXILIARY

    @property
    def peak_feedforward_nm(self) -> Array:
        """(4,) peak |feed-forward| per joint, N·m (``summary.json``: ``peak_feedforward_nm``)."""
        return np.asarray(np.max(np.abs(self.feedforward_nm), axis=0), dtype=np.float64)

    @classmethod
    def from_recorder(
        cls,
        k: int,
        role: str,
        reference: Mapping[str, Array],
        channels: Mapping[str, Array],
        metrics: Mapping[str, Any],
        gains: Mapping[str, Any] | None = None,
    ) -> TrialResult:
        """A trial from the drives' integer recorder channels (:data:`host.experiment.arrays.TRACE_CHANNELS`,
        ``feedforward_nm``) and the joint reference, as the host computes them."""
        q_ref = np.asarray(reference["q_rad"], dtype=np.float64)
        actual = np.asarray(channels["position_counts"]).astype(np.float64) * units.RAD_PER_COUNT
        return cls(
            trial=int(k),
            role=role,
            time_s=np.asarray(reference["t_s"], dtype=np.float64),
            reference_rad=q_ref,
            actual_rad=actual,
            error_rad=q_ref - actual,
            feedforward_nm=np.asarray(channels["feedforward_nm"], dtype=np.float64),
            feedback_nm=np.asarray(channels["torque_fb_units"]).astype(np.float64) * units.TORQUE_LSB_NM,
            torque_nm=np.asarray(channels["torque_units"]).astype(np.float64) * units.TORQUE_LSB_NM,
            gains=dict(gains or {}),
            **{m: np.asarray(metrics[m], dtype=np.float64) for m in METRICS},
        )


class Results:
    """The trials of one run (in-process or on the rig) and what the run says about itself.

    :param summary: the run's summary (schema ``ilcrig.summary/1``)
    :param trials: the completed trials, in order
    :param out_dir: the run folder, if the run wrote one
    """

    def __init__(self, summary: Mapping[str, Any], trials: Sequence[TrialResult], out_dir: Path | None = None) -> None:
        self.summary: dict[str, Any] = dict(summary)
        self.trials: list[TrialResult] = list(trials)
        self.out_dir = out_dir

    def __len__(self) -> int:
        return len(self.trials)

    def __getitem__(self, k: int) -> TrialResult:
        return self.trials[k]

    def __repr__(self) -> str:
        state = "completed" if self.completed else (f"fault: {self.fault}" if self.fault else "incomplete")
        return f"Results({self.mode}, law {self.config.get('law')}, {len(self)} trials, {state}, digest {self.digest[:16]}…)"

    # -- the run ---------------------------------------------------------------------------------

    @property
    def mode(self) -> str:
        """``sim`` (in-process) or ``rig``."""
        return str(self.summary.get("mode", "?"))

    @property
    def config(self) -> dict[str, Any]:
        """The experiment's configuration (plus ``n_ticks``, ``trial_s``)."""
        return dict(self.summary.get("config", {}))

    @property
    def digest(self) -> str:
        """``trace_sha256`` over every trial's recorded integer traces (equal for sim and rig)."""
        return str(self.summary.get("trace_sha256", ""))

    @property
    def completed(self) -> bool:
        return bool(self.summary.get("completed"))

    @property
    def fault(self) -> str | None:
        """The fault that ended the run (one line), or None."""
        faults = self.summary.get("faults") or []
        return str(faults[0].get("message")) if faults else None

    @property
    def interrupted(self) -> bool:
        return bool(self.summary.get("interrupted"))

    @property
    def end_reason(self) -> str | None:
        """How the run ended: ``completed``, ``fault``, ``interrupted``, ``law_error``,
        ``user_exception``, ``stopped``, on the rig ``launcher_lost``, or ``writer_lost`` (the
        process that wrote the summary is gone and left it without an end: killed with nobody left
        to say so); None while it runs."""
        return end_reason_of(self.summary)

    @property
    def check(self) -> dict[str, Any]:
        """The convergence check made before the run (``checked`` False: the law gives no map)."""
        return dict(self.summary.get("convergence_check", {}))

    # -- arrays ----------------------------------------------------------------------------------

    def _stack(self, name: str) -> Array:
        if not self.trials:
            return np.zeros((0,) + ((4,) if name in METRICS else (0, 4)))
        return np.stack([np.asarray(getattr(t, name)) for t in self.trials])

    @property
    def roles(self) -> list[str]:
        return [t.role for t in self.trials]

    @property
    def auxiliary(self) -> npt.NDArray[np.bool_]:
        """(K,) True for the auxiliary rollouts."""
        return np.array([t.auxiliary for t in self.trials], dtype=bool)

    @property
    def learning(self) -> npt.NDArray[np.bool_]:
        """(K,) True for the learning trials."""
        return ~self.auxiliary

    @property
    def rmse_deg(self) -> Array:
        """(K, 4) RMSE per trial and joint, deg."""
        return self._stack("rmse_deg")

    @property
    def max_abs_deg(self) -> Array:
        """(K, 4) MaxE, deg."""
        return self._stack("max_abs_deg")

    @property
    def mae_deg(self) -> Array:
        """(K, 4) MAE, deg."""
        return self._stack("mae_deg")

    @property
    def peak_torque_nm(self) -> Array:
        """(K, 4) peak total torque, N·m."""
        return self._stack("peak_torque_nm")

    @property
    def peak_feedforward_nm(self) -> Array:
        """(K, 4) peak |feed-forward| per trial and joint, N·m."""
        return self._stack("peak_feedforward_nm") if self.trials else np.zeros((0, 4))

    @property
    def time_s(self) -> Array:
        """(N,) sample times."""
        return self.trials[0].time_s if self.trials else np.zeros(0)

    @property
    def reference_rad(self) -> Array:
        """(N, 4) the joint reference."""
        return self.trials[0].reference_rad if self.trials else np.zeros((0, 4))

    @property
    def actual_rad(self) -> Array:
        """(K, N, 4)."""
        return self._stack("actual_rad")

    @property
    def error_rad(self) -> Array:
        """(K, N, 4) e = q_d − q."""
        return self._stack("error_rad")

    @property
    def feedforward_nm(self) -> Array:
        """(K, N, 4)."""
        return self._stack("feedforward_nm")

    @property
    def feedback_nm(self) -> Array:
        """(K, N, 4)."""
        return self._stack("feedback_nm")

    @property
    def torque_nm(self) -> Array:
        """(K, N, 4) total torque applied."""
        return self._stack("torque_nm")

    @property
    def final(self) -> TrialResult:
        """The last learning trial."""
        learning = [t for t in self.trials if not t.auxiliary]
        if not learning:
            raise IndexError("no learning trial completed")
        return learning[-1]

    # -- tables ----------------------------------------------------------------------------------

    def rows(self) -> list[dict[str, Any]]:
        """One plain dict per trial: ``trial``, ``role`` and every metric per joint (``rmse_deg_j1`` …)."""
        out = []
        for t in self.trials:
            row: dict[str, Any] = {"trial": t.trial, "role": t.role}
            for m in METRICS:
                for j, v in enumerate(np.asarray(getattr(t, m)), start=1):
                    row[f"{m}_j{j}"] = float(v)
            out.append(row)
        return out

    def table(self, metrics: Sequence[str] = ("rmse_deg", "max_abs_deg")) -> str:
        """The metrics as a plain-text table, one row per trial (an auxiliary rollout marked ``aux``)."""
        for m in metrics:
            if m not in METRICS:
                raise ValueError(f"unknown metric {m!r}; choose from {', '.join(METRICS)}")
        head = ["trial"] + [f"{m} j{j}" for m in metrics for j in range(1, 5)] + ["role"]
        body = [
            [str(t.trial)] + [f"{float(v):.6g}" for m in metrics for v in getattr(t, m)] + [t.role if t.auxiliary else ""]
            for t in self.trials
        ]
        widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]
        return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths)).rstrip() for r in [head, *body]) + "\n"

    # -- files on request -----------------------------------------------------------------------

    def recording(self, path: str | Path | None = None) -> Path:
        """The Rerun recording of the run: the run folder's ``recording.rrd`` when there is one (and
        no ``path`` is given), else written to ``path`` (default ``recording.rrd`` here) from the
        trials' arrays."""
        if path is None and self.out_dir is not None and (self.out_dir / "recording.rrd").is_file():
            return self.out_dir / "recording.rrd"
        from host.analysis.recording import RunRecorder
        from host.learning.metrics import TrialMetrics
        from host.planning.joint_reference import JointReference

        target = Path(path) if path is not None else Path("recording.rrd")
        ref = JointReference(
            t=self.time_s, q=self.reference_rad, qd=np.zeros_like(self.reference_rad), qdd=np.zeros_like(self.reference_rad)
        )
        rec = RunRecorder(target, recording_id=target.stem, config_summary=self.config)
        try:
            for t in self.trials:
                traces = [SimpleNamespace(q_rad=t.actual_rad[:, j], tau_fb_nm=t.feedback_nm[:, j]) for j in range(4)]
                m = TrialMetrics(t.trial, *(tuple(float(v) for v in getattr(t, name)) for name in METRICS))
                rec.log_trial(t.trial, ref, traces, t.feedforward_nm, t.error_rad, m)
        finally:
            rec.close()
        return target

    def figures(self, folder: str | Path | None = None) -> list[Path]:
        """``report.md`` with ``convergence.png`` (RMSE per trial) and ``tracking.png`` (the error of
        the first and the last learning trial per joint) in ``folder`` (default: the run folder)."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from host.analysis.run_report import write_run_report

        d = Path(folder) if folder is not None else self.out_dir
        if d is None:
            raise ValueError("figures: give a folder (this run wrote no run folder)")
        report = write_run_report(d, self.summary)
        paths = [report, d / "convergence.png"] if (d / "convergence.png").is_file() else [report]
        learning = [t for t in self.trials if not t.auxiliary]
        if learning:
            fig = Figure(figsize=(10, 6), dpi=110)
            FigureCanvasAgg(fig)
            ax = fig.subplots(2, 2, squeeze=False)
            for j in range(4):
                a = ax[j // 2, j % 2]
                for t in (learning[0], learning[-1]):
                    a.plot(t.time_s, np.degrees(t.error_rad[:, j]), label=f"trial {t.trial}")
                a.set_title(f"joint {j + 1}")
                a.set_xlabel("t [s]")
                a.set_ylabel("e [deg]")
                a.grid(True, alpha=0.3)
                a.legend()
            fig.tight_layout()
            fig.savefig(d / "tracking.png", format="png")
            paths.append(d / "tracking.png")
        return paths


def load(run_dir: str | Path) -> Results:
    """The results of a run folder (``ilcrig sim``, ``ilcrig run``, or the API with ``out``).

    :raises InputError: no run folder there (no readable ``summary.json``), naming the path.
    """
    d = Path(run_dir)
    try:
        summary = summary_of(d)
    except FileNotFoundError:
        what = "no such folder" if not d.exists() else "not a run folder (no summary.json)"
        raise InputError(f"load: {d}: {what}") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"load: {d / 'summary.json'}: cannot be read ({exc})") from None
    its = summary.get("iterations", [])
    trials = []
    if its:
        reference = load_reference(d)
        gains = dict(summary.get("gains", {}))
        changes = {int(c["before_trial"]): c["gains"] for c in summary.get("gain_changes", [])}
        for k, it in enumerate(its):
            gains = changes.get(k, gains)
            trials.append(TrialResult.from_recorder(k, it.get("role", LEARNING), reference, load_trial(d, k), it, gains))
    return Results(summary, trials, d)
