"""Exact point-triangle geometry of C2M and the prepared mesh (:class:`MeshIndex`, :func:`prepare_mesh`).

A float64 global shift (the mesh bounding-box centre) is subtracted from the mesh (and, by the
caller, from the cloud), so georeferenced coordinates (1e6 m) keep their precision. Duplicate
vertices (same coordinates) are merged for the topology (pseudo-normals, one-rings), so split-vertex
OBJ/STL files work. The nearest-triangle search structures live in :mod:`mst.eval.c2m.grids`
(grid engine) or Open3D's ``RaycastingScene`` (BVH engine); the index builds and owns them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from mst import InputError


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
    _table: object = field(default=None, repr=False)  # the kernels' packed triangles (grids.triangle_table)

    @property
    def n_triangles(self) -> int:
        return len(self.F)

    def build_search(self, small_mesh_triangles: int = 5000, compiled: bool = True) -> None:
        """Build the nearest-triangle search of :attr:`engine` (called once by :func:`prepare_mesh`).

        Grid engine: meshes up to ``small_mesh_triangles`` triangles get the lazily filled dense grid
        of candidate lists, larger ones the binned grid with shell search; ``compiled=False`` makes the
        dense grid use its numpy path instead of the numba kernels (the reference the tests compare
        with). BVH engine: Open3D's ``RaycastingScene`` over the float32 shifted vertices.
        """
        if self.engine == "grid":
            from mst.eval.c2m.grids import BinGrid, DenseGrid

            if self.n_triangles <= small_mesh_triangles:
                self._grid = DenseGrid(self, compiled=compiled)
            else:
                from mst.eval.c2m.compiled import kernels

                self._grid = BinGrid(self, kernels)
            return
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(self.V.astype(np.float32)), o3d.core.Tensor(self.F.astype(np.uint32)))
        self._scene = scene

    @property
    def search(self):
        """The grid engine's search structure (:class:`~mst.eval.c2m.grids.DenseGrid` or
        :class:`~mst.eval.c2m.grids.BinGrid`); None for the BVH engine."""
        return self._grid

    @property
    def kernels(self):
        """The compiled kernel module the grid search uses (None: numpy path or BVH engine)."""
        return getattr(self._grid, "nb", None)

    def grid_nearest(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grid engine: ``(tri, d2, feature)`` of shifted points ``P``; tri = -1 beyond ``max_dist``."""
        return self._grid.nearest(P, max_dist)

    def bvh_closest_triangles(self, P32: np.ndarray) -> np.ndarray:
        """BVH engine: the triangle Open3D picks for each float32 shifted point (int64 ids)."""
        import open3d as o3d

        ans = self._scene.compute_closest_points(o3d.core.Tensor(P32))
        return ans["primitive_ids"].numpy().astype(np.int64)

    def exact_nearest(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tri, d2, feature)`` by the exact numpy grid (:class:`~mst.eval.c2m.grids.TriangleGrid`),
        built on first use: the BVH engine's re-search of points far from the mesh."""
        if self._exact is None:
            from mst.eval.c2m.grids import TriangleGrid

            self._exact = TriangleGrid(self)
        return self._exact.nearest(P, None)


def prepare_mesh(V: np.ndarray, F: np.ndarray, path: str | os.PathLike | None = None, signed: bool = False,
                 engine: str = "auto", small_mesh_triangles: int = 5000, compiled: bool = True) -> MeshIndex:
    """Validate and index a triangle mesh ``V (n, 3)`` metres, ``F (m, 3)`` vertex indices.

    ``engine``: "auto" (= "grid"), "grid" or "bvh" (see :meth:`MeshIndex.build_search` for
    ``small_mesh_triangles`` and ``compiled``). Raises :class:`mst.InputError` (naming ``path``) for a
    mesh without triangles, with non-finite vertices, out-of-range indices, or only degenerate triangles.
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
    nv = len(Vm)
    aa, ab, bb = _dot(AB, AB), _dot(AB, AC), _dot(AC, AC)
    det = aa * bb - ab * ab
    G = np.stack([bb / det, -ab / det, aa / det], axis=1)
    N = cr / area2[:, None]
    vert_n, edge_n = _pseudo_normals(Fm, Vm, N) if signed else (None, None)
    ring_ptr, ring_idx = _one_rings(Fm, nv) if engine == "bvh" else (None, None)
    idx = MeshIndex(shift, Vm, Fm, A, AB, AC, AC - AB, N, G, n_dropped=int((~ok).sum()), ring_ptr=ring_ptr,
                    ring_idx=ring_idx, edge_n=edge_n, vert_n=vert_n, engine=engine)
    idx.build_search(small_mesh_triangles, compiled=compiled)
    return idx


def _one_rings(Fm: np.ndarray, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """BVH: one-ring of every triangle (triangles sharing at least one vertex), CSR ``(ptr, idx)``, for
    the exact recheck."""
    m = len(Fm)
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
    ring_idx = v_tris[np.repeat(starts - np.cumsum(np.r_[0, lens[:-1]]), lens) + np.arange(lens.sum())]
    return ring_ptr, ring_idx


def _pseudo_normals(F: np.ndarray, V: np.ndarray, Nf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle-weighted vertex ``(nv, 3)`` and edge ``(m, 3, 3)`` pseudo-normals of the triangles ``F`` of
    the vertices ``V`` with face normals ``Nf`` (Baerentzen & Aanaes 2005)."""
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
    # edges ab, ac, bc of every triangle, keyed by sorted merged vertex ids
    pairs = np.stack([F[:, [0, 1]], F[:, [0, 2]], F[:, [1, 2]]], axis=1).reshape(-1, 2)
    pairs.sort(axis=1)
    key = pairs[:, 0] * nv + pairs[:, 1]
    _, einv = np.unique(key, return_inverse=True)
    en = np.zeros((einv.max() + 1, 3))
    fn_rep = np.repeat(Nf, 3, axis=0)
    for j in range(3):
        en[:, j] = np.bincount(einv, weights=fn_rep[:, j], minlength=len(en))
    return vn, en[einv].reshape(m, 3, 3)
