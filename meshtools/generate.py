"""Procedural polygon models and TINs for tests, demos and benchmarks.

Two layers:

* ``*_model(...)`` functions build the *ground-truth* :class:`PolygonModel` of a shape (planar
  polygons, holes where the shape has them, outward normals: outer loops counter-clockwise seen
  from outside).
  ``city_block_model(...)`` is a procedural LoD2-like city (flat and gabled roofs) up to 50k+ polygons.
* ``box(...)``, ``l_shape(...)``, ``courtyard(...)``, ``gabled_house(...)``, ``cylinder(...)``,
  ``city_block(...)`` return the shape as a TIN ``(V, F)``: V (N, 3) float64 metres (model frame,
  z up), F (M, 3) int64 triangles wound outward (right-hand normal points out of the solid; up for
  the terrain). ``split=n`` cuts every triangle of the polygons' triangulation into n*n triangles
  (an n-step lattice, conforming across shared edges, vertices welded exactly), so that every
  planar face becomes many triangles like a real TIN.

Everything is deterministic (``seed`` where randomness is used).
"""

from __future__ import annotations

import numpy as np

from mst.meshtools.model import PolygonModel


# ====================================================================== ground-truth polygon models
def extrude_model(rings: list[np.ndarray], z0: float, z1: float, name: str | None = None) -> PolygonModel:
    """Prism over a footprint: ``rings[0]`` the outer (K, 2) ring counter-clockwise seen from +z,
    ``rings[1:]`` holes clockwise; from height ``z0`` to ``z1`` (metres). Faces: floor, roof (with
    the holes), one wall quad per ring edge; all outward."""
    rings = [np.asarray(r, np.float64).reshape(-1, 2) for r in rings]
    V, offs = [], []
    off = 0
    for r in rings:
        k = len(r)
        V.append(np.column_stack([r, np.full(k, z0)]))
        V.append(np.column_stack([r, np.full(k, z1)]))
        offs.append(off)
        off += 2 * k
    faces, holes = [], []
    bot = [np.arange(o, o + len(r)) for o, r in zip(offs, rings)]
    top = [np.arange(o + len(r), o + 2 * len(r)) for o, r in zip(offs, rings)]
    # floor: seen from below -> reverse every ring
    faces.append(bot[0][::-1].copy())
    holes.append([b[::-1].copy() for b in bot[1:]])
    faces.append(top[0])
    holes.append(list(top[1:]))
    for b, t in zip(bot, top):
        k = len(b)
        for i in range(k):
            j = (i + 1) % k
            faces.append(np.array([b[i], b[j], t[j], t[i]]))
            holes.append([])
    return PolygonModel(np.concatenate(V), faces, holes=holes, names=[name] * len(faces))


def box_model(size=(10.0, 6.0, 4.0), origin=(0.0, 0.0, 0.0)) -> PolygonModel:
    """Axis-aligned box ``size`` (metres) with its min corner at ``origin``: 6 quads."""
    sx, sy, sz = size
    ox, oy, oz = origin
    ring = np.array([[0, 0], [sx, 0], [sx, sy], [0, sy]], float) + [ox, oy]
    return extrude_model([ring], oz, oz + sz, "box")


def l_shape_model(a: float = 12.0, b: float = 8.0, w: float = 4.0, h: float = 6.0, origin=(0.0, 0.0, 0.0)) -> PolygonModel:
    """L-shaped building: legs ``a`` (along x) and ``b`` (along y), leg width ``w``, height ``h``.
    8 walls, a non-convex roof and floor (hexagons)."""
    ox, oy, oz = origin
    ring = np.array([[0, 0], [a, 0], [a, w], [w, w], [w, b], [0, b]], float) + [ox, oy]
    return extrude_model([ring], oz, oz + h, "l_shape")


def courtyard_model(outer=(20.0, 16.0), inner=(8.0, 6.0), h: float = 7.0, origin=(0.0, 0.0, 0.0)) -> PolygonModel:
    """Courtyard building: an ``outer`` rectangle with a centred ``inner`` courtyard (a hole through
    the roof and the floor), height ``h``. Roof and floor are faces with one hole each; the 4
    courtyard walls face into the courtyard (out of the solid). Genus-1 closed solid."""
    ox, oy, oz = origin
    X, Y = outer
    x, y = inner
    ring = np.array([[0, 0], [X, 0], [X, Y], [0, Y]], float)
    x0, y0 = (X - x) / 2, (Y - y) / 2
    hole = np.array([[x0, y0], [x0, y0 + y], [x0 + x, y0 + y], [x0 + x, y0]], float)  # clockwise
    return extrude_model([ring + [ox, oy], hole + [ox, oy]], oz, oz + h, "courtyard")


def gabled_house_model(length: float = 12.0, width: float = 8.0, eaves: float = 5.0, ridge: float = 3.0,
                       origin=(0.0, 0.0, 0.0)) -> PolygonModel:
    """House with a gabled roof: ridge along x at ``y = width/2``, ``ridge`` metres above the eaves.
    Faces: floor, 2 long walls (quads), 2 gable walls (pentagons), 2 roof slopes."""
    L, W, H, R = length, width, eaves, ridge
    V = np.array([[0, 0, 0], [L, 0, 0], [L, W, 0], [0, W, 0],
                  [0, 0, H], [L, 0, H], [L, W, H], [0, W, H],
                  [0, W / 2, H + R], [L, W / 2, H + R]], float) + np.asarray(origin, float)
    faces = [
        [0, 3, 2, 1],  # floor (normal -z)
        [0, 1, 5, 4],  # wall y=0 (normal -y)
        [2, 3, 7, 6],  # wall y=W (normal +y)
        [1, 2, 6, 9, 5],  # gable x=L (normal +x)
        [3, 0, 4, 8, 7],  # gable x=0 (normal -x)
        [4, 5, 9, 8],  # roof slope facing -y
        [6, 7, 8, 9],  # roof slope facing +y
    ]
    return PolygonModel(V, faces, names=["gabled_house"] * len(faces))


def cylinder_model(radius: float = 3.0, height: float = 8.0, sections: int = 64, origin=(0.0, 0.0, 0.0)) -> PolygonModel:
    """Upright prism approximating a cylinder: ``sections`` wall quads (adjacent walls differ by
    360/sections degrees) and two ``sections``-gon caps."""
    t = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    ring = np.column_stack([radius * np.cos(t), radius * np.sin(t)]) + np.asarray(origin[:2], float)
    return extrude_model([ring], origin[2], origin[2] + height, "cylinder")


# ====================================================================== TIN from polygons
def lattice_split(V: np.ndarray, F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Cut each triangle into ``n*n`` triangles on a barycentric lattice (conforming, welded).

    New points on an edge are keyed by (lower vertex, upper vertex, step) and computed with the
    vertices in index order, so neighbouring triangles share them exactly. Orientation is kept.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if n <= 1:
        return V.copy(), F.copy()
    T = len(F)
    # lattice points (i, j, k), i + j + k = n, weights of the sorted vertices (s0 < s1 < s2)
    ij = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)], np.int64)
    lid = {tuple(p): q for q, p in enumerate(ij.tolist())}
    W = np.column_stack([ij, n - ij.sum(1)])  # (P, 3)
    # small triangles in lattice ids, oriented like (e0, e1, e2) = weights on (corner0, corner1, corner2)
    small = []
    for i in range(n):
        for j in range(n - i):
            small.append((lid[(i, j)], lid[(i + 1, j)], lid[(i, j + 1)]))
            if i + j < n - 1:
                small.append((lid[(i + 1, j)], lid[(i + 1, j + 1)], lid[(i, j + 1)]))
    small = np.array(small, np.int64)
    # orientation of the lattice template relative to (c0, c1, c2): weight i on c0 ... check sign
    Wt = W.astype(float)
    a, b, c = Wt[small[0, 0]], Wt[small[0, 1]], Wt[small[0, 2]]
    # corners c0=(1,0,0), c1=(0,1,0), c2=(0,0,1) -> 2D coords (w1, w2) keep orientation of (c0, c1, c2)
    s_tpl = (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1])
    if s_tpl < 0:  # the reference corners (w1, w2) = (0,0), (1,0), (0,1) turn counter-clockwise
        small = small[:, [0, 2, 1]]
    # sort vertices of each triangle, remember the parity
    order = np.argsort(F, axis=1, kind="stable")
    S = np.take_along_axis(F, order, 1)
    parity = (order[:, 0] > order[:, 1]).astype(int) + (order[:, 0] > order[:, 2]) + (order[:, 1] > order[:, 2])
    flip = parity % 2 == 1
    P = len(W)
    # keys per lattice point: (kind, a, b, c)
    nz = W > 0
    cnt = nz.sum(1)
    keys = np.zeros((T, P, 4), np.int64)
    tri_ids = np.arange(T)[:, None]
    for q in range(P):
        w = W[q]
        if cnt[q] == 1:
            keys[:, q, 0] = 0
            keys[:, q, 1] = S[:, int(np.argmax(w))]
        elif cnt[q] == 2:
            lo, hi = np.flatnonzero(w)
            keys[:, q, 0] = 1
            keys[:, q, 1] = S[:, lo]
            keys[:, q, 2] = S[:, hi]
            keys[:, q, 3] = w[hi]
        else:
            keys[:, q, 0] = 2
            keys[:, q, 1] = tri_ids[:, 0]
            keys[:, q, 2] = w[0]
            keys[:, q, 3] = w[1]
    # coordinates: canonical sum in sorted-vertex order
    X = (W[None, :, 0:1] * V[S[:, 0]][:, None, :] + W[None, :, 1:2] * V[S[:, 1]][:, None, :]
         + W[None, :, 2:3] * V[S[:, 2]][:, None, :]) / n + 0.0
    kflat = keys.reshape(-1, 4)
    # original vertices keep their index; new points appended
    is_orig = kflat[:, 0] == 0
    _, first, inv = np.unique(kflat, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    uk = kflat[first]
    new_mask = uk[:, 0] != 0
    idx_map = np.empty(len(uk), np.int64)
    idx_map[~new_mask] = uk[~new_mask, 1]
    idx_map[new_mask] = len(V) + np.arange(new_mask.sum())
    Vout = np.concatenate([V, X.reshape(-1, 3)[first[new_mask]]])
    gid = idx_map[inv].reshape(T, P)
    del is_orig
    Fs = gid[:, small]  # (T, s, 3)
    Fs[flip] = Fs[flip][:, :, [0, 2, 1]]
    Fout = Fs.reshape(-1, 3)
    used = np.zeros(len(Vout), bool)
    used[Fout] = True
    if not used.all():
        remap = np.cumsum(used) - 1
        Vout = Vout[used]
        Fout = remap[Fout]
    return Vout, Fout


def model_to_tin(model: PolygonModel, split: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate ``model`` (earcut, holes kept) and cut each triangle ``split*split`` times."""
    V, F = model.triangulate()
    used = np.zeros(len(V), bool)
    used[F] = True
    remap = np.cumsum(used) - 1
    V, F = V[used], remap[F]
    return lattice_split(V, F, split)


def box(size=(10.0, 6.0, 4.0), split: int = 1, origin=(0.0, 0.0, 0.0)):
    """Box TIN (see :func:`box_model`), ``(V, F)``."""
    return model_to_tin(box_model(size, origin), split)


def l_shape(split: int = 1, **kw):
    """L-shaped building TIN (see :func:`l_shape_model`), ``(V, F)``."""
    return model_to_tin(l_shape_model(**kw), split)


def courtyard(split: int = 1, **kw):
    """Courtyard building TIN: roof and floor with a hole (see :func:`courtyard_model`), ``(V, F)``."""
    return model_to_tin(courtyard_model(**kw), split)


def gabled_house(split: int = 1, **kw):
    """Gabled house TIN (see :func:`gabled_house_model`), ``(V, F)``."""
    return model_to_tin(gabled_house_model(**kw), split)


def cylinder(split: int = 1, **kw):
    """Cylinder-like prism TIN (see :func:`cylinder_model`), ``(V, F)``."""
    return model_to_tin(cylinder_model(**kw), split)


# ====================================================================== curved objects (render-based tracking)
def _grid_faces(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Triangles (two per cell) of an ``nu x nv`` vertex grid (row-major, index ``i * nv + j``)."""
    iu = np.arange(nu if wrap_u else nu - 1)
    jv = np.arange(nv if wrap_v else nv - 1)
    i, j = np.meshgrid(iu, jv, indexing="ij")
    i, j = i.ravel(), j.ravel()
    i1, j1 = (i + 1) % nu, (j + 1) % nv
    a, b, c, d = i * nv + j, i1 * nv + j, i1 * nv + j1, i * nv + j1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)


def _orient_outward(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Flip all triangles when the mesh's signed volume is negative (closed, consistently wound meshes)."""
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum()
    return F[:, ::-1].copy() if vol < 0 else F


def torus(R: float = 0.15, r: float = 0.05, n_major: int = 96, n_minor: int = 48, split: int = 1,
          aspect: float = 1.0, standing: bool = False):
    """Torus TIN: major radius ``R``, tube radius ``r`` (metres), ``n_major x n_minor x split^2`` quads (2
    triangles each), wound outward, resting on z = 0. Lying (axis z) by default; ``standing``: axis y (a
    wheel). ``aspect`` < 1 squeezes the major circle into an ellipse (semi-axes R, aspect R): a true torus is
    symmetric about its axis, so a camera turning about that axis cannot be tracked from its contours
    (every view is the same image). Returns ``(V, F)``."""
    nu, nv = n_major * split, n_minor * split
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)[:, None]
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)[None, :]
    x = (R + r * np.cos(v)) * np.cos(u)
    y = (aspect * R + r * np.cos(v)) * np.sin(u)
    z = r * np.sin(v) + 0.0 * u
    V = np.stack([x, y, z], -1).reshape(-1, 3)
    if standing:
        V = V[:, [0, 2, 1]] * [1.0, -1.0, 1.0]  # axis z -> y (a rotation: keeps the winding)
    V[:, 2] -= V[:, 2].min()
    F = _grid_faces(nu, nv, True, True)
    return V, _orient_outward(V, F)


def blob(radius: float = 0.15, subdivisions: int = 5, bumps: int = 14, amplitude: float = 0.4, seed: int = 0,
         split: int = 1):
    """Smooth procedural "sculpture": an icosphere (``subdivisions`` = 5: 20,480 triangles) whose radius is
    modulated by ``bumps`` Gaussian bumps and dents (relative amplitude up to ``amplitude``; the dents
    make concavities and self-occluding contours), resting on z = 0. Deterministic (``seed``). ``(V, F)``."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions + max(split, 1) // 2, radius=1.0)
    D = np.asarray(m.vertices, np.float64)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    C = rng.normal(size=(bumps, 3))
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    amp = amplitude * rng.uniform(0.5, 1.0, bumps) * np.where(np.arange(bumps) % 2 == 0, 1.0, -1.0)
    width = rng.uniform(0.06, 0.2, bumps)  # 1 - cos(angle) scale of each bump
    rad = np.maximum(1.0 + (amp[None, :] * np.exp(-(1.0 - D @ C.T) / width[None, :])).sum(1), 0.3)  # star-shaped
    V = radius * D * rad[:, None]
    V[:, 2] -= V[:, 2].min()
    F = np.asarray(m.faces, np.int64)
    return V, _orient_outward(V, F)


def vase(height: float = 0.30, n_theta: int = 96, n_profile: int = 64, split: int = 1, aspect: float = 1.0):
    """Body of revolution (a vase / bottle, axis z, standing on z = 0): radius profile
    ``r(z) = 0.09 + 0.035 sin(1.5 pi z/h + 0.3) - 0.04 (z/h)^3`` scaled to ``height`` (metres), with flat
    bottom and top caps (creases at both rims); ``aspect`` < 1 makes the cross-sections ellipses (y
    semi-axis ``aspect r``: breaks the symmetry about the axis, see :func:`torus`). ``(V, F)`` wound outward."""
    nt, npf = n_theta * split, n_profile * split
    zz = np.linspace(0.0, 1.0, npf)
    rr = (0.09 + 0.035 * np.sin(1.5 * np.pi * zz + 0.3) - 0.04 * zz**3) * (height / 0.30)
    th = np.linspace(0, 2 * np.pi, nt, endpoint=False)
    # grid index i * npf + j: i around the axis, j along the profile
    x = rr[None, :] * np.cos(th)[:, None]
    y = aspect * rr[None, :] * np.sin(th)[:, None]
    z = np.broadcast_to(zz[None, :] * height, x.shape)
    V = np.stack([x, y, z], -1).reshape(-1, 3)
    F = _grid_faces(nt, npf, True, False)
    ib, it = len(V), len(V) + 1
    V = np.vstack([V, [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    i = np.arange(nt)
    i1 = (i + 1) % nt
    bot = np.stack([np.full(nt, ib), i1 * npf, i * npf], 1)
    top = np.stack([np.full(nt, it), i * npf + npf - 1, i1 * npf + npf - 1], 1)
    F = np.concatenate([F, bot, top]).astype(np.int64)
    return V, _orient_outward(V, F)


# ====================================================================== terrain + city block
def terrain(size: float = 400.0, cells: int = 100, n_creases: int = 6, slope: float = 0.08, seed: int = 0,
            origin=(0.0, 0.0)):
    """Open terrain TIN over ``[0, size]^2`` (metres): a ``cells x cells`` grid, 2 triangles per
    cell, normals up. Height ``z = f(x) + g(y)`` with ``f, g`` piecewise linear with ``n_creases``
    kinks on grid lines, so the terrain is made of planar patches (rectangles between creases)
    and every crease is a grid line. Returns ``(V, F, z_of(x, y))``: the last item evaluates the
    height (vectorised) for placing buildings."""
    rng = np.random.default_rng(seed)
    step = size / cells
    xs = np.arange(cells + 1) * step

    def pl(n):
        knots = np.sort(rng.choice(np.arange(1, cells), size=min(n, cells - 1), replace=False)) * step
        k = np.concatenate([[0.0], knots, [size]])
        vals = np.concatenate([[0.0], np.cumsum(rng.uniform(-slope, slope, len(k) - 1) * np.diff(k))])
        return k, vals

    kx, fx = pl(n_creases)
    ky, fy = pl(n_creases)
    ox, oy = origin

    def z_of(x, y):
        return np.interp(np.asarray(x) - ox, kx, fx) + np.interp(np.asarray(y) - oy, ky, fy)

    X, Y = np.meshgrid(xs, xs, indexing="ij")
    Z = np.interp(X, kx, fx) + np.interp(Y, ky, fy)
    V = np.column_stack([X.ravel() + ox, Y.ravel() + oy, Z.ravel()])
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    # alternate diagonals like a real TIN
    alt = ((np.arange(cells)[:, None] + np.arange(cells)[None, :]) % 2).ravel().astype(bool)
    t1 = np.where(alt[:, None], np.column_stack([a, b, c]), np.column_stack([a, b, d]))
    t2 = np.where(alt[:, None], np.column_stack([a, c, d]), np.column_stack([b, c, d]))
    F = np.concatenate([t1, t2]).astype(np.int64)
    return V, F, z_of


def uneven_arc(sagitta: float = 0.013, length: float = 2.0, width: float = 1.0, coarse: int = 2, dense: int = 40):
    """A gently curved sheet ``z = -sagitta * (2x/length)^2`` over ``x in [-length/2, length/2]``,
    ``y in [0, width]`` (metres), meshed unevenly: ``coarse`` steps on the left half, ``dense`` on
    the right. Its area-weighted plane and the least-squares plane of its boundary vertices differ
    (the dense half pulls the latter), the case where checking a region against one plane does not
    bound the distances to the output polygon's own plane. Returns ``(V, F)``, normals up."""
    h = length / 2
    xs = np.concatenate([np.linspace(-h, 0, coarse + 1)[:-1], np.linspace(0, h, dense + 1)])
    ys = np.array([0.0, width])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), (-sagitta * (X / h) ** 2).ravel()])
    idx = np.arange(len(V)).reshape(len(xs), 2)
    a, b, c, d = idx[:-1, 0], idx[1:, 0], idx[1:, 1], idx[:-1, 1]
    F = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])]).astype(np.int64)
    return V, F


def city_block(n_triangles: int = 1_000_000, buildings: int = 64, seed: int = 0, size: float = 400.0):
    """A city block TIN: a piecewise-planar terrain plus ``buildings`` closed buildings (boxes,
    L-shapes, courtyards with a hole, gabled houses) standing on lots of a regular grid, their
    floors 0.5 m below the lowest terrain point under them (walls pass through the terrain,
    no shared vertices). About half of ``n_triangles`` is terrain, half buildings (lattice split
    chosen per building). Returns ``(V, F)``: V (N, 3) float64 metres, F (M, 3) int64, outward."""
    rng = np.random.default_rng(seed)
    cells = max(2, int(round(np.sqrt(n_triangles / 4))))
    Vt, Ft, z_of = terrain(size, cells, seed=seed)
    Vs, Fs = [Vt], [Ft]
    off = len(Vt)
    lots = int(np.ceil(np.sqrt(buildings)))
    lot = size / lots
    per_building = max(1, (n_triangles - len(Ft)) / max(buildings, 1))
    kinds = ["box", "l_shape", "courtyard", "gabled_house"]
    made = 0
    for gi in range(lots):
        for gj in range(lots):
            if made >= buildings:
                break
            kind = kinds[made % len(kinds)]
            x0, y0 = gi * lot + 0.15 * lot, gj * lot + 0.15 * lot
            span = 0.7 * lot * rng.uniform(0.7, 1.0)
            h = rng.uniform(6, 25)
            foot = np.array([[x0, y0], [x0 + span, y0], [x0 + span, y0 + span], [x0, y0 + span]])
            zb = float(np.min(z_of(foot[:, 0], foot[:, 1]))) - 0.5
            if kind == "box":
                m = box_model((span, span * 0.8, h), (x0, y0, zb))
            elif kind == "l_shape":
                m = l_shape_model(span, span, span * 0.4, h, (x0, y0, zb))
            elif kind == "courtyard":
                m = courtyard_model((span, span), (span * 0.4, span * 0.3), h, (x0, y0, zb))
            else:
                m = gabled_house_model(span, span * 0.6, h * 0.6, span * 0.2, (x0, y0, zb))
            Vb, Fb = model_to_tin(m, 1)
            split = max(1, int(round(np.sqrt(per_building / len(Fb)))))
            Vb, Fb = lattice_split(Vb, Fb, split)
            Vs.append(Vb)
            Fs.append(Fb + off)
            off += len(Vb)
            made += 1
    return np.concatenate(Vs), np.concatenate(Fs)


def city_block_model(buildings: int = 64, seed: int = 0, lot_m: float = 30.0, street_m: float = 12.0,
                     gabled: float = 0.5, height_m=(6.0, 30.0), max_yaw_deg: float = 15.0,
                     ground: bool = False) -> PolygonModel:
    """A procedural LoD2-like city block as a *polygon* model (the ground truth of a CityJSON-style
    city): ``buildings`` closed buildings on the ground plane z = 0, one per lot of a square grid of
    ``lot_m`` metre lots with ``street_m`` metre streets between blocks of 4 x 4 lots.

    Each building is a box footprint (35-80 % of its lot per side, turned by up to ``max_yaw_deg``
    about its centre) of eaves height uniform in ``height_m`` (metres), with a flat roof (6 faces:
    floor, 4 walls, roof) or, with probability ``gabled``, a gabled roof (7 faces: floor, 2 walls,
    2 gable pentagons, 2 roof slopes; ridge along the longer side, 25-50 % of the shorter side
    high). ``ground``: add one ground quad at z = 0 around the block (no hole: the buildings' floors
    lie on it). Polygon count: 6-7 per building (+1): ``buildings=7710`` gives about 50,000.
    Deterministic (``seed``). Model frame: x east, y north, z up, metres; outward normals.
    """
    rng = np.random.default_rng(seed)
    n = int(buildings)
    side = max(1, int(np.ceil(np.sqrt(n))))
    gi, gj = np.divmod(np.arange(n), side)
    cx = gi * lot_m + (gi // 4) * street_m + 0.5 * lot_m
    cy = gj * lot_m + (gj // 4) * street_m + 0.5 * lot_m
    a = lot_m * rng.uniform(0.35, 0.8, n)  # footprint along the local x
    b = lot_m * rng.uniform(0.35, 0.8, n)
    h = rng.uniform(height_m[0], height_m[1], n)
    yaw = np.radians(rng.uniform(-max_yaw_deg, max_yaw_deg, n))
    is_gabled = rng.random(n) < gabled
    ridge = rng.uniform(0.25, 0.5, n) * np.minimum(a, b)
    Vs, faces = [], []
    off = 0
    for k in range(n):
        L, W = (a[k], b[k]) if a[k] >= b[k] else (b[k], a[k])
        c, s = np.cos(yaw[k] + (0.0 if a[k] >= b[k] else np.pi / 2)), np.sin(yaw[k] + (0.0 if a[k] >= b[k] else np.pi / 2))
        if is_gabled[k]:
            m = gabled_house_model(L, W, h[k], ridge[k], (-L / 2, -W / 2, 0.0))
        else:
            m = box_model((L, W, h[k]), (-L / 2, -W / 2, 0.0))
        V = m.vertices
        V = np.column_stack([c * V[:, 0] - s * V[:, 1] + cx[k], s * V[:, 0] + c * V[:, 1] + cy[k], V[:, 2]])
        Vs.append(V)
        faces += [f + off for f in m.faces]
        off += len(V)
    if ground:
        x1 = float(cx.max() + lot_m)
        y1 = float(cy.max() + lot_m)
        Vs.append(np.array([[-lot_m, -lot_m, 0.0], [x1, -lot_m, 0.0], [x1, y1, 0.0], [-lot_m, y1, 0.0]]))
        faces.append(np.arange(off, off + 4))
    return PolygonModel(np.concatenate(Vs), faces, names=["city_block"] * len(faces))


# ====================================================================== command line
SHAPES = ("box", "l_shape", "courtyard", "gabled_house", "cylinder", "terrain", "city_block", "torus", "blob", "vase")


def main(argv: list[str] | None = None) -> int:
    """``python -m mst.meshtools.generate SHAPE -o tin.ply [--split N] [--triangles N]``: write a
    procedural TIN (.obj/.ply/.stl/.off) or its ground-truth polygon model (.wrl/.cao with --polygons)."""
    import argparse

    from mst.meshtools.formats import save_model, save_triangles

    ap = argparse.ArgumentParser(prog="python -m mst.meshtools.generate", description=main.__doc__)
    ap.add_argument("shape", choices=SHAPES)
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--split", type=int, default=4, help="cut each triangle into split^2 (default 4)")
    ap.add_argument("--triangles", type=int, default=1_000_000, help="city_block size (default 1e6)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--polygons", action="store_true", help="write the ground-truth polygon model instead")
    ap.add_argument("--buildings", type=int, default=None,
                    help="city_block --polygons: buildings (6-7 polygons each; 7710 ~ 50k polygons) [64]")
    a = ap.parse_args(argv)
    if a.polygons and a.shape == "city_block":
        m = city_block_model(a.buildings or 64, seed=a.seed)
        save_model(a.output, m)
        print(f"{a.output}: {len(m.vertices)} vertices, {m.n_faces} polygons")
        return 0
    if a.polygons:
        if a.shape in ("terrain", "city_block", "torus", "blob", "vase"):
            ap.error("--polygons exists for the single buildings only")
        save_model(a.output, globals()[f"{a.shape}_model"]())
        return 0
    if a.shape == "city_block":
        V, F = city_block(a.triangles, seed=a.seed)
    elif a.shape == "terrain":
        V, F, _ = terrain(cells=max(2, a.split * 25), seed=a.seed)
    else:
        V, F = globals()[a.shape](split=a.split)
    save_triangles(a.output, V, F)
    print(f"{a.output}: {len(V)} vertices, {len(F)} triangles")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
