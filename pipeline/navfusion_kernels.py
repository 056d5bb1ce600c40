"""Numba kernel of :mod:`mst.pipeline.navfusion`: a linear Kalman filter + RTS smoother.

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
