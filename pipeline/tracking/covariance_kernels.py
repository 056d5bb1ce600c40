"""The numba kernels of :mod:`mst.pipeline.tracking.covariance` (the cluster-robust covariance, the PSD
floor, the edge runs), alone in their module so that the covariance's callers need not import numba:
:mod:`mst.pipeline.tracking.compiled` gives them from the ahead-of-time extension when it is current
(:mod:`mst.core.aot`), from numba's JIT otherwise. Their documentation is the covariance module's."""

from __future__ import annotations

import numpy as np
from numba import njit

from mst.pipeline.tracking.covariance import SERIES_LEVERAGE
from mst.pipeline.tracking.kernels import _solve6  # x = A^-1 b, 6x6, the VVS solve's fixed order


@njit(cache=True, nogil=True, error_model="numpy")
def cluster_cov_kernel(X, e, nE, cl, nC, AB, T, fx, fy, w, r, gn, glam, cr2, C_out):
    """The cluster-robust covariance (module docstring; ``cr2`` False: the delete-one-cluster
    jackknife ``(G - 1) / G sum_g ((H - H_g)^-1 s_g) (...)^T``, kept for comparison) into ``C_out (6, 6)``.
    ``X (n, 3)`` model
    points of the samples with a candidate, ``e (n,)`` their edge, ``cl (n,)`` their cluster (``0 ..
    nC - 1``, :func:`edge_chunks`), ``AB (2 nE, 3)`` the edge end
    points, ``w, r (n,)`` their last VVS weights and residuals (px); Jacobians at the pose ``T``; ``glam gn gn^T``
    added to every information matrix (a gauge freedom ``gn`` (6,) fixed; ``glam`` 0: none). Returns
    ``(clusters, ok)``: ``ok`` False when ``H`` (CR2) or a fit without one cluster (CR3) is singular (one cluster alone
    pins a direction: no finite estimate)."""
    n = X.shape[0]
    R00, R01, R02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    R10, R11, R12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    R20, R21, R22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    lnx = np.zeros(nE)
    lny = np.zeros(nE)
    for k in range(nE):
        a0 = R00 * AB[k, 0] + R01 * AB[k, 1] + R02 * AB[k, 2] + t0
        a1 = R10 * AB[k, 0] + R11 * AB[k, 1] + R12 * AB[k, 2] + t1
        a2 = R20 * AB[k, 0] + R21 * AB[k, 1] + R22 * AB[k, 2] + t2
        j = nE + k
        b0 = R00 * AB[j, 0] + R01 * AB[j, 1] + R02 * AB[j, 2] + t0
        b1 = R10 * AB[j, 0] + R11 * AB[j, 1] + R12 * AB[j, 2] + t1
        b2 = R20 * AB[j, 0] + R21 * AB[j, 1] + R22 * AB[j, 2] + t2
        du = fx * b0 / b2 - fx * a0 / a2
        dv = fy * b1 / b2 - fy * a1 / a2
        ln = np.sqrt(du * du + dv * dv) + 1e-12
        lnx[k] = -dv / ln
        lny[k] = du / ln
    G = nC
    S = np.zeros((G, 6))  # s_g
    Hg = np.zeros((G, 6, 6))  # H_g
    used = np.zeros(G, np.bool_)
    J = np.empty(6)
    for i in range(n):
        if w[i] <= 0.0:
            continue
        g = cl[i]
        k = e[i]
        x0 = R00 * X[i, 0] + R01 * X[i, 1] + R02 * X[i, 2] + t0
        x1 = R10 * X[i, 0] + R11 * X[i, 1] + R12 * X[i, 2] + t1
        x2 = R20 * X[i, 0] + R21 * X[i, 1] + R22 * X[i, 2] + t2
        q = 1.0 / x2
        xi, yi = x0 * q, x1 * q
        a_ = lnx[k] * fx
        b_ = lny[k] * fy
        J[0] = a_ * q
        J[1] = b_ * q
        J[2] = -(a_ * xi + b_ * yi) * q
        J[3] = -a_ * xi * yi - b_ * (1.0 + yi * yi)
        J[4] = a_ * (1.0 + xi * xi) + b_ * xi * yi
        J[5] = b_ * xi - a_ * yi
        used[g] = True
        wr = w[i] * r[i]
        for p in range(6):
            S[g, p] += wr * J[p]
            wp = w[i] * J[p]
            for c in range(6):
                Hg[g, p, c] += wp * J[c]
    H = np.zeros((6, 6))
    m = 0
    for g in range(G):
        if used[g]:
            m += 1
            for p in range(6):
                for c in range(6):
                    H[p, c] += Hg[g, p, c]
    for p in range(6):
        for c in range(6):
            C_out[p, c] = 0.0
    if m < 2:
        return m, False
    A = np.empty((6, 6))
    D = np.empty(6)
    if cr2:
        for p in range(6):
            for c in range(6):
                A[p, c] = H[p, c] + glam * gn[p] * gn[c]
        L = np.zeros((6, 6))
        if not _chol6(A, L):
            return m, False
        Y = np.empty((6, 6))
        M = np.empty((6, 6))
        U = np.empty((6, 6))
        lam = np.empty(6)
        y = np.empty(6)
        z = np.empty(6)
    for g in range(G):
        if not used[g]:
            continue
        if cr2:
            # D = L^-T U diag((1 - l)^-1/2) U^T L^-1 s_g with L^-1 H_g L^-T = U diag(l) U^T
            _lower_solve(L, Hg[g], Y)  # Y = L^-1 H_g
            _lower_solve(L, Y.T, M)  # M = L^-1 Y^T = L^-1 H_g L^-T (a view, no copy)
            tr = 0.0
            for p in range(6):
                tr += M[p, p]
                for c in range(p + 1, 6):
                    v = 0.5 * (M[p, c] + M[c, p])
                    M[p, c] = v
                    M[c, p] = v
            for p in range(6):
                v = S[g, p]
                for k in range(p):
                    v -= L[p, k] * y[k]
                y[p] = v / L[p, p]
            if tr < SERIES_LEVERAGE:
                # (I - M)^-1/2 y = sum_k c_k M^k y, c_k = c_(k-1) (2k - 1) / (2k), to the term whose bound
                # c_k tr^k (the leverages sum to tr, each below it) is under 1e-9 relative
                for p in range(6):
                    z[p] = y[p]
                ck = 1.0
                bound = 1.0
                k = 0
                while bound > 1e-9 and k < 200:
                    k += 1
                    for p in range(6):
                        v = 0.0
                        for q in range(6):
                            v += M[p, q] * z[q]
                        lam[p] = v
                    ck *= (2.0 * k - 1.0) / (2.0 * k)
                    bound *= tr
                    for p in range(6):
                        z[p] = lam[p]
                        y[p] += ck * lam[p]
                    bound_k = ck * bound
                    if bound_k <= 1e-9:
                        break
            else:
                _jacobi_eig(M, U, lam)
                for j in range(6):  # z = U diag(f) U^T y
                    v = 0.0
                    for k in range(6):
                        v += U[k, j] * y[k]
                    z[j] = v / np.sqrt(max(1.0 - lam[j], 1e-12))
                for p in range(6):
                    v = 0.0
                    for j in range(6):
                        v += U[p, j] * z[j]
                    y[p] = v
            for p in range(5, -1, -1):  # D = L^-T y
                v = y[p]
                for k in range(p + 1, 6):
                    v -= L[k, p] * D[k]
                D[p] = v / L[p, p]
        else:
            for p in range(6):
                for c in range(6):
                    A[p, c] = H[p, c] - Hg[g, p, c] + glam * gn[p] * gn[c]
            if not _solve6(A, S[g], D):
                return m, False
        for p in range(6):
            for c in range(p, 6):
                C_out[p, c] += D[p] * D[c]
    f = 1.0 if cr2 else (m - 1.0) / m
    for p in range(6):
        for c in range(p, 6):
            C_out[p, c] *= f
            C_out[c, p] = C_out[p, c]
    ok = True
    for p in range(6):
        v = C_out[p, p]
        if not (v == v) or v == np.inf:
            ok = False
    return m, ok


@njit(cache=True, nogil=True, error_model="numpy")
def _chol6(A, L):
    """Lower Cholesky factor ``L`` of the symmetric 6x6 ``A`` (fixed order); False when not positive definite."""
    for j in range(6):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0):
            return False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, 6):
            s = 0.5 * (A[i, j] + A[j, i])
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _lower_solve(L, B, out):
    """``out = L^-1 B`` for a lower-triangular 6x6 ``L`` and a 6x6 ``B`` (forward substitution per column)."""
    for c in range(6):
        for i in range(6):
            s = B[i, c]
            for k in range(i):
                s -= L[i, k] * out[k, c]
            out[i, c] = s / L[i, i]


@njit(cache=True, nogil=True, error_model="numpy")
def _jacobi_eig(M, V, lam):
    """Eigen-decomposition of a symmetric (n, n) ``M`` (destroyed) by cyclic Jacobi rotations in a fixed order:
    ``M = V diag(lam) V^T``."""
    n = M.shape[0]
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(50):
        off = 0.0
        scale = 0.0
        for i in range(n):
            scale += M[i, i] * M[i, i]
            for j in range(i + 1, n):
                off += M[i, j] * M[i, j]
        if off <= 1e-30 * scale or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                if M[p, q] == 0.0:
                    continue
                th = (M[q, q] - M[p, p]) / (2.0 * M[p, q])
                t = (1.0 if th >= 0.0 else -1.0) / (abs(th) + np.sqrt(th * th + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # M <- M G (columns p, q)
                    mkp, mkq = M[k, p], M[k, q]
                    M[k, p] = c * mkp - s * mkq
                    M[k, q] = s * mkp + c * mkq
                for k in range(n):  # M <- G^T M (rows p, q)
                    mpk, mqk = M[p, k], M[q, k]
                    M[p, k] = c * mpk - s * mqk
                    M[q, k] = s * mpk + c * mqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    for i in range(n):
        lam[i] = M[i, i]


@njit(cache=True, nogil=True, error_model="numpy")
def psd_max_kernel(Cf, Cj, out):
    """``out``: the covariance that is ``Cf`` or ``Cj`` along every direction, whichever is larger (the
    ellipsoid containing both, aligned with their joint eigenbasis): with ``Cf = L L^T`` and
    ``L^-1 Cj L^-T = U diag(l) U^T``, ``out = L U diag(max(l, 1)) U^T L^T``. Returns False when ``Cf`` is not
    positive definite (``out`` untouched)."""
    n = 6
    L = np.zeros((n, n))
    if not _chol6(Cf, L):
        return False
    # Y = L^-1 Cj (forward substitution per column), then M = Y L^-T = L^-1 (L^-1 Cj)^T
    Y = np.empty((n, n))
    _lower_solve(L, Cj, Y)
    M = np.empty((n, n))
    _lower_solve(L, Y.T, M)  # M = L^-1 Y^T (a view, no copy)
    for i in range(n):
        for j in range(i + 1, n):
            m = 0.5 * (M[i, j] + M[j, i])
            M[i, j] = m
            M[j, i] = m
    U = np.empty((n, n))
    lam = np.empty(n)
    _jacobi_eig(M, U, lam)
    B = np.empty((n, n))  # L U diag(sqrt(max(l, 1)))
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += L[i, k] * U[k, j]
            B[i, j] = s * np.sqrt(max(lam[j], 1.0))
    for i in range(n):
        for j in range(i, n):
            s = 0.0
            for k in range(n):
                s += B[i, k] * B[j, k]
            out[i, j] = s
            out[j, i] = s
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def edge_chunks_kernel(e, chunk, cl):
    """The cluster ids of :func:`edge_chunks` into ``cl (n,)`` (``e (n,)`` edge ids >= 0); returns their
    count. The clusters in (edge, run) order: an edge's runs start after those of the lower edge ids,
    a sample's run is its rank among its edge's samples (in their order) // ``chunk``."""
    n = e.shape[0]
    ne = 0
    for i in range(n):
        ne = max(ne, e[i] + 1)
    cnt = np.zeros(ne, np.int64)
    for i in range(n):
        cnt[e[i]] += 1
    first = np.empty(ne, np.int64)  # the first cluster id of each edge
    total = 0
    for j in range(ne):
        first[j] = total
        total += (cnt[j] + chunk - 1) // chunk
    seen = np.zeros(ne, np.int64)
    for i in range(n):
        j = e[i]
        cl[i] = first[j] + seen[j] // chunk
        seen[j] += 1
    return total
