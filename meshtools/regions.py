"""Steps 1-4 of TIN -> polygons (:mod:`mst.meshtools.convert`): vertex welding, half-edge grouping,
consistent outward orientation, planar region growing (vectorised, with a queue-based regrowth for
components that would chain) and the planarity check of the output polygons.

Imports numpy, the kernels of :mod:`mst.meshtools.kernels` (through :mod:`mst.meshtools.compiled`: ahead of time,
or numba) and, for inconsistently wound input only, scipy.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from mst.meshtools.compiled import components, edge_groups, pair_candidates, plane_ok, region_sums

#: regrowth rounds in a thinner slab before failing regions are split into triangles
PLANARITY_ROUNDS = 6


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
    _, lab = components(n, np.concatenate(I), np.concatenate(J))
    rep = np.full(lab.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(rep, lab, used)
    m = np.arange(len(X))
    m[used] = rep[lab]
    merged = int(n - (lab.max() + 1))
    return m[F], merged


class Edges:
    """Half-edge grouping. Half-edge ``h = 3*f + k`` goes ``F[f, k] -> F[f, (k+1)%3]``.

    Attributes: ``order`` (3M,) half-edges sorted by undirected key; ``start``/``count`` per
    undirected edge (into ``order``); ``edge`` (3M,) undirected edge id of each half-edge;
    ``pair`` (P, 2) the two half-edges of each manifold edge.
    """

    def __init__(self, F: np.ndarray, nv: int):
        u = F.ravel()
        v = F[:, [1, 2, 0]].ravel()
        # = argsort of the undirected key min(u, v) * nv + max(u, v) (stable), grouped, in O(n)
        self.order, self.start, self.count, self.edge, self.pair = edge_groups(u, v, nv)
        self.u, self.v = u, v


def edges(F: np.ndarray, nv: int) -> Edges:
    return Edges(F, nv)


def orient(X, F, E: Edges, area2, cr):
    """Consistent winding over manifold edges, outward for closed components (:mod:`mst.meshtools.convert` doc, step 3).

    Returns ``(F, n_flipped, comp_label, n_comp, closed_per_comp)``.
    """
    M = len(F)
    f1, f2 = E.pair[:, 0] // 3, E.pair[:, 1] // 3
    same_dir = E.u[E.pair[:, 0]] == E.u[E.pair[:, 1]]  # inconsistent pair
    n_comp, comp = components(M, f1, f2)
    flip = np.zeros(M, bool)
    if same_dir.any():
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import breadth_first_order

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


def grow_regions(X, F, N, area2, E: Edges, angle_tol: float, dist_tol: float) -> tuple[np.ndarray, int]:
    """Label each triangle with a region id (:mod:`mst.meshtools.convert` doc, step 4). Returns ``(labels, n_regrown)``."""
    M = len(F)
    f1, f2 = E.pair[:, 0] // 3, E.pair[:, 1] // 3
    # manifold, consistently oriented pairs with a small dihedral angle are growth candidates
    consistent = E.u[E.pair[:, 0]] == E.v[E.pair[:, 1]]
    cand = pair_candidates(N, f1, f2, consistent, np.cos(angle_tol) - 1e-15)
    f1, f2 = f1[cand], f2[cand]
    n_lab, lab = components(M, f1, f2)
    # region plane per component: area-weighted normal through the area-weighted centroid
    nsum, cR, wsum = region_sums(X, F, N, area2, lab, n_lab)
    nn = np.linalg.norm(nsum, axis=1, keepdims=True)
    nR = np.divide(nsum, nn, out=np.zeros_like(nsum), where=nn > 0)
    cR /= wsum[:, None]
    ok = plane_ok(X, F, N, lab, nR, cR, np.cos(angle_tol / 2) - 1e-12, dist_tol)
    comp_ok = np.bincount(lab, weights=~ok, minlength=n_lab) == 0
    bad = ~comp_ok[lab]
    n_bad = int(bad.sum())
    if n_bad:
        # regrow the failing components: first group them into near-exact facets (dihedral below
        # a tight angle), then grow regions over facets with a queue (seeds by decreasing area)
        sub = np.flatnonzero(bad)
        keep = bad[f1] & bad[f2]
        sf1, sf2 = f1[keep], f2[keep]
        newlab = queue_grow(X, F, N, area2, sub, sf1, sf2, angle_tol, dist_tol)
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


def queue_grow(X, F, N, area2, sub, f1, f2, angle_tol, dist_tol) -> np.ndarray:
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
    M = len(F)
    loc = np.full(M, -1)
    loc[sub] = np.arange(len(sub))
    a, b = loc[f1], loc[f2]
    fac, nf, nF, spread, areaF, cenF = _facets(X, F, N, area2, sub, a, b, angle_tol, dist_tol)
    label = _grow_facets(X, F, sub, fac, nf, nF, spread, areaF, cenF, a, b, angle_tol, dist_tol)
    return np.array(label, np.int64)[fac]


def _facets(X, F, N, area2, sub, a, b, angle_tol, dist_tol):
    """The facets of :func:`queue_grow`: ``(facet per entry of sub, n_facets, facet normals,
    spreads, areas, centroids)``."""
    n = len(sub)
    Ns = N[sub]
    # facets: tight components, each checked against its own plane (else split into triangles)
    tight_edge = np.einsum("ij,ij->i", Ns[a], Ns[b]) >= np.cos(angle_tol / 10)
    nf, fac = components(n, a[tight_edge], b[tight_edge])
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
    return fac, nf, nF, spread, areaF, cenF


def _grow_facets(X, F, sub, fac, nf, nF, spread, areaF, cenF, a, b, angle_tol, dist_tol) -> list[int]:
    """Breadth-first region growing over the facet graph (:func:`queue_grow`): a label per facet."""
    fa, fb = fac[a], fac[b]
    cross_e = fa != fb
    # facet adjacency in CSR form: neighbours of each facet sorted, without duplicates
    adj = np.unique(np.concatenate([fa[cross_e] * nf + fb[cross_e], fb[cross_e] * nf + fa[cross_e]]))
    indptr = np.searchsorted(adj // nf, np.arange(nf + 1)).tolist()
    indices = (adj % nf).tolist()
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
    return label


def renumber(lab: np.ndarray) -> np.ndarray:
    """Region labels renumbered 0.. in the order of their first triangle (canonical, deterministic)."""
    _, first, inv = np.unique(lab, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    return rank[inv.ravel()]


def regrow(X, F, N, area2, E: Edges, region, bad_tri, angle_tol: float, dist_tol: float) -> np.ndarray:
    """Regrow the triangles ``bad_tri`` (whole regions) with :func:`queue_grow` at ``dist_tol``;
    the other regions keep their triangles. Returns canonical labels."""
    f1, f2 = E.pair[:, 0] // 3, E.pair[:, 1] // 3
    consistent = E.u[E.pair[:, 0]] == E.v[E.pair[:, 1]]
    cand = consistent & (np.einsum("ij,ij->i", N[f1], N[f2]) >= np.cos(angle_tol) - 1e-15)
    cand &= bad_tri[f1] & bad_tri[f2] & (region[f1] == region[f2])
    sub = np.flatnonzero(bad_tri)
    newlab = queue_grow(X, F, N, area2, sub, f1[cand], f2[cand], angle_tol, dist_tol)
    # keep regrown pieces inside their old region (label pairs), so two old regions never merge
    out = region.copy()
    out[sub] = region.max() + 1 + newlab * (region.max() + 1) + region[sub]
    return renumber(out)


def nonplanar_regions(X, faces, holes, face_region, dist_tol: float, diag: float) -> np.ndarray:
    """Regions having an output polygon whose vertices (outer loop and holes) are farther than
    ``dist_tol`` from the polygon's own least-squares plane (through their centroid, normal = the
    smallest principal axis). This is the plane a user of the written model fits, so it is the one
    the ``dist_tol_m`` promise is checked against. Vectorised over polygons."""
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
