"""The C2M distance pass of a chunk of points: nearest triangle (grid or BVH engine), exact float64
distance, and the sign from the pseudo-normal of the nearest feature (face, edge or vertex)."""

from __future__ import annotations

import numpy as np

from mst.eval.c2m.geometry import MeshIndex, _dot, triangle_distances


def point_distances(idx: MeshIndex, P: np.ndarray, signed: bool = False, max_dist: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """Exact distances (metres, float64) of shifted points ``P (n, 3)`` to the mesh.

    Returns ``(d (n,) unsigned, s (n,) signed or None)``; NaN where the point is farther than
    ``max_dist`` (when given).
    """
    n = len(P)
    if n == 0:
        return np.full(0, np.nan), (np.full(0, np.nan) if signed else None)
    todo = slice(None)  # the rows of P that Q holds (all of them until some are left out)
    Q = P
    if max_dist is not None and idx.engine != "grid":  # outside the mesh box grown by max_dist (the
        # grid engine skips far cells itself, from their distance lower bound)
        lo, hi = idx.V.min(0) - max_dist, idx.V.max(0) + max_dist
        todo = np.nonzero(((P >= lo) & (P <= hi)).all(1))[0]
        if not len(todo):
            return np.full(n, np.nan), (np.full(n, np.nan) if signed else None)
        Q = P[todo]
    if idx.engine == "grid":
        tri, d2, feat = idx.grid_nearest(Q, max_dist)
        ok = tri >= 0
        if not ok.all():
            todo = np.arange(n)[todo][ok]
            Q, tri, d2, feat = Q[ok], tri[ok], d2[ok], feat[ok]
    else:
        tri, d2, feat = _bvh_nearest(idx, Q)
    dist = np.sqrt(d2, out=d2)  # in place: d2 is this call's own array
    if max_dist is not None:
        dist[dist > max_dist] = np.nan
    every = isinstance(todo, slice)  # Q is P: no NaN rows to fill, no copy
    d = dist if every else _at_rows(dist, todo, n)
    s = None
    if signed:
        sgn = np.empty(len(Q))
        inner = feat == 0
        # interior: the side of the triangle's plane (height over the face)
        sgn[inner] = _dot(Q[inner] - idx.A[tri[inner]], idx.N[tri[inner]])
        bi = np.nonzero(~inner)[0]
        if len(bi):
            _, fb, Cb = triangle_distances(idx, Q[bi], tri[bi], need_closest=True)
            sgn[bi] = _dot(Q[bi] - Cb, _feature_normals(idx, tri[bi], fb))
        sd = np.where(sgn < 0, -1.0, 1.0) * dist
        s = sd if every else _at_rows(sd, todo, n)
    return d, s


def _at_rows(v: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """``v`` at ``rows`` of a length-``n`` array, NaN elsewhere."""
    out = np.full(n, np.nan)
    out[rows] = v
    return out


def _bvh_nearest(idx: MeshIndex, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BVH engine: ``(tri, d2, feature)`` of shifted points ``Q``: Open3D's float32 pick, refined
    exactly in float64 (one-ring near ties, far points searched again)."""
    # query in spatially coherent order (coarse cell key): halves the BVH time on shuffled clouds
    h = max(float(np.ptp(idx.V, axis=0).max()) / 256.0, 1e-9)
    ijk = np.clip(np.floor((Q - idx.V.min(0)) * (1.0 / h)), 0, (1 << 21) - 1).astype(np.int64)
    order = np.argsort((ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2])
    del ijk
    Qs = Q[order]
    tri = idx.bvh_closest_triangles(Qs.astype(np.float32))
    d2, feat, _ = triangle_distances(idx, Qs, tri)  # exact, in the same cache-friendly order
    # near-tie safety for float32 BVH answers: closest point on an edge/vertex -> try the one-ring
    bnd = np.nonzero(feat != 0)[0]
    if len(bnd):
        t0 = tri[bnd]
        lens = idx.ring_ptr[t0 + 1] - idx.ring_ptr[t0]
        pi = np.repeat(bnd, lens)
        offs = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
        ti = idx.ring_idx[np.repeat(idx.ring_ptr[t0], lens) + offs]
        e2, f2, _ = triangle_distances(idx, Qs[pi], ti)
        better = e2 < d2[pi]
        if better.any():
            bi = np.nonzero(better)[0]
            o = np.lexsort((e2[bi], pi[bi]))
            bi = bi[o]
            firsts = np.r_[True, pi[bi][1:] != pi[bi][:-1]]
            sel = bi[firsts]
            pts = pi[sel]
            d2[pts], tri[pts], feat[pts] = e2[sel], ti[sel], f2[sel]
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    d2, tri, feat = d2[inv], tri[inv], feat[inv]
    # points farther than 100 mesh extents: the float32 pick degrades (~1e-7 of the distance, the
    # size of the mesh at 1e7 extents), so they are searched again exactly in float64
    ext = float(np.ptp(idx.V, axis=0).max())
    far = np.nonzero(d2 > (100.0 * ext) ** 2)[0]
    if len(far):
        tri[far], d2[far], feat[far] = idx.exact_nearest(Q[far])
    return tri, d2, feat


def _feature_normals(idx: MeshIndex, tri: np.ndarray, feat: np.ndarray) -> np.ndarray:
    """Pseudo-normal of the closest feature (face / edge / vertex) per pair."""
    nrm = idx.N[tri].copy()
    for code, e in ((4, 0), (5, 1), (6, 2)):
        k = feat == code
        nrm[k] = idx.edge_n[tri[k], e]
    for code, c in ((1, 0), (2, 1), (3, 2)):
        k = feat == code
        nrm[k] = idx.vert_n[idx.F[tri[k], c]]
    return nrm
