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

The kernel is :func:`mst.pipeline.tracking.exact_kernels._lu_solve` (compiled ahead of time or
numba's JIT, :mod:`mst.pipeline.tracking.compiled`). Single-threaded, ``cache=True`` (warmed by
:mod:`mst.eval.c2m.warmup` through ``solve_pose``).
Transcendental functions (sin, exp, atan2) are not covered: numpy's SIMD versions and glibc's FMA
variants differ by an ulp between CPUs (tests/test_reproducibility_cpu.py runs those variants too).
"""

from __future__ import annotations

import math

import numpy as np

from mst.pipeline.tracking.compiled import exact as _ek  # the LU kernel (mst.pipeline.tracking.exact_kernels)


def solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A^-1 b`` for a small square ``A`` (n, n) and ``b`` (n,) or (n, m), by Gaussian elimination
    with partial pivoting in a fixed order (the same bits on every CPU). Raises
    ``numpy.linalg.LinAlgError`` for a singular ``A`` (an exact zero pivot) like ``numpy.linalg.solve``."""
    A = np.array(A, dtype=np.float64, order="C")
    b = np.asarray(b, dtype=np.float64)
    B = np.array(b.reshape(len(b), -1), dtype=np.float64, order="C")
    if not _ek._lu_solve(A, B):
        raise np.linalg.LinAlgError("Singular matrix")
    return B.reshape(b.shape)


def inverse(A: np.ndarray) -> np.ndarray:
    """``A^-1`` of a small square matrix (see :func:`solve`)."""
    return solve(A, np.eye(len(A)))


# ---------------------------------------------------------------------------- small products without BLAS
# numpy's ``@`` hands float64 products, even a 3-vector's dot, to BLAS (gemm, gemv, dot), whose kernels
# round differently per CPU; these sum in a fixed order with separate multiplies and adds instead.
def mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``M @ x`` for a (N, 3) matrix (a 3x3 rotation, N normals) and a (3,) vector:
    ``(M[:, 0] x0 + M[:, 1] x1) + M[:, 2] x2``, (N,)."""
    M = np.asarray(M, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    return (M[:, 0] * x[0] + M[:, 1] * x[1]) + M[:, 2] * x[2]


def dot3(a: np.ndarray, b: np.ndarray) -> float:
    """``a @ b`` of two (3,) vectors: ``(a0 b0 + a1 b1) + a2 b2``."""
    return float((float(a[0]) * float(b[0]) + float(a[1]) * float(b[1])) + float(a[2]) * float(b[2]))


def rigid(X: np.ndarray, R: np.ndarray, t=None) -> np.ndarray:
    """``X @ R.T (+ t)`` for (N, 3) points (:func:`mst.pipeline.tracking.depth_buffer._mat3`: a kernel for
    float64, numpy's elementwise products for float32)."""
    from mst.pipeline.tracking.depth_buffer import _mat3

    X = np.asarray(X)
    return _mat3(X, np.asarray(R, dtype=np.float32 if X.dtype == np.float32 else np.float64), t)


def centre(T_cam_model: np.ndarray) -> np.ndarray:
    """(3,) camera centre in the model frame, ``-R^T t`` of a (4, 4) ``T_cam_model``."""
    T = np.asarray(T_cam_model, dtype=np.float64)
    return -mv(T[:3, :3].T, T[:3, 3])


def norm3(v: np.ndarray) -> float:
    """Euclidean length of a (3,) vector (``numpy.linalg.norm`` of a vector is a BLAS ``dot``)."""
    return math.sqrt(dot3(v, v))


def eigh(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (n,) ascending and unit eigenvectors (columns of (n, n)) of a small symmetric ``S``, as
    ``numpy.linalg.eigh`` (LAPACK ``syevd``, whose bits depend on the CPU's BLAS kernels) by cyclic Jacobi
    rotations (:func:`mst.pipeline.tracking.exact_kernels._jacobi_eigh`): the same bits on every CPU; within
    1e-13 of the largest eigenvalue of numpy's (tests/test_exact_linalg.py; a 6x6: ~10 us, numpy's 8 us). The vectors' signs are arbitrary (LAPACK's
    too). NaN in, NaN out."""
    A = np.array(S, dtype=np.float64, order="C")
    V = np.eye(len(A))
    _ek._jacobi_eigh(A, V, 60)
    lam = np.diagonal(A).copy()
    order = np.argsort(lam, kind="stable")
    return lam[order], np.ascontiguousarray(V[:, order])


def eigvalsh(S: np.ndarray) -> np.ndarray:
    """Eigenvalues (n,) ascending of a small symmetric ``S`` (:func:`eigh`)."""
    return eigh(S)[0]


def quad_form(x: np.ndarray, W: np.ndarray) -> float:
    """``x @ W @ x`` for a (n,) vector and a (n, n) matrix, summed in index order."""
    from mst.core.poses import matmul_exact

    Wx = matmul_exact(W, np.asarray(x, dtype=np.float64)[:, None])[:, 0]
    s = 0.0
    for a, b in zip(np.asarray(x, dtype=np.float64).tolist(), Wx.tolist()):
        s += a * b
    return s
