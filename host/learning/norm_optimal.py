"""Norm-optimal ILC in its Riccati form (Amann, Owens & Rogers 1996), O(N) per update.

This module owns :class:`NormOptimalStep`: for the closed-loop model x_{n+1} = A_n x_n + B_n δu_n,
δe_n = C x_n of :mod:`host.learning.model` it computes the input change that minimises

    J(δu) = Σ_n ‖e_k[n] + δe[n]‖²  +  r Σ_n ‖δu[n]‖²          (e in rad, δu in N·m)

i.e. δu = −(GᵀG + r I)⁻¹ Gᵀ e_k, the lifted norm-optimal update, without forming G:

* once (preparation): the backward Riccati recursion
  P_N = 0,  S_n = r I + B_nᵀP_{n+1}B_n,  K_n = S_n⁻¹B_nᵀP_{n+1}A_n,  F_n = S_n⁻¹B_nᵀ,
  P_n = CᵀC + A_nᵀP_{n+1}(A_n − B_nK_n);
* per update: a backward sweep ξ_N = 0, ξ_n = Cᵀe_k[n] + (A_n − B_nK_n)ᵀξ_{n+1}, then the causal
  forward sweep x_0 = 0, δu_n = −K_n x_n − F_n ξ_{n+1}, x_{n+1} = A_n x_n + B_n δu_n.

The weight r = w·s with w the relative weight (``GainSpec.no_weight``) and s the largest squared
column norm of G (:meth:`ClosedLoopModel.column_norms_sq`), so w is scale-free.  Memory: the gains
K_n, F_n, (N, J, 3J) each; time O(N·J³) once, O(N·J²) per update.
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt
from numba import njit

from host.learning.model import ClosedLoopModel, closed_loop_step, state_matrices

logger = logging.getLogger(__name__)

__all__ = ["NormOptimalStep"]

Array = npt.NDArray[np.float64]


@njit(cache=True)
def _riccati(minv: Array, fq: Array, fp: Array, ts: float, r: float) -> tuple[Array, Array]:
    n_s, nj = minv.shape[0], minv.shape[1]
    ns = 3 * nj
    kfb = np.zeros((n_s, nj, ns))
    kff = np.zeros((n_s, nj, ns))
    p = np.zeros((ns, ns))
    a = np.zeros((ns, ns))
    b = np.zeros((ns, nj))
    eye = np.eye(nj)
    for n in range(n_s - 1, -1, -1):
        state_matrices(minv[n], fq, fp, ts, a, b)
        pb = p @ b
        s = r * eye + b.T @ pb
        sinv = np.linalg.inv(0.5 * (s + s.T))
        kf = sinv @ b.T
        kb = kf @ (p @ a)
        kfb[n] = kb
        kff[n] = kf
        p = a.T @ (p @ (a - b @ kb))
        for i in range(nj):
            p[i, i] += 1.0  # CᵀC, C = −[I 0 0]
        p = 0.5 * (p + p.T)
    return kfb, kff


@njit(cache=True)
def _sweep(minv: Array, fq: Array, fp: Array, ts: float, kfb: Array, kff: Array, e: Array) -> Array:
    """The per-update sweeps with the structure of A_n, B_n written out (no allocation per sample)."""
    n_s, nj = e.shape
    ns = 3 * nj
    h2 = 0.5 * ts * ts
    xi = np.zeros((n_s + 1, ns))
    bx = np.zeros(nj)
    s = np.zeros(nj)
    g = np.zeros(nj)
    for n in range(n_s - 1, -1, -1):
        # ξ_n = A_nᵀξ_{n+1} − K_nᵀ(B_nᵀξ_{n+1}) + Cᵀe_n, B_nᵀξ = M_n⁻ᵀ(½Ts² ξ_q + Ts ξ_v)
        for j in range(nj):
            s[j] = h2 * xi[n + 1, j] + ts * xi[n + 1, nj + j]
        for j in range(nj):
            acc = 0.0
            for i in range(nj):
                acc += minv[n, i, j] * s[i]
            g[j] = acc
            bx[j] = acc
        for j in range(nj):
            lq = xi[n + 1, j]
            lv = xi[n + 1, nj + j]
            lp = xi[n + 1, 2 * nj + j]
            xi[n, j] = lq + fq[j] * g[j] + lp - e[n, j]
            xi[n, nj + j] = ts * lq + lv
            xi[n, 2 * nj + j] = fp[j] * g[j]
        for c in range(ns):
            acc = 0.0
            for i in range(nj):
                acc += kfb[n, i, c] * bx[i]
            xi[n, c] -= acc
    du = np.zeros((n_s, nj))
    q = np.zeros(nj)
    v = np.zeros(nj)
    qp = np.zeros(nj)
    tau = np.zeros(nj)
    for n in range(n_s):
        for i in range(nj):
            acc = 0.0
            for c in range(nj):
                acc += kfb[n, i, c] * q[c] + kfb[n, i, nj + c] * v[c] + kfb[n, i, 2 * nj + c] * qp[c]
            for c in range(ns):
                acc += kff[n, i, c] * xi[n + 1, c]
            du[n, i] = -acc
        closed_loop_step(minv, fq, fp, ts, h2, n, du[n], q, v, qp, tau)
    return du


class NormOptimalStep:
    """δu = −(GᵀG + r I)⁻¹ Gᵀ e for the model G, by the Riccati sweeps (module docstring).

    :param model: the closed-loop model G
    :param relative_weight: w; the input weight is r = w · max column norm² of G
    """

    def __init__(self, model: ClosedLoopModel, relative_weight: float) -> None:
        if not (np.isfinite(relative_weight) and relative_weight > 0):
            raise ValueError(f"norm-optimal weight must be a finite number > 0, got {relative_weight}")
        self.model = model
        scale = float(np.max(model.column_norms_sq()))
        #: the input weight r, rad²/(N·m)²
        self.r = float(relative_weight) * scale + 1e-300
        self._kfb, self._kff = _riccati(model.minv, model.fq, model.fp, model.ts_s, self.r)
        logger.debug("norm-optimal gains for N = %d: r = %.3g (w = %g, s = %.3g)", model.n, self.r, relative_weight, scale)

    def __call__(self, e: Array) -> Array:
        """The input change δu (N, J) N·m for the error e (N, J) rad."""
        m = self.model
        return _sweep(m.minv, m.fq, m.fp, m.ts_s, self._kfb, self._kff, np.ascontiguousarray(e, dtype=float))
