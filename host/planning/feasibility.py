"""The feasibility check of a joint reference before anything moves: joint range, joint speed and
the nominal inverse-dynamics torque against :class:`JointLimits` (:func:`check_feasibility` →
:class:`FeasibilityReport`; :class:`host.planning.planning_errors.InfeasibleTaskError` otherwise).

May import: ``numpy``, ``plant`` (params, dynamics: inside functions), :mod:`host.planning`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.planning.joint_reference import JointReference
from host.planning.planning_errors import InfeasibleTaskError, TrajectoryError

logger = logging.getLogger(__name__)

__all__ = ["FeasibilityReport", "JointLimits", "check_feasibility"]


@dataclass(frozen=True)
class JointLimits:
    """Joint-side limits checked before anything moves.

    Defaults: speed and torque from the plant's drive train (``plant.params.TruePlantConfig``:
    5000 rpm / n = 52.4 rad/s, n·η·τ_peak = 264.6 N·m), 90 % torque margin, joint range
    −20°..80° [P] (q = 0 arm horizontal, 90° straight down; the built-in paths use 4°..60°).

    :param qd_max_rad_s: max |q̇| per joint, rad/s.
    :param tau_max_nm: drive torque limit (joint side), N·m.
    :param tau_margin: fraction of ``tau_max_nm`` the nominal inverse dynamics may use.
    :param q_min_rad: lowest joint angle, rad.
    :param q_max_rad: highest joint angle, rad.
    """

    qd_max_rad_s: float = field(default_factory=lambda: _plant_limits()[0])
    tau_max_nm: float = field(default_factory=lambda: _plant_limits()[1])
    tau_margin: float = 0.9
    q_min_rad: float = math.radians(-20.0)
    q_max_rad: float = math.radians(80.0)

    def __post_init__(self) -> None:
        if not (self.qd_max_rad_s > 0 and self.tau_max_nm > 0 and 0 < self.tau_margin <= 1):
            raise TrajectoryError("JointLimits: speed and torque limits must be > 0, margin in (0, 1]")
        if not self.q_min_rad < self.q_max_rad:
            raise TrajectoryError("JointLimits: q_min_rad must be below q_max_rad")


def _plant_limits() -> tuple[float, float]:
    """(joint speed limit rad/s, joint torque limit N·m) of the plant's drive train."""
    from plant.params import TruePlantConfig

    cfg = TruePlantConfig()
    return cfg.joint_speed_limit_rad_s, cfg.joint_torque_limit_nm


@dataclass(frozen=True)
class FeasibilityReport:
    """Peaks of a joint reference: torque (N·m), speed (rad/s), angle range (rad), per joint."""

    peak_tau_nm: tuple[float, ...]
    rms_tau_nm: tuple[float, ...]
    peak_qd_rad_s: tuple[float, ...]
    q_min_rad: tuple[float, ...]
    q_max_rad: tuple[float, ...]
    tau_limit_nm: float
    qd_limit_rad_s: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (for summary.json)."""
        return {
            "peak_tau_nm": list(self.peak_tau_nm),
            "rms_tau_nm": list(self.rms_tau_nm),
            "peak_qd_rad_s": list(self.peak_qd_rad_s),
            "q_min_deg": [math.degrees(v) for v in self.q_min_rad],
            "q_max_deg": [math.degrees(v) for v in self.q_max_rad],
            "tau_limit_nm": self.tau_limit_nm,
            "qd_limit_rad_s": self.qd_limit_rad_s,
        }

    def format(self) -> str:
        """A few lines for the CLI."""
        f = lambda xs, k=1.0, d=1: " ".join(f"{k * x:7.{d}f}" for x in xs)  # noqa: E731
        return "\n".join(
            [
                f"peak |tau| N·m  {f(self.peak_tau_nm)}   (limit {self.tau_limit_nm:.1f})",
                f"rms tau N·m     {f(self.rms_tau_nm)}",
                f"peak |qd| rad/s {f(self.peak_qd_rad_s, d=2)}   (limit {self.qd_limit_rad_s:.1f})",
                "q min..max deg  "
                + " ".join(f"{math.degrees(a):.1f}..{math.degrees(b):.1f}" for a, b in zip(self.q_min_rad, self.q_max_rad)),
            ]
        )


def check_feasibility(ref: JointReference, model: Any, limits: JointLimits | None = None) -> FeasibilityReport:
    """Check a joint reference against joint range, speed and torque limits.

    Order: joint range, joint speed, torque.  The torque is the nominal inverse dynamics
    τ = M q̈ + C q̇ + G at every sample (``plant.dynamics.inverse_dynamics`` with ``model``),
    compared with ``tau_margin · tau_max_nm``.  (Reach was checked by :func:`joint_reference`.)

    :param ref: joint reference.
    :param model: ``plant.params.MassModel`` (normally ``nominal_mass_model()``).
    :param limits: joint limits (default :class:`JointLimits`, from the plant's drive train).
    :returns: peaks per joint, for the CLI and summary.json.
    :raises InfeasibleTaskError: one-line message naming the joint, the value, the limit and t.
    """
    from plant.dynamics import inverse_dynamics

    lim = limits if limits is not None else JointLimits()
    where = ""
    if ref.task is not None:
        where = f"{ref.task.path.name} ({ref.task.profile}, {ref.task.cycle_s:g} s): "

    q_lo = ref.q.min(axis=0)
    q_hi = ref.q.max(axis=0)
    for j in range(4):
        if q_lo[j] < lim.q_min_rad:
            n = int(np.argmin(ref.q[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} angle {math.degrees(q_lo[j]):.1f} deg is below the range limit "
                f"{math.degrees(lim.q_min_rad):.1f} deg at t = {ref.t[n]:.3f} s"
            )
        if q_hi[j] > lim.q_max_rad:
            n = int(np.argmax(ref.q[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} angle {math.degrees(q_hi[j]):.1f} deg is above the range limit "
                f"{math.degrees(lim.q_max_rad):.1f} deg at t = {ref.t[n]:.3f} s"
            )

    qd_abs = np.abs(ref.qd)
    qd_peak = qd_abs.max(axis=0)
    for j in range(4):
        if qd_peak[j] > lim.qd_max_rad_s:
            n = int(np.argmax(qd_abs[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} speed {qd_peak[j]:.2f} rad/s exceeds the limit "
                f"{lim.qd_max_rad_s:.2f} rad/s at t = {ref.t[n]:.3f} s"
            )

    tau = np.asarray(inverse_dynamics(ref.q, ref.qd, ref.qdd, model))
    tau_abs = np.abs(tau)
    tau_peak = tau_abs.max(axis=0)
    tau_allowed = lim.tau_margin * lim.tau_max_nm
    for j in range(4):
        if tau_peak[j] > tau_allowed:
            n = int(np.argmax(tau_abs[:, j]))
            raise InfeasibleTaskError(
                f"{where}joint {j + 1} peak torque {tau_peak[j]:.1f} N·m exceeds the limit "
                f"{tau_allowed:.1f} N·m ({lim.tau_margin:g} × {lim.tau_max_nm:.1f} N·m) "
                f"at t = {ref.t[n]:.3f} s"
            )

    report = FeasibilityReport(
        peak_tau_nm=tuple(float(v) for v in tau_peak),
        rms_tau_nm=tuple(float(v) for v in np.sqrt(np.mean(tau**2, axis=0))),
        peak_qd_rad_s=tuple(float(v) for v in qd_peak),
        q_min_rad=tuple(float(v) for v in q_lo),
        q_max_rad=tuple(float(v) for v in q_hi),
        tau_limit_nm=float(tau_allowed),
        qd_limit_rad_s=float(lim.qd_max_rad_s),
    )
    logger.debug("feasibility %s", report.as_dict())
    return report
