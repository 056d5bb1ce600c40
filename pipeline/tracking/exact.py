"""CPU-independent arithmetic of the tracker's rounding-sensitive steps (the same bits on every x86-64 CPU).

BLAS and LAPACK pick their kernels by CPU (OpenBLAS: Haswell/SkylakeX kernels with fused
multiply-adds, Sandybridge/Nehalem ones without, each with its own blocking and summation order),
so a matrix product or a solve differs in its last bits from one CPU to the next. In the tracker a
last bit can flip a decision (a moving-edge contrast test, a local maximum between two equal reads,
a pixel rounding), and the trajectory then takes another path: the tea-box trajectory moved by
0.68 mm / 0.14 deg under ``OPENBLAS_CORETYPE=Sandybridge``. These kernels fix the order of every
operation instead: each sum runs sequentially in index order with separate IEEE-754 multiplies and
adds (numba without ``fastmath`` neither fuses nor reorders them), so the result is the same on
every CPU and equals the numpy formulations that spell out the same order (the tests' references).

* :func:`masked_conv`: the moving-edge convolutions, ``conv[i, m] = sum_s patches[i, m, s] *
  masks[idx[i], s]``, ``s`` ascending, accumulated in float64 and rounded once to float32.
* :func:`normal_equations`: ``H = J^T wJ`` (6x6) and ``g = wJ^T r`` (6) of a VVS iteration, sums
  over the samples in order, float64.
* :func:`solve` / :func:`inverse`: Gaussian elimination with partial pivoting (LAPACK ``getrf``'s
  pivot rule: the largest magnitude, first on ties) of a small system; an exact zero pivot is a
  singular matrix (``numpy.linalg.LinAlgError``, as ``numpy.linalg.solve`` raises).

No fastmath, single-threaded, ``cache=True`` (warmed by :mod:`mst.eval.c2m.warmup` through
``solve_pose`` and ``search_edges``). Transcendental functions (sin, exp, atan2) are not covered:
numpy's SIMD versions and glibc's FMA variants differ by an ulp between CPUs, which is far below
the thresholds they feed (tests/test_reproducibility_cpu.py runs those variants too).
"""

from __future__ import annotations

import numpy as np
from numba import njit

F32 = np.float32


@njit(cache=True, nogil=True, error_model="numpy")
def masked_conv(patches, masks, mask_idx, conv):
    """``conv (N, M)`` float32 (filled in place): the dot product of each gathered patch
    ``patches (N, M, S)`` float32 with its sample's oriented mask ``masks[mask_idx[i]] (S,)``,
    accumulated in float64 over ``s = 0 .. S-1`` in order and rounded once to float32 (the
    float32 sum in that order gives the same tea-box trajectory; float64 is the more accurate)."""
    N, M, S = patches.shape
    for i in range(N):
        k = mask_idx[i]
        for m in range(M):
            acc = np.float64(patches[i, m, 0]) * np.float64(masks[k, 0])
            for s in range(1, S):
                acc = acc + np.float64(patches[i, m, s]) * np.float64(masks[k, s])
            conv[i, m] = F32(acc)


def masked_conv_numpy(patches: np.ndarray, masks: np.ndarray, mask_idx: np.ndarray) -> np.ndarray:
    """The numpy formulation of :func:`masked_conv` (one elementwise multiply-add per mask pixel,
    the same order): its reference."""
    mk = masks[mask_idx][:, None, :].astype(np.float64)
    p = patches.astype(np.float64)
    conv = p[..., 0] * mk[..., 0]
    for s in range(1, patches.shape[2]):
        conv = conv + p[..., s] * mk[..., s]
    return conv.astype(np.float32)


@njit(cache=True, nogil=True, error_model="numpy")
def _normal_equations(J, wJ, r, H, g):
    n, p = J.shape
    for a in range(p):
        for b in range(p):
            H[a, b] = 0.0
        g[a] = 0.0
    for i in range(n):
        for a in range(p):
            wa = wJ[i, a]
            for b in range(a, p):
                H[a, b] = H[a, b] + wa * J[i, b]
            g[a] = g[a] + wa * r[i]
    for a in range(p):
        for b in range(a):
            H[a, b] = H[b, a]


def normal_equations(J: np.ndarray, wJ: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(H, g) = (J^T wJ, wJ^T r)`` for ``J, wJ (N, P)`` and ``r (N,)`` float64, summed over the
    rows in order (``H[a, b] = sum_i wJ[i, a] J[i, b]`` for ``a <= b``, mirrored below the
    diagonal: symmetric to the bit, as ``J^T W J`` is, and half the products): the CPU-independent
    form of the two BLAS products."""
    p = J.shape[1]
    H = np.empty((p, p))
    g = np.empty(p)
    _normal_equations(np.ascontiguousarray(J, np.float64), np.ascontiguousarray(wJ, np.float64),
                      np.ascontiguousarray(r, np.float64), H, g)
    return H, g


def normal_equations_numpy(J: np.ndarray, wJ: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy formulation of :func:`normal_equations` (row by row, the same order): its reference."""
    p = J.shape[1]
    H = np.zeros((p, p))
    g = np.zeros(p)
    for i in range(len(J)):
        H = H + wJ[i][:, None] * J[i][None, :]
        g = g + wJ[i] * r[i]
    iu = np.triu_indices(p, 1)
    H[iu[1], iu[0]] = H[iu]
    return H, g


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
