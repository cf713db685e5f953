"""External joint disturbance torques per trial (the paper's §5.2, eq. (37)), N·m.

This module owns :func:`disturbance_torque`.

Interpretation of eq. (37).  The printed formula is garbled::

    τ_dis    = 2 sin(q_d) − sin(q_d)          (non-repetitive)
    τ_dis,re = λ sin(α t + φ)                 (repetitive)

The repetitive line is clear: a sinusoid of gain λ, angular frequency α and phase φ, the same
in every trial.  The non-repetitive line cannot be what was meant (it equals sin(q_d), which is
repetitive); its Fig. 9B shows an irregular torque of a few N·m that changes from trial to trial.
We therefore implement:

* ``"repetitive"``: d_j(t) = λ sin(ω t + φ_j) with λ = 2 N·m (docs/robot-model.md §5.4), ω = 2π/T_cycle
  (T_cycle = ``period_s``, default the trial length (n_ticks − 1)·Ts, i.e. the cycle
  frequency of a pick→place→pick trial) and φ_j = j·π/2 for joint j = 0..3.  Independent of
  seed and trial.
* ``"nonrepetitive"``: drawn from ``numpy.random.default_rng([seed, PURPOSE_NONREPETITIVE,
  trial])``, per joint the sum of
  (a) three sinusoids with amplitude U(0, 0.5) N·m, frequency U(0.5, 10) Hz, phase U(0, 2π), and
  (b) a band-limited random torque: white Gaussian noise through a 2nd-order Butterworth
  low-pass at 20 Hz (256 warm-up samples discarded), scaled to 0.3 N·m RMS and clipped at
  ±0.9 N·m (3σ).
  So |d_j| ≤ 2.4 N·m; every trial differs, the same (seed, trial) is bit-identical.
* ``"both"``: the sum (|d_j| ≤ 4.4 N·m); ``"none"``: zeros.

Time base: sample n is at t_n = n·Ts, n = 0..n_ticks−1 (docs/architecture.md).
"""

from __future__ import annotations

import logging
import math

import numpy as np

logger = logging.getLogger(__name__)

#: RNG purpose id of the non-repetitive disturbance (rng = default_rng([seed, this, trial]))
PURPOSE_NONREPETITIVE: int = 3701
#: the disturbance kinds accepted by :func:`disturbance_torque`
KINDS: tuple[str, ...] = ("none", "repetitive", "nonrepetitive", "both")

#: repetitive gain λ, N·m
REPETITIVE_AMPLITUDE_NM: float = 2.0
#: repetitive phase of joint j, rad
REPETITIVE_PHASES_RAD: tuple[float, float, float, float] = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)
#: non-repetitive: sinusoids per joint, amplitude bound (N·m) and frequency range (Hz)
NR_SINES: int = 3
NR_SINE_MAX_NM: float = 0.5
NR_FREQ_HZ: tuple[float, float] = (0.5, 10.0)
#: non-repetitive band-limited part: cut-off (Hz), RMS (N·m), clip (N·m)
NR_NOISE_CUTOFF_HZ: float = 20.0
NR_NOISE_RMS_NM: float = 0.3
NR_NOISE_CLIP_NM: float = 0.9
_WARMUP = 256


class DisturbanceError(ValueError):
    """Bad arguments to :func:`disturbance_torque`."""


def repetitive_torque(
    n_ticks: int, ts_s: float, amplitude_nm: float = REPETITIVE_AMPLITUDE_NM, period_s: float | None = None
) -> np.ndarray:
    """λ sin(ω t + φ_j), (n_ticks, 4) N·m, identical in every trial."""
    t = np.arange(n_ticks, dtype=np.float64) * ts_s
    T = period_s if period_s is not None else max(n_ticks - 1, 1) * ts_s
    if not T > 0.0:
        raise DisturbanceError(f"period must be > 0 s, got {T!r}")
    omega = 2.0 * math.pi / T
    phases = np.asarray(REPETITIVE_PHASES_RAD)
    return amplitude_nm * np.sin(omega * t[:, None] + phases[None, :])


def nonrepetitive_torque(seed: int, trial: int, n_ticks: int, ts_s: float) -> np.ndarray:
    """Random sinusoids + band-limited noise, (n_ticks, 4) N·m, new in every trial."""
    rng = np.random.default_rng([int(seed), PURPOSE_NONREPETITIVE, int(trial)])
    t = np.arange(n_ticks, dtype=np.float64) * ts_s
    amp = rng.uniform(0.0, NR_SINE_MAX_NM, size=(NR_SINES, 4))
    freq = rng.uniform(NR_FREQ_HZ[0], NR_FREQ_HZ[1], size=(NR_SINES, 4))
    phase = rng.uniform(0.0, 2.0 * math.pi, size=(NR_SINES, 4))
    out = np.zeros((n_ticks, 4))
    for k in range(NR_SINES):
        out += amp[k] * np.sin(2.0 * math.pi * freq[k] * t[:, None] + phase[k])
    white = rng.standard_normal(size=(n_ticks + _WARMUP, 4))
    fs = 1.0 / ts_s
    fc = min(NR_NOISE_CUTOFF_HZ, 0.4 * fs)
    from scipy import signal  # imported here: the kind names above must stay cheap to import

    b, a = signal.butter(2, fc, btype="low", fs=fs)
    colored = signal.lfilter(b, a, white, axis=0)[_WARMUP:]
    rms = np.sqrt(np.mean(colored**2, axis=0))
    rms[rms == 0.0] = 1.0
    colored = np.clip(colored * (NR_NOISE_RMS_NM / rms), -NR_NOISE_CLIP_NM, NR_NOISE_CLIP_NM)
    return out + colored


def disturbance_torque(
    kind: str,
    seed: int,
    trial: int,
    n_ticks: int,
    ts_s: float,
    *,
    amplitude_nm: float = REPETITIVE_AMPLITUDE_NM,
    period_s: float | None = None,
) -> np.ndarray:
    """External joint torque d[n] (n_ticks, 4), N·m, for one trial.

    :param kind: "none", "repetitive", "nonrepetitive" or "both"
    :param seed: experiment seed (non-repetitive part)
    :param trial: trial index k (non-repetitive part)
    :param n_ticks: number of samples N
    :param ts_s: sample period Ts, s
    :param amplitude_nm: repetitive gain λ, N·m
    :param period_s: repetitive period, s (default: the trial length (N−1)·Ts)
    """
    if kind not in KINDS:
        raise DisturbanceError(f"unknown disturbance kind {kind!r}; expected one of {', '.join(KINDS)}")
    if int(n_ticks) != n_ticks or n_ticks < 0:
        raise DisturbanceError(f"n_ticks must be a non-negative integer, got {n_ticks!r}")
    if not ts_s > 0.0:
        raise DisturbanceError(f"ts_s must be > 0, got {ts_s!r}")
    n_ticks = int(n_ticks)
    out = np.zeros((n_ticks, 4))
    if n_ticks == 0 or kind == "none":
        return out
    if kind in ("repetitive", "both"):
        out += repetitive_torque(n_ticks, ts_s, amplitude_nm, period_s)
    if kind in ("nonrepetitive", "both"):
        out += nonrepetitive_torque(seed, trial, n_ticks, ts_s)
    return out
