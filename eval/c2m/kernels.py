"""Numba kernels of the C2M grid engine (compiled on first use, cached on disk).

Same mathematics as :func:`mst.eval.c2m.triangle_distances` (float64, no fastmath): the projection
on the triangle's plane decides "interior" (distance = height over the plane), otherwise the nearest
of the three edge segments. Feature codes: 0 interior, 1/2/3 vertex a/b/c, 4/5/6 edge ab/ac/bc.

The triangles come as one packed table ``T`` (m, 24) float64 (:func:`mst.eval.c2m.grids.triangle_table`):
columns 0-2 corner a, 3-5 b - a, 6-8 c - a, 9-11 c - b, 12-14 unit normal, 15-17 inverse Gram entries
(g00, g01, g11), 18-23 bounding box (min xyz, max xyz). One array instead of seven: a triangle is one
192-byte row, and an inlined helper binds one array, whose reference count numba updates (atomically)
where it cannot prove the update redundant: with seven arrays that was 2-8 atomic updates per
triangle or cell tested, 3x the search time of the serial (ahead-of-time) build. For the same reason
the searches of :func:`grid_query` and :func:`bins_query` (its cell scan included) are written out in
their loops: as inlined helpers taking the arrays they ran 2x slower, 25% of the 200k-triangle bench
case went to those atomic updates (only the rare far-point scan keeps :func:`_scan_cell`).
Kernels never write into their array arguments (the ahead-of-time build marks them noalias).
Loops run in parallel over points (``prange``), using every core; the searches visit their points in
blocks of :data:`QUERY_BLOCK` (gathered in visiting order, searched, scattered back).

Longer than 500 lines: the searches are written out in their loops (helpers taking arrays cost the
atomic reference counting above), and the dense grid's, the binned grid's and the shared geometry
kernels are compiled ahead of time as one extension module (:mod:`mst.core.aot`), one source file.
"""

from __future__ import annotations

import os

# idle OpenMP workers sleep instead of spinning (read when the OpenMP layer starts, at the first
# parallel call): spinning workers would steal the main thread's core on a 2-core machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402

if "numba.np.arraymath" not in sys.modules and "scipy.linalg.cython_blas" not in sys.modules:
    # numba's first compile or cache load imports numba.np.arraymath, which probes for BLAS by
    # importing scipy.linalg (~0.25 s of every run). The probe only selects BLAS for np.correlate /
    # np.convolve inner products (a plain loop otherwise); no kernel here uses them, so it is
    # answered "absent" (a None entry in sys.modules makes that import fail at once), then restored.
    sys.modules["scipy.linalg.cython_blas"] = None
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules["scipy.linalg.cython_blas"]

# OpenMP first: the TBB found beside some wheels is too old and numba warns on stderr when it tries it
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


#: no kernel here writes into an array argument: the ahead-of-time build may mark the array
#: arguments noalias (mst.core.aot.build)
AOT_NOALIAS = True


@njit(cache=True, inline="always")
def _seg(qx, qy, qz, dx, dy, dz):
    den = dx * dx + dy * dy + dz * dz
    t = (qx * dx + qy * dy + qz * dz) / den
    if t < 0.0:
        t = 0.0
    elif t > 1.0:
        t = 1.0
    rx, ry, rz = qx - t * dx, qy - t * dy, qz - t * dz
    return rx * rx + ry * ry + rz * rz, t


@njit(cache=True, inline="always")
def pt_tri(px, py, pz, k, T):
    """Squared distance and feature code of point p to triangle k of the table ``T``."""
    apx, apy, apz = px - T[k, 0], py - T[k, 1], pz - T[k, 2]
    abx, aby, abz = T[k, 3], T[k, 4], T[k, 5]
    acx, acy, acz = T[k, 6], T[k, 7], T[k, 8]
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    v = T[k, 15] * d1 + T[k, 16] * d2
    w = T[k, 16] * d1 + T[k, 17] * d2
    if v >= 0.0 and w >= 0.0 and v + w <= 1.0:
        h = apx * T[k, 12] + apy * T[k, 13] + apz * T[k, 14]
        return h * h, 0
    best, t = _seg(apx, apy, apz, abx, aby, abz)
    e, bt = 0, t
    r, t = _seg(apx, apy, apz, acx, acy, acz)
    if r < best:
        best, e, bt = r, 1, t
    r, t = _seg(apx - abx, apy - aby, apz - abz, T[k, 9], T[k, 10], T[k, 11])
    if r < best:
        best, e, bt = r, 2, t
    if bt <= 0.0:
        f = 1 if e < 2 else 2
    elif bt >= 1.0:
        f = 2 if e == 0 else 3
    else:
        f = 4 + e
    return best, f


@njit(cache=True, inline="always")
def _box_d2(px, py, pz, k, T):
    """Squared distance from p to the bounding box of triangle k (a lower bound of its distance)."""
    ex = max(T[k, 18] - px, 0.0, px - T[k, 21])
    ey = max(T[k, 19] - py, 0.0, py - T[k, 22])
    ez = max(T[k, 20] - pz, 0.0, pz - T[k, 23])
    return ex * ex + ey * ey + ez * ez


@njit(cache=True, inline="always")
def _scan_cell(px, py, pz, c, start, items, T, best, bt, bf):
    """The nearest of grid cell ``c``'s triangles (``items[start[c]:start[c + 1]]``) to the point,
    if nearer than ``best`` (squared, m^2): the updated ``(best, triangle, feature)``; a triangle
    whose bounding box is already no nearer is skipped."""
    for j in range(start[c], start[c + 1]):
        k = np.int64(items[j])
        if _box_d2(px, py, pz, k, T) >= best:
            continue
        r2, f = pt_tri(px, py, pz, k, T)
        if r2 < best:
            best, bt, bf = r2, k, f
    return best, bt, bf


@njit(cache=True, parallel=True)
def pairs_d2(C, cell_of, ti, T):
    """Squared distances of points ``C[cell_of[i]]`` to triangles ``ti[i]``."""
    n = len(ti)
    out = np.empty(n)
    for i in prange(n):
        c = cell_of[i]
        out[i] = pt_tri(C[c, 0], C[c, 1], C[c, 2], ti[i], T)[0]
    return out


@njit(cache=True)
def bucket_order(P, lo, inv_h, dims, shift):
    """Permutation grouping points by coarse buckets (grid cells ``>> shift`` per axis), counting sort.

    Visiting points in this order keeps the grid lookups of consecutive points in cache.
    """
    n = len(P)
    bx, by, bz = (dims[0] >> shift) + 1, (dims[1] >> shift) + 1, (dims[2] >> shift) + 1
    nb = bx * by * bz + 1
    cnt = np.zeros(nb + 1, np.int64)
    order = np.empty(n, np.int64)
    # two passes computing each point's bucket (the last one: outside the grid), counting then placing:
    # no (n,) key array (6.5 MB of fresh pages per 810k points); written out, not as a helper taking
    # the arrays (see the module docstring)
    for rep in range(2):
        for i in range(n):
            fx = (P[i, 0] - lo[0]) * inv_h
            fy = (P[i, 1] - lo[1]) * inv_h
            fz = (P[i, 2] - lo[2]) * inv_h
            b = nb - 1
            if 0.0 <= fx < dims[0] and 0.0 <= fy < dims[1] and 0.0 <= fz < dims[2]:
                ix, iy, iz = int(fx), int(fy), int(fz)
                if ix < dims[0] and iy < dims[1] and iz < dims[2]:
                    b = ((ix >> shift) * by + (iy >> shift)) * bz + (iz >> shift)
            if rep == 0:
                cnt[b + 1] += 1
            else:
                order[cnt[b]] = i
                cnt[b] += 1
        if rep == 0:
            for b in range(nb):
                cnt[b + 1] += cnt[b]
    return order


#: points per block of the searches: each block's points are gathered into visiting order in a
#: small buffer (96 KiB, reused: no fresh pages), searched in sequence, the results scattered back
QUERY_BLOCK = 4096


@njit(cache=True, parallel=True)
def grid_query(P, lo, inv_h, dims, cell, lb, cand, max_dist, T, order):
    """Nearest triangle of every point from its grid cell's candidate list.

    ``cell[c]`` packs ``(start << 16) | count`` of cell c's candidates in ``cand`` (-1: not computed).
    The triangles' bounding boxes (``T[:, 18:24]``) skip candidates cheaply. Points are visited in
    ``order`` (a spatially coherent permutation), :data:`QUERY_BLOCK` at a time: gathered into a
    buffer, searched in sequence, the results scattered back (indexing through ``order`` inside the
    search was 2x slower on a shuffled cloud: a random read and four random writes between the steps
    of every search). Returns ``(tri, d2, feature, status)``; status 0 done, 1 outside the grid (not
    evaluated), 2 cell not computed yet (not evaluated), 3 farther than ``max_dist`` (tri -1).
    ``max_dist`` < 0: none.
    """
    n = len(P)
    tri = np.empty(n, np.int64)
    d2 = np.empty(n)
    feat = np.empty(n, np.int8)
    status = np.empty(n, np.int8)
    dy, dz = dims[1], dims[2]
    B = QUERY_BLOCK
    for blk in prange((n + B - 1) // B):
        b0 = blk * B
        m = min(n, b0 + B) - b0
        Ps = np.empty((B, 3))
        ts = np.empty(B, np.int64)
        ds = np.empty(B)
        fs = np.empty(B, np.int8)
        ss = np.empty(B, np.int8)
        for t in range(m):
            i = order[b0 + t]
            Ps[t, 0], Ps[t, 1], Ps[t, 2] = P[i, 0], P[i, 1], P[i, 2]
        for t in range(m):  # the search, written out (an inlined helper taking the arrays ran 2x slower)
            px, py, pz = Ps[t, 0], Ps[t, 1], Ps[t, 2]
            ts[t], ds[t], fs[t], ss[t] = -1, np.inf, 0, 0
            fx = (px - lo[0]) * inv_h
            fy = (py - lo[1]) * inv_h
            fz = (pz - lo[2]) * inv_h
            if not (0.0 <= fx < dims[0] and 0.0 <= fy < dims[1] and 0.0 <= fz < dims[2]):
                ss[t] = 1
                continue
            ix, iy, iz = int(fx), int(fy), int(fz)
            if ix >= dims[0] or iy >= dy or iz >= dz:
                ss[t] = 1
                continue
            c = (ix * dy + iy) * dz + iz
            word = cell[c]
            if word < 0:
                ss[t] = 2
                continue
            if max_dist >= 0.0 and lb[c] > max_dist:
                ss[t] = 3
                continue
            best = np.inf
            bt = -1
            bf = 0
            s = word >> 16
            for j in range(word & 0xFFFF):
                k = np.int64(cand[s + j])
                if j > 0 and _box_d2(px, py, pz, k, T) >= best:  # box already farther than the best
                    continue
                r, f = pt_tri(px, py, pz, k, T)
                if r < best:
                    best, bt, bf = r, k, f
            ts[t], ds[t], fs[t] = bt, best, bf
        for t in range(m):
            i = order[b0 + t]
            tri[i], d2[i], feat[i], status[i] = ts[t], ds[t], fs[t], ss[t]
    return tri, d2, feat, status


@njit(cache=True)
def missing_cells(P, lo, inv_h, dims, cell):
    """Sorted flat ids of the grid cells that hold a point of ``P`` and have no candidate list yet
    (``cell[c] < 0``): ``np.unique`` of the points' cells without the sort (a mark per cell)."""
    mark = np.zeros(len(cell), np.bool_)
    cnt = 0
    for i in range(len(P)):
        fx = (P[i, 0] - lo[0]) * inv_h
        fy = (P[i, 1] - lo[1]) * inv_h
        fz = (P[i, 2] - lo[2]) * inv_h
        if not (0.0 <= fx < dims[0] and 0.0 <= fy < dims[1] and 0.0 <= fz < dims[2]):
            continue
        ix, iy, iz = int(fx), int(fy), int(fz)
        if ix >= dims[0] or iy >= dims[1] or iz >= dims[2]:
            continue
        c = (ix * dims[1] + iy) * dims[2] + iz
        if cell[c] < 0 and not mark[c]:
            mark[c] = True
            cnt += 1
    out = np.empty(cnt, np.int64)
    k = 0
    for c in range(len(cell)):
        if mark[c]:
            out[k] = c
            k += 1
    return out


@njit(cache=True, parallel=True)
def refine_cells(centres, r, par, pptr, ptri, tol, T):
    """Candidate lists of cells (centres (n, 3), half-diagonal ``r``) from their parents' lists.

    Keeps the parent candidates whose distance to the cell centre is at most ``dmin + 2 r + tol``,
    ordered by that distance (ties: by triangle id). One pass over a parent's list finds ``dmin``
    and keeps each candidate's box bound and distance (when computed) in a scratch row, a second pass
    over the scratch selects; the selected lists go to an upper-bound buffer (the parents' list
    lengths), then are packed. Returns ``(ptr (n + 1,), tri, lower_bound (n,) = dmin - r)``.
    """
    n = len(centres)
    dmin = np.empty(n)
    cnt = np.zeros(n, np.int64)
    ub = np.zeros(n + 1, np.int64)
    mx = 0
    for i in range(n):
        c = pptr[par[i] + 1] - pptr[par[i]]
        ub[i + 1] = ub[i] + c
        mx = max(mx, c)
    tbuf = np.empty(ub[n], np.int64)
    kbuf = np.empty(ub[n])
    blk = 256
    for bi in prange((n + blk - 1) // blk):
        sbox = np.empty(mx)
        sd2 = np.empty(mx)
        for i in range(bi * blk, min(n, (bi + 1) * blk)):
            p = par[i]
            cx, cy, cz = centres[i, 0], centres[i, 1], centres[i, 2]
            j0, j1 = pptr[p], pptr[p + 1]
            best = np.inf
            for j in range(j0, j1):
                bx = _box_d2(cx, cy, cz, ptri[j], T)
                sbox[j - j0] = bx
                if bx >= best:
                    sd2[j - j0] = -1.0  # not computed
                    continue
                d2 = pt_tri(cx, cy, cz, ptri[j], T)[0]
                sd2[j - j0] = d2
                if d2 < best:
                    best = d2
            dmin[i] = np.sqrt(best)
            lim = dmin[i] + 2.0 * r + tol
            lim2 = lim * lim
            b = ub[i]
            k = b
            for j in range(j0, j1):
                if sbox[j - j0] > lim2:
                    continue
                d2 = sd2[j - j0]
                if d2 < 0.0:
                    d2 = pt_tri(cx, cy, cz, ptri[j], T)[0]
                if d2 <= lim2:
                    # insertion by distance to the centre, then triangle id (lists are short): the
                    # order does not depend on the parent list's
                    t = ptri[j]
                    q = k
                    while q > b and (kbuf[q - 1] > d2 or (kbuf[q - 1] == d2 and tbuf[q - 1] > t)):
                        tbuf[q] = tbuf[q - 1]
                        kbuf[q] = kbuf[q - 1]
                        q -= 1
                    tbuf[q] = t
                    kbuf[q] = d2
                    k += 1
            cnt[i] = k - b
    ptr = np.zeros(n + 1, np.int64)
    for i in range(n):
        ptr[i + 1] = ptr[i] + cnt[i]
    tri = np.empty(ptr[n], np.int64)
    for i in prange(n):
        for q in range(cnt[i]):
            tri[ptr[i] + q] = tbuf[ub[i] + q]
    return ptr, tri, dmin - r


@njit(cache=True, parallel=True)
def shift_points(xyz, shift, max_coord):
    """``(xyz - shift, finite mask, rows with a finite |coordinate| > max_coord)`` in one pass (float64)."""
    n = len(xyz)
    P = np.empty((n, 3))
    fin = np.empty(n, np.bool_)
    n_far = 0
    for i in prange(n):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        fx, fy, fz = np.isfinite(x), np.isfinite(y), np.isfinite(z)
        fin[i] = fx and fy and fz
        if (fx and abs(x) > max_coord) or (fy and abs(y) > max_coord) or (fz and abs(z) > max_coord):
            n_far += 1
        P[i, 0], P[i, 1], P[i, 2] = x - shift[0], y - shift[1], z - shift[2]
    return P, fin, n_far


@njit(cache=True)
def threshold_sums(d, thresholds):
    """Per threshold t: count, sum and sum of squares of the finite ``d < t``; plus overall
    count, sum, sum of squares, min, max of the finite values (one pass)."""
    k = len(thresholds)
    cnt = np.zeros(k + 1, np.int64)
    s1 = np.zeros(k + 1)
    s2 = np.zeros(k + 1)
    lo, hi = np.inf, -np.inf
    for i in range(len(d)):
        x = d[i]
        if not np.isfinite(x):
            continue
        cnt[k] += 1
        s1[k] += x
        s2[k] += x * x
        if x < lo:
            lo = x
        if x > hi:
            hi = x
        for j in range(k):
            if x < thresholds[j]:
                cnt[j] += 1
                s1[j] += x
                s2[j] += x * x
    return cnt, s1, s2, lo, hi


# ------------------------------------------------------------------ binned grid (large meshes)
@njit(cache=True)
def bin_triangles(BB, lo, inv_h, dims):
    """Conservative binning of triangles into the cells their bounding boxes overlap (CSR).

    ``BB`` (m, 6) triangle boxes (min xyz, max xyz), ``lo`` (3,) grid origin, ``inv_h`` 1 / cell size,
    ``dims`` (3,) cells per axis. Returns ``(start (cells + 1,) int64, items (start[-1],) int32)``:
    the triangles of cell ``c = (ix * ny + iy) * nz + iz`` are ``items[start[c]:start[c + 1]]``.
    """
    m = len(BB)
    nx, ny, nz = dims[0], dims[1], dims[2]
    rng = np.empty((m, 6), np.int64)
    start = np.zeros(nx * ny * nz + 1, np.int64)
    for k in range(m):
        for a in range(3):
            n_a = dims[a]
            i0 = int(np.floor((BB[k, a] - lo[a]) * inv_h))
            i1 = int(np.floor((BB[k, 3 + a] - lo[a]) * inv_h))
            rng[k, a] = min(max(i0, 0), n_a - 1)
            rng[k, 3 + a] = min(max(i1, 0), n_a - 1)
        for ix in range(rng[k, 0], rng[k, 3] + 1):
            for iy in range(rng[k, 1], rng[k, 4] + 1):
                for iz in range(rng[k, 2], rng[k, 5] + 1):
                    start[(ix * ny + iy) * nz + iz + 1] += 1
    for c in range(nx * ny * nz):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    items = np.empty(start[-1], np.int32)
    for k in range(m):
        for ix in range(rng[k, 0], rng[k, 3] + 1):
            for iy in range(rng[k, 1], rng[k, 4] + 1):
                for iz in range(rng[k, 2], rng[k, 5] + 1):
                    c = (ix * ny + iy) * nz + iz
                    items[fill[c]] = k
                    fill[c] += 1
    return start, items


@njit(cache=True, inline="always")
def _axis_gap(p, lo, h, i, r, n):
    """Lower bound of the distance along one axis from coordinate p to the cells farther than r
    from cell i (inf when there are none on either side)."""
    g = np.inf
    if i - r - 1 >= 0:
        g = min(g, p - (lo + (i - r) * h))
    if i + r + 1 <= n - 1:
        g = min(g, lo + (i + r + 1) * h - p)
    return g


@njit(cache=True, parallel=True)
def bins_query(P, lo, h, dims, start, items, max_d2, far_d2, T, order, box):
    """Exact nearest triangle of every point by an expanding search over the binned grid.

    Shells of cells (Chebyshev radius r = 0, 1, ...) around the point's cell (clamped into the
    grid) are searched until the best squared distance is at most the squared gap to the cells not
    yet searched: the closest point of the nearest triangle lies in a cell the triangle is binned in,
    so the answer is exact (float64, ties keep the first found). ``max_d2`` (inf: none) starts the
    search radius: nothing farther is looked at (tri -1, status 3). Points whose distance to the grid
    box exceeds ``sqrt(far_d2)`` are not evaluated (status 1). ``box`` (6,) the mesh's bounding box (min
    xyz, max xyz), a lower bound that ends the search early. Points are visited in ``order``, in blocks
    as in :func:`grid_query`. Returns ``(tri, d2, feature, status)``.
    """
    n = len(P)
    tri = np.empty(n, np.int64)
    d2 = np.empty(n)
    feat = np.empty(n, np.int8)
    status = np.empty(n, np.int8)
    nx, ny, nz = dims[0], dims[1], dims[2]
    inv_h = 1.0 / h
    eps = 1e-9 * h
    B = QUERY_BLOCK
    for blk in prange((n + B - 1) // B):
        b0 = blk * B
        m = min(n, b0 + B) - b0
        Ps = np.empty((B, 3))
        ts = np.empty(B, np.int64)
        ds = np.empty(B)
        fs = np.empty(B, np.int8)
        ss = np.empty(B, np.int8)
        for t in range(m):
            i = order[b0 + t]
            Ps[t, 0], Ps[t, 1], Ps[t, 2] = P[i, 0], P[i, 1], P[i, 2]
        for t in range(m):  # the search, written out (an inlined helper taking the arrays ran 2x slower)
            px, py, pz = Ps[t, 0], Ps[t, 1], Ps[t, 2]
            ts[t], ds[t], fs[t], ss[t] = -1, np.inf, 0, 0
            ox = max(lo[0] - px, 0.0, px - (lo[0] + nx * h))
            oy = max(lo[1] - py, 0.0, py - (lo[1] + ny * h))
            oz = max(lo[2] - pz, 0.0, pz - (lo[2] + nz * h))
            if not (ox * ox + oy * oy + oz * oz <= far_d2):  # also catches NaN
                ss[t] = 1
                continue
            # the point's offsets from the mesh's box (every triangle lies in it), for the bound below
            mx = max(box[0] - px, 0.0, px - box[3])
            my = max(box[1] - py, 0.0, py - box[4])
            mz = max(box[2] - pz, 0.0, pz - box[5])
            ix = min(max(int(np.floor((px - lo[0]) * inv_h)), 0), nx - 1)
            iy = min(max(int(np.floor((py - lo[1]) * inv_h)), 0), ny - 1)
            iz = min(max(int(np.floor((pz - lo[2]) * inv_h)), 0), nz - 1)
            best = max_d2
            bt = -1
            bf = 0
            r = 0
            while True:
                for cx in range(max(ix - r, 0), min(ix + r, nx - 1) + 1):
                    ex = max(lo[0] + cx * h - px, 0.0, px - (lo[0] + (cx + 1) * h))
                    ax = cx == ix - r or cx == ix + r
                    for cy in range(max(iy - r, 0), min(iy + r, ny - 1) + 1):
                        ey = max(lo[1] + cy * h - py, 0.0, py - (lo[1] + (cy + 1) * h))
                        exy = ex * ex + ey * ey
                        if exy >= best:
                            continue
                        full = ax or cy == iy - r or cy == iy + r
                        z0 = max(iz - r, 0)
                        z1 = min(iz + r, nz - 1)
                        step = 1 if (full or r == 0) else 2 * r
                        for cz in range(iz - r if not full else z0, z1 + 1, step):
                            if cz < z0:
                                continue
                            ez = max(lo[2] + cz * h - pz, 0.0, pz - (lo[2] + (cz + 1) * h))
                            if exy + ez * ez >= best:
                                continue
                            c = (cx * ny + cy) * nz + cz
                            # the cell scan written out: as an inlined helper (_scan_cell) taking the
                            # arrays, numba's atomic reference counting of them was 25% of the run
                            for jj in range(start[c], start[c + 1]):
                                k = np.int64(items[jj])
                                if _box_d2(px, py, pz, k, T) >= best:
                                    continue
                                r2, f = pt_tri(px, py, pz, k, T)
                                if r2 < best:
                                    best, bt, bf = r2, k, f
                gx = _axis_gap(px, lo[0], h, ix, r, nx)
                gy = _axis_gap(py, lo[1], h, iy, r, ny)
                gz = _axis_gap(pz, lo[2], h, iz, r, nz)
                if gx == np.inf and gy == np.inf and gz == np.inf:
                    break
                # a triangle not searched yet lies in a cell beyond the shell on some axis a (gap g_a)
                # and inside the mesh's box (offsets m_b of the point from it on each axis): its
                # squared distance is at least min_a(max(g_a, m_a)^2 + sum_b!=a m_b^2); for a point
                # far outside the mesh this ends the search after a few shells, not at the grid's end
                lb = np.inf
                if gx < np.inf:
                    lb = min(lb, max(gx - eps, mx) ** 2 + my * my + mz * mz)
                if gy < np.inf:
                    lb = min(lb, max(gy - eps, my) ** 2 + mx * mx + mz * mz)
                if gz < np.inf:
                    lb = min(lb, max(gz - eps, mz) ** 2 + mx * mx + my * my)
                lb *= 1.0 - 1e-12  # rounding of the offsets, on the safe side
                if lb < np.inf and lb >= best:
                    break
                r += 1
            if bt < 0:
                ss[t] = 3
            else:
                ts[t], ds[t], fs[t] = bt, best, bf
        for t in range(m):
            i = order[b0 + t]
            tri[i], d2[i], feat[i], status[i] = ts[t], ds[t], fs[t], ss[t]
    return tri, d2, feat, status


@njit(cache=True, inline="always")
def _cell_d2(px, py, pz, c, lo, h, ny, nz):
    ix = c // (ny * nz)
    iy = (c // nz) % ny
    iz = c % nz
    ex = max(lo[0] + ix * h - px, 0.0, px - (lo[0] + (ix + 1) * h))
    ey = max(lo[1] + iy * h - py, 0.0, py - (lo[1] + (iy + 1) * h))
    ez = max(lo[2] + iz * h - pz, 0.0, pz - (lo[2] + (iz + 1) * h))
    return ex * ex + ey * ey + ez * ez


@njit(cache=True, parallel=True)
def bins_far_query(P, lo, h, dims, start, items, occ, max_d2, T):
    """Exact nearest triangle of points far outside the grid: the occupied cells ``occ`` are scanned,
    nearest cell first, then every cell whose box is nearer than the best distance so far.
    Returns ``(tri, d2, feature)`` (tri -1: farther than ``max_d2``)."""
    n = len(P)
    tri = np.full(n, -1, np.int64)
    d2 = np.full(n, np.inf)
    feat = np.zeros(n, np.int8)
    ny, nz = dims[1], dims[2]
    for i in prange(n):
        px, py, pz = P[i, 0], P[i, 1], P[i, 2]
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            continue
        best = max_d2
        bt = -1
        bf = 0
        first = -1
        fd = np.inf
        for q in range(len(occ)):
            e = _cell_d2(px, py, pz, occ[q], lo, h, ny, nz)
            if e < fd:
                fd, first = e, q
        for rep in range(2):
            for q in range(len(occ)):
                if (rep == 0) != (q == first):
                    continue
                c = occ[q]
                if _cell_d2(px, py, pz, c, lo, h, ny, nz) >= best:
                    continue
                best, bt, bf = _scan_cell(px, py, pz, c, start, items, T, best, bt, bf)
        tri[i] = bt
        if bt >= 0:
            d2[i] = best
            feat[i] = bf
    return tri, d2, feat
