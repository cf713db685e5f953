"""Float64 twin of the drive's control law (tests only).

Owns the reference implementation the fixed-point kernel
(:func:`firmware_model.control_law.control_tick`) is checked against: the same law, in the
same units (counts, counts/s, µN·m), with real-valued gains and no rounding or
saturation (tests keep inputs inside the int32 ranges): the PD loop (:class:`FirmwareTwin`) and
the cascade of 0x2110:4 = 1 (:class:`CascadeTwin`).  See the laws in :mod:`bus.fixedpoint`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bus import fixedpoint as fp


@dataclass(frozen=True)
class TwinParams:
    """kp µN·m/count, kd µN·m/(count/s), alpha (0, 1], rate_hz 1/Ts, limit µN·m."""

    kp: float
    kd: float
    alpha: float
    rate_hz: float
    limit: float

    @classmethod
    def from_fixed(cls, kp_q16: int, kd_q16: int, a_q15: int, period_us: int, limit_units: int) -> TwinParams:
        """The exact real values the drive's integer parameters stand for."""
        return cls(
            kp=kp_q16 / (1 << fp.KP_Q),
            kd=kd_q16 / (1 << fp.KD_Q),
            alpha=a_q15 / (1 << fp.VEL_FILTER_Q),
            rate_hz=1e6 / period_us,
            limit=float(limit_units),
        )

    def torque_bound_units(self) -> float:
        """Worst-case |τ_fixed − τ_twin| in µN·m, derived from the formats.

        * filter state: each update rounds by <= 1/2 LSB of Q12; the error contracts by
          (1 − α) per tick, so |δv_f| <= 0.5 / α Q12 LSB = 1 / (8192 α) counts/s;
        * v_est is that state rounded to counts/s: another <= 0.5 counts/s;
        * so |δė| <= 0.5 + 1/(8192 α) counts/s, times Kd;
        * the accumulator (Kp·e + Kd·ė, exact in int64) is rounded once: <= 0.5 µN·m;
        * + ff is exact, the clamp is 1-Lipschitz.
        Plus a float64 allowance of 1e-9 relative to the largest term.
        """
        return self.kd * self.velocity_bound() + 0.5

    def velocity_bound(self) -> float:
        """Worst-case |v_est_fixed − v_twin| in counts/s."""
        return 0.5 + 1.0 / (8192.0 * self.alpha)


class FirmwareTwin:
    """The control law in float64 (state: previous count, filter state)."""

    def __init__(self, params: TwinParams) -> None:
        self.p = params
        self.prev: float | None = None
        self.vf = 0.0

    def reset_estimator(self, v0_counts_s: float = 0.0) -> None:
        """No previous count; filter state = v0 (trial start: the reference velocity)."""
        self.prev = None
        self.vf = float(v0_counts_s)

    def step(self, count: float, ref_pos: float, ref_vel: float, ff: float) -> tuple[float, float, float]:
        """One tick; returns (τ total, τ feedback, velocity estimate) in µN·m, µN·m, counts/s."""
        p = self.p
        v_raw = self.vf if self.prev is None else (count - self.prev) * p.rate_hz
        self.vf = self.vf + p.alpha * (v_raw - self.vf)
        self.prev = count
        e = ref_pos - count
        ed = ref_vel - self.vf
        fb = p.kp * e + p.kd * ed
        tau = min(max(fb + ff, -p.limit), p.limit)
        return tau, fb, self.vf


def run_twin(
    counts: npt.ArrayLike,
    ref_pos: npt.ArrayLike,
    ref_vel: npt.ArrayLike,
    ff: npt.ArrayLike,
    params: TwinParams,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Play a trial (tick n uses table entry min(n, N−1)); estimator starts at ref_vel[0]."""
    c = np.asarray(counts, dtype=np.float64)
    rp = np.asarray(ref_pos, dtype=np.float64)
    rv = np.asarray(ref_vel, dtype=np.float64)
    f = np.asarray(ff, dtype=np.float64)
    n_tab = rp.shape[0]
    twin = FirmwareTwin(params)
    twin.reset_estimator(rv[0])
    tau = np.zeros(c.shape[0])
    fb = np.zeros(c.shape[0])
    vel = np.zeros(c.shape[0])
    for n in range(c.shape[0]):
        i = min(n, n_tab - 1)
        tau[n], fb[n], vel[n] = twin.step(c[n], rp[i], rv[i], f[i])
    return tau, fb, vel


@dataclass(frozen=True)
class CascadeParams:
    """The cascade's real gains: kpp 1/s, kvff, ktff (1.0 = full), kvp µN·m/(count/s),
    kvi_tick µN·m/(count/s) per control period, rate_hz 1/Ts, limit µN·m (velocity unfiltered)."""

    kpp: float
    kvff: float
    ktff: float
    kvp: float
    kvi_tick: float
    rate_hz: float
    limit: float


class CascadeTwin:
    """The cascade (position P → velocity PI with clamping anti-windup → torque) in float64, as
    :mod:`bus.fixedpoint` writes it, without rounding or saturation of the formats."""

    def __init__(self, params: CascadeParams) -> None:
        self.p = params
        self.prev: float | None = None
        self.v = 0.0
        self.integ = 0.0

    def step(self, count: float, ref_pos: float, ref_vel: float, ff: float) -> float:
        """One tick: τ [µN·m]."""
        p = self.p
        self.v = self.v if self.prev is None else (count - self.prev) * p.rate_hz
        self.prev = count
        tff = p.ktff * ff
        v_cmd = p.kpp * (ref_pos - count) + p.kvff * ref_vel
        ev = v_cmd - self.v
        trial = min(max(self.integ + p.kvi_tick * ev, -p.limit), p.limit)
        u = p.kvp * ev + trial + tff
        if not ((u > p.limit and ev > 0) or (u < -p.limit and ev < 0)):
            self.integ = trial
        return min(max(p.kvp * ev + self.integ + tff, -p.limit), p.limit)
