"""Numba kernel of :mod:`mst.pipeline.navfusion`: a linear Kalman filter + RTS smoother (compiled once,
cached on disk; kept in its own module so edits of the fusion code do not invalidate the cache)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def kf_rts(F, Q, x0, P0, ptr, z, H, R, w, gate_k, smooth):  # pragma: no cover - numba
    """Linear Kalman filter (+ RTS smoother). F, Q (K, n, n): transition into step k (F[0] unused);
    measurements of step k are rows ptr[k]:ptr[k+1] of z (L, m), H (L, m, n), R (L, m, m), with
    weights w (L,) (variance / w). gate_k > 0: Huber on the innovation. Returns x (K, n), P (K, n, n)
    and the weights used (L,)."""
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
            Fk = F[k]
            x = Fk @ x
            P = Fk @ P @ Fk.T.copy() + Q[k]
        xp[k] = x
        Pp[k] = P
        for ll in range(ptr[k], ptr[k + 1]):
            Hl = H[ll]
            HT = Hl.T.copy()
            Rl = R[ll] / w[ll]
            nu = z[ll] - Hl @ x
            S = Hl @ P @ HT + Rl
            if gate_k > 0:
                d = np.sqrt(max(nu @ np.linalg.solve(S, nu), 0.0))
                if d > gate_k:
                    Rl = Rl * (d / gate_k)
                    S = Hl @ P @ HT + Rl
                    wout[ll] = w[ll] * gate_k / d
            G = P @ HT @ np.linalg.inv(S)
            x = x + G @ nu
            A = eye - G @ Hl
            P = A @ P @ A.T.copy() + G @ Rl @ G.T.copy()
        xf[k] = x
        Pf[k] = 0.5 * (P + P.T)
    if not smooth:
        return xf, Pf, wout
    xs = xf.copy()
    Ps = Pf.copy()
    for k in range(K - 2, -1, -1):
        C = Pf[k] @ F[k + 1].T.copy() @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + C @ (xs[k + 1] - xp[k + 1])
        Pk = Pf[k] + C @ (Ps[k + 1] - Pp[k + 1]) @ C.T.copy()
        Ps[k] = 0.5 * (Pk + Pk.T)
    return xs, Ps, wout
