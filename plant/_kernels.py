"""Numba kernels shared by plant.kinematics, plant.dynamics and plant.simulator.

This module owns the hot path: closed-form IK, Newton FK with warm start, the A/B Jacobian
matrices of docs/robot-model.md §3.5, J̇q̇ of §3.6, the lumped dynamics of §4.1 (+ true-plant friction and
the tool-spin term) and the RK4 integrator of one control period.  Everything works on float64
arrays with hand-written 4×4 LU / Cholesky solves; nothing here allocates in the per-step path
(the caller passes a workspace).  No fastmath, no parallel: results are bit-reproducible.

Parameter vector ``p`` (built by :func:`pack_params`) — index constants ``P_*`` below.
Units: m, rad, kg, N·m, s.

Matrices are stored row-major in 16-element rows: ``A[4*i + j]``.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit

from plant.params import LIMB_ON_UPPER, Geometry, MassModel, TruePlantConfig

logger = logging.getLogger(__name__)

# ---- parameter vector layout -------------------------------------------------------------
P_LA = 0  # inner arm length l_a, m
P_LB = 1  # rod length l_b, m
P_R = 2  # base radius R, m
P_RP = 3  # platform radius r, m
P_D0 = 4  # nominal screw gap d0, m
P_H = 5  # screw lead h, m/rev
P_E = 6  # TCP offset e, m
P_COS = 7  # cos φ_i (4)
P_SIN = 11  # sin φ_i (4)
P_MBAR = 15  # constant Y-space mass matrix (16), kg
P_IB = 31  # joint inertia I_b per joint (4), kg·m²
P_KB = 35  # arm gravity coefficient (m_a l_c + ρ m_fa l_a) g per joint (4), N·m
P_GU = 39  # m_up_eff g, N
P_GL = 40  # m_low_eff g, N
P_FC = 41  # Coulomb friction per joint (4), N·m
P_FV = 45  # viscous friction per joint (4), N·m·s/rad
P_VSM = 49  # Coulomb smoothing velocity, rad/s
P_FSR = 50  # Stribeck ratio F_s/F_c (1 = off)
P_VST = 51  # Stribeck velocity, rad/s
P_TLIM = 52  # joint torque limit, N·m (<= 0: no clamp)
P_FRIC = 53  # 1.0 if friction is on
P_NTOL = 54  # Newton step tolerance, m
P_NMAX = 55  # Newton max iterations
P_TS = 56  # control period, s
P_NSUB = 57  # RK4 sub-steps per control period
P_RPC = 58  # rad per encoder count
P_TLSB = 59  # N·m per torque unit
N_PARAMS = 60

# ---- workspace rows (each 16 float64) ----------------------------------------------------
R_STATE = 0  # q[0:4], qd[4:8]
R_FK = 1  # Y[0:4] warm start, q_last[4:8], have_last[8], Newton steps of the last FK[9]
R_SPARE = 2  # unused
R_A = 3  # A, LU-factorised in place
R_VEC = 4  # piv[0:4], b[4:8], w[8:12], newton residual / step [12:16]
R_J = 5  # J = A^-1 B of the last evaluation (also the predictor's J)
R_M = 6  # M, Cholesky factor in place
R_V2 = 7  # Yd[0:4], jdq[4:8], Cqd[8:12], G[12:16]
R_V3 = 8  # rhs[0:4], tmp[4:8], friction[8:12], tau_applied[12:16]
R_K1 = 9  # kq1, kv1, kq2, kv2
R_K2 = 10  # kq3, kv3, kq4, kv4
R_STG = 11  # qs[0:4], qds[4:8], qdd[8:12], tau_cmd[12:16]
R_MJ = 12  # Mbar J
R_AUX = 13  # saturated flags [0:4]
R_TRIG = 14  # cos q [0:4], sin q [4:8] of the current evaluation
N_ROWS = 15

#: the ``locked`` mask of :func:`accel_locked` / :func:`plant_step_locked` with no joint held
_NONE_HELD = np.zeros(4, dtype=np.int64)

# status codes
ST_OK = 0
ST_FK_FAIL = 1
ST_SINGULAR_A = 2
ST_M_NOT_PD = 3
ST_NONFINITE = 4
ST_SERIAL_SINGULAR = 5

STATUS_TEXT = {
    ST_OK: "ok",
    ST_FK_FAIL: "forward kinematics did not converge",
    ST_SINGULAR_A: "parallel singularity (A singular)",
    ST_M_NOT_PD: "mass matrix not positive definite",
    ST_NONFINITE: "state became non-finite",
    ST_SERIAL_SINGULAR: "serial singularity (b_i = 0)",
}


def pack_params(
    geometry: Geometry,
    mass: MassModel | None = None,
    config: TruePlantConfig | None = None,
    ts_s: float = 1e-3,
    substeps: int = 4,
    rad_per_count: float = 1.0,
    torque_lsb_nm: float = 1.0,
    newton_tol_m: float = 1e-10,
    newton_max_iter: int = 30,
) -> np.ndarray:
    """Build the float64 parameter vector of the kernels.

    ``config`` (if given) supplies friction and the torque limit; ``mass`` defaults to
    ``config.mass`` (or a zero-mass model if neither is given: kinematics only).
    """
    p = np.zeros(N_PARAMS, dtype=np.float64)
    p[P_LA] = geometry.l_a
    p[P_LB] = geometry.l_b
    p[P_R] = geometry.R
    p[P_RP] = geometry.r
    p[P_D0] = geometry.d0
    p[P_H] = geometry.h
    p[P_E] = geometry.e
    for i, phi in enumerate(geometry.azimuths_rad):
        p[P_COS + i] = math.cos(phi)
        p[P_SIN + i] = math.sin(phi)
    if mass is None and config is not None:
        mass = config.mass
    if mass is not None:
        mu = mass.m_up_eff
        ml = mass.m_low_eff
        k_spin = mass.spin_equivalent_mass(geometry.h)
        mbar = np.diag([mu + ml, mu + ml, mu + k_spin, ml + k_spin])
        mbar[2, 3] = -k_spin
        mbar[3, 2] = -k_spin
        p[P_MBAR : P_MBAR + 16] = mbar.ravel()
        p[P_IB : P_IB + 4] = mass.joint_inertia(geometry.l_a)
        p[P_KB : P_KB + 4] = mass.arm_gravity_coefficient(geometry.l_a)
        p[P_GU] = mu * mass.g
        p[P_GL] = ml * mass.g
    if config is not None:
        p[P_FC : P_FC + 4] = config.coulomb_nm
        p[P_FV : P_FV + 4] = config.viscous_nm_s_per_rad
        p[P_VSM] = config.friction_smoothing_rad_s
        p[P_FSR] = config.stribeck_ratio
        p[P_VST] = config.stribeck_velocity_rad_s
        p[P_TLIM] = config.joint_torque_limit_nm if config.torque_limit_enabled else 0.0
        p[P_FRIC] = 1.0 if config.has_friction else 0.0
    else:
        p[P_VSM] = 0.01
        p[P_FSR] = 1.0
        p[P_VST] = 0.05
    p[P_NTOL] = newton_tol_m
    p[P_NMAX] = float(newton_max_iter)
    p[P_TS] = ts_s
    p[P_NSUB] = float(substeps)
    p[P_RPC] = rad_per_count
    p[P_TLSB] = torque_lsb_nm
    assert LIMB_ON_UPPER == (True, False, True, False)  # the kernels hard-code this layout
    return p


# ---- small linear algebra ----------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def lu4(a: np.ndarray, piv: np.ndarray) -> bool:
    """In-place LU with partial pivoting of a row-major 4×4 ``a``; ``piv`` gets row swaps
    (as float).  Returns False if a pivot is (numerically) zero."""
    scale = 0.0
    for k in range(16):
        v = abs(a[k])
        if v > scale:
            scale = v
    if scale == 0.0:
        return False
    tiny = scale * 1e-13
    for k in range(4):
        pr = k
        best = abs(a[4 * k + k])
        for i in range(k + 1, 4):
            v = abs(a[4 * i + k])
            if v > best:
                best = v
                pr = i
        piv[k] = pr
        if best <= tiny:
            return False
        if pr != k:
            for j in range(4):
                t = a[4 * k + j]
                a[4 * k + j] = a[4 * pr + j]
                a[4 * pr + j] = t
        inv = 1.0 / a[4 * k + k]
        for i in range(k + 1, 4):
            f = a[4 * i + k] * inv
            a[4 * i + k] = f
            for j in range(k + 1, 4):
                a[4 * i + j] -= f * a[4 * k + j]
    return True


@njit(cache=True, error_model="numpy")
def lu4_solve(lu: np.ndarray, piv: np.ndarray, x: np.ndarray, xo: int) -> None:
    """Solve in place: ``x[xo:xo+4]`` holds the right-hand side and gets the solution."""
    for k in range(4):
        pr = int(piv[k])
        if pr != k:
            t = x[xo + k]
            x[xo + k] = x[xo + pr]
            x[xo + pr] = t
    for i in range(1, 4):
        s = x[xo + i]
        for j in range(i):
            s -= lu[4 * i + j] * x[xo + j]
        x[xo + i] = s
    for i in range(3, -1, -1):
        s = x[xo + i]
        for j in range(i + 1, 4):
            s -= lu[4 * i + j] * x[xo + j]
        x[xo + i] = s / lu[4 * i + i]


@njit(cache=True, error_model="numpy")
def chol4_solve(m: np.ndarray, x: np.ndarray, xo: int) -> bool:
    """Cholesky of the SPD row-major 4×4 ``m`` in place (lower factor) and solve
    ``m y = x[xo:xo+4]`` in place.  Returns False if ``m`` is not positive definite."""
    for j in range(4):
        d = m[4 * j + j]
        for k in range(j):
            d -= m[4 * j + k] * m[4 * j + k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        m[4 * j + j] = d
        for i in range(j + 1, 4):
            s = m[4 * i + j]
            for k in range(j):
                s -= m[4 * i + k] * m[4 * j + k]
            m[4 * i + j] = s / d
    for i in range(4):
        s = x[xo + i]
        for k in range(i):
            s -= m[4 * i + k] * x[xo + k]
        x[xo + i] = s / m[4 * i + i]
    for i in range(3, -1, -1):
        s = x[xo + i]
        for k in range(i + 1, 4):
            s -= m[4 * k + i] * x[xo + k]
        x[xo + i] = s / m[4 * i + i]
    return True


# ---- kinematics --------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def subplatform_from_task4(x: float, y: float, z: float, th: float, p: np.ndarray, out: np.ndarray, oo: int) -> None:
    """Y = (x, y, z_u, z_l) from X = (x, y, z, θ) (docs/robot-model.md §3.1, TCP e below the ball plane)."""
    zl = z + p[P_E]
    out[oo + 0] = x
    out[oo + 1] = y
    out[oo + 2] = zl + p[P_D0] + p[P_H] * th / (2.0 * math.pi)
    out[oo + 3] = zl


@njit(cache=True, error_model="numpy")
def ik_limbs(y0: float, y1: float, zu: float, zl: float, p: np.ndarray, q: np.ndarray, qo: int) -> int:
    """Closed-form elbow-out IK of the four limbs (docs/robot-model.md §3.3) for sub-platform Y.
    Writes ``q[qo:qo+4]``; returns -1 or the 0-based index of the first limb out of reach."""
    la = p[P_LA]
    lb = p[P_LB]
    for i in range(4):
        c = p[P_COS + i]
        s = p[P_SIN + i]
        zs = zu if (i % 2) == 0 else zl
        dx = y0 + p[P_RP] * c - p[P_R] * c
        dy = y1 + p[P_RP] * s - p[P_R] * s
        dz = zs
        de = dx * c + dy * s
        dd = dx * dx + dy * dy + dz * dz
        k = (dd + la * la - lb * lb) / (2.0 * la)
        a = de
        b = -dz
        rr = math.sqrt(a * a + b * b)
        if not (rr > 0.0) or abs(k) > rr:
            return i
        q[qo + i] = math.atan2(b, a) - math.acos(k / rr)
    return -1


@njit(cache=True, error_model="numpy")
def trig4(q: np.ndarray, qo: int, tr: np.ndarray) -> None:
    """tr[0:4] = cos q, tr[4:8] = sin q (computed once per evaluation)."""
    for i in range(4):
        tr[i] = math.cos(q[qo + i])
        tr[4 + i] = math.sin(q[qo + i])


@njit(cache=True, error_model="numpy")
def build_a_b(tr: np.ndarray, y: np.ndarray, yo: int, p: np.ndarray, a: np.ndarray, vec: np.ndarray) -> None:
    """Rows of A (docs/robot-model.md §3.5) into ``a``; b_i into vec[4:8]; constraint residuals
    f_i/2 = (|s_i|² - l_b²)/2 into vec[12:16].  ``tr`` = (cos q, sin q) from :func:`trig4`."""
    la = p[P_LA]
    lb = p[P_LB]
    for i in range(4):
        c = p[P_COS + i]
        s = p[P_SIN + i]
        cq = tr[i]
        sq = tr[4 + i]
        rad = p[P_R] + la * cq
        sx = y[yo + 0] + p[P_RP] * c - rad * c
        sy = y[yo + 1] + p[P_RP] * s - rad * s
        if (i % 2) == 0:
            sz = y[yo + 2] + la * sq
            a[4 * i + 2] = sz
            a[4 * i + 3] = 0.0
        else:
            sz = y[yo + 3] + la * sq
            a[4 * i + 2] = 0.0
            a[4 * i + 3] = sz
        a[4 * i + 0] = sx
        a[4 * i + 1] = sy
        # dB/dq = l_a(-sin q e_i - cos q k)
        vec[4 + i] = -la * sq * (sx * c + sy * s) - la * cq * sz
        vec[12 + i] = 0.5 * (sx * sx + sy * sy + sz * sz - lb * lb)


@njit(cache=True, error_model="numpy")
def fk_newton(tr: np.ndarray, y: np.ndarray, yo: int, p: np.ndarray, a: np.ndarray, vec: np.ndarray) -> int:
    """Newton FK (docs/robot-model.md §3.4) from the guess in ``y[yo:yo+4]`` (updated in place).

    On success ``a`` holds the LU factors of A at the converged Y (pivots in vec[0:4]) and
    vec[4:8] holds b.  Returns the number of Newton steps, -1 if not converged, -2 if A
    became singular."""
    tol = p[P_NTOL]
    nmax = int(p[P_NMAX])
    last = 1e300
    for it in range(nmax + 1):
        build_a_b(tr, y, yo, p, a, vec)
        if not lu4(a, vec):
            return -2
        if last < tol:
            return it
        if it == nmax:
            break
        lu4_solve(a, vec, vec, 12)
        last = 0.0
        for j in range(4):
            d = vec[12 + j]
            y[yo + j] -= d
            if abs(d) > last:
                last = abs(d)
        if not last < 1.0:  # diverging or NaN
            return -1
    return -1


@njit(cache=True, error_model="numpy")
def jacobian_from_lu(a: np.ndarray, vec: np.ndarray, jout: np.ndarray) -> None:
    """J = A⁻¹ diag(b) from the LU of A (in ``a``, pivots vec[0:4]) and b (vec[4:8]).

    All four columns are solved together (right-hand side P·diag(b))."""
    for i in range(4):
        for j in range(4):
            jout[4 * i + j] = 0.0
        jout[4 * i + i] = vec[4 + i]
    for k in range(4):
        pr = int(vec[k])
        if pr != k:
            for j in range(4):
                t = jout[4 * k + j]
                jout[4 * k + j] = jout[4 * pr + j]
                jout[4 * pr + j] = t
    for i in range(1, 4):
        for m in range(i):
            f = a[4 * i + m]
            for j in range(4):
                jout[4 * i + j] -= f * jout[4 * m + j]
    for i in range(3, -1, -1):
        for m in range(i + 1, 4):
            f = a[4 * i + m]
            for j in range(4):
                jout[4 * i + j] -= f * jout[4 * m + j]
        d = a[4 * i + i]
        for j in range(4):
            jout[4 * i + j] /= d


@njit(cache=True, error_model="numpy")
def w_vector(
    tr: np.ndarray,
    qd: np.ndarray,
    qdo: int,
    y: np.ndarray,
    yo: int,
    yd: np.ndarray,
    ydo: int,
    p: np.ndarray,
    out: np.ndarray,
    oo: int,
) -> None:
    """w_i = ḃ_i q̇_i − ṡ_i·v_s(i) of docs/robot-model.md §3.6 (A Ÿ = B q̈ + w); ``tr`` from :func:`trig4`."""
    la = p[P_LA]
    for i in range(4):
        c = p[P_COS + i]
        s = p[P_SIN + i]
        cq = tr[i]
        sq = tr[4 + i]
        qdi = qd[qdo + i]
        rad = p[P_R] + la * cq
        sx = y[yo + 0] + p[P_RP] * c - rad * c
        sy = y[yo + 1] + p[P_RP] * s - rad * s
        if (i % 2) == 0:
            sz = y[yo + 2] + la * sq
            vz = yd[ydo + 2]
        else:
            sz = y[yo + 3] + la * sq
            vz = yd[ydo + 3]
        vx = yd[ydo + 0]
        vy = yd[ydo + 1]
        dbx = -la * sq * c
        dby = -la * sq * s
        dbz = -la * cq
        d2x = -la * cq * c
        d2y = -la * cq * s
        d2z = la * sq
        sdx = vx - dbx * qdi
        sdy = vy - dby * qdi
        sdz = vz - dbz * qdi
        bdot = sdx * dbx + sdy * dby + sdz * dbz + (sx * d2x + sy * d2y + sz * d2z) * qdi
        out[oo + i] = bdot * qdi - (sdx * vx + sdy * vy + sdz * vz)


@njit(cache=True, error_model="numpy")
def eval_terms(q: np.ndarray, qo: int, qd: np.ndarray, qdo: int, p: np.ndarray, ws: np.ndarray, predict: bool) -> int:
    """FK (warm start ws[R_FK,0:4], optional second-order predictor) and the dynamic terms:
    J → ws[R_J], Yd, J̇q̇, C q̇, G → ws[R_V2], M → ws[R_M].  Returns a status code."""
    fk = ws[R_FK]
    a = ws[R_A]
    vec = ws[R_VEC]
    jm = ws[R_J]
    v2 = ws[R_V2]
    mm = ws[R_M]
    mj = ws[R_MJ]
    tr = ws[R_TRIG]
    if predict and fk[8] == 1.0:
        # second-order predictor along the straight line q_last -> q (uses the last trig,
        # J and LU of A):  Y ≈ Y + J Δq + ½ A⁻¹ w(q̇ := Δq)
        t = ws[R_V3]
        for i in range(4):
            t[i] = q[qo + i] - fk[4 + i]
        for i in range(4):
            acc = 0.0
            for j in range(4):
                acc += jm[4 * i + j] * t[j]
            t[4 + i] = acc
        w_vector(tr, t, 0, fk, 0, t, 4, p, vec, 8)
        lu4_solve(a, vec, vec, 8)
        for i in range(4):
            fk[i] += t[4 + i] + 0.5 * vec[8 + i]
    trig4(q, qo, tr)
    its = fk_newton(tr, fk, 0, p, a, vec)
    if its == -2:
        return ST_SINGULAR_A
    if its < 0:
        return ST_FK_FAIL
    fk[9] = its
    for i in range(4):
        fk[4 + i] = q[qo + i]
    fk[8] = 1.0
    jacobian_from_lu(a, vec, jm)
    # Yd = J qd
    for i in range(4):
        acc = 0.0
        for j in range(4):
            acc += jm[4 * i + j] * qd[qdo + j]
        v2[i] = acc
    # w -> J̇q̇ = A^-1 w  (into v2[4:8])
    w_vector(tr, qd, qdo, fk, 0, v2, 0, p, v2, 4)
    lu4_solve(a, vec, v2, 4)
    # Mbar = [[mxy, 0, 0, 0], [0, mxy, 0, 0], [0, 0, m22, m23], [0, 0, m23, m33]] (pack_params)
    mxy = p[P_MBAR + 0]
    m22 = p[P_MBAR + 10]
    m23 = p[P_MBAR + 11]
    m33 = p[P_MBAR + 15]
    # MJ = Mbar J
    for j in range(4):
        mj[j] = mxy * jm[j]
        mj[4 + j] = mxy * jm[4 + j]
        mj[8 + j] = m22 * jm[8 + j] + m23 * jm[12 + j]
        mj[12 + j] = m23 * jm[8 + j] + m33 * jm[12 + j]
    # M = J^T Mbar J + diag(I_b)
    for i in range(4):
        for j in range(i, 4):
            acc = (jm[i] * mj[j] + jm[4 + i] * mj[4 + j]) + (jm[8 + i] * mj[8 + j] + jm[12 + i] * mj[12 + j])
            if i == j:
                acc += p[P_IB + i]
            mm[4 * i + j] = acc
            mm[4 * j + i] = acc
    # C qd = J^T Mbar (J̇q̇):  tmp = Mbar jdq into vec[8:12]
    vec[8] = mxy * v2[4]
    vec[9] = mxy * v2[5]
    vec[10] = m22 * v2[6] + m23 * v2[7]
    vec[11] = m23 * v2[6] + m33 * v2[7]
    for i in range(4):
        acc = 0.0
        for k in range(4):
            acc += jm[4 * k + i] * vec[8 + k]
        v2[8 + i] = acc
    # G = dV/dq = J^T (0, 0, m_u g, m_l g) - kb cos q
    for i in range(4):
        v2[12 + i] = jm[8 + i] * p[P_GU] + jm[12 + i] * p[P_GL] - p[P_KB + i] * tr[i]
    return ST_OK


@njit(cache=True, error_model="numpy")
def friction_torque(qd: np.ndarray, qdo: int, p: np.ndarray, out: np.ndarray, oo: int) -> None:
    """Joint friction τ_f (N·m) of the true plant; zeros if friction is off."""
    if p[P_FRIC] == 0.0:
        for i in range(4):
            out[oo + i] = 0.0
        return
    vsm = p[P_VSM]
    fsr = p[P_FSR]
    vst = p[P_VST]
    for i in range(4):
        v = qd[qdo + i]
        fc = p[P_FC + i]
        if fsr != 1.0:
            r = v / vst
            fc = fc * (1.0 + (fsr - 1.0) * math.exp(-r * r))
        x = v / vsm
        # tanh(x) is exactly ±1.0 in double precision for |x| > 22 (libm gives the same)
        if x > 22.0:
            th = 1.0
        elif x < -22.0:
            th = -1.0
        else:
            th = math.tanh(x)
        out[oo + i] = fc * th + p[P_FV + i] * v


@njit(cache=True, error_model="numpy")
def accel(
    q: np.ndarray,
    qo: int,
    qd: np.ndarray,
    qdo: int,
    tau: np.ndarray,
    to: int,
    p: np.ndarray,
    ws: np.ndarray,
    out: np.ndarray,
    oo: int,
) -> int:
    """q̈ = M⁻¹(τ − C q̇ − G − τ_f) into out[oo:oo+4]; returns a status code (:func:`accel_locked`
    with no joint held: the same arithmetic)."""
    return accel_locked(q, qo, qd, qdo, tau, to, p, ws, out, oo, _NONE_HELD)


@njit(cache=True, error_model="numpy")
def plant_step(ws: np.ndarray, p: np.ndarray, torque_units: np.ndarray, dist_nm: np.ndarray, counts: np.ndarray) -> int:
    """One control period: τ = clamp(units·LSB) + d held, RK4 with P_NSUB sub-steps.

    State ws[R_STATE] = (q, q̇) is advanced in place; ``counts`` gets the nearest encoder
    counts of the new q.  Returns a status code (state untouched-or-partial on failure).
    :func:`plant_step_locked` with no joint held: the same arithmetic."""
    return plant_step_locked(ws, p, torque_units, dist_nm, counts, _NONE_HELD)


@njit(cache=True, error_model="numpy")
def plant_reset(ws: np.ndarray, p: np.ndarray, q0: np.ndarray, qd0: np.ndarray, y_guess: np.ndarray, counts: np.ndarray) -> int:
    """Set the state, solve FK from ``y_guess`` (cold start, no predictor) and the counts."""
    for r in range(ws.shape[0]):
        for k in range(16):
            ws[r, k] = 0.0
    x = ws[R_STATE]
    fk = ws[R_FK]
    for i in range(4):
        x[i] = q0[i]
        x[4 + i] = qd0[i]
        fk[i] = y_guess[i]
    st = eval_terms(x, 0, x, 4, p, ws, False)
    if st != ST_OK:
        return st
    rpc = p[P_RPC]
    for i in range(4):
        counts[i] = np.int64(np.rint(x[i] / rpc))
    return ST_OK


@njit(cache=True, error_model="numpy")
def accel_locked(
    q: np.ndarray,
    qo: int,
    qd: np.ndarray,
    qdo: int,
    tau: np.ndarray,
    to: int,
    p: np.ndarray,
    ws: np.ndarray,
    out: np.ndarray,
    oo: int,
    locked: np.ndarray,
) -> int:
    """:func:`accel` with the joints ``locked[i] != 0`` held (a closed holding brake): q̈_i = 0, and
    the free joints' accelerations solve M_ff q̈_f = (τ − C q̇ − G − τ_f)_f (the locked rows and
    columns of M replaced by the identity, their right-hand side by 0).  Returns a status code."""
    st = eval_terms(q, qo, qd, qdo, p, ws, True)
    if st != ST_OK:
        return st
    v2 = ws[R_V2]
    v3 = ws[R_V3]
    mm = ws[R_M]
    friction_torque(qd, qdo, p, v3, 8)
    for i in range(4):
        out[oo + i] = tau[to + i] - v2[8 + i] - v2[12 + i] - v3[8 + i]
    for i in range(4):
        if locked[i] != 0:
            out[oo + i] = 0.0
            for j in range(4):
                mm[4 * i + j] = 0.0
                mm[4 * j + i] = 0.0
            mm[4 * i + i] = 1.0
    if not chol4_solve(mm, out, oo):
        return ST_M_NOT_PD
    for i in range(4):
        if not math.isfinite(out[oo + i]):
            return ST_NONFINITE
    return ST_OK


@njit(cache=True, error_model="numpy")
def plant_step_locked(
    ws: np.ndarray, p: np.ndarray, torque_units: np.ndarray, dist_nm: np.ndarray, counts: np.ndarray, locked: np.ndarray
) -> int:
    """One control period like :func:`plant_step` with the joints ``locked[i] != 0`` held by their
    brakes: their velocity is set to 0 at the start of the period and they do not move during it
    (:func:`accel_locked`); the other joints move under the torques held.  Returns a status code."""
    x = ws[R_STATE]
    stg = ws[R_STG]
    k1 = ws[R_K1]
    k2 = ws[R_K2]
    aux = ws[R_AUX]
    v3 = ws[R_V3]
    lsb = p[P_TLSB]
    tlim = p[P_TLIM]
    for i in range(4):
        if locked[i] != 0:
            x[4 + i] = 0.0
        t = float(torque_units[i]) * lsb
        sat = 0.0
        if tlim > 0.0:
            if t > tlim:
                t = tlim
                sat = 1.0
            elif t < -tlim:
                t = -tlim
                sat = 1.0
        aux[i] = sat
        v3[12 + i] = t
        stg[12 + i] = t + dist_nm[i]
    nsub = int(p[P_NSUB])
    dt = p[P_TS] / nsub
    h2 = 0.5 * dt
    for _ in range(nsub):
        # the four RK4 stages stay written out for numba: fixed workspace offsets, no closure or allocation per stage
        st = accel_locked(x, 0, x, 4, stg, 12, p, ws, k1, 4, locked)
        if st != ST_OK:
            return st
        for i in range(4):
            k1[i] = x[4 + i]
            stg[i] = x[i] + h2 * x[4 + i]
            stg[4 + i] = x[4 + i] + h2 * k1[4 + i]
        st = accel_locked(stg, 0, stg, 4, stg, 12, p, ws, k1, 12, locked)
        if st != ST_OK:
            return st
        for i in range(4):
            k1[8 + i] = stg[4 + i]
            stg[i] = x[i] + h2 * k1[8 + i]
            stg[4 + i] = x[4 + i] + h2 * k1[12 + i]
        st = accel_locked(stg, 0, stg, 4, stg, 12, p, ws, k2, 4, locked)
        if st != ST_OK:
            return st
        for i in range(4):
            k2[i] = stg[4 + i]
            stg[i] = x[i] + dt * k2[i]
            stg[4 + i] = x[4 + i] + dt * k2[4 + i]
        st = accel_locked(stg, 0, stg, 4, stg, 12, p, ws, k2, 12, locked)
        if st != ST_OK:
            return st
        for i in range(4):
            k2[8 + i] = stg[4 + i]
        c = dt / 6.0
        for i in range(4):
            x[i] += c * (k1[i] + 2.0 * k1[8 + i] + 2.0 * k2[i] + k2[8 + i])
            x[4 + i] += c * (k1[4 + i] + 2.0 * k1[12 + i] + 2.0 * k2[4 + i] + k2[12 + i])
        for i in range(8):
            if not math.isfinite(x[i]):
                return ST_NONFINITE
    rpc = p[P_RPC]
    for i in range(4):
        counts[i] = np.int64(np.rint(x[i] / rpc))
    return ST_OK


# ---- batch kernels for the public (vectorised) API ----------------------------------------


@njit(cache=True, error_model="numpy")
def ik_batch(xs: np.ndarray, p: np.ndarray, qs: np.ndarray) -> int:
    """IK of N task points (N,4) -> qs (N,4); returns -1 or 4*n + limb of the first failure."""
    ybuf = np.empty(4)
    for n in range(xs.shape[0]):
        subplatform_from_task4(xs[n, 0], xs[n, 1], xs[n, 2], xs[n, 3], p, ybuf, 0)
        r = ik_limbs(ybuf[0], ybuf[1], ybuf[2], ybuf[3], p, qs[n], 0)
        if r >= 0:
            return 4 * n + r
    return -1


@njit(cache=True, error_model="numpy")
def fk_batch(qs: np.ndarray, y0: np.ndarray, p: np.ndarray, ys: np.ndarray) -> int:
    """FK of N joint vectors, warm-starting each from the previous solution; -1 or first failing n."""
    a = np.empty(16)
    vec = np.empty(16)
    tr = np.empty(8)
    y = y0.copy()
    for n in range(qs.shape[0]):
        trig4(qs[n], 0, tr)
        its = fk_newton(tr, y, 0, p, a, vec)
        if its < 0:
            return n
        for j in range(4):
            ys[n, j] = y[j]
    return -1


@njit(cache=True, error_model="numpy")
def jacobian_batch(qs: np.ndarray, ys: np.ndarray, p: np.ndarray, js: np.ndarray) -> int:
    """J (N,4,4) at given (q, Y); -1 or first n where A is singular."""
    a = np.empty(16)
    vec = np.empty(16)
    jm = np.empty(16)
    tr = np.empty(8)
    for n in range(qs.shape[0]):
        trig4(qs[n], 0, tr)
        build_a_b(tr, ys[n], 0, p, a, vec)
        if not lu4(a, vec):
            return n
        jacobian_from_lu(a, vec, jm)
        for i in range(4):
            for j in range(4):
                js[n, i, j] = jm[4 * i + j]
    return -1


@njit(cache=True, error_model="numpy")
def jdot_qdot_batch(qs: np.ndarray, qds: np.ndarray, ys: np.ndarray, p: np.ndarray, out: np.ndarray) -> int:
    """J̇q̇ = A⁻¹ w (N,4); Ẏ is computed as J q̇.  -1 or first singular n."""
    a = np.empty(16)
    vec = np.empty(16)
    jm = np.empty(16)
    yd = np.empty(4)
    tr = np.empty(8)
    for n in range(qs.shape[0]):
        trig4(qs[n], 0, tr)
        build_a_b(tr, ys[n], 0, p, a, vec)
        if not lu4(a, vec):
            return n
        jacobian_from_lu(a, vec, jm)
        for i in range(4):
            acc = 0.0
            for j in range(4):
                acc += jm[4 * i + j] * qds[n, j]
            yd[i] = acc
        w_vector(tr, qds[n], 0, ys[n], 0, yd, 0, p, out[n], 0)
        lu4_solve(a, vec, out[n], 0)
    return -1


@njit(cache=True, error_model="numpy")
def joint_rates_batch(
    qs: np.ndarray,
    ys: np.ndarray,
    yds: np.ndarray,
    ydds: np.ndarray,
    p: np.ndarray,
    qds: np.ndarray,
    qdds: np.ndarray,
    want_acc: bool,
) -> int:
    """q̇ = B⁻¹ A Ẏ and (optionally) q̈ = B⁻¹(A Ÿ − w); -1 or 4*n + limb at a serial singularity."""
    a = np.empty(16)
    vec = np.empty(16)
    w = np.empty(4)
    tr = np.empty(8)
    for n in range(qs.shape[0]):
        trig4(qs[n], 0, tr)
        build_a_b(tr, ys[n], 0, p, a, vec)
        for i in range(4):
            b = vec[4 + i]
            if abs(b) < 1e-12:
                return 4 * n + i
            acc = 0.0
            for j in range(4):
                acc += a[4 * i + j] * yds[n, j]
            qds[n, i] = acc / b
        if want_acc:
            w_vector(tr, qds[n], 0, ys[n], 0, yds[n], 0, p, w, 0)
            for i in range(4):
                acc = 0.0
                for j in range(4):
                    acc += a[4 * i + j] * ydds[n, j]
                qdds[n, i] = (acc - w[i]) / vec[4 + i]
    return -1


@njit(cache=True, error_model="numpy")
def dynamics_batch(
    qs: np.ndarray, qds: np.ndarray, y0: np.ndarray, p: np.ndarray, ys: np.ndarray, ms: np.ndarray, cs: np.ndarray, gs: np.ndarray
) -> int:
    """Y, M (N,4,4), C q̇ (N,4), G (N,4) along N states (FK warm-started sample to sample).
    Returns -1, or 16*n + status of the first failure."""
    ws = np.zeros((N_ROWS, 16))
    for j in range(4):
        ws[R_FK, j] = y0[j]
    for n in range(qs.shape[0]):
        st = eval_terms(qs[n], 0, qds[n], 0, p, ws, False)
        if st != ST_OK:
            return 16 * n + st
        for i in range(4):
            ys[n, i] = ws[R_FK, i]
            cs[n, i] = ws[R_V2, 8 + i]
            gs[n, i] = ws[R_V2, 12 + i]
            for j in range(4):
                ms[n, i, j] = ws[R_M, 4 * i + j]
    return -1


@njit(cache=True, error_model="numpy")
def forward_dynamics_batch(
    qs: np.ndarray, qds: np.ndarray, taus: np.ndarray, y0: np.ndarray, p: np.ndarray, qdds: np.ndarray
) -> int:
    """q̈ (N,4) for given τ (incl. friction if configured).  -1 or 16*n + status."""
    ws = np.zeros((N_ROWS, 16))
    for j in range(4):
        ws[R_FK, j] = y0[j]
    for n in range(qs.shape[0]):
        st = accel(qs[n], 0, qds[n], 0, taus[n], 0, p, ws, qdds[n], 0)
        if st != ST_OK:
            return 16 * n + st
    return -1


@njit(cache=True, error_model="numpy")
def friction_batch(qds: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """Friction torque (N,4) for joint velocities (N,4)."""
    for n in range(qds.shape[0]):
        friction_torque(qds[n], 0, p, out[n], 0)
