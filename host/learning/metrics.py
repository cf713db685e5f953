"""Tracking metrics of one trial (the paper's eq. 36) and the run's trace digest.

Errors are joint errors e = q_d − q in rad, evaluated on every recorded sample of a trial;
the metrics are reported in degrees, as in the paper's tables:

* MaxE = max |e|, MAE = mean |e|, RMSE = sqrt(mean e²) per joint.

``trace_sha256`` hashes the integer traces recorded by the drives (what actually crossed the
bus), trial by trial, drive by drive, channel by channel, as little-endian int32, so that the
in-process and the distributed modes can be compared bit for bit.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["TrialMetrics", "trial_metrics", "TraceDigest"]


@dataclass(frozen=True)
class TrialMetrics:
    """Per-joint metrics of one trial, degrees and N·m."""

    k: int
    rmse_deg: tuple[float, ...]
    max_abs_deg: tuple[float, ...]
    mae_deg: tuple[float, ...]
    peak_torque_nm: tuple[float, ...]

    def as_dict(self) -> dict:
        return {
            "k": self.k,
            "rmse_deg": list(self.rmse_deg),
            "max_abs_deg": list(self.max_abs_deg),
            "mae_deg": list(self.mae_deg),
            "peak_torque_nm": list(self.peak_torque_nm),
        }


def trial_metrics(k: int, error_rad: np.ndarray, torque_nm: np.ndarray) -> TrialMetrics:
    """Metrics of trial ``k``.

    :param error_rad: (N, J) joint errors q_d − q, rad
    :param torque_nm: (N, J) total applied torque, N·m
    """
    e_deg = np.degrees(np.asarray(error_rad, dtype=float))
    return TrialMetrics(
        k=k,
        rmse_deg=tuple(float(v) for v in np.sqrt(np.mean(e_deg**2, axis=0))),
        max_abs_deg=tuple(float(v) for v in np.max(np.abs(e_deg), axis=0)),
        mae_deg=tuple(float(v) for v in np.mean(np.abs(e_deg), axis=0)),
        peak_torque_nm=tuple(float(v) for v in np.max(np.abs(torque_nm), axis=0)),
    )


class TraceDigest:
    """Running SHA-256 over the recorded integer traces of every trial, in order."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()
        self.trials = 0

    def add_trial(self, channels_per_drive: Sequence[Iterable[np.ndarray]]) -> None:
        """Add one trial: for each drive (node order), each recorded channel (recorder order)."""
        for channels in channels_per_drive:
            for arr in channels:
                a = np.asarray(arr)
                if a.dtype.kind not in "iu":
                    raise TypeError("trace digest takes integer traces only")
                self._h.update(a.astype("<i4", copy=False).tobytes())
        self.trials += 1

    def hexdigest(self) -> str:
        return self._h.hexdigest()
