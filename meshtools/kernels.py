"""Numba kernels of ``mst convert-model`` (:mod:`mst.meshtools.regions`, :mod:`mst.meshtools.outlines`),
compiled on first use and cached on disk (``cache=True``; :mod:`mst.eval.c2m.warmup` compiles them at
install).

* :func:`components`: connected components of an undirected graph given as an edge list, labelled
  ``0..`` in the order of each component's smallest node: the same labels as
  ``scipy.sparse.csgraph.connected_components(directed=False)`` (or ``connection="weak"``), without
  building a sparse matrix and without importing scipy (about 0.3 s of CPU per process).

* :func:`edge_order`: the half-edges sorted by undirected edge in O(n) (a stable counting sort; the
  order of the two half-edges of one edge never mattered downstream, the order of the edges is the same).
* :func:`triangle_cross`: triangle cross products and their norms in one pass.
* :func:`pair_candidates`, :func:`region_sums`, :func:`plane_ok`: the per-pair and per-triangle passes
  of :func:`mst.meshtools.regions.grow_regions` fused into single loops (no (M, 3, 3) temporaries).

The floating-point kernels do the numpy code's arithmetic in the numpy code's order (dot products
in ``np.einsum``'s order ``(x0*y0 + x2*y2) + x1*y1``, centroids ``((a + b) + c) / 3``, sums over triangles in index
order as ``np.bincount`` does; no fastmath, so no reassociation or fused multiply-add): every result is
bit-identical, and so is every decision taken on it (tests/test_convert_model.py checks it).
"""

from __future__ import annotations

import sys

import numba  # noqa: F401
import numpy as np
from numba import njit

if "numba.np.arraymath" not in sys.modules and "scipy.linalg.cython_blas" not in sys.modules:
    # numba's first compile or cache load imports numba.np.arraymath, which probes for BLAS by importing
    # scipy.linalg (~0.25 s). No kernel here uses BLAS: answer "absent", then restore (as mst.eval.c2m.kernels).
    sys.modules["scipy.linalg.cython_blas"] = None
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules["scipy.linalg.cython_blas"]


#: no kernel here writes into an array argument: the ahead-of-time build may mark the array
#: arguments noalias (mst.core.aot.build)
AOT_NOALIAS = True


@njit(cache=True)
def _components(n, a, b):
    # union-find with path halving; the root of a set is always its smallest node
    parent = np.arange(n)
    for k in range(a.shape[0]):
        x = a[k]
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        y = b[k]
        while parent[y] != y:
            parent[y] = parent[parent[y]]
            y = parent[y]
        if x < y:
            parent[y] = x
        elif y < x:
            parent[x] = y
    lab = np.empty(n, np.int64)
    c = 0
    for i in range(n):  # a root comes before the other nodes of its set
        p = parent[i]
        if p == i:
            lab[i] = c
            c += 1
        else:
            while parent[p] != p:
                p = parent[p]
            parent[i] = p
            lab[i] = lab[p]
    return c, lab


@njit(cache=True, inline="always")
def _dot3(x0, x1, x2, y0, y1, y2):
    # numpy's einsum("ij,ij->i") order for 3 terms: (x0*y0 + x2*y2) + x1*y1 (checked bit for bit by
    # tests/test_convert_model.py against np.einsum, in case another numpy build sums differently)
    return (x0 * y0 + x2 * y2) + x1 * y1


@njit(cache=True)
def pair_candidates(N, f1, f2, consistent, thr):
    """``consistent & (N[f1] . N[f2] >= thr)`` per manifold pair."""
    out = np.empty(f1.shape[0], np.bool_)
    for k in range(f1.shape[0]):
        a = f1[k]
        b = f2[k]
        c = _dot3(N[a, 0], N[a, 1], N[a, 2], N[b, 0], N[b, 1], N[b, 2])
        out[k] = consistent[k] and c >= thr
    return out


@njit(cache=True)
def region_sums(X, F, N, w, lab, n_lab):
    """Per label: ``sum(N * w)`` (n_lab, 3), ``sum(centroid * w)`` (n_lab, 3) and ``sum(w)`` (n_lab,)."""
    nsum = np.zeros((n_lab, 3))
    csum = np.zeros((n_lab, 3))
    wsum = np.zeros(n_lab)
    for i in range(F.shape[0]):
        r = lab[i]
        wi = w[i]
        a = F[i, 0]
        b = F[i, 1]
        c = F[i, 2]
        for k in range(3):
            nsum[r, k] += N[i, k] * wi
            csum[r, k] += (X[a, k] + X[b, k] + X[c, k]) / 3.0 * wi
        wsum[r] += wi
    return nsum, csum, wsum


@njit(cache=True)
def plane_ok(X, F, N, lab, nR, cR, half, dist_tol):
    """Per triangle: its normal within ``half`` (a cosine) of its region's normal ``nR`` and its three
    vertices within ``dist_tol`` of the region plane (normal ``nR`` through ``cR``)."""
    out = np.empty(F.shape[0], np.bool_)
    for i in range(F.shape[0]):
        r = lab[i]
        n0 = nR[r, 0]
        n1 = nR[r, 1]
        n2 = nR[r, 2]
        if not _dot3(N[i, 0], N[i, 1], N[i, 2], n0, n1, n2) >= half:
            out[i] = False
            continue
        off = _dot3(cR[r, 0], cR[r, 1], cR[r, 2], n0, n1, n2)
        d = 0.0
        for j in range(3):
            v = F[i, j]
            dj = abs(_dot3(X[v, 0], X[v, 1], X[v, 2], n0, n1, n2) - off)
            if dj > d:
                d = dj
        out[i] = d <= dist_tol
    return out


@njit(cache=True)
def triangle_cross(X, F):
    """Per triangle ``cr = (b - a) x (c - a)`` (M, 3) and ``|cr|`` (M,), in numpy's order
    (``np.cross``: ``y1*z2 - y2*z1`` ...; ``np.linalg.norm``: ``sqrt((c0^2 + c1^2) + c2^2)``)."""
    M = F.shape[0]
    cr = np.empty((M, 3))
    area2 = np.empty(M)
    for i in range(M):
        a = F[i, 0]
        b = F[i, 1]
        c = F[i, 2]
        e0 = X[b, 0] - X[a, 0]
        e1 = X[b, 1] - X[a, 1]
        e2 = X[b, 2] - X[a, 2]
        g0 = X[c, 0] - X[a, 0]
        g1 = X[c, 1] - X[a, 1]
        g2 = X[c, 2] - X[a, 2]
        c0 = e1 * g2 - e2 * g1
        c1 = e2 * g0 - e0 * g2
        c2 = e0 * g1 - e1 * g0
        cr[i, 0] = c0
        cr[i, 1] = c1
        cr[i, 2] = c2
        area2[i] = np.sqrt((c0 * c0 + c1 * c1) + c2 * c2)
    return cr, area2


@njit(cache=True, inline="always")  # compiled into edge_groups
def edge_order(u, v, nv):
    """Half-edges ``u[h] -> v[h]`` sorted by undirected key ``(min, max)``, stably (ties in index
    order): a counting sort by the smaller vertex, then each bucket by the larger one."""
    n = u.shape[0]
    cnt = np.zeros(nv + 1, np.int64)
    for h in range(n):
        cnt[min(u[h], v[h]) + 1] += 1
    for i in range(nv):
        cnt[i + 1] += cnt[i]
    pos = cnt[:-1].copy()
    order = np.empty(n, np.int64)
    for h in range(n):
        m = min(u[h], v[h])
        order[pos[m]] = h
        pos[m] += 1
    for i in range(nv):
        lo = cnt[i]
        hi = cnt[i + 1]
        if hi - lo > 32:  # a high-valence vertex: merge sort (stable), not insertion
            sub = order[lo:hi].copy()
            keys = np.empty(hi - lo, np.int64)
            for j in range(hi - lo):
                keys[j] = max(u[sub[j]], v[sub[j]])
            o = np.argsort(keys, kind="mergesort")
            for j in range(hi - lo):
                order[lo + j] = sub[o[j]]
            continue
        for j in range(lo + 1, hi):
            h = order[j]
            k = max(u[h], v[h])
            q = j - 1
            while q >= lo and max(u[order[q]], v[order[q]]) > k:
                order[q + 1] = order[q]
                q -= 1
            order[q + 1] = h
    return order


@njit(cache=True)
def edge_groups(u, v, nv):
    """:func:`edge_order` and the grouping of :class:`mst.meshtools.regions.Edges` in one pass:
    ``(order, start, count, edge, pair)``."""
    order = edge_order(u, v, nv)
    n = order.shape[0]
    start = np.empty(n, np.int64)
    edge = np.empty(n, np.int64)
    ne = 0
    prev = -1
    for j in range(n):
        h = order[j]
        key = min(u[h], v[h]) * nv + max(u[h], v[h])
        if j == 0 or key != prev:
            start[ne] = j
            ne += 1
            prev = key
        edge[h] = ne - 1
    start = start[:ne].copy()
    count = np.empty(ne, np.int64)
    n_pair = 0
    for e in range(ne):
        count[e] = (start[e + 1] if e + 1 < ne else n) - start[e]
        if count[e] == 2:
            n_pair += 1
    pair = np.empty((n_pair, 2), np.int64)
    k = 0
    for e in range(ne):
        if count[e] == 2:
            pair[k, 0] = order[start[e]]
            pair[k, 1] = order[start[e] + 1]
            k += 1
    return order, start, count, edge, pair


# the validating wrapper of _components lives in mst.meshtools.compiled (no numba import there)
from mst.meshtools.compiled import components  # noqa: E402

__all__ = ["components", "edge_groups", "edge_order", "triangle_cross", "pair_candidates", "plane_ok", "region_sums"]
