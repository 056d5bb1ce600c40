"""Steps 5-6 of TIN -> polygons (:mod:`mst.meshtools.convert`): boundary loops of each planar region
(outer loop + holes, chained by list ranking, pinch vertices resolved) simplified without cracks.

Imports numpy, the kernels of :mod:`mst.meshtools.kernels` (through :mod:`mst.meshtools.compiled`) and
:mod:`mst.meshtools.polygons` only.
"""

from __future__ import annotations

import numpy as np

from mst.meshtools.compiled import components
from mst.meshtools.regions import Edges


def outlines(X, F, region, n_regions, cr, E: Edges, col_tol: float, diag: float):
    """Boundary loops per region: outer loop + holes, simplified without cracks (:mod:`mst.meshtools.convert` doc, steps 5-6).

    Returns ``(faces, holes, stats, face_region)`` with vertex indices into ``X``.
    """
    R = n_regions
    # region normals (area-weighted) for planar coordinates
    nsum = np.stack([np.bincount(region, weights=cr[:, k], minlength=R) for k in range(3)], 1)
    nR = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-300)
    bu, bv, br, n_open = _boundary_half_edges(X, F, region, E)
    B = len(bu)
    if B == 0:
        return [], [], {"loops": 0, "slit_loops_dropped": 0, "pinch_vertices": 0, "vertices_removed": 0,
                        "regions_without_outer_loop": int(R), "open_boundary_edges_dropped": n_open}, np.zeros(0, np.int64)
    order, lab_o, n_loops, n_pinch = _chain_loops(X, bu, bv, br, nR)
    u_o = bu[order]
    loop_start = np.concatenate([[0], np.flatnonzero(np.diff(lab_o)) + 1])
    loop_len = np.diff(np.concatenate([loop_start, [B]]))
    loop_reg = br[order][loop_start]
    # signed area of each loop in its region plane
    pu, pv = X[bu[order]], X[bv[order]]
    cx = np.cross(pu, pv)
    av = np.stack([np.bincount(lab_o, weights=cx[:, k], minlength=n_loops) for k in range(3)], 1)
    loop_area = 0.5 * np.einsum("ij,ij->i", av[lab_o[loop_start]], nR[loop_reg])
    removable = _removable_vertices(X, u_o, lab_o, loop_start, loop_len, n_loops, col_tol)
    loops, n_split = _simple_loops(X, nR, u_o[~removable], lab_o[~removable], lab_o[loop_start], loop_area,
                                   loop_reg, n_loops)
    faces, holes, face_region, n_dropped, regions_without_outer = _faces_of_loops(loops, R, 1e-12 * diag**2)
    stats = {"loops": len(loops), "slit_loops_dropped": int(n_dropped), "pinch_vertices": int(n_pinch),
             "loops_split_at_pinches": n_split, "vertices_removed": int(len(np.unique(u_o[removable]))),
             "regions_without_outer_loop": int(regions_without_outer), "open_boundary_edges_dropped": n_open}
    return faces, holes, stats, np.array(face_region, np.int64)


def _boundary_half_edges(X, F, region, E: Edges):
    """Boundary half-edges ``(u, v, region)``: opposite triangle missing, non-manifold, or in another
    region; with the number dropped to balance tangles."""
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
    return bu, bv, br, n_open


def _chain_loops(X, bu, bv, br, nR):
    """Chain the boundary half-edges into loops: ``(order, loop label in that order, n_loops,
    n_pinch)``, ``order`` listing each loop's half-edges in turn (list ranking)."""
    B = len(bu)
    nv = len(X)
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
        succ, n_pinch = resolve_pinches(X, bu, bv, br, nR, o, lo, hi, multi, succ)
    # cycles = loops
    n_loops, lab = components(B, np.arange(B), succ)
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
    return order, lab[order], n_loops, n_pinch


def _removable_vertices(X, u_o, lab_o, loop_start, loop_len, n_loops, col_tol: float) -> np.ndarray:
    """Simplification: vertices that are straight pass-throughs in every loop using them (never
    reducing a loop below 3 vertices); a mask over the chained half-edges."""
    B = len(u_o)
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
    return removable


def _simple_loops(X, nR, kept_u, kept_lab, lab_at_start, loop_area, loop_reg, n_loops):
    """``[(region, signed area, vertex loop)]`` of the simplified loops; loops that pass a vertex
    twice (pinches) are split there into simple loops (counted)."""
    from mst.meshtools.polygons import split_simple

    nv = len(X)
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(kept_lab)) + 1, [len(kept_lab)]])
    loop_of_seg = kept_lab[bounds[:-1]]
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
    return loops, int(repeated.sum())


def _faces_of_loops(loops, R: int, tiny: float):
    """Faces (the largest outer loop of a region, with the region's holes; further outer loops as
    faces of their own), dropping zero-area slits: ``(faces, holes, face_region, n_dropped,
    regions_without_outer)``."""
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
    return faces, holes, face_region, n_dropped, regions_without_outer


def resolve_pinches(X, bu, bv, br, nR, o, lo, hi, multi, succ):
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
