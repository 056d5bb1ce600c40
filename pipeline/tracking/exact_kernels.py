"""The numba kernel of :mod:`mst.pipeline.tracking.exact` (Gaussian elimination in a fixed order), alone in
its module so that its callers need not import numba (:mod:`mst.pipeline.tracking.compiled`)."""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def _lu_solve(A, B):
    """Solve ``A X = B`` in place (``A`` (n, n) overwritten by its LU factors, ``B`` (n, m) by X).
    Returns False on an exact zero pivot (singular)."""
    n = A.shape[0]
    m = B.shape[1]
    for k in range(n):
        p = k
        best = abs(A[k, k])
        for i in range(k + 1, n):
            v = abs(A[i, k])
            if v > best:
                best = v
                p = i
        if best == 0.0:  # an exact zero column: singular (NaN propagates, as through LAPACK)
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            for j in range(m):
                B[k, j], B[p, j] = B[p, j], B[k, j]
        d = A[k, k]
        for i in range(k + 1, n):
            f = A[i, k] / d
            A[i, k] = f
            for j in range(k + 1, n):
                A[i, j] = A[i, j] - f * A[k, j]
            for j in range(m):
                B[i, j] = B[i, j] - f * B[k, j]
    for k in range(n - 1, -1, -1):
        d = A[k, k]
        for j in range(m):
            s = B[k, j]
            for c in range(k + 1, n):
                s = s - A[k, c] * B[c, j]
            B[k, j] = s / d
    return True
