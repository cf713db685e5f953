"""Every trial's signals in the run folder as numpy files, and reading them back.

This module owns the layout of ``<run>/trials/`` (written by ``ilcrig sim`` and by the host role of
``ilcrig run``, so a run's signals can be had as arrays whatever process ran it):

* ``reference.npz`` (once): ``t_s`` (N,), ``q_rad``, ``qd_rad_s``, ``qdd_rad_s2`` (N, 4) — the joint
  reference as the host planned it;
* ``trial-KKKKK.npz`` (one per trial k): the drives' recorder traces exactly as uploaded —
  ``position_counts``, ``velocity_counts_s``, ``torque_units`` (µN·m, total, after the clamp),
  ``torque_fb_units`` (µN·m, feedback), each (N, 4) int32 — and ``feedforward_nm`` (N, 4) float64,
  the table the trial played.

:class:`TrialArrays` writes them (a :class:`host.experiment.bench.TrialRecorder`; each file
written to a temporary name and renamed, so a file is whole or absent); :class:`Recorders` hands a
trial to several recorders (and says what the first of them that knows holds durably);
:func:`load_reference` and :func:`load_trial` read them back.  A trial file of N = 501 takes
48 KiB.  A failing write is one :class:`host.experiment.outputs.OutputError` (a fault of the run,
a full disk included).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bus.atomic import atomic_path
from host.experiment.outputs import RunFolder, output_error
from host.learning.metrics import TrialMetrics
from host.planning.joint_reference import JointReference

logger = logging.getLogger(__name__)

__all__ = ["TRIALS_DIR", "TRACE_CHANNELS", "TrialArrays", "Recorders", "load_reference", "load_trial", "trial_path"]

#: the folder of the arrays inside a run folder
TRIALS_DIR = "trials"
#: the recorder channels of a trial file, int32 (N, 4) each
TRACE_CHANNELS: tuple[str, ...] = ("position_counts", "velocity_counts_s", "torque_units", "torque_fb_units")


def trial_path(run_dir: str | Path, k: int) -> Path:
    """The file of trial ``k`` in the run folder ``run_dir``."""
    return Path(run_dir) / TRIALS_DIR / f"trial-{int(k):05d}.npz"


def _save(path: Path, arrays: dict[str, np.ndarray], folder: RunFolder | None, trial: int | None) -> None:
    try:
        if folder is not None:
            folder.check_write(trial)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]
    except OSError as err:
        raise output_error(str(path), err) from None


class TrialArrays:
    """Writes ``trials/`` of a run folder (module docstring); a :class:`TrialRecorder`.

    :param run_dir: the run folder
    :param folder: its space reserve and write-failure switch, if any
    """

    def __init__(self, run_dir: str | Path, folder: RunFolder | None = None) -> None:
        self.run_dir = Path(run_dir)
        self.folder = folder
        self._reference_written = False

    def log_trial(
        self, k: int, ref: JointReference, traces: Sequence[Any], u: np.ndarray, error_rad: np.ndarray, metrics: TrialMetrics
    ) -> None:
        """Write trial ``k`` (and the reference with the first trial)."""
        if not self._reference_written:
            _save(
                self.run_dir / TRIALS_DIR / "reference.npz",
                {
                    "t_s": np.asarray(ref.t, dtype=np.float64),
                    "q_rad": np.asarray(ref.q, dtype=np.float64),
                    "qd_rad_s": np.asarray(ref.qd, dtype=np.float64),
                    "qdd_rad_s2": np.asarray(ref.qdd, dtype=np.float64),
                },
                self.folder,
                k,
            )
            self._reference_written = True
        arrays = {ch: np.stack([np.asarray(getattr(tr, ch)) for tr in traces], axis=1).astype(np.int32) for ch in TRACE_CHANNELS}
        arrays["feedforward_nm"] = np.asarray(u, dtype=np.float64)
        _save(trial_path(self.run_dir, k), arrays, self.folder, k)

    def close(self) -> None:
        """Nothing to finish: every file is whole when written."""


class Recorders:
    """Hands every trial to each recorder in turn (the first failure is raised); closes them all."""

    def __init__(self, *recorders: Any) -> None:
        self.recorders = list(recorders)

    def log_trial(
        self, k: int, ref: JointReference, traces: Sequence[Any], u: np.ndarray, error_rad: np.ndarray, metrics: TrialMetrics
    ) -> None:
        for rec in self.recorders:
            rec.log_trial(k, ref, traces, u, error_rad, metrics)

    def committed(self) -> dict[str, Any] | None:
        """What the first recorder that says so holds durably (``committed()``), else None."""
        for rec in self.recorders:
            committed = getattr(rec, "committed", None)
            if committed is not None:
                state: dict[str, Any] | None = committed()
                return state
        return None

    def close(self) -> None:
        for rec in self.recorders:
            try:
                rec.close()
            except Exception:  # noqa: BLE001 - closing one recorder must not keep the others open
                logger.warning("closing %s failed", type(rec).__name__, exc_info=True)


def load_reference(run_dir: str | Path) -> dict[str, np.ndarray]:
    """``trials/reference.npz`` of a run folder: ``t_s``, ``q_rad``, ``qd_rad_s``, ``qdd_rad_s2``.

    :raises FileNotFoundError: the run wrote no trial.
    """
    with np.load(Path(run_dir) / TRIALS_DIR / "reference.npz") as z:
        return {k: z[k] for k in z.files}


def load_trial(run_dir: str | Path, k: int) -> dict[str, np.ndarray]:
    """``trials/trial-KKKKK.npz`` of trial ``k``: the recorder channels and ``feedforward_nm``.

    :raises FileNotFoundError: no such trial (yet).
    """
    with np.load(trial_path(run_dir, k)) as z:
        return {name: z[name] for name in z.files}
