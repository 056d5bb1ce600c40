"""Numba kernel of :mod:`mst.pipeline.nav.fusion`: a linear Kalman filter + RTS smoother.

Small dense matrices (n <= 9, m = 3) with explicit loops instead of BLAS/LAPACK calls: compiling
those bindings took ~10-30 s, the loops compile in a few seconds (cached on disk; kept in their own
module so edits of the fusion code do not invalidate the cache).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _mm(A, B):  # pragma: no cover - numba
    n, k = A.shape
    m = B.shape[1]
    C = np.zeros((n, m))
    for i in range(n):
        for p in range(k):
            a = A[i, p]
            if a != 0.0:
                for j in range(m):
                    C[i, j] += a * B[p, j]
    return C


@njit(cache=True)
def _mmt(A, B):  # pragma: no cover - numba
    """A @ B.T"""
    n, k = A.shape
    m = B.shape[0]
    C = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for p in range(k):
                s += A[i, p] * B[j, p]
            C[i, j] = s
    return C


@njit(cache=True)
def _mv(A, x):  # pragma: no cover - numba
    n, k = A.shape
    y = np.zeros(n)
    for i in range(n):
        s = 0.0
        for p in range(k):
            s += A[i, p] * x[p]
        y[i] = s
    return y


@njit(cache=True)
def _inv(A):  # pragma: no cover - numba
    """Gauss-Jordan inverse with partial pivoting (small, well-conditioned SPD matrices)."""
    n = A.shape[0]
    M = A.copy()
    I = np.eye(n)
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if p != c:
            for j in range(n):
                M[c, j], M[p, j] = M[p, j], M[c, j]
                I[c, j], I[p, j] = I[p, j], I[c, j]
        d = M[c, c]
        for j in range(n):
            M[c, j] /= d
            I[c, j] /= d
        for r in range(n):
            if r != c:
                f = M[r, c]
                if f != 0.0:
                    for j in range(n):
                        M[r, j] -= f * M[c, j]
                        I[r, j] -= f * I[c, j]
    return I


@njit(cache=True)
def kf_rts(F, Q, x0, P0, ptr, z, H, R, w, gate_k, smooth):  # pragma: no cover - numba
    """Linear Kalman filter (+ RTS smoother). F, Q (K, n, n): transition into step k (F[0] unused);
    measurements of step k are rows ptr[k]:ptr[k+1] of z (L, m), H (L, m, n), R (L, m, m), with
    weights w (L,) (variance / w). gate_k > 0: Huber on the innovation (Mahalanobis d > gate_k:
    variance x d / gate_k). Returns x (K, n), P (K, n, n) and the weights used (L,)."""
    K = F.shape[0]
    n = x0.shape[0]
    xf = np.empty((K, n))
    Pf = np.empty((K, n, n))
    xp = np.empty((K, n))
    Pp = np.empty((K, n, n))
    wout = w.copy()
    x = x0.copy()
    P = P0.copy()
    eye = np.eye(n)
    for k in range(K):
        if k > 0:
            x = _mv(F[k], x)
            P = _mmt(_mm(F[k], P), F[k]) + Q[k]
        xp[k] = x
        Pp[k] = P
        for ll in range(ptr[k], ptr[k + 1]):
            Hl = H[ll]
            Rl = R[ll] / w[ll]
            nu = z[ll] - _mv(Hl, x)
            PHt = _mmt(P, Hl)
            S = _mm(Hl, PHt) + Rl
            if gate_k > 0:
                Si = _inv(S)
                d = np.sqrt(max(np.dot(nu, _mv(Si, nu)), 0.0))
                if d > gate_k:
                    Rl = Rl * (d / gate_k)
                    S = _mm(Hl, PHt) + Rl
                    wout[ll] = w[ll] * gate_k / d
            G = _mm(PHt, _inv(S))
            x = x + _mv(G, nu)
            A = eye - _mm(G, Hl)
            P = _mmt(_mm(A, P), A) + _mmt(_mm(G, Rl), G)
        xf[k] = x
        Pf[k] = 0.5 * (P + P.T)
    if not smooth:
        return xf, Pf, wout
    xs = xf.copy()
    Ps = Pf.copy()
    for k in range(K - 2, -1, -1):
        C = _mm(_mmt(Pf[k], F[k + 1]), _inv(Pp[k + 1]))
        xs[k] = xf[k] + _mv(C, xs[k + 1] - xp[k + 1])
        Pk = Pf[k] + _mmt(_mm(C, Ps[k + 1] - Pp[k + 1]), C)
        Ps[k] = 0.5 * (Pk + Pk.T)
    return xs, Ps, wout


@njit(cache=True)
def _exp3(w):  # pragma: no cover - numba
    """Rodrigues: rotation vector (3,) -> (3, 3)."""
    th = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    if th < 1e-9:
        a, b = 1.0, 0.5
    else:
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / (th * th)
    return np.eye(3) + a * K + b * _mm(K, K)


@njit(cache=True)
def _log3(R):  # pragma: no cover - numba
    """(3, 3) -> rotation vector (3,) (angles well below pi: the innovations of a filter)."""
    c = min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    th = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = 0.5 if th < 1e-9 else th / (2.0 * np.sin(th))
    return v * s


@njit(cache=True)
def mekf_attitude(dts, q_alpha, R0, ptr, R_meas, dtau, C, gate_k):  # pragma: no cover - numba
    """Causal multiplicative EKF of the attitude on a frame grid.

    Nominal rotation R (model frame) and angular rate w (model frame, rad/s), error state
    [theta, dw] with R_true = exp(theta) R; constant-rate model, white angular acceleration PSD
    ``q_alpha``. Measurements of step k: rows ptr[k]:ptr[k+1] of R_meas (L, 3, 3) at times
    step + dtau (L,) with covariances C (L, 3, 3); Huber on the innovation as in :func:`kf_rts`.
    Returns R (K, 3, 3), w (K, 3), P (K, 6, 6), weights (L,)."""
    K = dts.shape[0]
    Rs = np.empty((K, 3, 3))
    ws = np.empty((K, 3))
    Ps = np.empty((K, 6, 6))
    wout = np.ones(R_meas.shape[0])
    R = R0.copy()
    w = np.zeros(3)
    P = np.zeros((6, 6))
    for i in range(3):
        P[i, i] = np.radians(10.0) ** 2
        P[i + 3, i + 3] = np.radians(10.0) ** 2
    eye = np.eye(6)
    for k in range(K):
        if k > 0:
            dt = dts[k]
            R = _mm(_exp3(w * dt), R)
            F = np.eye(6)
            Q = np.zeros((6, 6))
            for i in range(3):
                F[i, i + 3] = dt
                Q[i, i] = q_alpha * dt**3 / 3.0
                Q[i, i + 3] = Q[i + 3, i] = q_alpha * dt**2 / 2.0
                Q[i + 3, i + 3] = q_alpha * dt
            P = _mmt(_mm(F, P), F) + Q
        for ll in range(ptr[k], ptr[k + 1]):
            H = np.zeros((3, 6))
            for i in range(3):
                H[i, i] = 1.0
                H[i, i + 3] = dtau[ll]
            Rp = _mm(_exp3(w * dtau[ll]), R)
            nu = _log3(_mmt(R_meas[ll], Rp))
            Rl = C[ll].copy()
            PHt = _mmt(P, H)
            S = _mm(H, PHt) + Rl
            if gate_k > 0:
                d = np.sqrt(max(np.dot(nu, _mv(_inv(S), nu)), 0.0))
                if d > gate_k:
                    Rl = Rl * (d / gate_k)
                    S = _mm(H, PHt) + Rl
                    wout[ll] = gate_k / d
            G = _mm(PHt, _inv(S))
            dx = _mv(G, nu)
            A = eye - _mm(G, H)
            P = _mmt(_mm(A, P), A) + _mmt(_mm(G, Rl), G)
            R = _mm(_exp3(dx[:3]), R)
            w = w + dx[3:]
        Rs[k] = R
        ws[k] = w
        Ps[k] = 0.5 * (P + P.T)
    return Rs, ws, Ps, wout
