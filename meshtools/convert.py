"""TIN -> polygon model: the ``mst convert-model`` stage.

Algorithm (all vectorised with numpy/scipy except the fallback queue and pinch vertices):

1. **Weld** vertices closer than ``weld_tol`` metres (KD-tree pairs + connected components; each
   cluster keeps its lowest-index vertex, coordinates unchanged). **Drop** triangles that become
   degenerate: repeated vertex or zero area (area <= ``1e-12 * scale^2``); they are counted.
2. **Edges**: half-edges grouped by undirected key. An edge with 2 triangles is manifold; 1 = border;
   3+ = non-manifold (counted; no region grows and no orientation propagates across it).
3. **Orientation**: triangles across manifold edges are made consistent (BFS tree over the face
   graph, parities resolved by pointer jumping). Then per connected component: a *closed* component
   (every edge manifold) is flipped if its signed volume is negative, so normals point out; an *open*
   component (a terrain, a facade) keeps the orientation of the majority (by area) of its input
   triangles.
4. **Regions**: a triangle joins a region only if its unit normal is within ``angle_tol/2`` of the
   region normal and its 3 vertices are within ``dist_tol`` of the region plane; regions grow over
   manifold edges whose dihedral angle is <= ``angle_tol``. So any two triangles of a region differ
   by at most ``angle_tol`` and every crease edge (dihedral > ``angle_tol``) lies on a region
   boundary. Fast path: connected components of the candidate edges whose triangles all pass the
   test against the component's area-weighted plane are accepted as they are. Components that fail
   (slowly curving surfaces that would chain) are regrown with an explicit queue (no recursion):
   seeds by decreasing area, region plane = seed plane.
5. **Outlines**: half-edges whose opposite triangle is in another region (or missing) form the region
   boundary, already oriented (region on the left). They are chained into loops (vectorised list
   ranking); at a pinch vertex (several outgoing edges) the region's wedges are closed locally and a
   loop that still visits a vertex twice is split there, so every loop is simple (holes may touch
   the outline or each other at single vertices). Loop signed area in the region plane tells the
   outer loop (> 0) from holes (< 0); zero-area loops (slits) are dropped and counted. Half-edges
   left unbalanced by non-orientable tangles are dropped and counted (never a crash).
6. **Simplify**: a vertex is removed when it is a straight pass-through (within ``collinear_tol``)
   in *every* loop that uses it; a vertex where any loop turns (corners, T-junctions of three
   regions) is kept in all loops, so neighbouring polygons share the same vertices and no crack opens.
7. **Write** ``.wrl``, ``.cao`` or ``.obj`` (holes bridged: see :mod:`mst.meshtools.formats`), atomically.

Units: metres (or the file's unit) for lengths, degrees for ``angle_tol_deg``.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst import InputError, atomic_output
from mst.meshtools.model import PolygonModel


@dataclass
class ConvertConfig:
    """Tolerances of :func:`convert_model`.

    angle_tol_deg : max angle (degrees) between any two triangle normals of one polygon.
    dist_tol : max distance (metres) of a region's vertices from its plane; None = 1e-4 of the
        bounding-box diagonal.
    weld_tol : vertices closer than this (metres) are merged; 0 = exact duplicates only.
    collinear_tol : max distance (metres) of a removed vertex from the line through its
        neighbours; None = ``max(weld_tol, 1e-6 * diagonal)``, at most ``dist_tol`` (float32 files
        carry ~1e-7 relative noise).
    """

    angle_tol_deg: float = 1.0
    dist_tol: float | None = None
    weld_tol: float = 1e-6
    collinear_tol: float | None = None


# ====================================================================== stage function
def convert_model(input_path: str | Path, output_path: str | Path, config: ConvertConfig | None = None,
                  progress: Callable[[str], None] | None = None) -> dict:
    """Read a TIN, group it into planar polygons, write the polygon model. Returns the summary dict.

    ``progress(step_name)`` is called after each of the steps (read, weld, orient, regions,
    outlines, write). Raises :class:`mst.InputError` for unreadable or degenerate input; nothing is
    written then.
    """
    from mst.meshtools.formats import WRITE_SUFFIXES, load_triangles, model_suffix, save_model

    cfg = config or ConvertConfig()
    out = Path(output_path)
    if model_suffix(out) not in WRITE_SUFFIXES:
        raise InputError(out, f"unknown output format {out.suffix!r} (use .wrl, .cao or .obj)")
    if not out.parent.is_dir():
        raise InputError(out, "output folder does not exist")
    if out.exists() and Path(input_path).exists() and out.resolve() == Path(input_path).resolve():
        raise InputError(out, "the output would overwrite the input")
    t0 = time.perf_counter()
    step = progress or (lambda name: None)
    V, F = load_triangles(input_path)
    step("read")
    model, stats = tin_to_polygons(V, F, cfg, path=str(input_path), progress=step)
    with atomic_output(out) as tmp:
        save_model(tmp, model)
    step("write")
    stats.update(input=str(input_path), output=str(out), seconds=round(time.perf_counter() - t0, 4))
    return stats


def tin_to_polygons(V: np.ndarray, F: np.ndarray, config: ConvertConfig | None = None, path: str | None = None,
                    progress: Callable[[str], None] | None = None) -> tuple[PolygonModel, dict]:
    """Core of :func:`convert_model` on arrays: ``V`` (N, 3) metres, ``F`` (M, 3) int.

    Returns the :class:`PolygonModel` (faces = outer loops CCW seen from outside, holes CW, only the
    vertices used, in input order) and a statistics dict.
    """
    cfg = config or ConvertConfig()
    step = progress or (lambda name: None)
    V = np.asarray(V, np.float64).reshape(-1, 3)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if len(F) == 0:
        raise InputError(path, "no triangles in the mesh")
    if not np.isfinite(V).all():
        bad = ~np.isfinite(V).all(axis=1)
        raise InputError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates (first: #{int(np.argmax(bad))})")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(path, "triangle vertex index out of range")
    used_mask = np.zeros(len(V), bool)
    used_mask[F] = True
    used_v = np.flatnonzero(used_mask)
    lo, hi = V[used_v].min(0), V[used_v].max(0)
    diag = float(np.linalg.norm(hi - lo))
    if diag == 0:
        raise InputError(path, "all vertices coincide (degenerate mesh)")
    dist_tol = float(cfg.dist_tol) if cfg.dist_tol is not None else 1e-4 * diag
    col_tol = (float(cfg.collinear_tol) if cfg.collinear_tol is not None
               else min(max(cfg.weld_tol, 1e-6 * diag), dist_tol))
    if not (cfg.angle_tol_deg >= 0 and dist_tol >= 0 and cfg.weld_tol >= 0):
        raise InputError(None, "tolerances must be >= 0")
    # work in coordinates centred on the bounding box (precision for large map coordinates)
    center = (lo + hi) / 2
    X = V - center
    stats: dict = {"triangles_in": int(len(F)), "vertices_in": int(len(used_v))}

    # ---- 1. weld + drop degenerate
    F, n_welded = weld(X, F, cfg.weld_tol)
    a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    cr = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cr, axis=1)
    degenerate = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2]) | (area2 <= 2e-12 * diag**2)
    stats.update(welded_vertices=int(n_welded), degenerate_dropped=int(degenerate.sum()))
    if degenerate.any():
        F, cr, area2 = F[~degenerate], cr[~degenerate], area2[~degenerate]
    if len(F) == 0:
        raise InputError(path, "every triangle is degenerate (zero area)")
    step("weld")

    # ---- 2. edges
    E = _edges(F, len(X))
    stats.update(nonmanifold_edges=int((E.count >= 3).sum()), border_edges=int((E.count == 1).sum()))

    # ---- 3. orientation
    F, flipped, comp, n_comp, closed = orient(X, F, E, area2, cr)
    stats.update(components=int(n_comp), closed_components=int(closed.sum()), flipped_triangles=int(flipped))
    if flipped:
        a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
        cr = np.cross(b - a, c - a)
        E = _edges(F, len(X))
    N = cr / area2[:, None]
    step("orient")

    # ---- 4. regions
    region, n_fallback = grow_regions(X, F, N, area2, E, np.deg2rad(cfg.angle_tol_deg), dist_tol)
    n_regions = int(region.max()) + 1
    stats.update(regions=n_regions, regrown_triangles=int(n_fallback))
    step("regions")

    # ---- 5./6. outlines, then the planarity promise checked on the OUTPUT polygons
    faces, holes, ostats, face_region = outlines(X, F, region, n_regions, cr, E, col_tol, diag)
    n_replanarised = 0
    for it in range(_PLANARITY_ROUNDS + 3):  # the last rounds split what still fails into triangles
        bad_reg = _nonplanar_regions(X, faces, holes, face_region, dist_tol, diag)
        if len(bad_reg) == 0:
            break
        bad_tri = np.isin(region, bad_reg)
        n_replanarised += int(bad_tri.sum())
        if it < _PLANARITY_ROUNDS:  # regrow those regions in a thinner slab
            region = _regrow(X, F, N, area2, E, region, bad_tri, np.deg2rad(cfg.angle_tol_deg),
                             dist_tol * 0.5 ** (it + 1))
        else:  # last resort: one region per triangle (a triangle is exactly planar)
            region = _renumber(np.where(bad_tri, region.max() + 1 + np.arange(len(F)), region))
        n_regions = int(region.max()) + 1
        faces, holes, ostats, face_region = outlines(X, F, region, n_regions, cr, E, col_tol, diag)
    stats.update(ostats, regions=n_regions, replanarised_triangles=n_replanarised)
    # keep only used vertices, input order
    loops = faces + [h for hs in holes for h in hs]
    used = np.zeros(len(X), bool)
    for lp in loops:
        used[lp] = True
    remap = np.cumsum(used) - 1
    if not faces:
        raise InputError(path, "no polygon could be formed (degenerate mesh)")
    model = PolygonModel(V[used], [remap[f] for f in faces], holes=[[remap[h] for h in hs] for hs in holes])
    stats.update(polygons_out=model.n_faces, vertices_out=int(used.sum()), holes=model.n_holes,
                 angle_tol_deg=float(cfg.angle_tol_deg), dist_tol=dist_tol, weld_tol=float(cfg.weld_tol))
    step("outlines")
    return model, stats


# ====================================================================== 1. welding
def weld(X: np.ndarray, F: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """Merge vertices closer than ``tol`` (exact duplicates when ``tol == 0``).

    Returns the remapped faces (each cluster -> its lowest vertex index) and the number of merged
    vertices. Clusters are connected components of the "closer than tol" graph. Close pairs are
    found by a sweep along a generic direction (points within ``tol`` are within ``tol`` in any
    projection): sorted projections are compared with their k-th successors for k = 1, 2, ...
    while any gap is below ``tol`` (a few passes for real meshes; no KD-tree needed).
    """
    used_mask = np.zeros(len(X), bool)
    used_mask[F] = True
    used = np.flatnonzero(used_mask)
    P = X[used]
    n = len(P)
    w = np.array([0.8097, 0.5123, 0.2862])  # generic unit-ish direction (not axis-aligned)
    w /= np.linalg.norm(w)
    proj = P @ w
    o = np.argsort(proj, kind="stable")
    ps = proj[o]
    I, J = [], []
    k = 1
    while k < n:
        gap_ok = ps[k:] - ps[:-k] <= tol
        if not gap_ok.any():
            break
        i = np.flatnonzero(gap_ok)
        a, b = o[i], o[i + k]
        close = ((P[a] - P[b]) ** 2).sum(1) <= tol * tol
        I.append(a[close])
        J.append(b[close])
        k += 1
    if not I or sum(len(x) for x in I) == 0:
        return F, 0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    I, J = np.concatenate(I), np.concatenate(J)
    g = coo_matrix((np.ones(len(I), np.int8), (I, J)), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    lab = lab.astype(np.int64)
    rep = np.full(lab.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(rep, lab, used)
    m = np.arange(len(X))
    m[used] = rep[lab]
    merged = int(n - (lab.max() + 1))
    return m[F], merged


# ====================================================================== 2. edges
class _Edges:
    """Half-edge grouping. Half-edge ``h = 3*f + k`` goes ``F[f, k] -> F[f, (k+1)%3]``.

    Attributes: ``order`` (3M,) half-edges sorted by undirected key; ``start``/``count`` per
    undirected edge (into ``order``); ``edge`` (3M,) undirected edge id of each half-edge;
    ``pair`` (P, 2) the two half-edges of each manifold edge.
    """

    def __init__(self, F: np.ndarray, nv: int):
        u = F.ravel()
        v = F[:, [1, 2, 0]].ravel()
        key = np.minimum(u, v) * nv + np.maximum(u, v)
        self.order = np.argsort(key)
        ks = key[self.order]
        brk = np.flatnonzero(np.diff(ks)) + 1
        self.start = np.concatenate([[0], brk])
        self.count = np.diff(np.concatenate([self.start, [len(ks)]]))
        self.edge = np.empty(len(ks), np.int64)
        self.edge[self.order] = np.repeat(np.arange(len(self.start)), self.count)
        man = self.start[self.count == 2]
        self.pair = np.stack([self.order[man], self.order[man + 1]], axis=1)
        self.u, self.v = u, v


def _edges(F: np.ndarray, nv: int) -> _Edges:
    return _Edges(F, nv)


# ====================================================================== 3. orientation
def orient(X, F, E: _Edges, area2, cr):
    """Consistent winding over manifold edges, outward for closed components (module doc, step 3).

    Returns ``(F, n_flipped, comp_label, n_comp, closed_per_comp)``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    M = len(F)
    f1, f2 = E.pair[:, 0] // 3, E.pair[:, 1] // 3
    same_dir = E.u[E.pair[:, 0]] == E.u[E.pair[:, 1]]  # inconsistent pair
    g = coo_matrix((np.ones(len(f1), np.int8), (f1, f2)), shape=(M, M))
    n_comp, comp = connected_components(g, directed=False)
    comp = comp.astype(np.int64)
    flip = np.zeros(M, bool)
    if same_dir.any():
        # BFS tree from a virtual root linked to the first face of each component
        first = np.full(n_comp, M)
        np.minimum.at(first, comp, np.arange(M))
        rows = np.concatenate([f1, f2, np.full(n_comp, M)])
        cols = np.concatenate([f2, f1, first])
        G = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(M + 1, M + 1)).tocsr()
        _, pred = breadth_first_order(G, M, directed=True, return_predecessors=True)
        pred = pred[:M].astype(np.int64)
        # parity of each tree edge (pred -> child)
        key_pair = np.concatenate([f1 * (M + 1) + f2, f2 * (M + 1) + f1])
        par_pair = np.concatenate([same_dir, same_dir])
        o = np.argsort(key_pair)
        key_sorted = key_pair[o]
        is_root_child = pred == M
        child = np.arange(M)
        q = np.where(is_root_child, 0, pred * (M + 1) + child)
        pos = np.clip(np.searchsorted(key_sorted, q), 0, len(key_sorted) - 1)
        par = np.where(is_root_child, False, par_pair[o][pos])
        # pointer jumping: flip(f) = xor of parities on the path to the root
        acc = par.copy()  # root children: parity False and nxt = self (terminals)
        nxt = np.where(is_root_child, child, pred)
        while True:
            acc = acc ^ acc[nxt]
            nxt2 = nxt[nxt]
            if np.array_equal(nxt2, nxt):
                break
            nxt = nxt2
        flip = acc
    # closed components: all edges manifold
    bad_edge_face = np.zeros(M, bool)
    nonman_h = E.order[np.repeat(E.count != 2, E.count)]
    bad_edge_face[nonman_h // 3] = True
    closed = np.bincount(comp, weights=bad_edge_face, minlength=n_comp) == 0
    # signed volume of the cone from the origin: a . (b x c) = a . ((b - a) x (c - a))
    vol = np.einsum("ij,ij->i", X[F[:, 0]], cr) / 6
    vol = np.where(flip, -vol, vol)
    comp_vol = np.bincount(comp, weights=vol, minlength=n_comp)
    flipped_area = np.bincount(comp, weights=area2 * flip, minlength=n_comp)
    total_area = np.bincount(comp, weights=area2, minlength=n_comp)
    comp_flip = np.where(closed, comp_vol < 0, flipped_area > 0.5 * total_area)
    flip = flip ^ comp_flip[comp]
    if flip.any():
        F = np.where(flip[:, None], F[:, [0, 2, 1]], F)
    return F, int(flip.sum()), comp, n_comp, closed


# ====================================================================== 4. regions
def grow_regions(X, F, N, area2, E: _Edges, angle_tol: float, dist_tol: float) -> tuple[np.ndarray, int]:
    """Label each triangle with a region id (module doc, step 4). Returns ``(labels, n_regrown)``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    M = len(F)
    f1, f2 = E.pair[:, 0] // 3, E.pair[:, 1] // 3
    # manifold, consistently oriented pairs with a small dihedral angle are growth candidates
    consistent = E.u[E.pair[:, 0]] == E.v[E.pair[:, 1]]
    cos_pair = np.einsum("ij,ij->i", N[f1], N[f2])
    cand = consistent & (cos_pair >= np.cos(angle_tol) - 1e-15)
    f1, f2 = f1[cand], f2[cand]
    g = coo_matrix((np.ones(len(f1), np.int8), (f1, f2)), shape=(M, M))
    n_lab, lab = connected_components(g, directed=False)
    lab = lab.astype(np.int64)
    # region plane per component: area-weighted normal through the area-weighted centroid
    w = area2
    nsum = np.stack([np.bincount(lab, weights=N[:, k] * w, minlength=n_lab) for k in range(3)], 1)
    nn = np.linalg.norm(nsum, axis=1, keepdims=True)
    nR = np.divide(nsum, nn, out=np.zeros_like(nsum), where=nn > 0)
    XF = X[F]
    cen = XF.mean(axis=1)
    cR = np.stack([np.bincount(lab, weights=cen[:, k] * w, minlength=n_lab) for k in range(3)], 1)
    cR /= np.bincount(lab, weights=w, minlength=n_lab)[:, None]
    half = np.cos(angle_tol / 2) - 1e-12
    ok_ang = np.einsum("ij,ij->i", N, nR[lab]) >= half
    nRl = nR[lab]
    d = np.abs(np.einsum("ijk,ik->ij", XF, nRl) - np.einsum("ij,ij->i", cR[lab], nRl)[:, None]).max(axis=1)
    del XF
    ok = ok_ang & (d <= dist_tol)
    comp_ok = np.bincount(lab, weights=~ok, minlength=n_lab) == 0
    bad = ~comp_ok[lab]
    n_bad = int(bad.sum())
    if n_bad:
        # regrow the failing components: first group them into near-exact facets (dihedral below
        # a tight angle), then grow regions over facets with a queue (seeds by decreasing area)
        sub = np.flatnonzero(bad)
        keep = bad[f1] & bad[f2]
        sf1, sf2 = f1[keep], f2[keep]
        newlab = _queue_grow(X, F, N, area2, sub, sf1, sf2, angle_tol, dist_tol)
        good_ids = np.flatnonzero(comp_ok)
        remap = np.full(n_lab, -1)
        remap[good_ids] = np.arange(len(good_ids))
        out = remap[lab]
        out[sub] = newlab + len(good_ids)
        lab = out
    # canonical numbering: by first triangle
    _, first = np.unique(lab, return_index=True)
    order = np.argsort(first)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    return rank[lab], n_bad


def _queue_grow(X, F, N, area2, sub, f1, f2, angle_tol, dist_tol) -> np.ndarray:
    """Region growing with an explicit FIFO queue (no recursion) over the triangles ``sub``.

    Nodes are *facets*: connected groups of triangles whose dihedral angles are below
    ``angle_tol / 10`` (a planar wall split into many triangles is one node; a facet whose triangles
    spread more than ``angle_tol / 4`` from its normal or whose vertices leave its plane by more than
    ``dist_tol`` is split back into single triangles), each with its
    area-weighted normal ``n_f``, the largest angle ``s_f`` between ``n_f`` and its triangles, and its
    vertices. A region starts at the largest unvisited facet; its plane is the seed's (normal
    ``n_s``, through the seed's centroid). A neighbouring facet joins if ``angle(n_f, n_s) + s_f <=
    angle_tol / 2`` (so every triangle is within ``angle_tol/2`` of ``n_s``) and all its vertices are
    within ``dist_tol`` of the plane. Returns a label per entry of ``sub``.
    """
    from scipy.sparse import coo_matrix, csr_matrix
    from scipy.sparse.csgraph import connected_components

    M = len(F)
    loc = np.full(M, -1)
    loc[sub] = np.arange(len(sub))
    a, b = loc[f1], loc[f2]
    n = len(sub)
    Ns = N[sub]
    # facets: tight components, each checked against its own plane (else split into triangles)
    tight_edge = np.einsum("ij,ij->i", Ns[a], Ns[b]) >= np.cos(angle_tol / 10)
    g = coo_matrix((np.ones(int(tight_edge.sum()), np.int8), (a[tight_edge], b[tight_edge])), shape=(n, n))
    nf, fac = connected_components(g, directed=False)
    fac = fac.astype(np.int64)
    w = area2[sub]
    nsum = np.stack([np.bincount(fac, weights=Ns[:, k] * w, minlength=nf) for k in range(3)], 1)
    nF = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-300)
    cosang = np.clip(np.einsum("ij,ij->i", Ns, nF[fac]), -1, 1)
    spread_t = np.arccos(cosang)
    spread = np.zeros(nf)
    np.maximum.at(spread, fac, spread_t)
    XFs = X[F[sub]]
    cen_t = XFs.mean(1)
    areaF = np.bincount(fac, weights=w, minlength=nf)
    cenF = np.stack([np.bincount(fac, weights=cen_t[:, k] * w, minlength=nf) for k in range(3)], 1)
    cenF /= np.maximum(areaF, 1e-300)[:, None]
    dist_t = np.abs(np.einsum("ijk,ik->ij", XFs - cenF[fac][:, None, :], nF[fac])).max(1)
    dmax = np.zeros(nf)
    np.maximum.at(dmax, fac, dist_t)
    bad_fac = (spread > angle_tol / 4) | (dmax > dist_tol)
    if bad_fac.any():  # chained curved strip: its triangles become facets of their own
        split = bad_fac[fac]
        fac = np.where(split, nf + np.arange(n), fac)
        _, fac = np.unique(fac, return_inverse=True)
        fac = fac.ravel().astype(np.int64)
        nf = int(fac.max()) + 1
        nsum = np.stack([np.bincount(fac, weights=Ns[:, k] * w, minlength=nf) for k in range(3)], 1)
        nF = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-300)
        spread = np.zeros(nf)
        np.maximum.at(spread, fac, np.arccos(np.clip(np.einsum("ij,ij->i", Ns, nF[fac]), -1, 1)))
        areaF = np.bincount(fac, weights=w, minlength=nf)
        cenF = np.stack([np.bincount(fac, weights=cen_t[:, k] * w, minlength=nf) for k in range(3)], 1)
        cenF /= np.maximum(areaF, 1e-300)[:, None]
    fa, fb = fac[a], fac[b]
    cross_e = fa != fb
    A = csr_matrix((np.ones(2 * int(cross_e.sum()), np.int8),
                    (np.concatenate([fa[cross_e], fb[cross_e]]), np.concatenate([fb[cross_e], fa[cross_e]]))),
                   shape=(nf, nf))
    A.sum_duplicates()
    indptr, indices = A.indptr.tolist(), A.indices.tolist()
    # facet vertices (unique per facet) for the distance test
    fv = np.repeat(fac, 3)
    vv = F[sub].ravel()
    key = np.unique(fv * (len(X) + 1) + vv)
    fv_s, vv_s = key // (len(X) + 1), key % (len(X) + 1)
    vstart = np.searchsorted(fv_s, np.arange(nf + 1))
    PV = X[vv_s]
    nFl = nF.tolist()
    half = angle_tol / 2
    # angle(n_f, n_s) + s_f <= half  <=>  n_f . n_s >= cos(half - s_f)   (never if s_f > half)
    thr = np.where(spread <= half, np.cos(np.clip(half - spread, 0, np.pi)) - 1e-12, 2.0).tolist()
    PVl = PV.tolist()
    vst = vstart.tolist()
    label = [-1] * nf
    seeds = np.argsort(-areaF, kind="stable").tolist()
    r = 0
    for s in seeds:
        if label[s] != -1:
            continue
        label[s] = r
        nx, ny, nz = nFl[s]
        cx, cy, cz = cenF[s].tolist()
        off = nx * cx + ny * cy + nz * cz
        lo_d, hi_d = off - dist_tol, off + dist_tol
        ns = nF[s]
        q = deque([s])
        while q:
            t = q.popleft()
            for j in range(indptr[t], indptr[t + 1]):
                u = indices[j]
                if label[u] != -1:
                    continue
                m = nFl[u]
                if m[0] * nx + m[1] * ny + m[2] * nz < thr[u]:
                    continue
                a0, a1 = vst[u], vst[u + 1]
                if a1 - a0 <= 16:
                    ok = True
                    for k in range(a0, a1):
                        x, y, z = PVl[k]
                        d = x * nx + y * ny + z * nz
                        if d < lo_d or d > hi_d:
                            ok = False
                            break
                    if not ok:
                        continue
                else:
                    dd = PV[a0:a1] @ ns
                    if dd.min() < lo_d or dd.max() > hi_d:
                        continue
                label[u] = r
                q.append(u)
        r += 1
    return np.array(label, np.int64)[fac]


_PLANARITY_ROUNDS = 6


def _renumber(lab: np.ndarray) -> np.ndarray:
    """Region labels renumbered 0.. in the order of their first triangle (canonical, deterministic)."""
    _, first, inv = np.unique(lab, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    return rank[inv.ravel()]


def _regrow(X, F, N, area2, E: _Edges, region, bad_tri, angle_tol: float, dist_tol: float) -> np.ndarray:
    """Regrow the triangles ``bad_tri`` (whole regions) with :func:`_queue_grow` at ``dist_tol``;
    the other regions keep their triangles. Returns canonical labels."""
    f1, f2 = E.pair[:, 0] // 3, E.pair[:, 1] // 3
    consistent = E.u[E.pair[:, 0]] == E.v[E.pair[:, 1]]
    cand = consistent & (np.einsum("ij,ij->i", N[f1], N[f2]) >= np.cos(angle_tol) - 1e-15)
    cand &= bad_tri[f1] & bad_tri[f2] & (region[f1] == region[f2])
    sub = np.flatnonzero(bad_tri)
    newlab = _queue_grow(X, F, N, area2, sub, f1[cand], f2[cand], angle_tol, dist_tol)
    # keep regrown pieces inside their old region (label pairs), so two old regions never merge
    out = region.copy()
    out[sub] = region.max() + 1 + newlab * (region.max() + 1) + region[sub]
    return _renumber(out)


def _nonplanar_regions(X, faces, holes, face_region, dist_tol: float, diag: float) -> np.ndarray:
    """Regions having an output polygon whose vertices (outer loop and holes) are farther than
    ``dist_tol`` from the polygon's own least-squares plane (through their centroid, normal = the
    smallest principal axis). This is the plane a user of the written model fits, so it is the one
    the ``--dist-tol`` promise is checked against. Vectorised over polygons."""
    if not faces:
        return np.zeros(0, np.int64)
    idx = [np.concatenate([f, *hs]) for f, hs in zip(faces, holes)]
    lens = np.array([len(i) for i in idx], np.int64)
    pid = np.repeat(np.arange(len(idx)), lens)
    P = X[np.concatenate(idx)]
    cnt = lens.astype(float)
    c = np.stack([np.bincount(pid, weights=P[:, k], minlength=len(idx)) for k in range(3)], 1) / cnt[:, None]
    Q = P - c[pid]
    C = np.empty((len(idx), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            C[:, a, b] = C[:, b, a] = np.bincount(pid, weights=Q[:, a] * Q[:, b], minlength=len(idx))
    n = np.linalg.eigh(C)[1][:, :, 0]  # eigenvector of the smallest eigenvalue
    d = np.abs(np.einsum("ij,ij->i", Q, n[pid]))
    dmax = np.zeros(len(idx))
    np.maximum.at(dmax, pid, d)
    bad = dmax > dist_tol * (1 + 1e-9) + 1e-12 * diag
    return np.unique(np.asarray(face_region, np.int64)[bad])


# ====================================================================== 5./6. outlines
def outlines(X, F, region, n_regions, cr, E: _Edges, col_tol: float, diag: float):
    """Boundary loops per region: outer loop + holes, simplified without cracks (module doc 5-6).

    Returns ``(faces, holes, stats)`` with vertex indices into ``X``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from mst.meshtools.polygons import split_simple

    R = n_regions
    # region normals (area-weighted) for planar coordinates
    nsum = np.stack([np.bincount(region, weights=cr[:, k], minlength=R) for k in range(3)], 1)
    nR = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-300)
    # boundary half-edges: opposite triangle missing, non-manifold, or in another region
    h_all = np.arange(3 * len(F))
    fr = region[h_all // 3]
    interior = np.zeros(len(h_all), bool)
    p0, p1 = E.pair[:, 0], E.pair[:, 1]
    same = fr[p0] == fr[p1]
    interior[p0[same]] = True
    interior[p1[same]] = True
    hb = h_all[~interior]
    bu, bv, br = E.u[hb], E.v[hb], fr[hb]
    nv = len(X)
    # every (region, vertex) must have as many boundary half-edges in as out; this holds for
    # consistently oriented regions. Non-orientable or non-manifold tangles can break it: drop the
    # half-edges at unbalanced vertices (repeat until balanced) and count them.
    n_open = 0
    while len(bu):
        k_out = br * nv + bu
        k_in = br * nv + bv
        keys, inv = np.unique(np.concatenate([k_out, k_in]), return_inverse=True)
        inv = inv.ravel()
        n = len(bu)
        bal = np.bincount(inv[:n], minlength=len(keys)) - np.bincount(inv[n:], minlength=len(keys))
        if not bal.any():
            break
        bad_key = bal != 0
        drop = bad_key[inv[:n]] | bad_key[inv[n:]]
        n_open += int(drop.sum())
        bu, bv, br = bu[~drop], bv[~drop], br[~drop]
    B = len(bu)
    if B == 0:
        return [], [], {"loops": 0, "slit_loops_dropped": 0, "pinch_vertices": 0, "vertices_removed": 0,
                        "regions_without_outer_loop": int(R), "open_boundary_edges_dropped": n_open}, np.zeros(0, np.int64)
    # successor: next boundary half-edge of the same region leaving bv
    out_key = br * nv + bu
    o = np.argsort(out_key, kind="stable")
    ks = out_key[o]
    want = br * nv + bv
    lo = np.searchsorted(ks, want, "left")
    hi = np.searchsorted(ks, want, "right")
    cnt = hi - lo
    succ = o[np.minimum(lo, len(o) - 1)]
    n_pinch = 0
    multi = np.flatnonzero(cnt > 1)
    if len(multi):
        succ, n_pinch = _resolve_pinches(X, bu, bv, br, nR, o, lo, hi, multi, succ)
    # cycles = loops
    g = coo_matrix((np.ones(B, np.int8), (np.arange(B), succ)), shape=(B, B))
    n_loops, lab = connected_components(g, directed=True, connection="weak")
    lab = lab.astype(np.int64)
    # rank inside each cycle by pointer jumping from the cycle's smallest half-edge
    startp = np.full(n_loops, B)
    np.minimum.at(startp, lab, np.arange(B))
    pred = np.empty(B, np.int64)
    pred[succ] = np.arange(B)
    last = pred[startp]
    nxt = succ.copy()
    dist = np.ones(B, np.int64)
    nxt[last] = last
    dist[last] = 0
    while True:  # list ranking: dist = steps to the cycle's last half-edge
        dist = dist + dist[nxt]
        nxt2 = nxt[nxt]
        if np.array_equal(nxt2, nxt):
            break
        nxt = nxt2
    order = np.lexsort((-dist, lab))
    lab_o = lab[order]
    u_o = bu[order]
    loop_start = np.concatenate([[0], np.flatnonzero(np.diff(lab_o)) + 1])
    loop_len = np.diff(np.concatenate([loop_start, [B]]))
    loop_reg = br[order][loop_start]
    # signed area of each loop in its region plane
    pu, pv = X[bu[order]], X[bv[order]]
    cx = np.cross(pu, pv)
    av = np.stack([np.bincount(lab_o, weights=cx[:, k], minlength=n_loops) for k in range(3)], 1)
    loop_area = 0.5 * np.einsum("ij,ij->i", av[lab_o[loop_start]], nR[loop_reg])
    # simplification: vertices that are straight pass-throughs in every loop using them
    pos = np.arange(B)
    ls = np.repeat(loop_start, loop_len)
    ll = np.repeat(loop_len, loop_len)
    prev_i = ls + (pos - ls - 1) % ll
    next_i = ls + (pos - ls + 1) % ll
    P, Pp, Pn = X[u_o], X[u_o[prev_i]], X[u_o[next_i]]
    d_pn = Pn - Pp
    L = np.linalg.norm(d_pn, axis=1)
    off_line = np.linalg.norm(np.cross(d_pn, P - Pp), axis=1) / np.maximum(L, 1e-300)
    forward = np.einsum("ij,ij->i", P - Pp, Pn - P) > 0
    straight = (off_line <= col_tol) & forward & (L > 0)
    turns = np.bincount(u_o, weights=~straight, minlength=len(X))
    removable = (turns == 0)[u_o]
    # never reduce a loop below 3 vertices
    keep_cnt = np.bincount(lab_o, weights=~removable, minlength=n_loops)
    removable &= keep_cnt[lab_o] >= 3
    keep = ~removable
    tiny = 1e-12 * diag**2
    kept_u = u_o[keep]
    kept_lab = lab_o[keep]
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(kept_lab)) + 1, [len(kept_lab)]])
    loop_of_seg = kept_lab[bounds[:-1]]
    lab_at_start = lab_o[loop_start]
    area_by_loop = np.empty(n_loops)
    area_by_loop[lab_at_start] = loop_area
    reg_by_loop = np.empty(n_loops, np.int64)
    reg_by_loop[lab_at_start] = loop_reg
    # loops that pass a vertex twice (pinches) are split there into simple loops
    uniq_per_loop = np.bincount(np.unique(kept_lab * nv + kept_u) // nv, minlength=n_loops)
    len_per_loop = np.bincount(kept_lab, minlength=n_loops)
    repeated = uniq_per_loop < len_per_loop
    loops: list[tuple[int, float, np.ndarray]] = []  # (region, signed area, vertex loop)
    for li, s0, e0 in zip(loop_of_seg.tolist(), bounds[:-1].tolist(), bounds[1:].tolist()):
        seq = kept_u[s0:e0]
        r = int(reg_by_loop[li])
        if not repeated[li]:
            loops.append((r, float(area_by_loop[li]), seq))
            continue
        for sub in split_simple(seq.tolist()):
            P = X[sub]
            a = 0.5 * float(np.cross(P, np.roll(P, -1, axis=0)).sum(0) @ nR[r])
            loops.append((r, a, np.asarray(sub, np.int64)))
    n_split = int(repeated.sum())
    outer_of_region: dict[int, list[int]] = {}
    holes_of_region: dict[int, list[int]] = {}
    n_dropped = 0
    for k, (r, a, seq) in enumerate(loops):
        if abs(a) <= tiny or len(seq) < 3:
            n_dropped += 1
            continue
        (outer_of_region if a > 0 else holes_of_region).setdefault(r, []).append(k)
    faces, holes, face_region = [], [], []
    regions_without_outer = 0
    for r in range(R):
        outs = outer_of_region.get(r, [])
        hs = holes_of_region.get(r, [])
        if not outs:
            regions_without_outer += 1 if hs else 0
            continue
        outs.sort(key=lambda k: -loops[k][1])
        faces.append(loops[outs[0]][2])
        holes.append([loops[h][2] for h in hs])
        face_region.append(r)
        for extra in outs[1:]:
            faces.append(loops[extra][2])
            holes.append([])
            face_region.append(r)
    stats = {"loops": len(loops), "slit_loops_dropped": int(n_dropped), "pinch_vertices": int(n_pinch),
             "loops_split_at_pinches": n_split, "vertices_removed": int(len(np.unique(u_o[removable]))),
             "regions_without_outer_loop": int(regions_without_outer), "open_boundary_edges_dropped": n_open}
    return faces, holes, stats, np.array(face_region, np.int64)


def _resolve_pinches(X, bu, bv, br, nR, o, lo, hi, multi, succ):
    """At vertices with several outgoing boundary half-edges of one region, pair each incoming
    half-edge with the first outgoing one met turning clockwise from the reversed incoming
    direction (the region's wedges close locally). Loops that still pass a vertex twice are split
    there afterwards (:func:`~mst.meshtools.polygons.split_simple`), so every output loop is simple; holes may touch
    the outer loop or each other at single vertices (as OGC simple features allow)."""
    from mst.meshtools.polygons import plane_basis

    succ = succ.copy()
    groups: dict[tuple[int, int], list[int]] = {}
    for e in multi.tolist():
        groups.setdefault((int(lo[e]), int(hi[e])), []).append(e)
    for (a, b), incoming in groups.items():
        outs = o[a:b].tolist()
        r = int(br[incoming[0]])
        Bm = plane_basis(nR[r])
        v = X[bv[incoming[0]]]
        ang_out = {h: np.arctan2(*((X[bv[h]] - v) @ Bm)[::-1]) for h in outs}
        free = set(outs)
        for e in incoming:
            w = np.arctan2(*((X[bu[e]] - v) @ Bm)[::-1])
            best, best_d = None, None
            for h in free:
                dcw = (w - ang_out[h]) % (2 * np.pi)
                if dcw <= 1e-15:
                    dcw = 2 * np.pi
                if best_d is None or dcw < best_d:
                    best, best_d = h, dcw
            succ[e] = best
            free.discard(best)
    return succ, len(groups)


def summary_lines(s: dict) -> list[str]:
    """Human summary (stderr) of a :func:`convert_model` result."""
    return [
        f"triangles in {s['triangles_in']:,} ({s['vertices_in']:,} vertices): welded {s['welded_vertices']:,}, "
        f"degenerate dropped {s['degenerate_dropped']:,}, non-manifold edges {s['nonmanifold_edges']:,}, "
        f"components {s['components']:,} ({s['closed_components']:,} closed), flipped {s['flipped_triangles']:,}",
        f"regions {s['regions']:,} -> polygons out {s['polygons_out']:,}, vertices out {s['vertices_out']:,}, "
        f"holes {s['holes']:,} (tolerances: angle {s['angle_tol_deg']:g} deg, dist {s['dist_tol']:.3g} m)",
        f"wrote {s['output']} in {s['seconds']:.2f} s",
    ]


__all__ = ["ConvertConfig", "convert_model", "tin_to_polygons", "summary_lines"]
