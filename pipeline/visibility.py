"""Which model edges a camera sees, and where: face culling, clipping, hidden lines, sampling.

Frames and units: ``X_model`` metres in the model frame; ``T_cam_model`` 4x4 (model -> camera,
camera x right, y down, z forward); pixels for image positions (pixel (0, 0) = centre of the
top-left pixel); angles in degrees.

Steps for one pose (:func:`visible_samples`):

1. Faces: the angle between a face's outward normal and the ray from the face to the camera
   (smallest over the face's vertices) with ViSP's hysteresis: a face appears below
   ``angle_appear`` and disappears above ``angle_disappear``.
2. Edges adjacent to at least one visible face are kept (edges between coplanar faces, e.g. inside
   a split TIN face, are never tracked); each is clipped in 3D against the near and far planes
   (nothing behind the camera is ever projected), then in 2D against the image border.
3. Samples every ``step`` pixels along each clipped projected edge, with the inverse depth of the
   3D point under each sample (perspective-correct interpolation).
4. Hidden-line removal for non-convex models: an inverse-depth buffer of the visible faces (one
   ``cv2.fillPoly`` + a plane equation per face, at reduced resolution); a sample survives when it
   is not farther than the nearest surface in its 3x3 neighbourhood. Convex models skip this step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CREASE_DEG = 5.0  # edges whose two faces' normals differ by less are not tracked


@dataclass
class ModelGeometry:
    """Per-model arrays prepared once for fast per-frame visibility.

    vertices (V,3) metres; face_normals (F,3) outward unit; face_point (F,3) a point on each face;
    loop_vid (L,) concatenated outer-loop vertex ids with loop_start (F,) offsets; edges (E,2)
    vertex ids; edge_faces (E,2) adjacent face ids (-1 = none, i.e. a boundary/line edge);
    convex: True when every vertex lies behind every face plane (no hidden-line pass needed).
    """

    vertices: np.ndarray
    faces: list
    holes: list
    face_normals: np.ndarray
    face_point: np.ndarray
    loop_vid: np.ndarray
    loop_start: np.ndarray
    edges: np.ndarray
    edge_faces: np.ndarray
    convex: bool
    scale_m: float

    @classmethod
    def from_model(cls, model) -> ModelGeometry:
        """Build from a :class:`mst.meshtools.model.PolygonModel` (outward winding expected)."""
        V = np.asarray(model.vertices, np.float64)
        faces = [np.asarray(f, np.int64) for f in model.faces]
        holes = [list(h) for h in model.holes] if model.holes else [[] for _ in faces]
        N = model.face_normals()
        P = np.array([V[f].mean(axis=0) for f in faces]) if faces else np.zeros((0, 3))
        lens = np.array([len(f) for f in faces], np.int64)
        loop_vid = np.concatenate(faces) if faces else np.zeros(0, np.int64)
        loop_start = np.concatenate([[0], np.cumsum(lens)[:-1]]) if faces else np.zeros(0, np.int64)
        # directed edges of every loop (outer + holes) -> face id
        segs, fid = [], []
        for i, f in enumerate(faces):
            for lp in [f, *holes[i]]:
                lp = np.asarray(lp, np.int64)
                segs.append(np.stack([lp, np.roll(lp, -1)], 1))
                fid.append(np.full(len(lp), i))
        if len(getattr(model, "lines", [])):
            segs.append(np.asarray(model.lines, np.int64))
            fid.append(np.full(len(model.lines), -1))
        S = np.concatenate(segs) if segs else np.zeros((0, 2), np.int64)
        fid = np.concatenate(fid) if fid else np.zeros(0, np.int64)
        S_sorted = np.sort(S, axis=1)
        keep = S_sorted[:, 0] != S_sorted[:, 1]
        S_sorted, fid = S_sorted[keep], fid[keep]
        uniq, inv = np.unique(S_sorted, axis=0, return_inverse=True)
        inv = inv.ravel()
        ef = np.full((len(uniq), 2), -1, np.int64)
        order = np.argsort(inv, kind="stable")
        first = np.ones(len(order), bool)
        first[1:] = inv[order][1:] != inv[order][:-1]
        ef[inv[order][first], 0] = fid[order][first]
        second = ~first
        # second adjacent face (an edge shared by > 2 faces keeps the first two)
        sec_idx = order[second]
        e_sec = inv[sec_idx]
        ef_tmp = ef[:, 1].copy()
        ef_tmp[e_sec[::-1]] = fid[sec_idx][::-1]
        ef[:, 1] = ef_tmp
        # drop creases flatter than CREASE_DEG (coplanar split faces)
        both = (ef[:, 0] >= 0) & (ef[:, 1] >= 0)
        cosang = np.ones(len(ef))
        cosang[both] = np.einsum("ij,ij->i", N[ef[both, 0]], N[ef[both, 1]])
        flat = both & (cosang > np.cos(np.radians(CREASE_DEG)))
        uniq, ef = uniq[~flat], ef[~flat]
        # convexity: all vertices behind all face planes (within 1e-6 of the model size)
        size = float(np.ptp(V, axis=0).max()) if len(V) else 1.0
        used = np.unique(loop_vid) if len(loop_vid) else np.zeros(0, np.int64)
        if len(faces) and len(faces) * len(used) <= 20_000_000:
            d = np.einsum("fk,fvk->fv", N, V[used][None, :, :] - P[:, None, :])
            convex = bool((d <= 1e-6 * size).all())
        else:
            convex = not len(faces)
        return cls(V, faces, holes, N, P, loop_vid, loop_start, uniq, ef, convex, size)


@dataclass
class Samples:
    """Edge samples for one pose. Positions in pixels of the image they were computed for.

    uv (N,2) px; normal (N,2) unit normal of the projected edge (image x right, y down);
    X_model (N,3) metres; edge (N,) index into the clipped-edge arrays; A_model/B_model (E',3)
    clipped edge endpoints in the model frame; edge_uv (E',2,2) projected clipped endpoints px.
    """

    uv: np.ndarray
    normal: np.ndarray
    X_model: np.ndarray
    edge: np.ndarray
    A_model: np.ndarray
    B_model: np.ndarray
    edge_uv: np.ndarray
    face_visible: np.ndarray
    model_edge: np.ndarray | None = None  #: (E',) index of each clipped edge into ``geom.edges``

    def __len__(self) -> int:
        return len(self.uv)


def face_visibility(geom: ModelGeometry, T_cam_model: np.ndarray, prev: np.ndarray | None,
                    appear_deg: float, disappear_deg: float) -> np.ndarray:
    """(F,) bool: faces seen from the front at less than the appear/disappear angle (hysteresis)."""
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    c_model = -R.T @ t  # camera centre in the model frame
    ray = c_model[None, :] - geom.vertices[geom.loop_vid]
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    fid = np.repeat(np.arange(len(geom.faces)), np.diff(np.append(geom.loop_start, len(geom.loop_vid))))
    cosv = np.einsum("ij,ij->i", ray, geom.face_normals[fid])
    cos_best = np.maximum.reduceat(cosv, geom.loop_start) if len(cosv) else np.zeros(0)
    ang = np.degrees(np.arccos(np.clip(cos_best, -1, 1)))
    vis = ang < appear_deg
    if prev is not None and len(prev) == len(vis):
        vis |= prev & (ang < disappear_deg)
    return vis


def _clip_near_far(A: np.ndarray, B: np.ndarray, near: float, far: float):
    """Clip camera-frame segments (E,3) to near <= z <= far. Returns (A', B', keep)."""
    zA, zB = A[:, 2], B[:, 2]
    keep = ~(((zA < near) & (zB < near)) | ((zA > far) & (zB > far)))
    dz = zB - zA
    with np.errstate(divide="ignore", invalid="ignore"):
        t_near = (near - zA) / dz
        t_far = (far - zA) / dz
    t0 = np.zeros(len(A))
    t1 = np.ones(len(A))
    t0 = np.where(zA < near, t_near, t0)
    t1 = np.where(zB < near, t_near, t1)
    t0 = np.where(zA > far, np.maximum(t0, t_far), t0)
    t1 = np.where(zB > far, np.minimum(t1, t_far), t1)
    keep &= t1 > t0
    D = B - A
    return A + t0[:, None] * D, A + t1[:, None] * D, keep, t0, t1


def _clip_rect(a: np.ndarray, b: np.ndarray, x0: float, y0: float, x1: float, y1: float):
    """Liang-Barsky clip of 2D segments (E,2) to a rectangle. Returns (s0, s1, keep) in [0,1]."""
    d = b - a
    s0 = np.zeros(len(a))
    s1 = np.ones(len(a))
    keep = np.ones(len(a), bool)
    for p, q in ((-d[:, 0], a[:, 0] - x0), (d[:, 0], x1 - a[:, 0]), (-d[:, 1], a[:, 1] - y0), (d[:, 1], y1 - a[:, 1])):
        par = np.abs(p) < 1e-12
        keep &= ~(par & (q < 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            r = q / p
        s0 = np.where(~par & (p < 0), np.maximum(s0, r), s0)
        s1 = np.where(~par & (p > 0), np.minimum(s1, r), s1)
    keep &= s1 > s0
    return s0, s1, keep


def _clip_poly_near(P: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of one camera-frame polygon (k,3) to z >= near."""
    out = []
    k = len(P)
    for i in range(k):
        a, b = P[i], P[(i + 1) % k]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


def inverse_depth_buffer(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int,
                         faces: np.ndarray, near: float, scale: float = 0.5) -> tuple[np.ndarray, float]:
    """Render ``1/z`` (1/metres, 0 = empty) of the given faces at ``scale`` x the image size.

    One ``cv2.fillPoly`` per face (polygons clipped at the near plane, holes honoured) and the
    face's plane equation, which makes ``1/z`` affine in the pixel coordinates.
    """
    import cv2

    W, H = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
    buf = np.zeros((H, W), np.float32)
    Ks = K.copy()
    Ks[:2] *= scale
    Ks[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
    Kinv = np.linalg.inv(Ks)
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    for f in np.flatnonzero(faces):
        n_c = R @ geom.face_normals[f]
        p_c = R @ geom.face_point[f] + t
        d = float(n_c @ p_c)
        if abs(d) < 1e-12:
            continue
        polys = []
        for lp in [geom.faces[f], *geom.holes[f]]:
            Pc = geom.vertices[lp] @ R.T + t
            Pc = _clip_poly_near(Pc, near)
            if len(Pc) < 3:
                continue
            uv = Pc @ Ks.T
            uv = uv[:, :2] / uv[:, 2:3]
            polys.append(np.round(uv * 16).astype(np.int32))
        if not polys:
            continue
        allp = np.concatenate(polys) / 16.0
        xa, ya = max(0, int(np.floor(allp[:, 0].min()))), max(0, int(np.floor(allp[:, 1].min())))
        xb, yb = min(W - 1, int(np.ceil(allp[:, 0].max()))), min(H - 1, int(np.ceil(allp[:, 1].max())))
        if xb < xa or yb < ya:
            continue
        m = np.zeros((yb - ya + 1, xb - xa + 1), np.uint8)
        cv2.fillPoly(m, [p - np.array([xa * 16, ya * 16], np.int32) for p in polys], 1, lineType=cv2.LINE_8, shift=4)
        # 1/z = (n_c . Kinv [u v 1]) / d
        a = (n_c @ Kinv) / d
        uu = np.arange(xa, xb + 1, dtype=np.float32)
        vv = np.arange(ya, yb + 1, dtype=np.float32)
        iz = (a[0] * uu[None, :] + a[1] * vv[:, None] + a[2]).astype(np.float32)
        roi = buf[ya:yb + 1, xa:xb + 1]
        upd = (m > 0) & (iz > roi)
        roi[upd] = iz[upd]
    return buf, scale


def visible_samples(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int,
                    step: float, near: float, far: float, appear_deg: float, disappear_deg: float,
                    prev_faces: np.ndarray | None = None, border_px: float = 4.0, hidden_lines: bool = True,
                    zbuffer_scale: float = 0.5, max_samples: int = 0) -> Samples:
    """Sample the visible projected model edges every ``step`` px (see module docstring)."""
    fv = face_visibility(geom, T_cam_model, prev_faces, appear_deg, disappear_deg)
    ef = geom.edge_faces
    ev = ((ef[:, 0] >= 0) & fv[np.maximum(ef[:, 0], 0)]) | ((ef[:, 1] >= 0) & fv[np.maximum(ef[:, 1], 0)])
    ev |= (ef[:, 0] < 0) & (ef[:, 1] < 0)  # free lines: always candidates
    E = geom.edges[ev]
    eid = np.flatnonzero(ev)
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    A = geom.vertices[E[:, 0]] @ R.T + t
    B = geom.vertices[E[:, 1]] @ R.T + t
    A, B, keep, _, _ = _clip_near_far(A, B, near, far)
    A, B, eid = A[keep], B[keep], eid[keep]
    ua = A @ K.T
    ua = ua[:, :2] / ua[:, 2:3]
    ub = B @ K.T
    ub = ub[:, :2] / ub[:, 2:3]
    s0, s1, k2 = _clip_rect(ua, ub, border_px, border_px, width - 1 - border_px, height - 1 - border_px)
    A, B, ua, ub, s0, s1, eid = A[k2], B[k2], ua[k2], ub[k2], s0[k2], s1[k2], eid[k2]
    izA, izB = 1.0 / A[:, 2], 1.0 / B[:, 2]
    # clipped 2D endpoints and their inverse depths (1/z is affine along the projected segment)
    d2 = ub - ua
    pa = ua + s0[:, None] * d2
    pb = ua + s1[:, None] * d2
    iza = izA + s0 * (izB - izA)
    izb = izA + s1 * (izB - izA)
    L = np.linalg.norm(pb - pa, axis=1)
    n_s = np.floor(L / step).astype(np.int64)
    good = n_s >= 1
    pa, pb, iza, izb, L, n_s, eid = pa[good], pb[good], iza[good], izb[good], L[good], n_s[good], eid[good]
    Ka = (pa - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    Kb = (pb - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    Ac = np.column_stack([Ka, np.ones(len(Ka))]) / iza[:, None]  # camera-frame clipped endpoints
    Bc = np.column_stack([Kb, np.ones(len(Kb))]) / izb[:, None]
    Tinv_R = R.T
    A_model = (Ac - t) @ Tinv_R.T
    B_model = (Bc - t) @ Tinv_R.T
    edge_id = np.repeat(np.arange(len(n_s)), n_s)
    start = np.concatenate([[0], np.cumsum(n_s)[:-1]]) if len(n_s) else np.zeros(0, np.int64)
    j = np.arange(len(edge_id)) - np.repeat(start, n_s)
    s = (j + 0.5) / np.repeat(n_s, n_s)
    d = (pb - pa)[edge_id]
    uv = pa[edge_id] + s[:, None] * d
    iz = iza[edge_id] + s * (izb - iza)[edge_id]
    tang = (pb - pa) / np.maximum(L, 1e-9)[:, None]
    nrm = np.column_stack([-tang[:, 1], tang[:, 0]])[edge_id]
    xn = (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    Xc = np.column_stack([xn, np.ones(len(xn))]) / iz[:, None]
    if hidden_lines and not geom.convex and len(uv):
        import cv2

        buf, sc = inverse_depth_buffer(geom, T_cam_model, K, width, height, fv, near, zbuffer_scale)
        far_nb = cv2.erode(buf, np.ones((3, 3), np.uint8))  # farthest surface in each 3x3 neighbourhood
        ix = np.clip(np.round((uv[:, 0] + 0.5) * sc - 0.5).astype(np.int64), 0, buf.shape[1] - 1)
        iy = np.clip(np.round((uv[:, 1] + 0.5) * sc - 0.5).astype(np.int64), 0, buf.shape[0] - 1)
        vis = iz >= far_nb[iy, ix] * (1.0 - 2e-3) - 1e-9
        uv, nrm, Xc, edge_id = uv[vis], nrm[vis], Xc[vis], edge_id[vis]
    if max_samples and len(uv) > max_samples:
        sel = np.linspace(0, len(uv) - 1, max_samples).round().astype(np.int64)
        uv, nrm, Xc, edge_id = uv[sel], nrm[sel], Xc[sel], edge_id[sel]
    X_model = (Xc - t) @ R
    return Samples(uv, nrm, X_model, edge_id, A_model, B_model, np.stack([pa, pb], 1), fv, eid)
