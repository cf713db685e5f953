"""The definitions the sweep's verdicts measure an RMSE history with (pure functions, no I/O).

An RMSE history r[k, j] holds the RMSE of joint j in trial k, deg; k = 0 is the first trial,
before any learning; the *final* RMSE is the last trial's.

* **settle iteration**: the first trial k from which every joint stays within
  :data:`SETTLE_FACTOR` (2×) of its final RMSE, r_final/2 ≤ r[i, j] ≤ 2·r_final for all i ≥ k
  (:func:`settle_iteration`; per joint :func:`settle_iterations`).
* **floor**: the mean RMSE per joint over the trials from the settle iteration on
  (:func:`settled_floor`).  Under a disturbance that changes from trial to trial one trial's RMSE
  is a random sample that scatters by more than 2× around the floor, so a disturbed run has no
  settle iteration of its own: it takes the one of the same experiment without disturbance (the
  learning transient is the law's; the disturbance only adds scatter), given as ``settle``.
* **block windows** of a long run: moving means over ``block`` trials of the RMSE averaged over
  joints; the best window after settling (it starts at the settle iteration or later) and the last
  window (:func:`settled_windows`).  A long run's settle iteration is the one over the paper's
  horizon (its first trials, as many as the short runs have): over the whole run a law that grows
  again would "settle" onto its grown final value.
* **repeatable / non-repeatable error** of a run over its last L = min(:data:`SPLIT_TRIALS`, K)
  trials: r[n] = mean_k e_k[n] is the repeatable part (what a further learning trial could still
  remove), e_k[n] − r[n] the non-repeatable part (what changes from trial to trial and no ILC can
  learn); each an RMS in deg, the latter with the unbiased factor √(L/(L−1))
  (:func:`split_repeatable`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from host.analysis.markdown import Floats

logger = logging.getLogger(__name__)

__all__ = [
    "SETTLE_FACTOR",
    "SPLIT_TRIALS",
    "SettledFloor",
    "history",
    "settle_iteration",
    "settle_iterations",
    "settled_floor",
    "block_means",
    "SettledWindows",
    "settled_windows",
    "split_repeatable",
]

#: settled = within this factor of the final RMSE, above and below
SETTLE_FACTOR = 2.0
#: trials the repeatable / non-repeatable split averages over
SPLIT_TRIALS = 4


def history(rmse: np.ndarray | Floats) -> np.ndarray:
    """An RMSE history as a (K, J) float array (a 1-D sequence is one joint).

    :raises ValueError: no trial.
    """
    h = np.asarray(rmse, dtype=float)
    h = h.reshape(len(h), -1) if h.ndim != 2 else h
    if h.shape[0] == 0:
        raise ValueError("an RMSE history needs at least one trial")
    return h


def _inside(h: np.ndarray, factor: float) -> np.ndarray:
    """(K, J) bool: r[k, j] within ``factor``× of r[K−1, j], above and below."""
    final = h[-1]
    return (h <= factor * final) & (factor * h >= final)


def settle_iterations(rmse: np.ndarray | Floats, factor: float = SETTLE_FACTOR) -> list[int]:
    """Per joint: the first k from which r[i, j] stays within ``factor``× of r[K−1, j] for all i ≥ k."""
    h = history(rmse)
    ks = []
    for j in range(h.shape[1]):
        outside = np.nonzero(~_inside(h[:, j : j + 1], factor)[:, 0])[0]
        ks.append(int(outside[-1] + 1) if outside.size else 0)
    return ks


def settle_iteration(rmse: np.ndarray | Floats, factor: float = SETTLE_FACTOR) -> int:
    """The first k from which every joint stays within ``factor``× of its final RMSE (module doc)."""
    return max(settle_iterations(rmse, factor))


@dataclass(frozen=True)
class SettledFloor:
    """The floor of an RMSE history: ``floor_deg`` (per joint) is the mean RMSE over the trials
    ``settle`` … K−1 (``trials`` = K − ``settle`` of them)."""

    floor_deg: np.ndarray
    settle: int
    trials: int


def settled_floor(rmse: np.ndarray | Floats, settle: int | None = None, factor: float = SETTLE_FACTOR) -> SettledFloor:
    """Mean RMSE per joint over the trials from the settle iteration on (module doc).

    :param settle: the settle iteration to use (a disturbed run: the one of its run without
        disturbance; clamped to the last trial); None = the history's own.
    """
    h = history(rmse)
    k = settle_iteration(h, factor) if settle is None else min(max(settle, 0), h.shape[0] - 1)
    return SettledFloor(h[k:].mean(axis=0), k, h.shape[0] - k)


def block_means(values: np.ndarray | Floats, block: int) -> np.ndarray:
    """Moving mean over ``block`` consecutive trials: element i = mean(values[i : i + block])."""
    v = np.asarray(values, dtype=float)
    return np.convolve(v, np.ones(block) / block, mode="valid")


@dataclass(frozen=True)
class SettledWindows:
    """Block means (RMSE averaged over joints, deg) of a long run: the settle iteration, the best
    ``block``-trial window starting at it or later (``best_start`` None when fewer than ``block``
    trials follow the settle iteration; ``best_mean_deg`` is then NaN) and the last window."""

    settle: int
    best_start: int | None
    best_mean_deg: float
    last_mean_deg: float


def settled_windows(rmse: np.ndarray | Floats, block: int, settle: int) -> SettledWindows:
    """The best ``block``-trial window starting at ``settle`` or later and the last one
    (:class:`SettledWindows`).

    :param settle: the settle iteration (module doc: over the paper's horizon for a long run, of
        the run without disturbance for a disturbed one)
    :raises ValueError: fewer than ``block`` trials.
    """
    h = history(rmse)
    if h.shape[0] < block:
        raise ValueError(f"needs at least {block} trials, got {h.shape[0]}")
    k_s = max(settle, 0)
    means = block_means(h.mean(axis=1), block)
    if h.shape[0] - k_s < block:
        return SettledWindows(k_s, None, float("nan"), float(means[-1]))
    best = k_s + int(np.argmin(means[k_s:]))
    return SettledWindows(k_s, best, float(means[best]), float(means[-1]))


def split_repeatable(errors_rad: np.ndarray, last: int = SPLIT_TRIALS) -> tuple[np.ndarray, np.ndarray]:
    """(repeatable RMS, non-repeatable RMS) per joint in deg over the last ``last`` trials.

    :param errors_rad: (K, N, J) errors q_d − q per trial, rad
    :raises ValueError: not a (K, N, J) array with K ≥ 1.
    """
    e = np.degrees(np.asarray(errors_rad, dtype=float))
    if e.ndim != 3 or e.shape[0] == 0:
        raise ValueError(f"errors must be (K, N, J) with K >= 1, got shape {e.shape}")
    n = min(last, e.shape[0])
    tail = e[-n:]
    rep = tail.mean(axis=0)
    rep_rms = np.sqrt(np.mean(rep**2, axis=0))
    if n < 2:
        return rep_rms, np.full(e.shape[2], np.nan)
    res = tail - rep
    nonrep = np.sqrt(np.mean(res**2, axis=(0, 1)) * n / (n - 1))
    return rep_rms, nonrep
