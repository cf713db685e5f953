"""Time operators on trial signals: the one-sample lead, the backward difference, the zero-phase
Q-filter — each with its transpose, so the convergence check can use them matrix-free.

Every signal is an (N, J) array, time along axis 0 (N samples at Ts, J joints); the operators act
on every joint alike.  The forward functions are the ones the laws apply between trials (their
arithmetic is fixed: the trace digest of a run depends on it); the ``*_t`` functions are the exact
transposes of the same linear maps (tests compare both with dense matrices on small N).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import numpy.typing as npt

logger = logging.getLogger(__name__)

__all__ = ["lead", "lead_t", "backward_difference", "backward_difference_t", "ZeroPhaseFilter"]

Array = npt.NDArray[np.float64]


def _scipy_signal() -> Any:
    """``scipy.signal``, imported on first use: it takes about 1 s to import, and a bad input must
    be refused before that (the CLI's checks import this module)."""
    from scipy import signal

    return signal


def backward_difference(x: Array, ts_s: float) -> Array:
    """(x[n] − x[n−1])/Ts along axis 0, with 0 at n = 0 (the trial starts aligned); units of x per s."""
    d = np.zeros_like(x, dtype=float)
    d[1:] = (x[1:] - x[:-1]) / ts_s
    return d


def backward_difference_t(y: Array, ts_s: float) -> Array:
    """Transpose of :func:`backward_difference`: x[n] = (y[n] − y[n+1])/Ts for 1 ≤ n < N−1,
    x[0] = −y[1]/Ts, x[N−1] = y[N−1]/Ts."""
    y = np.asarray(y, dtype=float)
    x = np.zeros_like(y)
    x[1:] += y[1:] / ts_s
    x[:-1] -= y[1:] / ts_s
    return x


def lead(x: Array, m: int) -> Array:
    """Non-causal shift by m samples along axis 0: y[n] = x[n+m], the last value repeated."""
    if m == 0:
        return np.array(x, dtype=float, copy=True)
    return np.concatenate([x[m:], np.repeat(x[-1:], m, axis=0)], axis=0)


def lead_t(y: Array, m: int) -> Array:
    """Transpose of :func:`lead`: x[n] = y[n−m] for m ≤ n < N−1; x[N−1] collects y[N−1−m..N−1]."""
    y = np.asarray(y, dtype=float)
    if m == 0:
        return y.copy()
    n = y.shape[0]
    x = np.zeros_like(y)
    if m >= n:
        x[-1] = y.sum(axis=0)
        return x
    x[m:] = y[: n - m]
    x[-1] += y[n - m :].sum(axis=0)
    return x


class ZeroPhaseFilter:
    """Zero-phase low-pass Q: a Butterworth filter run forward and backward (``scipy.signal.filtfilt``
    with odd padding of ``3·max(len(a), len(b))`` samples, at most N − 1), and its exact transpose.

    ``cutoff_hz`` is the −3 dB frequency of one pass (the zero-phase gain there is ½); the filter is
    linear in the signal (the edge initial conditions scale with the first sample), so its transpose
    is built from the same pieces in reverse order.
    """

    def __init__(self, cutoff_hz: float, order: int, ts_s: float) -> None:
        nyq_hz = 0.5 / ts_s
        if not 0 < cutoff_hz < nyq_hz:
            raise ValueError(f"Q-filter cut-off must be in (0, {nyq_hz:g}) Hz, got {cutoff_hz}")
        if order < 1:
            raise ValueError(f"Q-filter order must be >= 1, got {order}")
        self.cutoff_hz, self.order, self.ts_s = float(cutoff_hz), int(order), float(ts_s)
        signal = _scipy_signal()
        self.b, self.a = signal.butter(order, cutoff_hz / nyq_hz)
        self._zi = signal.lfilter_zi(self.b, self.a)
        self._free: dict[int, Array] = {}

    def padlen(self, n: int) -> int:
        return min(3 * max(len(self.a), len(self.b)), n - 1)

    def __call__(self, x: Array) -> Array:
        """Q x along axis 0 (what the laws apply)."""
        signal = _scipy_signal()
        return np.asarray(signal.filtfilt(self.b, self.a, x, axis=0, padtype="odd", padlen=self.padlen(x.shape[0])))

    # -- transpose ------------------------------------------------------------------------------

    def _free_response(self, n: int) -> Array:
        """Response of one pass to the initial state ``zi`` with zero input (length n)."""
        if n not in self._free:
            self._free[n] = _scipy_signal().lfilter(self.b, self.a, np.zeros(n), zi=self._zi)[0]
        return self._free[n]

    def _pass_t(self, w: Array) -> Array:
        """Transpose of one pass y = lfilter(b, a, v, zi=zi·v[0]) (along axis 0)."""
        out = _scipy_signal().lfilter(self.b, self.a, w[::-1], axis=0)[::-1]
        out[0] += self._free_response(w.shape[0]) @ w
        return np.asarray(out)

    def transpose(self, y: Array) -> Array:
        """Qᵀ y along axis 0."""
        y = np.asarray(y, dtype=float)
        n = y.shape[0]
        p = self.padlen(n)
        if n <= 1:  # filtfilt needs more samples than the padding: nothing to transpose
            return y.copy()
        w = np.zeros((n + 2 * p,) + y.shape[1:])
        w[p : p + n] = y  # crop^T
        w = w[::-1]  # the second pass ran on the reversed signal and was reversed back
        w = self._pass_t(w)
        w = w[::-1]
        w = self._pass_t(w)
        # pad^T: ext = [2x0 − x[p..1], x, 2x[-1] − x[-2..-p-1]]
        x = w[p : p + n].copy()
        if p > 0:
            left, right = w[:p], w[p + n :]
            x[0] += 2.0 * left.sum(axis=0)
            x[1 : p + 1] -= left[::-1]
            x[-1] += 2.0 * right.sum(axis=0)
            x[n - 1 - p : n - 1] -= right[::-1]
        return x
