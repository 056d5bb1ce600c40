"""Polygon geometry of :class:`~mst.meshtools.model.PolygonModel` faces: holes bridged into one
weakly-simple loop and back (:func:`bridge_holes`, :func:`unbridge_faces`), loops started at a
strictly convex corner (:func:`start_loops_at_convex_corners`), plane bases, and earcut
triangulation (:func:`triangulate_model`).

Imports numpy, mapbox_earcut (lazily) and the standard library only.
"""

from __future__ import annotations

import math

import numpy as np

from mst.meshtools.model import PolygonModel


def output_loops(model: PolygonModel) -> list[np.ndarray]:
    """One index loop per face: holes bridged, loop started at a strictly convex corner."""
    normals = model.face_normals()
    loops = [bridge_holes(model.vertices, f, hs, n) if hs else np.asarray(f, np.int64)
             for f, hs, n in zip(model.faces, model.holes, normals)]
    return start_loops_at_convex_corners(model.vertices, loops, normals)


def start_loops_at_convex_corners(V: np.ndarray, loops: list[np.ndarray], normals: np.ndarray) -> list[np.ndarray]:
    """Rotate each loop so that its vertex 1 is a strictly convex corner: points 0, 1, 2 then give
    the face's outward normal (ViSP computes face visibility from them). Vectorised over all loops.

    Among the corners whose turn about the face normal is clearly positive (sine > 1e-9), the one
    spanning the largest triangle with its two neighbours (``(b - a) x (c - b) . n``) is chosen, ties
    by the smallest (vertex index, next vertex index): the plane of points 0, 1, 2 is then as well
    conditioned as the loop allows (a short or nearly straight corner would tilt ViSP's normal; on the
    real Rotterdam set the first-corner choice put vertices 71 mm off that plane at ``--dist-tol
    0.01``). The choice does not depend on where the loop starts, so writing a model read back from
    our own file gives the same bytes. Loops without such a corner (degenerate) are left as they are.
    """
    if not loops:
        return []
    lens = np.array([len(lp) for lp in loops], np.int64)
    idx = np.concatenate([np.asarray(lp, np.int64) for lp in loops])
    L = len(loops)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    lid = np.repeat(np.arange(L), lens)
    ls = starts[lid]
    ll = np.maximum(lens[lid], 1)
    loc = np.arange(len(idx)) - ls
    prv = idx[ls + (loc - 1) % ll]
    nxt = idx[ls + (loc + 1) % ll]
    a = V[idx] - V[prv]
    b = V[nxt] - V[idx]
    turn = np.einsum("ij,ij->i", np.cross(a, b), np.asarray(normals, float)[lid])
    scale = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    convex = (turn > 1e-9 * scale) & (scale > 0) & (lens[lid] >= 3)
    big = np.iinfo(np.int64).max
    # near-ties (within 1e-6 of the loop's best turn: rounding depends on where the loop starts)
    # are broken by vertex index, so the choice is the same for every rotation of the loop
    best = np.full(L, -np.inf)
    np.maximum.at(best, lid, np.where(convex, turn, -np.inf))
    good = convex & (turn >= best[lid] * (1 - 1e-6))
    k1 = np.where(good, idx, big)
    k2 = np.where(good, nxt, big)
    order = np.lexsort((k2, k1, lid))
    first = order[np.concatenate([[0], np.flatnonzero(np.diff(lid[order])) + 1])]
    shift = np.where(good[first], (loc[first] - 1) % np.maximum(lens, 1), 0)
    rotated = idx[ls + (loc + shift[lid]) % ll]
    return np.split(rotated, starts[1:])


def start_at_convex_corner(V: np.ndarray, loop: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Single-loop form of :func:`start_loops_at_convex_corners`."""
    return start_loops_at_convex_corners(V, [np.asarray(loop, np.int64)], np.asarray(n, float)[None])[0]


def plane_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal in-plane axes (u, v) with u x v = n (so CCW about n stays CCW in 2D)."""
    nx, ny, nz = (float(x) for x in n)
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn == 0:
        return np.eye(3)[:, :2]
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    k = min(range(3), key=lambda i: abs((nx, ny, nz)[i]))
    ax, ay, az = (1.0 if k == 0 else 0.0), (1.0 if k == 1 else 0.0), (1.0 if k == 2 else 0.0)
    ux, uy, uz = ay * nz - az * ny, az * nx - ax * nz, ax * ny - ay * nx  # a x n
    un = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / un, uy / un, uz / un
    vx, vy, vz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux  # n x u
    return np.array([[ux, vx], [uy, vy], [uz, vz]])


def unbridge_faces(model: PolygonModel) -> PolygonModel:
    """Turn weakly-simple faces written by :func:`bridge_holes` back into outer loop + holes.

    For a face loop that visits a vertex twice: edges used in both directions by the loop (bridges)
    are removed, the remaining edges are chained in loop order and split at repeated vertices. The
    result is accepted only if it is one loop turning like the face (positive signed area about the
    face normal) plus loops turning the other way (holes) with the same total vector area;
    otherwise the face is kept as read. Faces without repeated vertices are untouched.
    """
    if not model.faces:
        return model
    lens = np.array([len(f) for f in model.faces], np.int64)
    fid = np.repeat(np.arange(len(lens)), lens)
    key = np.sort(fid * (len(model.vertices) + 1) + np.concatenate(model.faces))
    dup_faces = np.unique(key[1:][key[1:] == key[:-1]] // (len(model.vertices) + 1))
    cand = [int(i) for i in dup_faces if not model.holes[i]]
    if not cand:
        return model
    faces = list(model.faces)
    holes = [list(h) for h in model.holes]
    normals = model.face_normals()
    areas = model.face_areas()
    V = model.vertices
    for i in cand:
        seq = faces[i].tolist()
        k = len(seq)
        edges = [(seq[j], seq[(j + 1) % k]) for j in range(k)]
        count: dict[tuple[int, int], int] = {}
        for e in edges:
            count[e] = count.get(e, 0) + 1
        keep = [True] * k
        used_rev: dict[tuple[int, int], int] = {}
        for j, (a, b) in enumerate(edges):
            if a == b:
                keep[j] = False
                continue
            r = (b, a)
            avail = min(count.get((a, b), 0), count.get(r, 0))
            if avail and used_rev.get((a, b), 0) < avail:
                used_rev[(a, b)] = used_rev.get((a, b), 0) + 1
                keep[j] = False
        if all(keep):
            loops = split_simple(seq)
        else:
            rem = [edges[j] for j in range(k) if keep[j]]
            loops = _chain_in_order(rem)
            if loops is None:
                continue
            loops = [sub for lp in loops for sub in split_simple(lp)]
        if len(loops) < 2:
            continue
        n = normals[i]
        sa = []
        for lp in loops:
            P = V[lp] - V[lp[0]]
            sa.append(0.5 * float(np.cross(P, np.roll(P, -1, axis=0)).sum(0) @ n))
        pos = [j for j, a in enumerate(sa) if a > 0]
        if len(pos) != 1 or any(a >= 0 for j, a in enumerate(sa) if j != pos[0]):
            continue
        if abs(sum(sa) - areas[i]) > 1e-9 * max(abs(areas[i]), 1e-300) + 1e-12:
            continue
        faces[i] = np.asarray(loops[pos[0]], np.int64)
        holes[i] = [np.asarray(lp, np.int64) for j, lp in enumerate(loops) if j != pos[0]]
    return PolygonModel(model.vertices, faces, holes=holes, names=list(model.names), lines=model.lines,
                        cylinders=model.cylinders, circles=model.circles)


def split_simple(seq: list[int]) -> list[list[int]]:
    """Split a closed vertex sequence at repeated vertices into simple closed loops (>= 3 vertices)."""
    out: list[list[int]] = []
    path: list[int] = []
    pos: dict[int, int] = {}
    for x in seq:
        if x in pos:
            p = pos[x]
            out.append(path[p:])
            for y in path[p + 1:]:
                del pos[y]
            path = path[: p + 1]
        else:
            pos[x] = len(path)
            path.append(x)
    out.append(path)
    return [lp for lp in out if len(lp) >= 3]


def _chain_in_order(edges: list[tuple[int, int]]) -> list[list[int]] | None:
    """Chain directed edges into closed vertex loops, taking at each vertex the first unused edge
    that follows in the given (cyclic) order. None if they do not close."""
    m = len(edges)
    out_at: dict[int, list[int]] = {}
    for j, (a, _) in enumerate(edges):
        out_at.setdefault(a, []).append(j)
    used = [False] * m
    loops = []
    for s in range(m):
        if used[s]:
            continue
        start = edges[s][0]
        lp: list[int] = []
        j = s
        while True:
            used[j] = True
            a, b = edges[j]
            lp.append(a)
            if b == start:
                break
            cands = [c for c in out_at.get(b, []) if not used[c]]
            if not cands:
                return None
            after = [c for c in cands if c > j]
            j = after[0] if after else cands[0]
        loops.append(lp)
    return loops


def bridge_holes(V: np.ndarray, outer: np.ndarray, holes: list[np.ndarray], n: np.ndarray) -> np.ndarray:
    """Cut every hole open into the outer loop with a bridge edge: one weakly-simple loop.

    Holes are processed by decreasing maximum u coordinate (plane basis from ``n``); each hole is
    joined from its rightmost vertex H to the closest vertex P of the current loop such that the
    segment H-P crosses no edge of the outer loop or of any hole (standard hole elimination, as in
    earcut). The result visits ``P ... H (hole loop) H P ...``: P and H appear twice. A hole that
    shares a vertex with the loop (touching holes) is spliced in at that vertex without a bridge.
    Outer loop CCW about ``n``, holes CW (as stored in :class:`PolygonModel`).
    """
    B = plane_basis(n)
    outer = np.asarray(outer, np.int64)
    P2 = lambda idx: (V[idx] - V[outer[0]]) @ B  # noqa: E731
    holes = [np.asarray(h, np.int64) for h in holes if len(h) >= 3]
    loop = list(outer.tolist())
    # all segments of outer + holes, for visibility tests
    segs_idx = [np.stack([lp, np.roll(lp, -1)], 1) for lp in [outer, *holes]]
    S = np.concatenate(segs_idx)
    SA, SB = P2(S[:, 0]), P2(S[:, 1])
    hole_pts = [P2(h) for h in holes]
    order = np.argsort([-hp[:, 0].max() for hp in hole_pts], kind="stable")
    for hi in order:
        h = holes[hi]
        hp = hole_pts[hi]
        shared = np.intersect1d(h, np.asarray(loop, np.int64))
        if len(shared):  # the hole touches the loop at a vertex: splice it in there, no bridge
            v = int(shared[0])
            c = loop.index(v)
            j = int(np.flatnonzero(h == v)[0])
            hrot = np.roll(h, -j).tolist()
            loop = loop[:c] + hrot + loop[c:]
            continue
        j = int(np.argmax(hp[:, 0]))
        H = hp[j]
        L = np.array(loop, np.int64)
        LP = P2(L)
        d2 = ((LP - H) ** 2).sum(1)
        cand = np.argsort(d2, kind="stable")
        chosen = None
        for c in cand:
            if _segment_clear(H, LP[c], SA, SB, S, int(h[j]), int(L[c])):
                chosen = int(c)
                break
        if chosen is None:
            chosen = int(cand[0])
        hrot = np.roll(h, -j).tolist()
        loop = loop[: chosen + 1] + hrot + [hrot[0]] + loop[chosen:]
        # the bridge itself becomes an obstacle for the next holes
        S = np.vstack([S, [[int(L[chosen]), int(h[j])]]])
        SA = np.vstack([SA, LP[chosen][None]])
        SB = np.vstack([SB, H[None]])
    return np.array(loop, np.int64)


def _segment_clear(a, b, SA, SB, S, ia, ib) -> bool:
    """True if segment a-b properly crosses none of the segments SA-SB (those sharing an endpoint
    index with a-b are ignored)."""
    share = (S[:, 0] == ia) | (S[:, 1] == ia) | (S[:, 0] == ib) | (S[:, 1] == ib)

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    d1 = orient(a, b, SA)
    d2 = orient(a, b, SB)
    d3 = orient(SA, SB, a)
    d4 = orient(SA, SB, b)
    cross = (d1 * d2 < 0) & (d3 * d4 < 0)
    return not np.any(cross & ~share)


def triangulate_model(model: PolygonModel, return_index: bool = False):
    """Triangulate every face (holes included) with earcut in the face's plane.

    Returns ``V`` (N, 3) float64 (= ``model.vertices``, unchanged) and ``F`` (M, 3) int64, each
    triangle wound like its polygon (right-hand normal = the polygon's Newell normal). With
    ``return_index`` also ``face_index`` (M,) int64: the source face of each triangle.
    Degenerate faces (zero area) give no triangles.
    """
    import mapbox_earcut

    V = model.vertices
    tris: list[np.ndarray] = []
    src: list[np.ndarray] = []
    # fast path: plain triangles
    simple_tri = [i for i, (f, hs) in enumerate(zip(model.faces, model.holes)) if len(f) == 3 and not hs]
    if simple_tri:
        tris.append(np.stack([model.faces[i] for i in simple_tri]))
        src.append(np.array(simple_tri, np.int64))
    simple = set(simple_tri)
    normals = None
    for i, (f, hs) in enumerate(zip(model.faces, model.holes)):
        if i in simple:
            continue
        if normals is None:
            normals = model.face_normals()
        n = normals[i]
        if not np.any(n):
            continue
        rings = [f, *[h for h in hs if len(h) >= 3]]
        idx = np.concatenate(rings)
        P = (V[idx] - V[f[0]]) @ plane_basis(n)
        ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
        t = np.asarray(mapbox_earcut.triangulate_float64(P, ends), np.int64).reshape(-1, 3)
        if len(t) == 0:
            continue
        a, b, c = P[t[:, 0]], P[t[:, 1]], P[t[:, 2]]
        s = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        t = np.where((s < 0)[:, None], t[:, [0, 2, 1]], t)
        tris.append(idx[t])
        src.append(np.full(len(t), i, np.int64))
    F = np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)
    fi = np.concatenate(src) if src else np.zeros(0, np.int64)
    if len(simple_tri) and len(tris) > 1:
        order = np.argsort(fi, kind="stable")
        F, fi = F[order], fi[order]
    if return_index:
        return V, F, fi
    return V, F
