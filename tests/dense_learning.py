"""Dense (lifted-matrix) reference implementations of the learning operators, for tests only.

The production code (host/learning) never forms an NJ × NJ matrix; these are the textbook lifted
forms (time-major vectors, index n·J + j) the O(N) implementations are compared with on small N.
"""

from __future__ import annotations

import numpy as np

from host.learning.signals import backward_difference, lead


def dense_g(minv: np.ndarray, kp: np.ndarray, kd: np.ndarray, ts: float) -> np.ndarray:
    """G (NJ × NJ): δu → δe = −δq of the closed loop (state (δq, δq̇, δq_prev), ZOH per sample)."""
    n, j = minv.shape[0], minv.shape[1]
    eye = np.eye(j)
    ns = 3 * j
    G = np.zeros((n * j, n * j))
    S = np.zeros((n, ns, j))
    for i in range(n):
        if i > 0:
            G[i * j : (i + 1) * j, : i * j] = -S[:i, :j, :].transpose(1, 0, 2).reshape(j, i * j)
        mi = minv[i]
        ftau = np.hstack([-np.diag(kp + kd / ts), np.zeros((j, j)), np.diag(kd / ts)])
        A = np.zeros((ns, ns))
        A[:j, :j] = eye
        A[:j, j : 2 * j] = ts * eye
        A[:j] += 0.5 * ts * ts * mi @ ftau
        A[j : 2 * j, j : 2 * j] = eye
        A[j : 2 * j] += ts * mi @ ftau
        A[2 * j :, :j] = eye
        B = np.vstack([0.5 * ts * ts * mi, ts * mi, np.zeros((j, j))])
        if i > 0:
            S[:i] = np.matmul(A, S[:i])
        S[i] = B
    return G


def time_op(op, n: int, j: int) -> np.ndarray:
    """The dense NJ × NJ matrix of a linear map on (N, J) arrays (applied column by column)."""
    out = np.zeros((n * j, n * j))
    for c in range(n * j):
        x = np.zeros(n * j)
        x[c] = 1.0
        out[:, c] = np.asarray(op(x.reshape(n, j))).reshape(-1)
    return out


def dense_k(n: int, kp: np.ndarray, kd: np.ndarray, ts: float) -> np.ndarray:
    return np.kron(np.eye(n), np.diag(kp)) + np.kron(backward_difference(np.eye(n), ts), np.diag(kd))


def dense_l(n: int, lp: np.ndarray, ld: np.ndarray, ts: float, m: int, use_p: bool = True, use_d: bool = True) -> np.ndarray:
    eye = np.eye(n)
    out = np.zeros((n * len(lp),) * 2)
    if use_p:
        out += np.kron(lead(eye, m), np.diag(lp))
    if use_d:
        out += np.kron(lead(backward_difference(eye, ts), m), np.diag(ld))
    return out


def dense_norm_optimal(G: np.ndarray, w: float) -> np.ndarray:
    """L_no = −(GᵀG + w·s·I)⁻¹Gᵀ with s the largest squared column norm of G."""
    scale = float(np.max(np.sum(G * G, axis=0)))
    r = w * scale + 1e-300
    # least squares on the stacked system [G; √r I] (better conditioned than the normal equations)
    n = G.shape[0]
    stacked = np.vstack([G, np.sqrt(r) * np.eye(n)])
    rhs = np.vstack([np.eye(n), np.zeros((n, n))])
    return -np.linalg.lstsq(stacked, rhs, rcond=None)[0]
