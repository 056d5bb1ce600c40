"""Edgelets: oriented 3D contour points of a triangle mesh, extracted from a CPU ray-cast render.

For one camera pose ``T_cam_model`` (model -> camera) the mesh is ray cast (Open3D Embree through
:class:`mst.pipeline.render.Renderer`) at a reduced resolution (``scale`` = 1/2 or 1/4 of the image):
a z-depth map (metres, ``inf`` = background) and a face-normal map (camera frame, turned toward the
camera). Neighbouring pixel pairs (horizontal and vertical) are contour candidates when

* **silhouette**: one pixel sees the mesh, the other the background;
* **self-occlusion**: both see the mesh, and each pixel's depth lies farther than ``depth_jump`` x
  depth from the other pixel's tangent plane (a slanted or curved continuous surface predicts its
  neighbour; an occlusion does not);
* **crease**: both see the same surface (no depth jump) and their normals differ by more than
  ``crease_deg`` (a box edge, the rim of a vase).

Each candidate gets a 2D edge normal (silhouettes and occlusions: the gradient of the smoothed
inverse-depth map; creases: the image of the 3D crease direction ``n_a x n_b``). Candidates are then
sampled evenly, **image buckets x 4 orientation sectors** (normal angle modulo 180 deg in 45-deg
sectors), one per cell: the candidate nearest the cell centre, so that the set changes little from one
render to the next. Only the kept few hundred are refined to sub-pixel precision: a 16-section search along
the pixel pair (``refine_rounds`` extra ray casts of 15 sub-samples per kept point: 2 rounds = 1/256
of a low-resolution pixel) on the candidate's own test (hit / miss, near / far depth, which normal);
the edgelet's 3D point is the surface hit on the near (or first) side of the bisected boundary, so its
projection lies on the mesh's exact contour at the render pose whatever ``scale``.

Per edgelet (model frame, metres): ``X_model`` the surface point, ``t_model`` a unit 3D tangent of the
contour (creases: the crease direction; occluding contours: the direction in the viewing plane of the
contour line, perpendicular to the view ray -- the true edge direction of a sharp silhouette, ``n_face x
m``, gave 10 % larger errors on the box TIN orbit), and at the render pose the full-resolution pixel
``uv_px`` and unit 2D edge normal ``normal_px`` (image x right, y down; for silhouettes and occlusions it
points away from the object / near surface, and ``t_model`` is signed so that every projection of the
local line keeps that orientation). The local line
``X +- h t`` projects onto the contour's tangent line: the tracker's point-to-line distance.

Cost: one ray per low-resolution pixel of the window holding the mesh's projected bounding box
(:func:`mesh_roi`) plus ``15 refine_rounds`` rays per kept edgelet; all steps are array operations (no
Python loop per pixel or per edgelet).

Length: :func:`extract_edgelets` is one numeric pass over all samples, longer than 80 lines by design: it was moved, not
rewritten, when the tracking package was formed (issue #10), so that the order of its floating-point
operations, and the outputs, stay bit-identical.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mst.pipeline.tracking.exact import rigid

SILHOUETTE, OCCLUSION, CREASE = 0, 1, 2


@dataclass
class Edgelets:
    """Contour points of one render (N edgelets).

    X_model (N,3) m, model frame; t_model (N,3) unit tangent, model frame; uv_px (N,2) full-resolution
    pixel at the render pose; normal_px (N,2) unit 2D edge normal at the render pose; depth_m (N,)
    camera z of ``X_model`` at the render pose; kind (N,) int8 (SILHOUETTE, OCCLUSION, CREASE);
    T_cam_model (4,4) the render pose; n_candidates: contour pixel pairs found before sampling.
    """

    X_model: np.ndarray
    t_model: np.ndarray
    uv_px: np.ndarray
    normal_px: np.ndarray
    depth_m: np.ndarray
    kind: np.ndarray
    T_cam_model: np.ndarray
    n_candidates: int = 0

    def __len__(self) -> int:
        return len(self.X_model)


def _empty(T: np.ndarray, n_cand: int = 0) -> Edgelets:
    z3 = np.zeros((0, 3))
    z2 = np.zeros((0, 2))
    return Edgelets(z3, z3.copy(), z2, z2.copy(), np.zeros(0), np.zeros(0, np.int8), T.copy(), n_cand)


def scaled_K(K: np.ndarray, s: float) -> np.ndarray:
    """Intrinsics of the image resized by ``s`` (pixel centres at integer coordinates)."""
    Ks = np.array(K, np.float64).copy()
    Ks[0, 0] *= s
    Ks[1, 1] *= s
    Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return Ks


def _cast_px(renderer, T: np.ndarray, Ks: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Cast rays through pixels (u, v) of camera Ks at pose T -> (z (N,) m, inf on miss; prim (N,) int64, -1)."""
    x = ((u - Ks[0, 2]) / Ks[0, 0]).astype(np.float32)
    y = ((v - Ks[1, 2]) / Ks[1, 1]).astype(np.float32)
    o, d = renderer.rays_for(T, x, y)
    if np.ndim(d[2]) == 0:
        d = (d[0], d[1], np.full(len(x), d[2], np.float32))
    t, prim = renderer.cast(o, d)
    hit = np.isfinite(t) & (prim != np.iinfo(np.uint32).max)
    return np.where(hit, t.astype(np.float64), np.inf), np.where(hit, prim.astype(np.int64), -1)


#: ``cv2.getGaussianKernel(9, 1.0, cv2.CV_32F)``, the kernel ``cv2.GaussianBlur`` uses for sigma 1 px on float32
GAUSS_SIGMA1_F32 = np.array([0.0001338306174147874, 0.004431861452758312, 0.053991127759218216, 0.2419714480638504,
                             0.3989434838294983, 0.2419714480638504, 0.053991127759218216, 0.004431861452758312,
                             0.0001338306174147874], np.float32)


def smoothed_gradient(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(gx, gy)`` (H, W) float32: the 3x3 Sobel derivatives of ``img`` blurred by a Gaussian of sigma 1 px
    (``cv2.GaussianBlur`` then ``cv2.Sobel``'s values to float32 rounding), summed in a fixed order
    (:func:`mst.pipeline.tracking.kernels.blur_sobel_f32`): OpenCV's float32 filters round by CPU (their SIMD
    code), which moved the render-based edgelets and the curved-mesh poses from one CPU to the next."""
    from mst.pipeline.tracking.compiled import kernels as kc

    a = np.ascontiguousarray(img, np.float32)
    gx, gy = np.empty_like(a), np.empty_like(a)
    if min(a.shape) <= len(GAUSS_SIGMA1_F32) // 2:  # a window too small to reflect the kernel: no gradient
        gx.fill(0.0)
        gy.fill(0.0)
        return gx, gy
    kc.blur_sobel_f32(a, GAUSS_SIGMA1_F32, gx, gy)
    return gx, gy


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    H, W = img.shape[:2]
    u = np.clip(u, 0, W - 1.001)
    v = np.clip(v, 0, H - 1.001)
    i0, j0 = np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)
    a, b = v - i0, u - j0
    return ((1 - a) * (1 - b) * img[i0, j0] + (1 - a) * b * img[i0, j0 + 1] + a * (1 - b) * img[i0 + 1, j0]
            + a * b * img[i0 + 1, j0 + 1])


def _image_dir(c: np.ndarray, X: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,2) image direction (px, unnormalised) of camera-frame 3D directions ``c`` at points ``X`` (derivative of the projection)."""
    return np.stack([K[0, 0] * (c[:, 0] * X[:, 2] - X[:, 0] * c[:, 2]), K[1, 1] * (c[:, 1] * X[:, 2] - X[:, 1] * c[:, 2])], 1)


def mesh_roi(renderer, T_cam_model: np.ndarray, Ks: np.ndarray, w: int, h: int, margin: int = 6):
    """``(i0, j0, h', w')`` low-resolution pixel window holding the projected bounding box of the mesh (+ margin);
    the whole ``h x w`` image when a box corner is behind the camera; ``None`` when it is out of the image.
    The margin keeps the smoothing of the inverse-depth map (sigma 1 px, 3x3 Sobel) off the window border."""
    lo, hi = renderer.V.min(0), renderer.V.max(0)
    C = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    Cc = rigid(C, T_cam_model[:3, :3], T_cam_model[:3, 3])
    if (Cc[:, 2] <= 1e-6).any():
        return 0, 0, h, w
    u = Ks[0, 0] * Cc[:, 0] / Cc[:, 2] + Ks[0, 2]
    v = Ks[1, 1] * Cc[:, 1] / Cc[:, 2] + Ks[1, 2]
    j0, j1 = max(int(np.floor(u.min())) - margin, 0), min(int(np.ceil(u.max())) + margin, w - 1)
    i0, i1 = max(int(np.floor(v.min())) - margin, 0), min(int(np.ceil(v.max())) + margin, h - 1)
    if j1 < j0 + 1 or i1 < i0 + 1:
        return None
    return i0, j0, i1 - i0 + 1, j1 - j0 + 1


def render_maps(renderer, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int, scale: float = 0.5,
                roi: bool = False):
    """Low-resolution geometry maps of the mesh seen from ``T_cam_model``.

    Returns ``(Ks (3,3), Z (h,w) camera z-depth m, inf = background, N (h,w,3) float32 unit face normal
    in the camera frame turned toward the camera (0 on background), prim (h,w) triangle id or -1, (i0, j0))``,
    ``h, w = ceil(H*s), ceil(W*s)``; with ``roi`` only the window of :func:`mesh_roi` is cast (``Ks`` then has
    its principal point shifted by ``(j0, i0)``; all maps are of the window; ``None`` when the mesh is out of view).
    """
    Ks = scaled_K(K, scale)
    w, h = int(np.ceil(width * scale)), int(np.ceil(height * scale))
    i0 = j0 = 0
    if roi:
        r = mesh_roi(renderer, T_cam_model, Ks, w, h)
        if r is None:
            return None
        i0, j0, h, w = r
        Ks[0, 2] -= j0
        Ks[1, 2] -= i0
    u = np.tile(np.arange(w, dtype=np.float64), h)
    v = np.repeat(np.arange(h, dtype=np.float64), w)
    Z, prim = _cast_px(renderer, T_cam_model, Ks, u, v)
    N = _normals_cam(renderer, T_cam_model, Ks, prim, u, v)
    return Ks, Z.reshape(h, w), N.reshape(h, w, 3), prim.reshape(h, w), (i0, j0)


def _normals_cam(renderer, T, Ks, prim, u, v):
    """(N,3) float32 face normals of ``prim`` in the camera frame, turned toward the camera (zeros on miss)."""
    n32 = getattr(renderer, "_normals32", None)
    if n32 is None:
        n32 = np.vstack([renderer.normals, np.zeros((1, 3))]).astype(np.float32)  # last row: miss
        renderer._normals32 = n32
    n = rigid(np.take(n32, np.where(prim >= 0, prim, len(n32) - 1), axis=0), np.asarray(T[:3, :3], np.float32))
    x = ((u - Ks[0, 2]) / Ks[0, 0]).astype(np.float32)
    y = ((v - Ks[1, 2]) / Ks[1, 1]).astype(np.float32)
    sgn = np.where(n[:, 0] * x + n[:, 1] * y + n[:, 2] > 0, np.float32(-1), np.float32(1))
    return n * sgn[:, None]


def _plane_depth(X: np.ndarray, n: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """z of the intersection of rays ``ray`` (z = 1) with planes (point X, normal n); inf when parallel."""
    den = (n * ray).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (n * X).sum(-1) / den
    return np.where(np.abs(den) > 1e-6, z, np.inf)


def extract_edgelets(renderer, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int, *,
                     scale: float = 0.5, crease_deg: float = 40.0, depth_jump: float = 0.03, budget: int = 300,
                     refine_rounds: int = 2, border_px: float = 4.0, near_m: float = 1e-3) -> Edgelets:
    """Edgelets of the mesh in ``renderer`` seen from ``T_cam_model`` with intrinsics ``K`` (full image W x H px).

    ``scale`` render resolution (fraction of the image), ``crease_deg`` normal angle of a crease,
    ``depth_jump`` relative depth gap of a self-occlusion, ``budget`` target number of edgelets,
    ``border_px`` edgelets closer than this to the image border are dropped. See the module doc.
    """
    T = np.asarray(T_cam_model, np.float64)
    K = np.asarray(K, np.float64)
    maps = render_maps(renderer, T, K, width, height, scale, roi=True)  # only the mesh's window is cast
    if maps is None:
        return _empty(T)
    Ks, Z, N, prim_map, (i0, j0) = maps
    h, w = Z.shape
    fg = np.isfinite(Z) & (Z > near_m)
    Z = np.where(fg, Z, np.inf)
    cos_crease = np.cos(np.radians(crease_deg))

    def ray_at(i, j):
        return np.column_stack([(j - Ks[0, 2]) / Ks[0, 0], (i - Ks[1, 2]) / Ks[1, 1], np.ones(len(i))])

    pa_l, pb_l, kind_l = [], [], []
    for di, dj in ((0, 1), (1, 0)):  # horizontal, vertical neighbour pairs (2 iterations, not per pixel)
        sl_p = (slice(0, h - di), slice(0, w - dj))
        sl_q = (slice(di, h), slice(dj, w))
        fp, fq = fg[sl_p], fg[sl_q]
        both = fp & fq
        ii_s, jj_s = np.nonzero(fp ^ fq)
        # pairs that may be occlusions (depth gap) or creases (two triangles): the tests on those only
        zp, zq = Z[sl_p], Z[sl_q]
        with np.errstate(invalid="ignore"):
            gap = both & (np.abs(zp - zq) > depth_jump * np.minimum(zp, zq))
        ii_g, jj_g = np.nonzero(gap)
        rp, rq = ray_at(ii_g, jj_g), ray_at(ii_g + di, jj_g + dj)
        Np, Nq = N[ii_g, jj_g].astype(np.float64), N[ii_g + di, jj_g + dj].astype(np.float64)
        z_p, z_q = Z[ii_g, jj_g], Z[ii_g + di, jj_g + dj]
        with np.errstate(invalid="ignore"):
            zmin = np.minimum(z_p, z_q)
            ezq = np.abs(_plane_depth(rp * z_p[:, None], Np, rq) - z_q)  # q against p's tangent plane
            ezp = np.abs(_plane_depth(rq * z_q[:, None], Nq, rp) - z_p)
        occ = (ezq > depth_jump * zmin) & (ezp > depth_jump * zmin)
        ii_o, jj_o = ii_g[occ], jj_g[occ]
        ii_c, jj_c = np.nonzero(both & (prim_map[sl_p] != prim_map[sl_q]))
        c_ok = (N[ii_c, jj_c] * N[ii_c + di, jj_c + dj]).sum(1) < cos_crease
        ii_c, jj_c = ii_c[c_ok], jj_c[c_ok]
        if len(ii_o):  # an occlusion pair is not also a crease
            m = np.zeros((h, w), bool)
            m[ii_o, jj_o] = True
            notocc = ~m[ii_c, jj_c]
            ii_c, jj_c = ii_c[notocc], jj_c[notocc]
        ii = np.concatenate([ii_s, ii_o, ii_c])
        jj = np.concatenate([jj_s, jj_o, jj_c])
        if not len(ii):
            continue
        k = np.concatenate([np.full(len(ii_s), SILHOUETTE), np.full(len(ii_o), OCCLUSION),
                            np.full(len(ii_c), CREASE)]).astype(np.int8)
        ip, jp, iq, jq = ii, jj, ii + di, jj + dj
        # side a: the mesh side of a silhouette, the near side of an occlusion, p for a crease
        swap = np.where(k == SILHOUETTE, ~fg[ip, jp], np.where(k == OCCLUSION, Z[iq, jq] < Z[ip, jp], False))
        a = np.stack([np.where(swap, iq, ip), np.where(swap, jq, jp)], 1)
        b = np.stack([np.where(swap, ip, iq), np.where(swap, jp, jq)], 1)
        pa_l.append(a)
        pb_l.append(b)
        kind_l.append(k)
    if not pa_l:
        return _empty(T)
    pa = np.concatenate(pa_l)
    pb = np.concatenate(pb_l)
    kind = np.concatenate(kind_l)
    n_cand = len(kind)

    # 2D normals (low-res pixel units are isotropic with the full image: same direction)
    mid_u = 0.5 * (pa[:, 1] + pb[:, 1]).astype(np.float64)
    mid_v = 0.5 * (pa[:, 0] + pb[:, 0]).astype(np.float64)
    gx, gy = smoothed_gradient(np.where(fg, 1.0 / np.where(fg, Z, 1.0), 0.0))
    nrm = np.stack([_bilinear(gx, mid_u, mid_v), _bilinear(gy, mid_u, mid_v)], 1).astype(np.float64)
    na = N[pa[:, 0], pa[:, 1]].astype(np.float64)
    nb = N[pb[:, 0], pb[:, 1]].astype(np.float64)
    Xa = ray_at(pa[:, 0], pa[:, 1]) * Z[pa[:, 0], pa[:, 1]][:, None]
    crease_dir = np.cross(na, nb)
    cr = kind == CREASE
    if cr.any():
        dcr = _image_dir(crease_dir[cr], Xa[cr], Ks)
        nrm[cr] = np.stack([-dcr[:, 1], dcr[:, 0]], 1)
    # smooth occluding contour (the surface grazes the view ray): the image of the surface normal is
    # the contour normal, exactly (the smoothed-gradient direction is only good to a few degrees)
    graze = (kind != CREASE) & (np.abs((na * Xa).sum(1)) < 0.3 * np.linalg.norm(Xa, axis=1))
    if graze.any():
        nrm[graze] = _image_dir(na[graze], Xa[graze], Ks)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-12
    nrm = nrm / np.maximum(ln, 1e-12)[:, None]

    # full-resolution position of the candidate (pair midpoint) and border test
    s = scale
    uf = (mid_u + j0 + 0.5) / s - 0.5
    vf = (mid_v + i0 + 0.5) / s - 0.5
    ok &= (uf >= border_px) & (uf <= width - 1 - border_px) & (vf >= border_px) & (vf <= height - 1 - border_px)
    idx = np.nonzero(ok)[0]
    if not len(idx):
        return _empty(T, n_cand)

    # even sampling: buckets x 4 orientation sectors, one candidate per cell (nearest the cell centre)
    contour_len_px = len(idx) / (2.0 * s)  # two pair directions see each contour pixel about once each
    bucket = float(np.clip(contour_len_px / max(budget, 1) * 1.0, 3.0, 64.0))
    ang = np.degrees(np.arctan2(nrm[idx, 1], nrm[idx, 0])) % 180.0
    sector = np.minimum((ang // 45.0).astype(np.int64), 3)
    bx = np.floor(uf[idx] / bucket).astype(np.int64)
    by = np.floor(vf[idx] / bucket).astype(np.int64)
    nbx = int(np.ceil(width / bucket)) + 1
    cell = (by * nbx + bx) * 4 + sector
    dc = (uf[idx] - (bx + 0.5) * bucket) ** 2 + (vf[idx] - (by + 0.5) * bucket) ** 2
    order = np.lexsort((dc, cell))
    first = np.ones(len(order), bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    keep = idx[order[first]]
    if len(keep) > budget:  # deterministic thinning in cell order (stable while the contour moves slowly)
        keep = keep[np.round(np.linspace(0, len(keep) - 1, budget)).astype(np.int64)]
    pa, pb, kind, nrm = pa[keep], pb[keep], kind[keep], nrm[keep]
    na, nb = na[keep], nb[keep]
    za, zb = Z[pa[:, 0], pa[:, 1]], Z[pb[:, 0], pb[:, 1]]

    # sub-pixel refinement: 16-section search between the pixel centres of side a (t=0) and side b (t=1)
    lo = np.zeros(len(keep))
    hi = np.ones(len(keep))
    ua, va = pa[:, 1].astype(np.float64), pa[:, 0].astype(np.float64)
    ub, vb = pb[:, 1].astype(np.float64), pb[:, 0].astype(np.float64)
    z_lo, z_hi = za.copy(), zb.copy()
    n_lo, n_hi = na.copy(), nb.copy()
    zmid = 0.5 * (za + np.where(np.isfinite(zb), zb, za))
    n_sub = 15  # sub-samples per round: each round divides the interval by 16 (2 rounds: 1/256 px)
    frac = np.arange(1, n_sub + 1) / (n_sub + 1.0)
    rows = np.arange(len(keep))
    kk = kind[:, None]
    for _ in range(refine_rounds):  # one batched cast of all kept edgelets' sub-samples per round
        t = lo[:, None] + (hi - lo)[:, None] * frac[None, :]
        u, v = ua[:, None] + t * (ub - ua)[:, None], va[:, None] + t * (vb - va)[:, None]
        z, prim = _cast_px(renderer, T, Ks, u.ravel(), v.ravel())
        nn = _normals_cam(renderer, T, Ks, prim, u.ravel(), v.ravel()).astype(np.float64).reshape(len(keep), n_sub, 3)
        z = z.reshape(len(keep), n_sub)
        hit = np.isfinite(z)
        side_a = np.where(kk == SILHOUETTE, hit,
                          np.where(kk == OCCLUSION, hit & (z < zmid[:, None]),
                                   hit & ((nn * na[:, None]).sum(2) >= (nn * nb[:, None]).sum(2))))
        nb_side = ~side_a
        j = np.where(nb_side.any(1), nb_side.argmax(1), n_sub)  # first sub-sample on side b
        jm = np.maximum(j - 1, 0)
        jh = np.minimum(j, n_sub - 1)
        new_lo = np.where(j > 0, t[rows, jm], lo)
        hi = np.where(j < n_sub, t[rows, jh], hi)
        z_lo = np.where(j > 0, z[rows, jm], z_lo)
        z_hi = np.where(j < n_sub, z[rows, jh], z_hi)
        n_lo = np.where((j > 0)[:, None], nn[rows, jm], n_lo)
        n_hi = np.where((j < n_sub)[:, None], nn[rows, jh], n_hi)
        lo = new_lo
    # a true occlusion or crease is still a jump 1/256 px apart; a continuous surface at a grazing angle
    # (a false occlusion) or a smoothly curved one (a false crease) is not: drop those
    with np.errstate(invalid="ignore"):
        real = np.where(kind == OCCLUSION, np.abs(z_hi - z_lo) > 0.5 * depth_jump * z_lo,
                        np.where(kind == CREASE, (n_lo * n_hi).sum(1) < np.cos(np.radians(0.5 * crease_deg)), True))
    u, v = ua + lo * (ub - ua), va + lo * (vb - va)
    Xcam = np.column_stack([(u - Ks[0, 2]) / Ks[0, 0], (v - Ks[1, 2]) / Ks[1, 1], np.ones(len(u))]) * z_lo[:, None]

    # 3D tangents (camera frame): crease direction, else the viewing-plane direction of the contour line
    t2 = np.stack([-nrm[:, 1], nrm[:, 0]], 1)  # image tangent
    d = Xcam / np.linalg.norm(Xcam, axis=1, keepdims=True)
    t2c = np.column_stack([t2[:, 0] / K[0, 0], t2[:, 1] / K[1, 1], np.zeros(len(t2))])
    m = np.cross(d, t2c)  # normal of the viewing plane of the contour line
    tan = np.cross(m, d)
    cdir = np.cross(na, nb)
    use_c = (kind == CREASE) & (np.linalg.norm(cdir, axis=1) > 0.2)
    tan = np.where(use_c[:, None], cdir, tan)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    R, tt = T[:3, :3], T[:3, 3]
    X_model = rigid(Xcam - tt, R.T)
    t_model = rigid(tan, R.T)
    # the exact image of each edgelet and of its local line at the render pose
    uv, nrm_px = project_lines(X_model, t_model, T, K, 0.01 * Xcam[:, 2])
    # orientation: the tangent's sign makes the projected normal point from side a to side b (silhouettes:
    # out of the object into the background; occlusions: from the near surface to the far one), at every
    # pose the line is projected at (the line and its distances are unchanged by the sign)
    out = ((ub - ua) * nrm_px[:, 0] + (vb - va) * nrm_px[:, 1]) < 0
    t_model = np.where(out[:, None], -t_model, t_model)
    nrm_px = np.where(out[:, None], -nrm_px, nrm_px)
    good = np.isfinite(uv).all(1) & np.isfinite(nrm_px).all(1) & real
    return Edgelets(X_model[good], t_model[good], uv[good], nrm_px[good], Xcam[good, 2], kind[good], T.copy(), n_cand)


def project_lines(X_model: np.ndarray, t_model: np.ndarray, T_cam_model: np.ndarray, K: np.ndarray,
                  half_len_m: np.ndarray | float):
    """Pixels (N,2) of ``X_model`` and unit normals (N,2) of the projected local lines ``X +- h t``."""
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    h = np.asarray(half_len_m, np.float64).reshape(-1, 1) if np.ndim(half_len_m) else half_len_m

    def proj(P):
        Pc = rigid(P, R, t)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.column_stack([K[0, 0] * Pc[:, 0] / Pc[:, 2] + K[0, 2], K[1, 1] * Pc[:, 1] / Pc[:, 2] + K[1, 2]])

    uv = proj(X_model)
    dl = proj(X_model + h * t_model) - proj(X_model - h * t_model)
    ln = np.linalg.norm(dl, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.column_stack([-dl[:, 1], dl[:, 0]]) / ln
    return uv, n
