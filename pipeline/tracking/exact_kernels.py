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


@njit(cache=True, nogil=True, error_model="numpy")
def _jacobi_eigh(A, V, sweeps):
    """Diagonalise the symmetric ``A`` (n, n) in place by cyclic Jacobi rotations (pairs (p, q), p < q, in
    order; the rotation of Numerical Recipes' ``jacobi``: ``theta = (a_qq - a_pp) / 2 a_pq``,
    ``t = sgn(theta) / (|theta| + sqrt(theta^2 + 1))``), accumulating the rotations in ``V`` (identity on
    entry): ``A`` ends diagonal (the eigenvalues), ``V``'s columns the unit eigenvectors. Stops when the
    off-diagonal sum is zero or 1e-17 of the diagonal's, or after ``sweeps`` sweeps. Only IEEE-754
    multiplies, adds, divides and square roots (correctly rounded), one at a time: the same bits on
    every CPU, where LAPACK's ``syevd`` depends on the BLAS kernels."""
    n = A.shape[0]
    for _ in range(sweeps):
        off = 0.0
        diag = 0.0
        for p in range(n):
            diag = diag + abs(A[p, p])
            for q in range(p + 1, n):
                off = off + abs(A[p, q])
        if off == 0.0 or off <= 1e-17 * diag:
            return
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:  # a rotation below double precision
                    t = 0.5 / theta
                else:
                    sg = 1.0 if theta >= 0.0 else -1.0
                    t = sg / (abs(theta) + (theta * theta + 1.0) ** 0.5)
                c = 1.0 / (t * t + 1.0) ** 0.5
                s = t * c
                for k in range(n):  # A <- A J
                    akp = A[k, p]
                    akq = A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(n):  # A <- J^T A
                    apk = A[p, k]
                    aqk = A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                A[p, q] = 0.0
                A[q, p] = 0.0
                for k in range(n):  # V <- V J
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
