"""Cloud-to-mesh (C2M) distances and the Table-1 statistics of ``mst c2m``.

Distance: for every cloud point, the exact Euclidean distance (metres, float64) to the nearest
triangle of the mesh, like CloudCompare's C2M. How it is computed:

1. A float64 global shift (the mesh bounding-box centre) is subtracted from mesh and cloud, so
   georeferenced coordinates (1e6 m) keep their precision; nothing below runs on raw coordinates.
2. The nearest triangle of each point is found by the compiled grid engine (default, ``engine="grid"``,
   numba, exact float64, no Open3D): meshes up to ``small_mesh_triangles`` triangles use a dense grid
   of lazily computed per-cell candidate lists; larger meshes bin every triangle into the cells its
   bounding box overlaps and search shells of cells around each point until the best distance is at
   most the distance to the cells not yet searched (exact, ties included); points far outside the
   grid scan the occupied cells. ``engine="bvh"`` uses Open3D's ``RaycastingScene`` BVH (float32 on
   the shifted coordinates) instead, followed by step 3.
3. (BVH engine) The distance to the picked triangle is recomputed exactly in float64 (Ericson's
   closest point on a triangle, vectorised), and when the closest point lies on an edge or vertex the
   triangles around that vertex are checked too, so a float32 near-tie cannot pick a farther triangle.
   Points farther than 100 mesh extents (where float32 picks degrade) are searched again exactly. A
   float32 BVH can still miss the nearest triangle by about 1e-6 m for points metres away from a
   wide flat region; the grid engine has no such error.

Sign (``signed=True``): positive on the side the triangle normals point to (outside of a closed
mesh wound counter-clockwise seen from outside), negative inside. The normal used is the
angle-weighted pseudo-normal of the nearest *feature* (Baerentzen & Aanaes 2005): the face normal
when the closest point is inside a triangle, the sum of the two adjacent face normals when it is on
an edge, the angle-weighted sum of the incident face normals when it is on a vertex. This is exact
for closed, consistently oriented meshes, also near edges and corners (where using the face normal
of the nearest triangle, as CloudCompare does, gives wrong signs). Duplicate vertices (same
coordinates) are merged for the topology, so split-vertex OBJ/STL files work.

Statistics (all in metres): for each threshold ``t`` of ``thresholds``, the percentage of valid points
with distance ``< t`` and the mean and population standard deviation of those distances (Table 1 of
the RGB-D paper); overall count, mean, median, std (population), RMS, min and max, unsigned and, with
``signed=True``, signed. Points with NaN/inf coordinates are counted and excluded. With ``max_dist``,
points farther than ``max_dist`` from the mesh are counted as ``beyond_max_dist``, get NaN distance in the
output cloud, and are excluded from the overall statistics (they still count in the Table-1
denominators: they are not under any threshold <= max_dist).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError, atomic_outputs, require_file

DEFAULT_THRESHOLDS = (0.1, 0.2, 0.5, 1.0)


@dataclass
class C2MConfig:
    """Settings of :func:`run_c2m` (distances in metres, i.e. the model's units)."""

    thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS
    signed: bool = False
    max_dist: float | None = None
    chunk_points: int = 1_000_000
    workers: int = 2
    #: grid engine: meshes up to this many triangles use the lazily filled dense grid of candidate
    #: lists (:class:`_DenseGrid`), larger ones the binned grid with shell search (:class:`_BinGrid`)
    small_mesh_triangles: int = 5000
    #: nearest-triangle engine: "auto" (= "grid"), "grid" (compiled float64, no Open3D) or "bvh"
    #: (Open3D's float32 BVH + exact float64 recheck)
    engine: str = "auto"


# ------------------------------------------------------------------------ exact point-triangle
def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", u, v)


def closest_point_on_triangles(P: np.ndarray, A: np.ndarray, AB: np.ndarray, AC: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of triangles to points, exact in float64 (Ericson, Real-Time Collision Detection 5.1.5).

    ``P, A`` (n, 3) points and triangle corners ``a``; ``AB = b - a``, ``AC = c - a`` (n, 3), row i pairs
    point i with triangle i. Returns ``(C (n, 3) closest points, feature (n,) int8)`` where feature is
    0 = interior, 1/2/3 = vertex a/b/c, 4/5/6 = edge ab/ac/bc. Triangles must not be degenerate.
    """
    AP = P - A
    d1 = _dot(AB, AP)
    d2 = _dot(AC, AP)
    BP = AP - AB
    d3 = _dot(AB, BP)
    d4 = _dot(AC, BP)
    CP = AP - AC
    d5 = _dot(AB, CP)
    d6 = _dot(AC, CP)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    # barycentric weights (v on AB, w on AC) of the interior solution
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        v = vb / den
        w = vc / den
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    conds = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    feat = np.select(conds, [1, 2, 4, 3, 5, 6], 0).astype(np.int8)
    # (v, w) for every feature
    V = np.select([feat == 0, feat == 2, feat == 4, feat == 6], [v, 1.0, t_ab, 1.0 - t_bc], 0.0)
    W = np.select([feat == 0, feat == 3, feat == 5, feat == 6], [w, 1.0, t_ac, t_bc], 0.0)
    C = A + AB * V[:, None] + AC * W[:, None]
    return C, feat


def triangle_distances(idx: MeshIndex, P: np.ndarray, ti: np.ndarray, need_closest: bool = False
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Exact squared distances (float64) of points ``P (n, 3)`` to triangles ``ti (n,)`` of ``idx``.

    Fast form of :func:`closest_point_on_triangles` using per-triangle precomputed data: the
    barycentric coordinates of the projection on the plane decide "interior" (distance = |height|
    over the plane, exact); other rows take the nearest of the three edge segments. Returns
    ``(d2 (n,), feature (n,) int8 as in closest_point_on_triangles, C (n, 3) or None)``.
    """
    A = idx.A[ti]
    AP = P - A
    AB = idx.AB[ti]
    AC = idx.AC[ti]
    d1 = _dot(AB, AP)
    d2 = _dot(AC, AP)
    G = idx.G[ti]
    v = G[:, 0] * d1 + G[:, 1] * d2
    w = G[:, 1] * d1 + G[:, 2] * d2
    h = _dot(AP, idx.N[ti])
    dist2 = h * h
    feat = np.zeros(len(P), np.int8)
    out = np.nonzero((v < 0) | (w < 0) | (v + w > 1))[0]
    C = None
    if need_closest:
        C = P - h[:, None] * idx.N[ti]
    if len(out):
        Po = AP[out]
        best = np.full(len(out), np.inf)
        bt = np.zeros(len(out))
        be = np.zeros(len(out), np.int8)
        for e, (org, D) in enumerate(((None, AB[out]), (None, AC[out]), (AB[out], idx.BC[ti[out]]))):
            Q = Po if org is None else Po - org
            t = np.clip(_dot(Q, D) / _dot(D, D), 0.0, 1.0)
            R = Q - t[:, None] * D
            r2 = _dot(R, R)
            b = r2 < best
            best[b] = r2[b]
            bt[b] = t[b]
            be[b] = e
        dist2[out] = best
        # feature codes: edge ab/ac/bc = 4/5/6; endpoints -> vertex a/b/c = 1/2/3
        f = 4 + be
        ends = np.array([[1, 2], [1, 3], [2, 3]], np.int8)
        f = np.where(bt <= 0.0, ends[be, 0], np.where(bt >= 1.0, ends[be, 1], f))
        feat[out] = f
        if need_closest:
            base = A[out] + np.where((be == 2)[:, None], AB[out], 0.0)
            Dsel = np.where((be == 0)[:, None], AB[out], np.where((be == 1)[:, None], AC[out], idx.BC[ti[out]]))
            C[out] = base + bt[:, None] * Dsel
    return dist2, feat, C


# ------------------------------------------------------------------------------------ the mesh
@dataclass
class MeshIndex:
    """A triangle mesh prepared for distance queries (coordinates shifted by ``shift``, metres)."""

    shift: np.ndarray                 # (3,) float64 subtracted from every coordinate
    V: np.ndarray                     # (nv, 3) float64 shifted vertices (duplicates merged)
    F: np.ndarray                     # (m, 3) int64 merged-vertex triangles
    A: np.ndarray                     # (m, 3) corner a
    AB: np.ndarray                    # (m, 3) b - a
    AC: np.ndarray                    # (m, 3) c - a
    BC: np.ndarray                    # (m, 3) c - b
    N: np.ndarray                     # (m, 3) unit normals (right-hand rule a, b, c)
    G: np.ndarray                     # (m, 3) inverse Gram matrix entries (g00, g01, g11) of (AB, AC)
    n_dropped: int = 0                # degenerate triangles removed
    ring_ptr: np.ndarray | None = None  # CSR: triangles sharing a vertex with triangle i
    ring_idx: np.ndarray | None = None
    edge_n: np.ndarray | None = None  # (m, 3, 3) pseudo-normals of edges ab, ac, bc
    vert_n: np.ndarray | None = None  # (nv, 3) angle-weighted vertex pseudo-normals
    engine: str = "bvh"
    _scene: object = field(default=None, repr=False)
    _grid: object = field(default=None, repr=False)
    _exact: object = field(default=None, repr=False)

    @property
    def n_triangles(self) -> int:
        return len(self.F)


def prepare_mesh(V: np.ndarray, F: np.ndarray, path: str | os.PathLike | None = None, signed: bool = False,
                 engine: str = "auto", small_mesh_triangles: int = 5000) -> MeshIndex:
    """Validate and index a triangle mesh ``V (n, 3)`` metres, ``F (m, 3)`` vertex indices.

    Raises :class:`mst.InputError` (naming ``path``) for a mesh without triangles, with non-finite
    vertices, out-of-range indices, or only degenerate triangles.
    """
    V = np.asarray(V, np.float64).reshape(-1, 3)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if len(F) == 0:
        raise InputError(path, "mesh has no triangles")
    if not np.isfinite(V).all():
        raise InputError(path, "mesh has NaN or infinite vertex coordinates")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(path, "mesh face indices out of range")
    if engine == "auto":
        engine = "grid"
    if engine not in ("grid", "bvh"):
        raise ValueError(f"unknown engine {engine!r}")
    shift = (V.min(0) + V.max(0)) / 2.0
    Vs = V - shift
    if signed or engine == "bvh":  # topology (pseudo-normals, one-rings): merge duplicate vertices
        Vm, inv = np.unique(Vs, axis=0, return_inverse=True)
        Fm = inv.reshape(-1)[F]
    else:
        Vm, Fm = Vs, F
    A = Vm[Fm[:, 0]]
    AB = Vm[Fm[:, 1]] - A
    AC = Vm[Fm[:, 2]] - A
    cr = np.cross(AB, AC)
    area2 = np.linalg.norm(cr, axis=1)
    scale = max(float(np.ptp(Vm, axis=0).max()), 1e-300)
    ok = area2 > 1e-12 * scale * scale
    if not ok.any():
        raise InputError(path, "mesh has only degenerate (zero-area) triangles")
    Fm, A, AB, AC, cr, area2 = Fm[ok], A[ok], AB[ok], AC[ok], cr[ok], area2[ok]
    m, nv = len(Fm), len(Vm)
    aa, ab, bb = _dot(AB, AB), _dot(AB, AC), _dot(AC, AC)
    det = aa * bb - ab * ab
    G = np.stack([bb / det, -ab / det, aa / det], axis=1)
    N = cr / area2[:, None]
    idx = MeshIndex(shift, Vm, Fm, A, AB, AC, AC - AB, N, G, n_dropped=int((~ok).sum()), engine=engine)
    if signed:
        _pseudo_normals(idx, N)
    if engine == "grid":
        if m <= small_mesh_triangles:
            idx._grid = _DenseGrid(idx)
        else:
            from mst.eval import c2m_kernels as nb

            idx._grid = _BinGrid(idx, nb)
        return idx
    # BVH: one-ring of every triangle (triangles sharing at least one vertex), CSR, for the exact recheck
    vt_tri = np.repeat(np.arange(m), 3)
    vt_v = Fm.reshape(-1)
    order = np.argsort(vt_v, kind="stable")
    v_ptr = np.zeros(nv + 1, np.int64)
    np.cumsum(np.bincount(vt_v, minlength=nv), out=v_ptr[1:])
    v_tris = vt_tri[order]
    deg = np.diff(v_ptr)
    cnt = deg[Fm].sum(1)
    ring_ptr = np.zeros(m + 1, np.int64)
    np.cumsum(cnt, out=ring_ptr[1:])
    # gather v_tris[v_ptr[v]:v_ptr[v+1]] for the 3 vertices of each triangle (duplicates are harmless)
    starts = v_ptr[Fm.reshape(-1)]
    lens = deg[Fm.reshape(-1)]
    idx.ring_idx = v_tris[np.repeat(starts - np.cumsum(np.r_[0, lens[:-1]]), lens) + np.arange(lens.sum())]
    idx.ring_ptr = ring_ptr
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(Vm.astype(np.float32)), o3d.core.Tensor(Fm.astype(np.uint32)))
    idx._scene = scene
    return idx


def _pseudo_normals(idx: MeshIndex, Nf: np.ndarray) -> None:
    """Face, edge and angle-weighted vertex pseudo-normals (Baerentzen & Aanaes 2005)."""
    F, V = idx.F, idx.V
    m, nv = len(F), len(V)
    # corner angles
    ang = np.empty((m, 3))
    for k in range(3):
        u = V[F[:, (k + 1) % 3]] - V[F[:, k]]
        w = V[F[:, (k + 2) % 3]] - V[F[:, k]]
        cos = _dot(u, w) / (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1))
        ang[:, k] = np.arccos(np.clip(cos, -1.0, 1.0))
    vn = np.zeros((nv, 3))
    for j in range(3):
        vn[:, j] = np.bincount(F.reshape(-1), weights=(ang[:, :, None] * Nf[:, None, :])[:, :, j].reshape(-1), minlength=nv)
    idx.vert_n = vn
    # edges ab, ac, bc of every triangle, keyed by sorted merged vertex ids
    pairs = np.stack([F[:, [0, 1]], F[:, [0, 2]], F[:, [1, 2]]], axis=1).reshape(-1, 2)
    pairs.sort(axis=1)
    key = pairs[:, 0] * nv + pairs[:, 1]
    _, einv = np.unique(key, return_inverse=True)
    en = np.zeros((einv.max() + 1, 3))
    fn_rep = np.repeat(Nf, 3, axis=0)
    for j in range(3):
        en[:, j] = np.bincount(einv, weights=fn_rep[:, j], minlength=len(en))
    idx.edge_n = en[einv].reshape(m, 3, 3)


# --------------------------------------------------------------------- grid engine (small meshes)
class _TriangleGrid:
    """Nearest-triangle search for small meshes, numpy float64 only (no Open3D).

    Points are binned in cubic cells. Every occupied cell gets a conservative candidate set: the
    triangles whose distance to the cell centre is at most ``dmin + 2 r`` (``dmin`` the smallest
    centre-triangle distance, ``r`` the cell half-diagonal); by the triangle inequality the nearest
    triangle of every point of the cell is in it. Candidate sets are computed coarse to fine (cell
    size halved per level, each cell testing only its parent's candidates, which is exact because a
    child cell lies inside its parent). Then, candidate slot by slot, each point is tested against
    its cell's j-th candidate exactly in float64; points are ordered by candidate count so every
    slot is a contiguous prefix.
    """

    def __init__(self, idx: MeshIndex, points_per_cell: float = 24.0):
        self.idx = idx
        self.ext = float(np.ptp(idx.V, axis=0).max()) or 1.0
        self.ppc = points_per_cell

    def _candidates(self, key_fine: np.ndarray, org: np.ndarray, h: float, levels: int, nb=None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """CSR candidate lists (ptr, tri) and distance lower bounds for the sorted unique fine cell keys."""
        idx = self.idx
        m = idx.n_triangles
        prev_k = ptr = tri = lb = None
        for lev in range(levels, -1, -1):
            hl = h * (1 << lev)
            u = np.unique(_shift_key(key_fine, lev))
            if prev_k is None:  # coarsest level: every triangle is a candidate
                cand_cnt = np.full(len(u), m, np.int64)
                parent_start = np.zeros(len(u), np.int64)
                tri = np.arange(m)
            else:  # each cell tests its parent's candidates only
                pi = np.searchsorted(prev_k, _shift_key(u, 1))
                cand_cnt = ptr[pi + 1] - ptr[pi]
                parent_start = ptr[pi]
            prev_k = u
            centres = org + (_unkey(u) + 0.5) * hl
            r = 0.5 * hl * np.sqrt(3.0)
            tot = int(cand_cnt.sum())
            cell_of = np.repeat(np.arange(len(u)), cand_cnt)
            offs = np.arange(tot) - np.repeat(np.cumsum(cand_cnt) - cand_cnt, cand_cnt)
            ti = tri[np.repeat(parent_start, cand_cnt) + offs]
            if nb is not None:
                d = np.sqrt(nb.pairs_d2(centres, cell_of, ti, idx.A, idx.AB, idx.AC, idx.BC, idx.N, idx.G))
            else:
                d = np.sqrt(triangle_distances(idx, centres[cell_of], ti)[0])
            dmin = np.minimum.reduceat(d, np.cumsum(cand_cnt) - cand_cnt)
            keep = d <= (dmin + 2 * r + 1e-9 * self.ext)[cell_of]
            ptr = np.zeros(len(u) + 1, np.int64)
            np.cumsum(np.bincount(cell_of[keep], minlength=len(u)), out=ptr[1:])
            tri = ti[keep]
            lb = dmin - r
        return ptr, tri, lb

    def nearest(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tri, d2, feature)`` per point; tri = -1 where provably farther than ``max_dist``."""
        idx = self.idx
        n = len(P)
        lo = P.min(0)
        span = np.maximum(P.max(0) - lo, 1e-9 * self.ext)
        area_guess = 2 * (span[0] * span[1] + span[1] * span[2] + span[0] * span[2])
        h = float(np.sqrt(area_guess * self.ppc / n))
        h = min(max(h, 1e-7 * self.ext, float(span.max()) / 1e6), float(span.max()) + 1e-9)
        ijk = np.floor((P - lo) / h).astype(np.int64)
        levels = max(0, int(np.ceil(np.log2(max(int(ijk.max()), 1) + 1))) - 2)
        key = _key(ijk)
        del ijk
        order = np.argsort(key)
        ks = key[order]
        first = np.r_[True, ks[1:] != ks[:-1]]
        cell_start = np.nonzero(first)[0]
        cnt = np.diff(np.r_[cell_start, n])
        ptr, tri, lb = self._candidates(ks[cell_start], lo, h, levels)
        ncand = np.diff(ptr)
        if max_dist is not None:
            ncand = np.where(lb > max_dist, 0, ncand)
        # order points by candidate count (descending) so that slot j is a prefix
        cell_of_sorted = np.repeat(np.arange(len(cnt)), cnt)
        pc = ncand[cell_of_sorted]
        o2 = np.argsort(-pc, kind="stable")
        perm = order[o2]
        pc = pc[o2]
        cstart = ptr[:-1][cell_of_sorted[o2]]
        Ps = P[perm]
        best_d2 = np.full(n, np.inf)
        best_t = np.full(n, -1, np.int64)
        best_f = np.zeros(n, np.int8)
        nj = np.searchsorted(-pc, -np.arange(1, int(pc.max(initial=0)) + 1), side="right")
        blk = 131072
        for j, nslot in enumerate(nj):
            for s in range(0, int(nslot), blk):
                e = min(int(nslot), s + blk)
                ti = tri[cstart[s:e] + j]
                d2, f, _ = triangle_distances(idx, Ps[s:e], ti)
                if j == 0:
                    best_d2[s:e], best_t[s:e], best_f[s:e] = d2, ti, f
                    continue
                b = d2 < best_d2[s:e]
                best_d2[s:e][b] = d2[b]
                best_t[s:e][b] = ti[b]
                best_f[s:e][b] = f[b]
        out_t = np.empty(n, np.int64)
        out_d = np.empty(n)
        out_f = np.empty(n, np.int8)
        out_t[perm], out_d[perm], out_f[perm] = best_t, best_d2, best_f
        return out_t, out_d, out_f


class _BinGrid:
    """Nearest-triangle search for large meshes (compiled, exact float64, no Open3D).

    A uniform grid of cubic cells over the mesh box (plus a margin); every triangle is listed in each
    cell its bounding box overlaps (conservative, CSR with int32 triangle ids). Per point, shells of
    cells around its cell are searched outward until the best distance is at most the distance to the
    cells not searched yet (:func:`mst.eval.c2m_kernels.bins_query`): exact, also near ties. The cell
    size is about ``cell_factor`` times the mean triangle edge (from the mean area), enlarged when the
    grid would exceed ``max_cells``. Points far outside the grid (more than ``far_cells`` cells) scan
    the occupied cells instead (:func:`mst.eval.c2m_kernels.bins_far_query`).
    """

    def __init__(self, idx: MeshIndex, nb, cell_factor: float = 2.0, max_cells: int = 4_000_000,
                 far_cells: float = 32.0):
        self.idx, self.nb = idx, nb
        m = idx.n_triangles
        vmin, vmax = idx.V.min(0), idx.V.max(0)
        ext = float((vmax - vmin).max()) or 1.0
        area = 0.5 * float(np.linalg.norm(np.cross(idx.AB, idx.AC), axis=1).sum())
        h = cell_factor * np.sqrt(2.0 * area / m)
        size = np.maximum(vmax - vmin, 1e-9 * ext)
        h = max(h, float(np.cbrt(np.prod(size + 4 * h) / max_cells)), ext / 4096)
        for _ in range(8):  # the margin (2 cells each side) depends on h
            dims = np.ceil((size + 4 * h) / h).astype(np.int64)
            if int(np.prod(dims)) <= max_cells:
                break
            h *= 1.26
        self.h = float(h)
        self.lo = vmin - 2 * h
        self.dims = dims
        corners = np.stack([idx.A, idx.A + idx.AB, idx.A + idx.AC])
        self.BB = np.concatenate([corners.min(0), corners.max(0)], axis=1)  # (m, 6) triangle boxes
        self.start, self.items = nb.bin_triangles(self.BB, self.lo, 1.0 / self.h, self.dims)
        self.far_d2 = (far_cells * self.h) ** 2
        self.occ = np.nonzero(np.diff(self.start))[0]  # occupied cells, for the far points

    def nearest(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tri, d2, feature)`` per point; tri = -1 where farther than ``max_dist``."""
        nb, idx = self.nb, self.idx
        P = np.ascontiguousarray(P, np.float64)
        md2 = np.inf if max_dist is None else (float(max_dist) * (1 + 1e-9)) ** 2
        order = nb.bucket_order(P, self.lo, 1.0 / self.h, self.dims, 2)
        tri, d2, feat, st = nb.bins_query(P, self.lo, self.h, self.dims, self.start, self.items, md2, self.far_d2,
                                          idx.A, idx.AB, idx.AC, idx.BC, idx.N, idx.G, self.BB, order)
        out = np.nonzero(st == 1)[0]
        if len(out):
            tri[out], d2[out], feat[out] = nb.bins_far_query(P[out], self.lo, self.h, self.dims, self.start,
                                                             self.items, self.occ, md2, idx.A, idx.AB, idx.AC,
                                                             idx.BC, idx.N, idx.G, self.BB)
        return tri, d2, feat


class _DenseGrid:
    """Nearest-triangle search for small meshes: a dense grid of cells over the mesh box.

    Candidate triangle lists (see :class:`_TriangleGrid` for the conservative rule) are computed
    lazily, the first time a point falls in a cell, and cached for the following chunks (thread
    safe). Per point the work is a cell lookup and exact float64 distances to the cell's few
    candidates: no sorting. Points outside the grid box go to :class:`_TriangleGrid`.
    """

    def __init__(self, idx: MeshIndex, max_cells: int = 500_000):
        import threading

        self.idx = idx
        vmin, vmax = idx.V.min(0), idx.V.max(0)
        ext = float((vmax - vmin).max()) or 1.0
        margin = 0.1 * ext
        self.lo = vmin - margin
        size = np.maximum(vmax + margin - self.lo, 1e-9 * ext)
        self.h = float((np.prod(size) / max_cells) ** (1.0 / 3.0))
        self.h = max(self.h, float(size.max()) / 1_000_000)
        self.dims = np.minimum(np.ceil(size / self.h).astype(np.int64), 1 << 20)
        n = int(np.prod(self.dims))
        # per cell: (start << 16) | count into ``cand`` (-1: not computed yet); one 8-byte word per
        # cell so that a point costs one cache miss; candidate ids as int32 (meshes < 65536 triangles)
        self.cell = np.full(n, -1, np.int64)
        self.lb = np.zeros(n, np.float32)
        self.cand = np.zeros(0, np.int32)
        self.levels = max(0, int(np.ceil(np.log2(int(self.dims.max())))) - 2)
        self._lock = threading.Lock()
        self._tg = _TriangleGrid(idx)
        self.ext = ext
        try:  # compiled kernels when numba is installed (about 10x faster), numpy otherwise
            from mst.eval import c2m_kernels as nb
        except ImportError:  # pragma: no cover - numba is a dependency, this is a safety net
            nb = None
        self.nb = nb
        corners = np.stack([idx.A, idx.A + idx.AB, idx.A + idx.AC])
        self.BB = np.concatenate([corners.min(0), corners.max(0)], axis=1)  # (m, 6) triangle boxes

    def _nearest_numba(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nb, idx = self.nb, self.idx
        md = -1.0 if max_dist is None else float(max_dist)
        lo, inv_h = self.lo.astype(np.float64), 1.0 / self.h
        args = (idx.A, idx.AB, idx.AC, idx.BC, idx.N, idx.G)
        order = nb.bucket_order(P, lo, inv_h, self.dims, 3)
        tri, d2, feat, st = nb.grid_query(P, lo, inv_h, self.dims, self.cell, self.lb, self.cand, md, *args, order,
                                          self.BB)
        new = np.nonzero(st == 2)[0]
        if len(new):
            flat = nb.cells_of(P[new], lo, inv_h, self.dims)
            self._fill(np.unique(flat))
            Pn = P[new]
            t2, e2, f2, s2 = nb.grid_query(Pn, lo, inv_h, self.dims, self.cell, self.lb, self.cand, md, *args,
                                           nb.bucket_order(Pn, lo, inv_h, self.dims, 3), self.BB)
            tri[new], d2[new], feat[new], st[new] = t2, e2, f2, s2
        out = np.nonzero(st == 1)[0]
        if len(out):
            tri[out], d2[out], feat[out] = self._tg.nearest(P[out], max_dist)
        return tri, d2, feat

    def _fill(self, flat: np.ndarray) -> None:
        """Compute candidate lists of the (unique, not yet computed) flat cell ids."""
        with self._lock:
            flat = flat[self.cell[flat] < 0]
            if not len(flat):
                return
            dy, dz = int(self.dims[1]), int(self.dims[2])
            ijk = np.stack([flat // (dy * dz), (flat // dz) % dy, flat % dz], axis=1)
            if self.nb is not None and self.levels >= 3:
                # parents 3 levels up (8x coarser cells), their lists by the numpy hierarchy, then
                # the fine cells refined from their parent's list in the compiled kernel
                pkey = _key(ijk >> 3)
                upk, pinv = np.unique(pkey, return_inverse=True)
                pptr, ptri, _ = self._tg._candidates(upk, self.lo, self.h * 8, self.levels - 3, self.nb)
                centres = self.lo + (ijk + 0.5) * self.h
                ptr, tri, lb = self.nb.refine_cells(centres, 0.5 * self.h * np.sqrt(3.0), pinv.reshape(-1), pptr, ptri,
                                                    1e-9 * self.ext, self.idx.A, self.idx.AB, self.idx.AC,
                                                    self.idx.BC, self.idx.N, self.idx.G, self.BB)
                cells = flat
            else:
                key = _key(ijk)
                o = np.argsort(key)
                ptr, tri, lb = self._tg._candidates(key[o], self.lo, self.h, self.levels, self.nb)
                cells = flat[o]
            base = len(self.cand)
            self.lb[cells] = lb
            self.cand = np.concatenate([self.cand, tri.astype(np.int32)])
            self.cell[cells] = ((base + ptr[:-1]) << 16) | np.diff(ptr)  # last: marks the cells as computed

    def nearest(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tri, d2, feature)`` per point; tri = -1 where provably farther than ``max_dist``."""
        if self.nb is not None:
            return self._nearest_numba(np.ascontiguousarray(P, np.float64), max_dist)
        idx = self.idx
        n = len(P)
        ijk = np.floor((P - self.lo) * (1.0 / self.h)).astype(np.int64)
        inside = ((ijk >= 0) & (ijk < self.dims)).all(1)
        tri = np.full(n, -1, np.int64)
        d2 = np.full(n, np.inf)
        feat = np.zeros(n, np.int8)
        out = np.nonzero(~inside)[0]
        if len(out):
            tri[out], d2[out], feat[out] = self._tg.nearest(P[out], max_dist)
            ins = np.nonzero(inside)[0]
            Pi, ijk = P[ins], ijk[ins]
        else:
            ins, Pi = None, P
        flat = (ijk[:, 0] * self.dims[1] + ijk[:, 1]) * self.dims[2] + ijk[:, 2]
        del ijk
        word = self.cell[flat]
        if (word < 0).any():
            self._fill(np.unique(flat[word < 0]))
            word = self.cell[flat]
        cand = self.cand
        st = word >> 16
        cnt = (word & 0xFFFF).astype(np.int64)
        if max_dist is not None:
            cnt = np.where(self.lb[flat] > max_dist, 0, cnt)
        bt = np.full(len(Pi), -1, np.int64)
        bd = np.full(len(Pi), np.inf)
        bf = np.zeros(len(Pi), np.int8)
        for j in range(int(cnt.max(initial=0))):
            sel = np.nonzero(cnt > j)[0]
            if j == 0 and len(sel) == len(Pi):
                ti = cand[st]
                bd, bf, _ = triangle_distances(idx, Pi, ti)
                bt = ti
                continue
            ti = cand[st[sel] + j]
            e2, f, _ = triangle_distances(idx, Pi[sel], ti)
            b = e2 < bd[sel]
            sb = sel[b]
            bd[sb], bt[sb], bf[sb] = e2[b], ti[b], f[b]
        if ins is None:
            return bt, bd, bf
        tri[ins], d2[ins], feat[ins] = bt, bd, bf
        return tri, d2, feat


_B = 21  # bits per axis in a cell key


def _key(ijk: np.ndarray) -> np.ndarray:
    """Int64 key of non-negative integer cell coordinates (21 bits each); key order = lexicographic."""
    ijk = np.asarray(ijk, np.int64)
    return (ijk[:, 0] << (2 * _B)) | (ijk[:, 1] << _B) | ijk[:, 2]


def _unkey(k: np.ndarray) -> np.ndarray:
    msk = (1 << _B) - 1
    return np.stack([k >> (2 * _B), (k >> _B) & msk, k & msk], axis=1)


def _shift_key(k: np.ndarray, lev: int) -> np.ndarray:
    """Keys of the parent cells ``lev`` levels up (each coordinate shifted right by ``lev``)."""
    if lev == 0:
        return k
    msk = ((1 << _B) - 1) >> lev << 0
    x, y, z = k >> (2 * _B), (k >> _B) & ((1 << _B) - 1), k & ((1 << _B) - 1)
    return ((x >> lev) << (2 * _B)) | (((y >> lev) & msk) << _B) | ((z >> lev) & msk)


# -------------------------------------------------------------------------------- distance pass
def point_distances(idx: MeshIndex, P: np.ndarray, signed: bool = False, max_dist: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """Exact distances (metres, float64) of shifted points ``P (n, 3)`` to the mesh.

    Returns ``(d (n,) unsigned, s (n,) signed or None)``; NaN where the point is farther than
    ``max_dist`` (when given).
    """
    n = len(P)
    d = np.full(n, np.nan)
    s = np.full(n, np.nan) if signed else None
    if n == 0:
        return d, s
    todo = slice(None)
    Q = P
    if max_dist is not None and idx.engine != "grid":  # outside the mesh box grown by max_dist (the
        # grid engine skips far cells itself, from their distance lower bound)
        lo, hi = idx.V.min(0) - max_dist, idx.V.max(0) + max_dist
        todo = np.nonzero(((P >= lo) & (P <= hi)).all(1))[0]
        if not len(todo):
            return d, s
        Q = P[todo]
    if idx.engine == "grid":
        tri, d2, feat = idx._grid.nearest(Q, max_dist)
        ok = tri >= 0
        if not ok.all():
            todo = np.arange(n)[todo][ok]
            Q, tri, d2, feat = Q[ok], tri[ok], d2[ok], feat[ok]
    else:
        import open3d as o3d

        # query in spatially coherent order (coarse cell key): halves the BVH time on shuffled clouds
        h = max(float(np.ptp(idx.V, axis=0).max()) / 256.0, 1e-9)
        ijk = np.clip(np.floor((Q - idx.V.min(0)) * (1.0 / h)), 0, (1 << 21) - 1).astype(np.int64)
        order = np.argsort((ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2])
        del ijk
        Qs = Q[order]
        ans = idx._scene.compute_closest_points(o3d.core.Tensor(Qs.astype(np.float32)))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
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
            if idx._exact is None:
                idx._exact = _TriangleGrid(idx)
            tri[far], d2[far], feat[far] = idx._exact.nearest(Q[far], None)
    dist = np.sqrt(d2)
    if max_dist is not None:
        dist[dist > max_dist] = np.nan
    d[todo] = dist
    if signed:
        sgn = np.empty(len(Q))
        inner = feat == 0
        # interior: the side of the triangle's plane (height over the face)
        sgn[inner] = _dot(Q[inner] - idx.A[tri[inner]], idx.N[tri[inner]])
        bi = np.nonzero(~inner)[0]
        if len(bi):
            _, fb, Cb = triangle_distances(idx, Q[bi], tri[bi], need_closest=True)
            sgn[bi] = _dot(Q[bi] - Cb, _feature_normals(idx, tri[bi], fb))
        s[todo] = np.where(sgn < 0, -1.0, 1.0) * dist
    return d, s


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


# ------------------------------------------------------------------------------------ statistics
class _Moments:
    """Streaming count / mean / M2 (Chan et al. merge), min, max, sum of squares."""

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, 0.0, 0.0
        self.sumsq = 0.0
        self.min, self.max = np.inf, -np.inf

    def add(self, x: np.ndarray, extremes: bool = True) -> None:
        k = len(x)
        if not k:
            return
        x = np.asarray(x, np.float64)
        mu = float(x.sum()) / k
        sq = float(np.dot(x, x))
        m2 = max(sq - k * mu * mu, 0.0)  # chunk M2; merged exactly below (Chan et al.)
        delta = mu - self.mean
        tot = self.n + k
        self.mean += delta * k / tot
        self.m2 += m2 + delta * delta * self.n * k / tot
        self.n = tot
        self.sumsq += sq
        if extremes:
            self.min = min(self.min, float(x.min()))
            self.max = max(self.max, float(x.max()))

    def add_sums(self, k: int, s1: float, s2: float, lo: float = np.inf, hi: float = -np.inf) -> None:
        """Merge a block given its count, sum and sum of squares (and optional min/max)."""
        if not k:
            return
        mu = s1 / k
        m2 = max(s2 - k * mu * mu, 0.0)
        delta = mu - self.mean
        tot = self.n + k
        self.mean += delta * k / tot
        self.m2 += m2 + delta * delta * self.n * k / tot
        self.n = tot
        self.sumsq += s2
        self.min = min(self.min, lo)
        self.max = max(self.max, hi)

    def std(self) -> float:
        return float(np.sqrt(self.m2 / self.n)) if self.n else float("nan")


def _summary(mo: _Moments, values: np.ndarray) -> dict:
    if mo.n == 0:
        return {k: None for k in ("count", "mean", "median", "std", "rms", "min", "max")} | {"count": 0}
    # overwrite_input: the stored distances are only needed unordered afterwards (histogram)
    return {"count": mo.n, "mean": mo.mean, "median": float(np.median(values, overwrite_input=True)), "std": mo.std(),
            "rms": float(np.sqrt(mo.sumsq / mo.n)), "min": mo.min, "max": mo.max}


# ------------------------------------------------------------------------------------ the stage
def _prefetch_open3d():
    """Start importing Open3D in a thread; returns the thread (None when already imported)."""
    import importlib
    import sys
    import threading

    if "open3d" in sys.modules:
        return None
    th = threading.Thread(target=importlib.import_module, args=("open3d",), daemon=True)
    th.start()
    return th


def _expand(v: np.ndarray, fin: np.ndarray, n: int) -> np.ndarray:
    """Values of the finite rows back at their rows of the chunk (NaN for non-finite rows)."""
    if len(v) == n:
        return v
    o = np.full(n, np.nan, np.float32)
    o[fin] = v
    return o


def load_mesh_triangles(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of a mesh or polygon model file (OBJ PLY STL OFF WRL CAO CityJSON, polygons
    triangulated): ``(V (n, 3) float64 metres, F (m, 3) int64)``."""
    from mst.meshtools.io import load_triangles

    return load_triangles(require_file(path, "mesh file"))


#: largest accepted |coordinate| of a cloud point, metres. Nothing measured lies 1e12 m away (Earth-
#: centred coordinates are ~6.4e6 m); such values are corrupt and, near 1e154, overflow the squared
#: distances into inf/NaN. Clouds holding them are refused (NaN/inf points are counted and excluded).
MAX_CLOUD_COORD_M = 1e12


def run_c2m(cloud_path: str | os.PathLike, mesh_path: str | os.PathLike, config: C2MConfig | None = None,
            out_cloud: str | os.PathLike | None = None, progress: Callable[[int], None] | None = None) -> dict:
    """Cloud-to-mesh distances of every point of ``cloud_path`` to the mesh ``mesh_path``.

    Streams the cloud in chunks of ``config.chunk_points`` (two chunks processed concurrently in a
    thread pool: numpy and Open3D release the GIL). Writes ``out_cloud`` (binary PLY with the scalar
    fields ``C2M_absolute_distances`` and, when signed, ``C2M_signed_distances``; NaN for invalid or
    beyond-max-dist points) atomically. ``progress(n)`` is called with the points done per chunk.

    Returns the summary dict (see module docstring; the key ``distances`` holds the float64 (or
    float32 beyond 20M points) array of finite unsigned distances, for plots; callers drop it for JSON).
    """
    from mst.eval.cloud_io import PlyChunkWriter, open_cloud

    cfg = config or C2MConfig()
    thr = np.asarray(sorted(float(t) for t in cfg.thresholds), np.float64)
    if len(thr) == 0 or (thr <= 0).any():
        raise InputError(None, "thresholds must be positive numbers")
    if cfg.max_dist is not None and cfg.max_dist <= 0:
        raise InputError(None, "--max-dist must be positive")
    t0 = time.perf_counter()
    src = open_cloud(cloud_path)
    if src.count == 0:
        raise InputError(cloud_path, "cloud has no points")
    pre = None
    if cfg.engine == "bvh":
        pre = _prefetch_open3d()  # overlap the ~1 s Open3D import with reading the mesh
    try:
        V, F = load_mesh_triangles(mesh_path)
        idx = prepare_mesh(V, F, mesh_path, signed=cfg.signed, engine=cfg.engine,
                           small_mesh_triangles=cfg.small_mesh_triangles)
    except BaseException:
        if pre is not None:  # never leave an import running in a thread at interpreter exit
            pre.join()
        raise
    if pre is not None:
        pre.join()
    t_mesh = time.perf_counter() - t0

    n_total = src.count
    keep_f64 = n_total <= 20_000_000
    store = np.empty(n_total, np.float64 if keep_f64 else np.float32)
    store_s = np.empty(n_total, np.float64 if keep_f64 else np.float32) if cfg.signed else None
    n_store = 0
    mo_u, mo_s = _Moments(), _Moments()
    th_mo = [_Moments() for _ in thr]
    n_nonfinite = n_beyond = n_seen = 0
    t_dist = 0.0
    shift = idx.shift
    fields = ["C2M_absolute_distances"] + (["C2M_signed_distances"] if cfg.signed else [])

    nb = getattr(idx._grid, "nb", None)  # compiled helpers when the grid engine has them

    def work(xyz: np.ndarray):
        ts = time.perf_counter()
        with np.errstate(invalid="ignore"):
            far = (np.abs(xyz) > MAX_CLOUD_COORD_M) & np.isfinite(xyz)
        if far.any():
            n_far = int(far.any(axis=1).sum())
            raise InputError(cloud_path, f"{n_far} point(s) with a coordinate beyond {MAX_CLOUD_COORD_M:g} m "
                                         "(corrupt values?); NaN/inf points are excluded, these are refused")
        if nb is not None:
            P, fin = nb.shift_points(np.ascontiguousarray(xyz, np.float64), shift)
            if not fin.all():
                P = P[fin]
        else:
            fin = np.isfinite(xyz).all(1)
            P = xyz - shift if fin.all() else xyz[fin] - shift
        du, ds = point_distances(idx, P, cfg.signed, cfg.max_dist)
        return xyz, fin, du, ds, time.perf_counter() - ts

    t_loop = time.perf_counter()
    with atomic_outputs(out_cloud) as (tmp_out,):
        writer = PlyChunkWriter(tmp_out, n_total, fields, src.xyz_dtype if src.xyz_dtype.itemsize == 8 or
                                np.abs(shift).max() < 1e5 else np.float64) if tmp_out is not None else None
        try:
            workers = 1 if getattr(idx._grid, "nb", None) is not None else max(1, cfg.workers)
            with ThreadPoolExecutor(max_workers=workers) as pool:
                pending = []
                chunks = src.chunks(cfg.chunk_points)
                exhausted = False
                while pending or not exhausted:
                    while not exhausted and len(pending) < workers + 1:
                        try:
                            pending.append(pool.submit(work, next(chunks)))
                        except StopIteration:
                            exhausted = True
                    if not pending:
                        break
                    xyz, fin, du, ds, dt = pending.pop(0).result()
                    t_dist += dt
                    n_seen += len(xyz)
                    n_nonfinite += int((~fin).sum())
                    valid = ~np.isnan(du)
                    nv = int(valid.sum())
                    n_beyond += len(du) - nv
                    dv = du if nv == len(du) else du[valid]
                    if nb is not None:
                        cnt, s1, s2, lo, hi = nb.threshold_sums(dv, thr)
                        mo_u.add_sums(int(cnt[-1]), float(s1[-1]), float(s2[-1]), float(lo), float(hi))
                        for j, mo in enumerate(th_mo):
                            mo.add_sums(int(cnt[j]), float(s1[j]), float(s2[j]))
                    else:
                        mo_u.add(dv)
                        for t, mo in zip(thr, th_mo):
                            mo.add(dv[dv < t], extremes=False)
                    store[n_store : n_store + len(dv)] = dv
                    if cfg.signed:
                        sv = ds if nv == len(ds) else ds[valid]
                        mo_s.add(sv)
                        store_s[n_store : n_store + len(sv)] = sv
                    n_store += len(dv)
                    if writer is not None:
                        sc = {"C2M_absolute_distances": _expand(du, fin, len(xyz))}
                        if cfg.signed:
                            sc["C2M_signed_distances"] = _expand(ds, fin, len(xyz))
                        writer.write(xyz, **sc)
                    if progress is not None:
                        progress(len(xyz))
        finally:
            if writer is not None:
                writer._f.close()
        if writer is not None:
            writer.close()
        t_loop = time.perf_counter() - t_loop
        if n_seen != n_total:
            raise InputError(cloud_path, f"read {n_seen} points, header says {n_total}")
        n_valid = n_total - n_nonfinite
        if n_valid == 0:
            raise InputError(cloud_path, "cloud has no finite points")
    dist = store[:n_store]
    table = []
    for t, mo in zip(thr, th_mo):
        table.append({"max_dist": float(t), "percent": 100.0 * mo.n / n_valid, "count": mo.n,
                      "mean": mo.mean if mo.n else None, "std": mo.std() if mo.n else None})
    total_s = time.perf_counter() - t0
    out = {
        "cloud": str(cloud_path), "mesh": str(mesh_path), "output": None if out_cloud is None else str(out_cloud),
        "points_total": n_total, "points_valid": n_valid, "points_nonfinite": n_nonfinite,
        "points_beyond_max_dist": n_beyond, "max_dist": cfg.max_dist,
        "mesh_triangles": idx.n_triangles, "mesh_degenerate_dropped": idx.n_dropped, "engine": idx.engine,
        "global_shift": idx.shift.tolist(),
        "thresholds": table,
        "unsigned": _summary(mo_u, dist),
        "signed": _summary(mo_s, store_s[:n_store]) if cfg.signed else None,
        # distance_s: wall time of the streamed pass (read + distances + write, chunks overlapping);
        # worker_s: summed per-chunk distance time of the workers
        "timing": {"mesh_s": t_mesh, "distance_s": t_loop, "worker_s": t_dist, "total_s": total_s,
                   "points_per_s": n_valid / t_loop if t_loop > 0 else None},
        "distances": dist,
    }
    return out


# ------------------------------------------------------------------------------------- reports
def table1_rows(summary: dict) -> list[list[str]]:
    """Table 1 of the RGB-D paper as rows of strings (label, one column per threshold).

    Means and standard deviations use the paper's 2 decimals for thresholds >= 0.1 m and one more
    decimal per decade below (a 0.01 m threshold prints 3), so centimetre tables stay readable.
    """
    t = summary["thresholds"]
    smallest = min((r["max_dist"] for r in t if r["max_dist"] > 0), default=0.1)
    nd_m = max(2, 1 - int(np.floor(np.log10(smallest) + 1e-9)))

    def f(v, nd):
        return "-" if v is None else f"{v:.{nd}f}"

    return [
        ["Max. C2M distance [m]"] + [f"{r['max_dist']:g}" for r in t],
        ["% of points less than max. distance"] + [f(r["percent"], 1) for r in t],
        ["Mean C2M dist. [m]"] + [f(r["mean"], nd_m) for r in t],
        ["Std. Dev. C2M dist. [m]"] + [f(r["std"], nd_m) for r in t],
    ]


def table1_csv(summary: dict) -> str:
    """Table 1 as CSV, full precision."""
    t = summary["thresholds"]

    def f(v):
        return "" if v is None else repr(float(v))

    rows = [["Max. C2M distance [m]"] + [f(r["max_dist"]) for r in t],
            ["% of points less than max. distance"] + [f(r["percent"]) for r in t],
            ["Mean C2M dist. [m]"] + [f(r["mean"]) for r in t],
            ["Std. Dev. C2M dist. [m]"] + [f(r["std"]) for r in t]]
    return "".join(",".join(r) + "\n" for r in rows)


def overall_rows(summary: dict) -> list[list[str]]:
    """Overall statistics rows: (statistic, unsigned[, signed])."""
    keys = ["count", "mean", "median", "std", "rms", "min", "max"]
    rows = []
    for k in keys:
        u = summary["unsigned"][k]
        r = [k if k == "count" else f"{k} [m]", str(u) if k == "count" else ("-" if u is None else f"{u:.6f}")]
        if summary.get("signed"):
            s = summary["signed"][k]
            r.append(str(s) if k == "count" else ("-" if s is None else f"{s:.6f}"))
        rows.append(r)
    return rows


def markdown_report(summary: dict) -> str:
    """Table 1 and the overall statistics as Markdown."""
    rows = table1_rows(summary)
    n = len(rows[0])
    lines = [f"# C2M: {Path(summary['cloud']).name} vs {Path(summary['mesh']).name}", "",
             "| " + " | ".join(rows[0]) + " |", "|" + "---|" * n]
    lines += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    lines += ["", f"Points: {summary['points_total']} total, {summary['points_valid']} valid, "
              f"{summary['points_nonfinite']} NaN/inf excluded"
              + (f", {summary['points_beyond_max_dist']} beyond max-dist {summary['max_dist']} m" if summary["max_dist"] else "")
              + f". Mesh: {summary['mesh_triangles']} triangles.", ""]
    hdr = ["statistic", "unsigned"] + (["signed"] if summary.get("signed") else [])
    lines += ["| " + " | ".join(hdr) + " |", "|" + "---|" * len(hdr)]
    lines += ["| " + " | ".join(r) + " |" for r in overall_rows(summary)]
    return "\n".join(lines) + "\n"
