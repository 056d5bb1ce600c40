"""CPU-independent small linear algebra of the tracker (the same bits on every x86-64 CPU).

BLAS and LAPACK pick their kernels by CPU (OpenBLAS: Haswell/SkylakeX kernels with fused
multiply-adds, Sandybridge/Nehalem ones without, each with its own blocking and summation order),
so a matrix product, a solve or an inverse differs in its last bits from one CPU to the next. In the
tracker a last bit can flip a decision (a contrast test, a local maximum, a pixel rounding, a health
threshold) and the trajectory then takes another path: before the moving-edge convolutions, the VVS
and the pose products were made BLAS-free, the tea-box trajectory moved by up to 1.0 mm / 0.14 deg
under ``OPENBLAS_CORETYPE=Sandybridge``, and the demo's UAV pass output 157, 80 or 86 model poses
(Haswell, Sandybridge, Nehalem kernels). The convolutions and the VVS loop are numba kernels of
:mod:`mst.pipeline.tracking.kernels`; the pose products are :func:`mst.core.poses.matmul_exact`.

* :func:`solve` / :func:`inverse`: Gaussian elimination with partial pivoting (LAPACK ``getrf``'s
  pivot rule: the largest magnitude, first on ties) in a fixed order, separate IEEE-754 multiplies
  and adds (numba without ``fastmath`` neither fuses nor reorders them); an exact zero pivot is a
  singular matrix (``numpy.linalg.LinAlgError``, as ``numpy.linalg.inv`` raises). Used for the
  pose covariance (an output, and the health tests' Mahalanobis distances).

Single-threaded, ``cache=True`` (warmed by :mod:`mst.eval.c2m.warmup` through ``solve_pose``).
Transcendental functions (sin, exp, atan2) are not covered: numpy's SIMD versions and glibc's FMA
variants differ by an ulp between CPUs (tests/test_reproducibility_cpu.py runs those variants too).
"""

from __future__ import annotations

import numpy as np
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


def solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A^-1 b`` for a small square ``A`` (n, n) and ``b`` (n,) or (n, m), by Gaussian elimination
    with partial pivoting in a fixed order (the same bits on every CPU). Raises
    ``numpy.linalg.LinAlgError`` for a singular ``A`` (an exact zero pivot) like ``numpy.linalg.solve``."""
    A = np.array(A, dtype=np.float64, order="C")
    b = np.asarray(b, dtype=np.float64)
    B = np.array(b.reshape(len(b), -1), dtype=np.float64, order="C")
    if not _lu_solve(A, B):
        raise np.linalg.LinAlgError("Singular matrix")
    return B.reshape(b.shape)


def inverse(A: np.ndarray) -> np.ndarray:
    """``A^-1`` of a small square matrix (see :func:`solve`)."""
    return solve(A, np.eye(len(A)))
