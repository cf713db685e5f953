"""Gains of the learning laws and the drive's feedback: what the user gives, presets, and their
normalisation to the plant.

This module owns :class:`GainSpec` (the ``[gains]`` table / ``--alpha`` … options), the presets
:data:`GAIN_PRESETS`, :class:`Gains` (per-joint values in SI units) and :func:`resolve_gains`.

Normalisation (one preset fits every joint and sample time): with I_j the mean nominal joint
inertia along the trajectory (kg·m²) and Ts the control period (s),

    Lp_j = lp_norm · I_j / Ts²  (N·m/rad)        Ld_j = ld_norm · I_j / Ts  (N·m·s/rad)
    Kp_j = (α − 1) · Lp_j       (N·m/rad)        Kd_j = (β − 1) · Ld_j       (N·m·s/rad)

Kp, Kd run in the drive (the paper's feedback, eq. 10, taken as printed); Lp, Ld are the learning
gains.  Absolute ``lp``/``ld`` (the same for every joint) override the normalised values.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from host.learning.names import GAIN_PRESET_NAMES

logger = logging.getLogger(__name__)

__all__ = ["GAIN_PRESETS", "GainSpec", "Gains", "resolve_gains"]


@dataclass(frozen=True)
class GainSpec:
    """Gains as the user gives them: α, β and learning gains, absolute or normalised, and the
    parameters of the filtered and model-based laws.

    Exactly one of (lp, lp_norm) and one of (ld, ld_norm) is used: absolute values (N·m/rad,
    N·m·s/rad, the same for every joint) win when given.
    """

    #: α of the paper's law: feedback Kp = (α − 1)·Lp (dimensionless, ≥ 1)
    alpha: float = 3.0
    #: β of the paper's law: feedback Kd = (β − 1)·Ld (dimensionless, ≥ 1)
    beta: float = 3.0
    #: Lp·Ts²/I_j (dimensionless)
    lp_norm: float = 0.001
    #: Ld·Ts/I_j (dimensionless)
    ld_norm: float = 0.15
    #: absolute learning P gain, N·m/rad (overrides lp_norm)
    lp: float | None = None
    #: absolute learning D gain, N·m·s/rad (overrides ld_norm)
    ld: float | None = None
    #: learning lead, samples
    lead: int = 1
    #: cut-off of the zero-phase Q filter of ``q-ilc``, Hz (one pass, −3 dB)
    q_cutoff_hz: float = 150.0
    #: Butterworth order of the Q filters (one pass)
    q_order: int = 2
    #: cut-off of the zero-phase Q filter of ``pd-ilc-q`` (the paper's law, robust form), Hz
    pdq_cutoff_hz: float = 40.0
    #: weight of the input change in the norm-optimal laws, relative to the largest squared
    #: column norm of G (dimensionless).  1e-5: smaller weights invert G further into the high
    #: frequencies, where the model is wrong (Coulomb reversals) and the error is encoder noise, and
    #: the error grows again after a few trials (the 0.5 s anomaly, docs/learning-laws.md §8)
    no_weight: float = 1e-5
    name: str = "normalized"


#: named gain presets; ``paper`` are the paper's literal numbers (which do not transfer here)
GAIN_PRESETS: dict[str, GainSpec] = {
    "normalized": GainSpec(),
    "paper": GainSpec(alpha=1.1, beta=1.22, lp=1000.0, ld=230.0, name="paper"),
}
assert tuple(GAIN_PRESETS) == GAIN_PRESET_NAMES, "host.learning.names.GAIN_PRESET_NAMES is out of date"


@dataclass(frozen=True)
class Gains:
    """Per-joint gains in SI units after normalisation."""

    kp: npt.NDArray[np.float64]  #: feedback, N·m/rad
    kd: npt.NDArray[np.float64]  #: feedback, N·m·s/rad
    lp: npt.NDArray[np.float64]  #: learning, N·m/rad
    ld: npt.NDArray[np.float64]  #: learning, N·m·s/rad
    inertia: npt.NDArray[np.float64]  #: mean nominal joint inertia, kg·m²
    spec: GainSpec = field(default_factory=GainSpec)

    def as_dict(self) -> dict[str, Any]:
        return {
            "preset": self.spec.name,
            "alpha": self.spec.alpha,
            "beta": self.spec.beta,
            "lead": self.spec.lead,
            "kp_nm_per_rad": self.kp.tolist(),
            "kd_nms_per_rad": self.kd.tolist(),
            "lp_nm_per_rad": self.lp.tolist(),
            "ld_nms_per_rad": self.ld.tolist(),
            "inertia_kgm2": self.inertia.tolist(),
        }


def resolve_gains(spec: GainSpec, inertia: npt.ArrayLike, ts_s: float) -> Gains:
    """Turn a :class:`GainSpec` into per-joint gains for joint inertias ``inertia`` (kg·m²) and the
    control period ``ts_s`` (s).  Raises ``ValueError`` (one line) on a value that cannot run."""
    inertia_kgm2 = np.asarray(inertia, dtype=float)
    for name in ("alpha", "beta", "lp_norm", "ld_norm", "q_cutoff_hz", "pdq_cutoff_hz", "no_weight"):
        v = getattr(spec, name)
        if not math.isfinite(v):
            raise ValueError(f"gain {name} must be a finite number, got {v}")
    for name in ("lp", "ld"):
        v = getattr(spec, name)
        if v is not None and (not math.isfinite(v) or v < 0):
            raise ValueError(f"gain {name} must be a finite number >= 0, got {v}")
    if spec.alpha < 1 or spec.beta < 1:
        raise ValueError(f"alpha and beta must be >= 1 (feedback (alpha-1)Lp must be >= 0), got {spec.alpha}, {spec.beta}")
    if spec.lead < 0:
        raise ValueError(f"lead must be >= 0 samples, got {spec.lead}")
    lp = np.full(4, spec.lp) if spec.lp is not None else spec.lp_norm * inertia_kgm2 / ts_s**2
    ld = np.full(4, spec.ld) if spec.ld is not None else spec.ld_norm * inertia_kgm2 / ts_s
    return Gains(kp=(spec.alpha - 1.0) * lp, kd=(spec.beta - 1.0) * ld, lp=lp, ld=ld, inertia=inertia_kgm2, spec=spec)
