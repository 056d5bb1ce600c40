"""Nearest-triangle search of the C2M grid engine (exact float64, no Open3D).

:class:`DenseGrid` (meshes up to ``small_mesh_triangles``): a dense grid of lazily computed per-cell
candidate lists; :class:`BinGrid` (larger meshes): every triangle binned into the cells its bounding
box overlaps, shells of cells searched around each point until provably exact; :class:`TriangleGrid`:
the numpy coarse-to-fine candidate search used for points outside the dense grid (and by the BVH
engine for points far from the mesh). The compiled loops are in :mod:`mst.eval.c2m.kernels`.
"""

from __future__ import annotations

import numpy as np

from mst.eval.c2m.geometry import MeshIndex, triangle_distances


class TriangleGrid:
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

    def candidates(self, key_fine: np.ndarray, org: np.ndarray, h: float, levels: int, nb=None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """CSR candidate lists (ptr, tri) and distance lower bounds for the sorted unique fine cell keys."""
        idx = self.idx
        m = idx.n_triangles
        prev_k = ptr = tri = lb = None
        for lev in range(levels, -1, -1):
            hl = h * (1 << lev)
            u = _unique(_shift_key(key_fine, lev))
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
                d = np.sqrt(nb.pairs_d2(centres, cell_of, ti, triangle_table(idx)))
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
        ptr, tri, lb = self.candidates(ks[cell_start], lo, h, levels)
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


class BinGrid:
    """Nearest-triangle search for large meshes (compiled, exact float64, no Open3D).

    A uniform grid of cubic cells over the mesh box (plus a margin); every triangle is listed in each
    cell its bounding box overlaps (conservative, CSR with int32 triangle ids). Per point, shells of
    cells around its cell are searched outward until the best distance is at most the distance to the
    cells not searched yet (:func:`mst.eval.c2m.kernels.bins_query`): exact, also near ties. The cell
    size is about ``cell_factor`` times the mean triangle edge (from the mean area), enlarged when the
    grid would exceed ``max_cells``. Points far outside the grid (more than ``far_cells`` cells) scan
    the occupied cells instead (:func:`mst.eval.c2m.kernels.bins_far_query`).
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
        self.box = np.concatenate([vmin, vmax]).astype(np.float64)  # every triangle lies in it
        self.T = triangle_table(idx)
        self.BB = np.ascontiguousarray(self.T[:, 18:])  # (m, 6) triangle boxes
        self.start, self.items = nb.bin_triangles(self.BB, self.lo, 1.0 / self.h, self.dims)
        self.far_d2 = (far_cells * self.h) ** 2
        self.occ = np.nonzero(np.diff(self.start))[0]  # occupied cells, for the far points

    def nearest(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tri, d2, feature)`` per point; tri = -1 where farther than ``max_dist``."""
        nb = self.nb
        P = np.ascontiguousarray(P, np.float64)
        md2 = np.inf if max_dist is None else (float(max_dist) * (1 + 1e-9)) ** 2

        def query(Q):
            return nb.bins_query(Q, self.lo, self.h, self.dims, self.start, self.items, md2, self.far_d2, self.T,
                                 nb.bucket_order(Q, self.lo, 1.0 / self.h, self.dims, 2), self.box)

        tri, d2, feat, st = row_blocks(nb, "bins_query", P, query)
        out = np.nonzero(st == 1)[0]
        if len(out):
            tri[out], d2[out], feat[out] = nb.bins_far_query(P[out], self.lo, self.h, self.dims, self.start,
                                                             self.items, self.occ, md2, self.T)
        return tri, d2, feat


class DenseGrid:
    """Nearest-triangle search for small meshes: a dense grid of cells over the mesh box.

    Candidate triangle lists (see :class:`TriangleGrid` for the conservative rule) are computed
    lazily, the first time a point falls in a cell, and cached for the following chunks (thread
    safe). Per point the work is a cell lookup and exact float64 distances to the cell's few
    candidates: no sorting. Points outside the grid box go to a :class:`BinGrid` of the same mesh
    (compiled path; :class:`TriangleGrid` on the numpy reference path).
    """

    def __init__(self, idx: MeshIndex, max_cells: int = 500_000, compiled: bool = True):
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
        self._filled = False  # any cell computed yet
        self._tg = TriangleGrid(idx)
        self._bins: BinGrid | None = None  # points outside the grid (compiled path), built on first need
        self.ext = ext
        nb = None
        if compiled:  # the compiled kernels (about 10x faster); the numpy path is the tests' reference
            from mst.eval.c2m.compiled import kernels as nb
        self.nb = nb
        self.T = triangle_table(idx) if compiled else None  # the kernels' packed triangles

    def _nearest_numba(self, P: np.ndarray, max_dist: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nb, idx = self.nb, self.idx
        md = -1.0 if max_dist is None else float(max_dist)
        lo, inv_h = self.lo.astype(np.float64), 1.0 / self.h
        if not self._filled:  # first chunk: no cell computed yet, so the query below would only
            # report "not computed" for every point and run again; fill the chunk's cells first
            flat = nb.missing_cells(P, lo, inv_h, self.dims, self.cell)
            if len(flat):
                self._fill(flat)

        def query(Q):  # the cells' lists are fixed during a query (filled only in this thread)
            return nb.grid_query(Q, lo, inv_h, self.dims, self.cell, self.lb, self.cand, md, self.T,
                                 nb.bucket_order(Q, lo, inv_h, self.dims, 3))

        tri, d2, feat, st = row_blocks(nb, "grid_query", P, query)
        new = np.nonzero(st == 2)[0]
        if len(new):
            Pn = P[new]
            self._fill(nb.missing_cells(Pn, lo, inv_h, self.dims, self.cell))
            tri[new], d2[new], feat[new], st[new] = row_blocks(nb, "grid_query", Pn, query)
        out = np.nonzero(st == 1)[0]
        if len(out):
            # outside the dense grid: the compiled shell search of a binned grid (exact, built once on
            # first need; the numpy coarse-to-fine search took 2.3 s for 3,000 points around a
            # 3,072-triangle box)
            with self._lock:
                if self._bins is None:
                    self._bins = BinGrid(idx, nb)
            tri[out], d2[out], feat[out] = self._bins.nearest(P[out], max_dist)
        return tri, d2, feat

    def _fill(self, flat: np.ndarray) -> None:
        """Compute candidate lists of the (unique, not yet computed) flat cell ids."""
        with self._lock:
            flat = flat[self.cell[flat] < 0]
            if not len(flat):
                return
            dy, dz = int(self.dims[1]), int(self.dims[2])
            ijk = np.stack([flat // (dy * dz), (flat // dz) % dy, flat % dz], axis=1)
            up = PARENT_LEVELS
            if self.nb is not None and self.levels >= up:
                # parents ``up`` levels up (2**up x coarser cells), their lists refined level by level
                # from the coarsest (:meth:`_ancestor_lists`), then the fine cells refined from their
                # parent's list, all in the compiled kernel. Any ancestor's list holds every triangle
                # within dmin + 2 r of a child's centre, so the children's lists (and their order:
                # distance, then triangle id) depend neither on ``up`` nor on how the parents' were made
                pkey = _key(ijk >> up)
                upk, pinv = np.unique(pkey, return_inverse=True)
                pptr, ptri = self._ancestor_lists(upk, up)
                centres = self.lo + (ijk + 0.5) * self.h
                r, tol, par = 0.5 * self.h * np.sqrt(3.0), 1e-9 * self.ext, pinv.reshape(-1)

                def refine(rows):  # cells [a, b): (counts, triangles, lower bounds); each cell on its own
                    a, b = int(rows[0]), int(rows[-1]) + 1
                    p, t, lbs = self.nb.refine_cells(centres[a:b], r, par[a:b], pptr, ptri, tol, self.T)
                    return np.diff(p), t, lbs

                cnt, tri, lb = row_blocks(self.nb, "refine_cells", np.arange(len(flat)), refine, min_rows=2000)
                ptr = np.zeros(len(cnt) + 1, np.int64)
                np.cumsum(cnt, out=ptr[1:])
                cells = flat
            else:
                key = _key(ijk)
                o = np.argsort(key)
                ptr, tri, lb = self._tg.candidates(key[o], self.lo, self.h, self.levels, self.nb)
                cells = flat[o]
            base = len(self.cand)
            self.lb[cells] = lb
            self.cand = np.concatenate([self.cand, tri.astype(np.int32)])
            self.cell[cells] = ((base + ptr[:-1]) << 16) | np.diff(ptr)  # last: marks the cells as computed
            self._filled = True

    def _ancestor_lists(self, keys: np.ndarray, up: int) -> tuple[np.ndarray, np.ndarray]:
        """CSR candidate lists ``(ptr, tri)`` of the cells ``up`` levels above the fine grid with the
        sorted unique ``keys``: the coarsest level's cells test every triangle, each finer level its
        parents' lists (:func:`mst.eval.c2m.kernels.refine_cells`, the rule of
        :meth:`TriangleGrid.candidates`; 16 -> 4 ms CPU for the UTM bench case's 5,051 parents)."""
        nb, m = self.nb, self.idx.n_triangles
        top = self.levels - up  # levels above ``keys``
        ptr, tri = np.array([0, m], np.int64), np.arange(m, dtype=np.int64)
        prev = None
        tol = 1e-9 * self.ext
        for lev in range(top, -1, -1):
            u = _unique(_shift_key(keys, lev))
            hl = self.h * (1 << (up + lev))
            par = np.zeros(len(u), np.int64) if prev is None else np.searchsorted(prev, _shift_key(u, 1))
            centres = self.lo + (_unkey(u) + 0.5) * hl
            ptr, tri, _ = nb.refine_cells(np.ascontiguousarray(centres), 0.5 * hl * np.sqrt(3.0), par, ptr, tri, tol,
                                          self.T)
            prev = u
        return ptr, tri

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
#: the dense grid fills a batch of cells from the candidate lists of their ancestors this many levels up
#: (4x coarser: 23 candidates per parent on the UTM bench building against 57 three levels up, so the
#: compiled refinement tests 2.5x fewer pairs for a few more parents; 56 -> 34 ms CPU for its 42k cells)
PARENT_LEVELS = 2
#: rows per thread below which a query is not split
MIN_BLOCK_ROWS = 50_000
_POOL = None


def row_blocks(nb, kernel: str, P: np.ndarray, query, min_rows: int = MIN_BLOCK_ROWS) -> tuple[np.ndarray, ...]:
    """``query(P)`` (a tuple of per-row arrays), split into row blocks over :func:`mst.core.aot.threads`
    threads when ``kernel`` runs ahead of time (its calls release the GIL, one core each); the JIT
    kernels are ``parallel=True`` themselves and get ``P`` whole. Every row's result depends on its
    row only, so the split changes no value."""
    global _POOL
    from mst.core.aot import threads

    t = min(threads(), len(P) // min_rows)
    if t < 2 or not getattr(nb, "is_aot", lambda k: False)(kernel):
        return query(P)
    from concurrent.futures import ThreadPoolExecutor

    if _POOL is None or _POOL._max_workers < t:
        _POOL = ThreadPoolExecutor(max_workers=t, thread_name_prefix="mst-c2m")
    edges = np.linspace(0, len(P), t + 1).astype(np.int64)
    parts = list(_POOL.map(lambda k: query(P[edges[k]:edges[k + 1]]), range(t)))
    return tuple(np.concatenate(a) for a in zip(*parts))


def triangle_table(idx: MeshIndex) -> np.ndarray:
    """The kernels' packed triangles of ``idx`` (m, 24) float64, built once per index: corner a,
    b - a, c - a, c - b, unit normal, inverse Gram entries, bounding box min and max (three columns
    each, the box six; :mod:`mst.eval.c2m.kernels`)."""
    T = getattr(idx, "_table", None)
    if T is None:
        corners = np.stack([idx.A, idx.A + idx.AB, idx.A + idx.AC])
        T = np.ascontiguousarray(np.concatenate([idx.A, idx.AB, idx.AC, idx.BC, idx.N, idx.G, corners.min(0),
                                                 corners.max(0)], axis=1), np.float64)
        idx._table = T
    return T


def _unique(a: np.ndarray) -> np.ndarray:
    """``np.unique`` of a 1-D integer array (sorted, no numpy.ma import)."""
    s = np.sort(a)
    return s[np.r_[True, s[1:] != s[:-1]]] if len(s) else s


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
