"""Numba kernel of :mod:`mst.pipeline.autoinit`: the chamfer scores of one pose's edge samples under a
grid of image similarities and shifts (cached on disk; its own module so edits of the search code do
not invalidate the cache). Pixels, radians."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _moved(uv, nrm, c, pp, s, r, n_bins, qu, qv, qb):  # pragma: no cover - numba
    """Samples ``uv`` scaled by ``s`` about ``c``, rotated by ``r`` rad about ``pp``, rounded to whole
    pixels (``qu``, ``qv``), and the orientation bin of their rotated normals (``qb``)."""
    cr, sr = np.cos(r), np.sin(r)
    w = np.pi / n_bins
    for i in range(uv.shape[0]):
        x = c[0] + s * (uv[i, 0] - c[0]) - pp[0]
        y = c[1] + s * (uv[i, 1] - c[1]) - pp[1]
        qu[i] = int(np.rint(cr * x - sr * y + pp[0]))
        qv[i] = int(np.rint(sr * x + cr * y + pp[1]))
        nx = cr * nrm[i, 0] - sr * nrm[i, 1]
        ny = sr * nrm[i, 0] + cr * nrm[i, 1]
        a = np.arctan2(ny, nx)
        if a < 0.0:
            a += np.pi
        if a >= np.pi:
            a -= np.pi
        b = int(a / w)
        qb[i] = b if b < n_bins else n_bins - 1


@njit(cache=True)
def _shift_sums(D, qu, qv, qb, su, sv, acc):  # pragma: no cover - numba
    """``acc[m]`` = mean over the samples of ``D[qb, qv + sv[m], qu + su[m]]`` (1 outside the image).
    Samples outer, shifts inner: consecutive samples lie along one edge in one bin, so their shifted
    reads hit the same cache lines (the sums run over the samples in the same order either way)."""
    B, H, W = D.shape
    M = su.shape[0]
    N = qu.shape[0]
    for m in range(M):
        acc[m] = 0.0
    for i in range(N):
        b, u0, v0 = qb[i], qu[i], qv[i]
        for m in range(M):
            u = u0 + su[m]
            v = v0 + sv[m]
            if u < 0 or u >= W or v < 0 or v >= H:
                acc[m] += 1.0
            else:
                acc[m] += D[b, v, u]
    for m in range(M):
        acc[m] = acc[m] / N


@njit(cache=True)
def sim_shift_means(D, uv, nrm, c, pp, sims, shifts, n_bins):  # pragma: no cover - numba
    """(k, M) mean of ``D[bin, v, u]`` (B, H, W) over the samples ``uv`` (N, 2) with unit normals ``nrm``
    (N, 2), each moved by similarity k (scale ``sims[k, 0]`` about ``c``, then rotation ``sims[k, 1]``
    rad about ``pp``) and shift m (``shifts[m]``, px), rounded to the nearest pixel; a sample moved out
    of the image counts 1. The bin of a normal: its orientation mod pi in ``n_bins`` equal bins."""
    K, M, N = sims.shape[0], shifts.shape[0], uv.shape[0]
    out = np.empty((K, M))
    qu, qv, qb = np.empty(N, np.int64), np.empty(N, np.int64), np.empty(N, np.int64)
    su, sv = np.empty(M, np.int64), np.empty(M, np.int64)
    for m in range(M):
        su[m] = int(np.rint(shifts[m, 0]))
        sv[m] = int(np.rint(shifts[m, 1]))
    for k in range(K):
        _moved(uv, nrm, c, pp, sims[k, 0], sims[k, 1], n_bins, qu, qv, qb)
        _shift_sums(D, qu, qv, qb, su, sv, out[k])
    return out


@njit(cache=True)
def sim_own_shift_means(D, uv, nrm, c, pp, sims, shifts, n_bins):  # pragma: no cover - numba
    """As :func:`sim_shift_means` with a shift set of its own per similarity: ``shifts`` (k, M, 2)."""
    K, M, N = sims.shape[0], shifts.shape[1], uv.shape[0]
    out = np.empty((K, M))
    qu, qv, qb = np.empty(N, np.int64), np.empty(N, np.int64), np.empty(N, np.int64)
    su, sv = np.empty(M, np.int64), np.empty(M, np.int64)
    for k in range(K):
        for m in range(M):
            su[m] = int(np.rint(shifts[k, m, 0]))
            sv[m] = int(np.rint(shifts[k, m, 1]))
        _moved(uv, nrm, c, pp, sims[k, 0], sims[k, 1], n_bins, qu, qv, qb)
        _shift_sums(D, qu, qv, qb, su, sv, out[k])
    return out
