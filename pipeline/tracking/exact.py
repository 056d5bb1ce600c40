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
