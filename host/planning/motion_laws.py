"""The polynomial motion laws :func:`poly4567` and :func:`poly5` (docs/robot-model.md §6.3:
analytic s, s', s'', s''' on normalised time τ ∈ [0, 1]), by profile name in :data:`POLY_LAWS`.

May import: ``numpy`` only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["LawResult", "POLY_LAWS", "poly4567", "poly5"]


LawResult = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _law(tau: Any, coeffs: tuple[float, ...], first_power: int) -> LawResult:
    """Evaluate s(τ) = Σ c_k τ^(first_power+k) and its first three derivatives on τ.

    Outside [0, 1] the law is held: s = 0 before, s = 1 after, all derivatives 0.
    """
    tau = np.asarray(tau, dtype=float)
    # both laws are point-symmetric about (1/2, 1/2): evaluate on the nearer end to avoid the
    # cancellation of the coefficients near τ = 1 (s(1) is then exactly 1, s monotonic)
    upper = tau > 0.5
    x = np.clip(np.where(upper, 1.0 - tau, tau), 0.0, 1.0)
    s = np.zeros_like(x)
    s1 = np.zeros_like(x)
    s2 = np.zeros_like(x)
    s3 = np.zeros_like(x)
    for k, c in enumerate(coeffs):
        p = first_power + k
        s = s + c * x**p
        s1 = s1 + c * p * x ** (p - 1)
        s2 = s2 + c * p * (p - 1) * x ** (p - 2)
        s3 = s3 + c * p * (p - 1) * (p - 2) * x ** (p - 3)
    s = np.where(upper, 1.0 - s, s)
    s2 = np.where(upper, -s2, s2)
    inside = (tau >= 0.0) & (tau <= 1.0)
    s1 = np.where(inside, s1, 0.0)
    s2 = np.where(inside, s2, 0.0)
    s3 = np.where(inside, s3, 0.0)
    return s, s1, s2, s3


def poly4567(tau: Any) -> LawResult:
    """4-5-6-7 law s = 35τ⁴ − 84τ⁵ + 70τ⁶ − 20τ⁷ (zero velocity, acceleration and jerk at both ends).

    :param tau: normalised time t/T (scalar or array); held outside [0, 1].
    :returns: (s, s', s'', s''') derivatives with respect to τ.  Max s' = 2.1875 (τ = 0.5),
        max |s''| = 7.513 (τ = 0.2764, 0.7236), max |s'''| = 52.5 (τ = 0.5).
    """
    return _law(tau, (35.0, -84.0, 70.0, -20.0), 4)


def poly5(tau: Any) -> LawResult:
    """5th-order law s = 10τ³ − 15τ⁴ + 6τ⁵ (zero velocity and acceleration at both ends; jerk 60 there).

    :param tau: normalised time t/T (scalar or array); held outside [0, 1].
    :returns: (s, s', s'', s''').  Max s' = 1.875 (τ = 0.5), max |s''| = 5.774 (τ = 0.2113, 0.7887).
    """
    return _law(tau, (10.0, -15.0, 6.0), 3)


POLY_LAWS: dict[str, Callable[[Any], LawResult]] = {"poly4567": poly4567, "poly5": poly5}
