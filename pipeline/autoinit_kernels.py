"""Numba kernel of :mod:`mst.pipeline.autoinit`: the chamfer scores of one pose's edge samples under a
grid of image similarities and shifts (cached on disk; its own module so edits of the search code do
not invalidate the cache). Pixels, radians."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def sim_shift_means(D, uv, nrm, c, pp, sims, shifts, n_bins):  # pragma: no cover - numba
    """(k, M) mean of ``D[bin, v, u]`` (B, H, W) over the samples ``uv`` (N, 2) with unit normals ``nrm``
    (N, 2), each moved by similarity k (scale ``sims[k, 0]`` about ``c``, then rotation ``sims[k, 1]``
    rad about ``pp``) and shift m (``shifts[m]``, px), rounded to the nearest pixel; a sample moved out
    of the image counts 1. The bin of a normal: its orientation mod pi in ``n_bins`` equal bins."""
    B, H, W = D.shape
    N = uv.shape[0]
    K = sims.shape[0]
    M = shifts.shape[0]
    out = np.empty((K, M))
    qu = np.empty(N)
    qv = np.empty(N)
    qb = np.empty(N, np.int64)
    w = np.pi / n_bins
    for k in range(K):
        s, r = sims[k, 0], sims[k, 1]
        cr, sr = np.cos(r), np.sin(r)
        for i in range(N):
            x = c[0] + s * (uv[i, 0] - c[0]) - pp[0]
            y = c[1] + s * (uv[i, 1] - c[1]) - pp[1]
            qu[i] = cr * x - sr * y + pp[0]
            qv[i] = sr * x + cr * y + pp[1]
            nx = cr * nrm[i, 0] - sr * nrm[i, 1]
            ny = sr * nrm[i, 0] + cr * nrm[i, 1]
            a = np.arctan2(ny, nx)
            if a < 0.0:
                a += np.pi
            if a >= np.pi:
                a -= np.pi
            b = int(a / w)
            qb[i] = b if b < n_bins else n_bins - 1
        for m in range(M):
            tot = 0.0
            for i in range(N):
                u = int(np.rint(qu[i])) + int(np.rint(shifts[m, 0]))
                v = int(np.rint(qv[i])) + int(np.rint(shifts[m, 1]))
                if u < 0 or u >= W or v < 0 or v >= H:
                    tot += 1.0
                else:
                    tot += D[qb[i], v, u]
            out[k, m] = tot / N
    return out
