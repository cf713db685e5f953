"""The closed loop linearised along the reference, as a linear time-varying state-space model.

This module owns :class:`ClosedLoopModel`: the map G from a feed-forward change δu (N·m) to the
error change δe = −δq (rad) of one trial, and the drive's feedback operator K, both applied in
O(N) by sweeps over the trial (numba kernels) instead of as dense lifted matrices.

Model (per sample n, J = 4 joints, Ts the control period):

* plant: nominal inertia M_n = M(q_d(t_n)) held over [t_n, t_n + Ts] (Coriolis, gravity and
  friction Jacobians neglected), zero-order hold — an exact double integrator per sample;
* drive: τ_n = δu_n − Kp δq_n − Kd (δq_n − δq_{n−1})/Ts (the drive's backward-difference velocity);
* state x_n = (δq_n, δq̇_n, δq_{n−1}) ∈ R^{3J}, x_0 = 0 (every trial starts on the reference):

      δq_{n+1} = δq_n + Ts δq̇_n + ½Ts² M_n⁻¹ τ_n,   δq̇_{n+1} = δq̇_n + Ts M_n⁻¹ τ_n,   e_n = −δq_n.

So x_{n+1} = A_n x_n + B_n δu_n and e_n = C x_n: G is causal with relative degree one (δu_n first
shows in e_{n+1}; the block from u_n to e_{n+1} is −½Ts² M_n⁻¹).  Gᵀ (needed by the norm-optimal
law and the matrix-free 2-norm) is the adjoint backward sweep λ_n = Cᵀy_n + A_nᵀλ_{n+1},
(Gᵀy)_n = B_nᵀλ_{n+1}.  Cost: O(N·J²) time and O(N·J²) memory (the inverse inertias).
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt
from numba import njit

from host.learning.signals import backward_difference, backward_difference_t

logger = logging.getLogger(__name__)

__all__ = ["ClosedLoopModel", "closed_loop_step", "state_matrices"]

Array = npt.NDArray[np.float64]


@njit(cache=True)
def _simulate(minv: Array, fq: Array, fp: Array, ts: float, u: Array) -> Array:
    """e = G u: forward sweep of the closed loop from x_0 = 0."""
    n_s, nj = u.shape
    e = np.zeros((n_s, nj))
    q = np.zeros(nj)
    v = np.zeros(nj)
    qp = np.zeros(nj)
    tau = np.zeros(nj)
    h2 = 0.5 * ts * ts
    for n in range(n_s):
        for j in range(nj):
            e[n, j] = -q[j]
        closed_loop_step(minv, fq, fp, ts, h2, n, u[n], q, v, qp, tau)
    return e


@njit(cache=True)
def closed_loop_step(
    minv: Array, fq: Array, fp: Array, ts: float, h2: float, n: int, u_n: Array, q: Array, v: Array, qp: Array, tau: Array
) -> None:
    """One sample of the closed loop in place: τ = u_n + fq·q + fp·q_prev, a = M⁻¹[n] τ, then
    q, v by a second-order step (h2 = Ts²/2); ``qp`` keeps the previous q, ``tau`` is scratch."""
    nj = q.shape[0]
    for j in range(nj):
        tau[j] = u_n[j] + fq[j] * q[j] + fp[j] * qp[j]
    for i in range(nj):
        a = 0.0
        for j in range(nj):
            a += minv[n, i, j] * tau[j]
        qp[i] = q[i]
        q[i] = q[i] + ts * v[i] + h2 * a
        v[i] = v[i] + ts * a


@njit(cache=True)
def _simulate_t(minv: Array, fq: Array, fp: Array, ts: float, y: Array) -> Array:
    """Gᵀ y: the adjoint backward sweep."""
    n_s, nj = y.shape
    out = np.zeros((n_s, nj))
    lq = np.zeros(nj)  # λ_{n+1}: co-states of (δq, δq̇, δq_prev)
    lv = np.zeros(nj)
    lp = np.zeros(nj)
    s = np.zeros(nj)
    g = np.zeros(nj)
    h2 = 0.5 * ts * ts
    for n in range(n_s - 1, -1, -1):
        # (Gᵀy)_n = B_nᵀ λ_{n+1} = M_n⁻ᵀ (½Ts² λq + Ts λv)
        for j in range(nj):
            s[j] = h2 * lq[j] + ts * lv[j]
        for j in range(nj):
            acc = 0.0
            for i in range(nj):
                acc += minv[n, i, j] * s[i]
            g[j] = acc
            out[n, j] = acc
        # λ_n = Cᵀ y_n + A_nᵀ λ_{n+1}
        for j in range(nj):
            lq_new = lq[j] + fq[j] * g[j] + lp[j] - y[n, j]
            lv_new = ts * lq[j] + lv[j]
            lp[j] = fp[j] * g[j]
            lq[j] = lq_new
            lv[j] = lv_new
    return out


@njit(cache=True)
def state_matrices(minv_n: Array, fq: Array, fp: Array, ts: float, a: Array, b: Array) -> None:
    """Fill A_n (3J × 3J) and B_n (3J × J) of sample n in place (state (δq, δq̇, δq_prev))."""
    nj = fq.shape[0]
    h2 = 0.5 * ts * ts
    a[:, :] = 0.0
    b[:, :] = 0.0
    for i in range(nj):
        a[i, nj + i] = ts
        a[nj + i, nj + i] = 1.0
        a[2 * nj + i, i] = 1.0
        a[i, i] = 1.0
        for j in range(nj):
            m = minv_n[i, j]
            a[i, j] += h2 * m * fq[j]
            a[i, 2 * nj + j] += h2 * m * fp[j]
            a[nj + i, j] += ts * m * fq[j]
            a[nj + i, 2 * nj + j] += ts * m * fp[j]
            b[i, j] = h2 * m
            b[nj + i, j] = ts * m


@njit(cache=True)
def _column_norms_sq(minv: Array, fq: Array, fp: Array, ts: float) -> Array:
    """diag(GᵀG) as (N, J): B_nᵀ W_{n+1} B_n with W_n = CᵀC + A_nᵀ W_{n+1} A_n, W_N = 0."""
    n_s, nj = minv.shape[0], minv.shape[1]
    ns = 3 * nj
    w = np.zeros((ns, ns))
    a = np.zeros((ns, ns))
    b = np.zeros((ns, nj))
    out = np.zeros((n_s, nj))
    for n in range(n_s - 1, -1, -1):
        state_matrices(minv[n], fq, fp, ts, a, b)
        wb = w @ b
        for j in range(nj):
            acc = 0.0
            for i in range(ns):
                acc += b[i, j] * wb[i, j]
            out[n, j] = acc
        w = a.T @ w @ a
        for i in range(nj):
            w[i, i] += 1.0  # CᵀC with C = −[I 0 0]
        w = 0.5 * (w + w.T)
    return out


class ClosedLoopModel:
    """Closed loop of one trial linearised along the reference (see the module docstring).

    :param inertia_kgm2: (N, J, J) mass matrix M(q_d(t_n)) at every sample, kg·m²
    :param kp_nm_per_rad: (J,) the drive's position gain Kp, N·m/rad
    :param kd_nms_per_rad: (J,) the drive's velocity gain Kd, N·m·s/rad
    :param ts_s: control period Ts, s
    """

    def __init__(self, inertia_kgm2: Array, kp_nm_per_rad: Array, kd_nms_per_rad: Array, ts_s: float) -> None:
        m = np.asarray(inertia_kgm2, dtype=float)
        if m.ndim != 3 or m.shape[1] != m.shape[2]:
            raise ValueError(f"inertia must be (N, J, J), got {m.shape}")
        self.n, self.j = int(m.shape[0]), int(m.shape[1])
        self.ts_s = float(ts_s)
        self.kp = np.asarray(kp_nm_per_rad, dtype=float).reshape(self.j)
        self.kd = np.asarray(kd_nms_per_rad, dtype=float).reshape(self.j)
        self.inertia = m
        self.minv = np.ascontiguousarray(np.linalg.inv(m))
        #: τ = δu + fq∘δq + fp∘δq_prev
        self.fq = -(self.kp + self.kd / self.ts_s)
        self.fp = self.kd / self.ts_s

    # -- the lifted operators, matrix-free -------------------------------------------------------

    def g(self, u: Array) -> Array:
        """e = G u: the error change (N, J) rad of a feed-forward change u (N, J) N·m."""
        return _simulate(self.minv, self.fq, self.fp, self.ts_s, np.ascontiguousarray(u, dtype=float))

    def g_t(self, y: Array) -> Array:
        """Gᵀ y for y (N, J) (rad → N·m-shaped co-vector)."""
        return _simulate_t(self.minv, self.fq, self.fp, self.ts_s, np.ascontiguousarray(y, dtype=float))

    def k(self, e: Array) -> Array:
        """τ_fb = K e = Kp e + Kd ė: the drive's feedback torque (N, J) N·m of an error e (N, J) rad."""
        return self.kp * e + self.kd * backward_difference(e, self.ts_s)

    def k_t(self, y: Array) -> Array:
        """Kᵀ y."""
        return self.kp * y + backward_difference_t(self.kd * y, self.ts_s)

    def first_markov(self) -> Array:
        """(N, J, J): the block of G from u_n to e_{n+1}, −½Ts² M_n⁻¹ (rad per N·m)."""
        return -0.5 * self.ts_s**2 * self.minv

    def column_norms_sq(self) -> Array:
        """(N, J): ‖G e_(n,j)‖², the squared 2-norm of every column of G (rad²/(N·m)²), O(N)."""
        return _column_norms_sq(self.minv, self.fq, self.fp, self.ts_s)

    def with_gains(self, kp_nm_per_rad: Array, kd_nms_per_rad: Array) -> ClosedLoopModel:
        """The same inertia sequence with other drive gains Kp (N·m/rad), Kd (N·m·s/rad), (J,) each."""
        return ClosedLoopModel(self.inertia, kp_nm_per_rad, kd_nms_per_rad, self.ts_s)

    def corrected(self, inertia_kgm2: Array) -> ClosedLoopModel:
        """The same drive gains around another inertia sequence (N, J, J), kg·m²."""
        return ClosedLoopModel(inertia_kgm2, self.kp, self.kd, self.ts_s)
