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
4. Hidden-line removal for non-convex models: an inverse-depth buffer of the visible faces (a
   numba scanline fill of every face's plane, at reduced resolution); a sample survives when it
   is not farther than the nearest surface in its 3x3 neighbourhood. Convex models skip this step.

Models with >= 1000 faces (a city) have a :class:`~.spatial_index.FaceIndex`: step 1 then looks only at
the faces of the grid cells in the view frustum (a query reused while the camera barely moves), and
the per-vertex and per-edge work covers the front faces in view only; the samples are bit-identical
to those of the all-faces path (tests/test_visibility_index.py). Such a model's face hysteresis is
kept for the faces in the view frustum (a face entering the view must be within ``angle_appear``).

Length: :func:`visible_samples` is one numeric pass over all samples, longer than 80 lines by design: it was moved, not
rewritten, when the tracking package was formed (issue #10), so that the order of its floating-point
operations, and the outputs, stay bit-identical. The depth buffer and the shared vectorised helpers are in
:mod:`.depth_buffer`, the face grid and the reuse rule for large models in :mod:`.spatial_index`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mst.pipeline.tracking.compiled import kernels as _kc  # ahead of time or numba JIT
from mst.pipeline.tracking.depth_buffer import _loops_of, _mat3, eroded_buffer, inverse_depth_buffer  # noqa: F401 (re-exported)
from mst.pipeline.tracking.edge_joints import flat_t_junctions
from mst.pipeline.tracking.exact import centre, mv
from mst.pipeline.tracking.spatial_index import INDEX_MIN_FACES, FaceIndex, csr_gather, frustum_planes

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
    #: every loop (outer first, then the holes) of every face, for the z-buffer rasteriser:
    #: ring_vid concatenated vertex ids, ring_start/ring_len per ring, face_ring0/face_nring per face
    ring_vid: np.ndarray | None = None
    ring_start: np.ndarray | None = None
    ring_len: np.ndarray | None = None
    face_ring0: np.ndarray | None = None
    face_nring: np.ndarray | None = None
    #: bounding sphere of each face's outer loop (centre (F,3) m, radius (F,) m), for frustum culling
    face_center: np.ndarray | None = None
    face_radius: np.ndarray | None = None
    #: (F+1,) offsets of each face's vertex ids (every ring, outer first) in ``ring_vid``
    face_vstart: np.ndarray | None = None
    #: grid over the faces for frustum queries (:mod:`.spatial_index`); None below INDEX_MIN_FACES
    index: FaceIndex | None = None

    @classmethod
    def from_model(cls, model) -> ModelGeometry:
        """Build from a :class:`mst.meshtools.model.PolygonModel` (outward winding expected)."""
        V = np.asarray(model.vertices, np.float64)
        faces = [np.asarray(f, np.int64) for f in model.faces]
        holes = [list(h) for h in model.holes] if model.holes else [[] for _ in faces]
        N = model.face_normals()
        lens = np.array([len(f) for f in faces], np.int64)
        loop_vid = np.concatenate(faces) if faces else np.zeros(0, np.int64)
        loop_start = np.concatenate([[0], np.cumsum(lens)[:-1]]) if faces else np.zeros(0, np.int64)
        P = _loop_means(V, loop_vid, loop_start, lens)
        rings = [np.asarray(lp, np.int64) for i, f in enumerate(faces) for lp in [f, *holes[i]]]
        ring_len = np.array([len(r) for r in rings], np.int64)
        ring_vid = np.concatenate(rings) if rings else np.zeros(0, np.int64)
        ring_start = np.concatenate([[0], np.cumsum(ring_len)[:-1]]).astype(np.int64) if rings else np.zeros(0, np.int64)
        face_nring = np.array([1 + len(holes[i]) for i in range(len(faces))], np.int64)
        # directed edges of every loop (outer + holes, in face order) -> face id, and the free lines (-1)
        nxt = np.arange(1, len(ring_vid) + 1)
        nxt[ring_start + ring_len - 1] = ring_start  # the last vertex of a ring closes it
        nxt = nxt[: len(ring_vid)]
        S = np.stack([ring_vid, ring_vid[nxt]], 1) if len(ring_vid) else np.zeros((0, 2), np.int64)
        fid = np.repeat(np.repeat(np.arange(len(faces)), face_nring), ring_len)
        if len(getattr(model, "lines", [])):
            S = np.concatenate([S, np.asarray(model.lines, np.int64).reshape(-1, 2)])
            fid = np.concatenate([fid, np.full(len(model.lines), -1)])
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
        flat |= flat_t_junctions(V, uniq, ef, N, CREASE_DEG)
        uniq, ef = uniq[~flat], ef[~flat]
        # convexity: all vertices behind all face planes (within 1e-6 of the model size)
        size = float(np.ptp(V, axis=0).max()) if len(V) else 1.0
        used = np.unique(loop_vid) if len(loop_vid) else np.zeros(0, np.int64)
        if len(faces) and len(faces) * len(used) <= 20_000_000:
            d = np.einsum("fk,fvk->fv", N, V[used][None, :, :] - P[:, None, :])
            convex = bool((d <= 1e-6 * size).all())
        else:
            convex = not len(faces)
        face_ring0 = (np.concatenate([[0], np.cumsum(face_nring)[:-1]]).astype(np.int64) if len(faces)
                      else np.zeros(0, np.int64))
        if len(faces):
            lo = np.minimum.reduceat(V[loop_vid], loop_start, axis=0)
            hi = np.maximum.reduceat(V[loop_vid], loop_start, axis=0)
            ctr = 0.5 * (lo + hi)
            rad = 0.5 * np.linalg.norm(hi - lo, axis=1)
        else:
            ctr, rad = np.zeros((0, 3)), np.zeros(0)
        face_vstart = np.append(ring_start[face_ring0], len(ring_vid)).astype(np.int64) if len(faces) \
            else np.zeros(1, np.int64)
        index = FaceIndex(ctr, rad, ef) if len(faces) >= INDEX_MIN_FACES else None
        return cls(V, faces, holes, N, P, loop_vid, loop_start, uniq, ef, convex, size, ring_vid, ring_start,
                   ring_len, face_ring0, face_nring, ctr, rad, face_vstart, index)

    def face_vertices(self, faces: np.ndarray) -> np.ndarray:
        """Vertex ids of every ring of ``faces`` (K,) face ids, concatenated (repeats kept)."""
        return csr_gather(self.ring_vid, self.face_vstart, faces)

    def to_camera(self, T_cam_model: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
        """(V,3) the model vertices in the camera frame; with ``faces`` (K,) face ids only the
        vertices of those faces and the free lines (the others NaN: never read)."""
        R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
        if faces is None:
            return _mat3(self.vertices, R, t)
        Xc = np.full(self.vertices.shape, np.nan)
        vid = np.concatenate([self.face_vertices(faces), self.edges[self.index.free_edges].ravel()]) \
            if self.index is not None else self.face_vertices(faces)
        Xc[vid] = _mat3(self.vertices[vid], R, t)
        return Xc


def _loop_means(V: np.ndarray, loop_vid: np.ndarray, loop_start: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """(F, 3) the mean of each loop's vertices: each loop's ``V[loop].mean(axis=0)`` to the bit (its rows added
    one after the other, then divided by the count), for all loops at once, one vertex position at a time."""
    if not len(lens):
        return np.zeros((0, 3))
    acc = np.zeros((len(lens), 3))
    for j in range(int(lens.max())):  # from +0.0, as numpy's add.reduce (a -0.0 coordinate gives +0.0)
        sel = np.flatnonzero(lens > j)
        acc[sel] += V[loop_vid[loop_start[sel] + j]]
    return acc / lens[:, None]


@dataclass
class Samples:
    """Edge samples for one pose. Positions in pixels of the image they were computed for.

    uv (N,2) px; normal (N,2) unit normal of the projected edge (image x right, y down);
    X_model (N,3) metres; edge (N,) index into the clipped-edge arrays; A_model/B_model (E',3)
    clipped edge endpoints in the model frame; edge_uv (E',2,2) projected clipped endpoints px.
    stats: counts of candidate edges removed by each step (``behind``, ``beyond_far``, ``lod``,
    ``outside``, ``short``, ``hidden`` samples) and ``z_min_m`` (nearest candidate edge point).
    """

    uv: np.ndarray
    normal: np.ndarray
    X_model: np.ndarray
    edge: np.ndarray
    A_model: np.ndarray
    B_model: np.ndarray
    edge_uv: np.ndarray
    face_visible: np.ndarray
    #: how many candidate edges each step removed (see :func:`explain_no_samples`)
    stats: dict = field(default_factory=dict)
    model_edge: np.ndarray | None = None  #: (E',) index of each clipped edge into ``geom.edges``

    def __len__(self) -> int:
        return len(self.uv)


def face_visibility(geom: ModelGeometry, T_cam_model: np.ndarray, prev: np.ndarray | None,
                    appear_deg: float, disappear_deg: float, among: np.ndarray | None = None) -> np.ndarray:
    """(F,) bool: faces seen from the front at less than the appear/disappear angle (hysteresis).
    ``among`` (F,) bool: test only these faces (e.g. those in the view frustum); the others are False.
    The angles and the hysteresis in one numba kernel (:func:`mst.pipeline.tracking.kernels.face_visibility_kernel`,
    the angles of :func:`mst.pipeline.tracking.kernels.face_angles`; issue #14: the numpy steps around
    it were ~15 us of each of the two calls a frame)."""
    face_visibility_kernel = _kc.face_visibility_kernel

    c_model = centre(T_cam_model)  # camera centre in the model frame (as face_visibility_numpy)
    F = len(geom.faces)
    sel = _all_faces(geom) if among is None else np.flatnonzero(among)
    has_prev = prev is not None and len(prev) == F
    return face_visibility_kernel(geom.vertices, geom.face_normals, geom.loop_vid, geom.loop_start, _loop_end(geom),
                                  np.ascontiguousarray(sel, np.int64), np.ascontiguousarray(c_model, np.float64),
                                  np.ascontiguousarray(prev, np.bool_) if has_prev else np.zeros(0, np.bool_), has_prev,
                                  float(appear_deg), float(disappear_deg), F)


def _all_faces(geom: ModelGeometry) -> np.ndarray:
    """(F,) int64 ids of every face (computed once per geometry)."""
    ids = geom.__dict__.get("_all_faces")
    if ids is None:
        ids = geom.__dict__["_all_faces"] = np.arange(len(geom.faces), dtype=np.int64)
    return ids


def _all_edges(geom: ModelGeometry) -> np.ndarray:
    """(E,) int64 ids of every edge (computed once per geometry)."""
    ids = geom.__dict__.get("_all_edges")
    if ids is None:
        ids = geom.__dict__["_all_edges"] = np.arange(len(geom.edges), dtype=np.int64)
    return ids


def _loop_end(geom: ModelGeometry) -> np.ndarray:
    """(F,) int64 end of each face's outer loop in ``geom.loop_vid`` (computed once per geometry)."""
    loop_end = geom.__dict__.get("_loop_end")
    if loop_end is None:
        loop_end = geom.__dict__["_loop_end"] = np.append(geom.loop_start[1:], len(geom.loop_vid)).astype(np.int64)
    return loop_end


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
    t0 = np.where(keep, t0, 0.0)  # dropped segments (both ends behind) may hold +-inf from dz = 0
    t1 = np.where(keep, t1, 1.0)
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


def frustum_faces(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int,
                  near: float, far: float | None = None, counts: dict | None = None,
                  among: np.ndarray | None = None) -> np.ndarray:
    """(F,) bool: faces whose bounding sphere reaches into the view frustum (the image rectangle,
    ``near`` .. ``far`` metres). One vectorised plane test per face: a city's faces behind the
    camera or beside the view never reach the per-vertex work. ``counts``: gets (F,) bool masks of
    the faces culled as ``behind``, ``beyond_far`` and ``outside``. ``among`` (K,) face ids: test
    only these (a superset of the answer from :meth:`FaceIndex.candidates`; the others are False)."""
    F = len(geom.faces)
    if not F:
        return np.zeros(0, bool)
    if counts is None:  # one kernel (kernels.frustum_cull): a few us instead of ~15 numpy calls a frame
        frustum_cull = _kc.frustum_cull

        out = np.zeros(F, np.bool_)
        sel_i = np.arange(F, dtype=np.int64) if among is None else np.ascontiguousarray(among, np.int64)
        frustum_cull(geom.face_center, geom.face_radius, sel_i, np.ascontiguousarray(T_cam_model[:3, :3], np.float64),
                     np.ascontiguousarray(T_cam_model[:3, 3], np.float64), frustum_planes(K, width, height), float(near),
                     float(np.inf if far is None else far), out)
        return out
    sel = slice(None) if among is None else among
    c = _mat3(geom.face_center[sel], T_cam_model[:3, :3], T_cam_model[:3, 3])
    r = geom.face_radius[sel]
    ok = c[:, 2] >= near - r
    if far is not None and np.isfinite(far):
        ok &= c[:, 2] <= far + r
    for n in frustum_planes(K, width, height):  # side planes through the camera centre, inward normals
        ok &= mv(c, n) >= -r
    if counts is not None:
        behind = c[:, 2] < near - r
        beyond = (c[:, 2] > far + r) if far is not None and np.isfinite(far) else np.zeros(len(c), bool)
        counts["behind"] = behind
        counts["beyond_far"] = beyond & ~behind
        counts["outside"] = ~ok & ~behind & ~beyond
    if among is None:
        return ok
    out = np.zeros(F, bool)
    out[among[ok]] = True
    return out


def view_faces(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int,
               near: float, far: float | None) -> np.ndarray | None:
    """(F,) bool faces in the view frustum through the model's :class:`FaceIndex` (candidates
    reused between close poses, then the exact test); None for a model without an index."""
    if geom.index is None:
        return None
    far = np.inf if far is None else far
    return frustum_faces(geom, T_cam_model, K, width, height, near, far,
                         among=geom.index.candidates(T_cam_model, K, width, height, near, far))


def projected_face_area_px2(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, near: float,
                            Xc_all: np.ndarray | None = None, faces: np.ndarray | None = None,
                            _numpy_reference: bool = False) -> np.ndarray:
    """(F,) area in px^2 of each face's outer loop projected with ``K`` (shoelace formula; holes
    ignored); ``inf`` for a face with a vertex in front of the near plane ``near`` (metres), whose
    projection is unbounded. ``faces`` (F,) bool: compute only these (the others get 0).
    ``Xc_all`` (V, 3): the vertices already in the camera frame (rows of the faces read must be set).
    One kernel (:func:`mst.pipeline.tracking.kernels.face_areas_px2`); ``_numpy_reference``: the
    numpy formulation it equals to the bit (its test's reference)."""
    F = len(geom.faces)
    if not F:
        return np.zeros(0)
    sel = np.arange(F) if faces is None else np.flatnonzero(faces)
    area = np.zeros(F)
    if not len(sel):
        return area
    if not _numpy_reference:  # one kernel, the same bits (kernels.face_areas_px2)
        face_areas_px2 = _kc.face_areas_px2

        Xc = _mat3(geom.vertices, T_cam_model[:3, :3], T_cam_model[:3, 3]) if Xc_all is None else Xc_all
        face_areas_px2(np.ascontiguousarray(Xc, np.float64), geom.loop_vid, geom.loop_start, _loop_end(geom),
                       sel.astype(np.int64), float(K[0, 0]), float(K[1, 1]), float(near), area)
        return area
    vid, start = _loops_of(geom, sel)
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    Xc = (_mat3(geom.vertices, R, t) if Xc_all is None else Xc_all)[vid]
    z = Xc[:, 2]
    zs = np.where(z > near, z, 1.0)
    u = K[0, 0] * Xc[:, 0] / zs
    v = K[1, 1] * Xc[:, 1] / zs
    n = len(vid)
    ends = np.append(start[1:], n)
    nxt = np.arange(1, n + 1)
    nxt[ends - 1] = start  # the last vertex of a loop closes it
    cross = u * v[nxt] - u[nxt] * v
    a = 0.5 * np.abs(np.add.reduceat(cross, start))
    a[np.minimum.reduceat(z, start) <= near] = np.inf
    area[sel] = a
    return area


def explain_no_samples(stats: dict, near: float, far: float | None, lod: tuple[float, float] = (0.0, 0.0)) -> str:
    """The actual reason why a pose gave (almost) no edge samples, from :attr:`Samples.stats`:
    the step that removed most candidate edges (behind the camera, beyond the far plane, too small
    in the image, outside the image, hidden)."""
    n = stats.get("candidates", 0)
    if n == 0:
        return "no model face is turned toward the camera (the pose looks at the model from behind or edge-on)"
    steps = {k: stats.get(k, 0) for k in ("behind", "beyond_far", "lod", "outside", "short")}
    worst = max(steps, key=steps.get)
    z = stats.get("z_min_m")
    if steps[worst] == 0:
        return f"too few visible edge samples ({stats.get('samples', 0)}, hidden {stats.get('hidden', 0)})"
    if worst == "behind":
        return "the pose puts the model behind the camera (every candidate edge is behind the near plane)"
    if worst == "beyond_far":
        near_txt = f"nearest edge at {z:.4g} m, " if z is not None else ""
        far_txt = f"far plane {far:g} m" if far is not None else "far plane"
        return f"the model is beyond the far clipping plane ({near_txt}{far_txt})"
    if worst == "lod" or worst == "short":
        return (f"the model is too small in the image ({steps['lod'] + steps['short']} of {n} edges shorter than "
                f"{max(lod[0], 1.0):g} px or on faces smaller than {lod[1]:g} px^2; nearest edge at "
                f"{z:.4g} m)" if z is not None else "the model is too small in the image")
    return "the model is outside the image at this pose"


def visible_samples(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int,
                    step: float, near: float, far: float | None, appear_deg: float, disappear_deg: float,
                    prev_faces: np.ndarray | None = None, border_px: float = 4.0, hidden_lines: bool = True,
                    zbuffer_scale: float = 0.5, max_samples: int = 0, lod_min_line_px: float = 0.0,
                    lod_min_face_px2: float = 0.0, _numpy_reference: bool = False) -> Samples:
    """Sample the visible projected model edges every ``step`` px (see module docstring).

    ``far`` None: no far plane. Level of detail (ViSP ``setLod``): edges whose projection (after
    near/far clipping, before the image-border clip) is shorter than ``lod_min_line_px``, and
    edges whose visible faces all project smaller than ``lod_min_face_px2``, are skipped.
    """
    far = np.inf if far is None else far
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    culled: dict = {}
    indexed = geom.index is not None
    if geom.face_center is not None and len(geom.faces):
        masks: dict = {}
        if indexed:  # the grid's candidates (reused between close poses), then the exact test
            in_view = view_faces(geom, T_cam_model, K, width, height, near, far)
        else:  # the culling counts only to explain a failure (below)
            in_view = frustum_faces(geom, T_cam_model, K, width, height, near, far)
        fv = face_visibility(geom, T_cam_model, prev_faces, appear_deg, disappear_deg, among=in_view)
        if not indexed and in_view.all():  # nothing culled (a small object in view): fv is the all-faces test
            fv_all = fv
            culled = {k: 0 for k in ("behind", "beyond_far", "outside")}
        elif fv.sum() < 6:  # a failure to explain: which front-facing faces were culled, and why
            frustum_faces(geom, T_cam_model, K, width, height, near, far, masks)
            fv_all = face_visibility(geom, T_cam_model, prev_faces, appear_deg, disappear_deg)
            culled = {k: int((m & fv_all).sum()) for k, m in masks.items()}
        else:
            fv_all = fv
    else:
        fv = fv_all = face_visibility(geom, T_cam_model, prev_faces, appear_deg, disappear_deg)
    # every vertex in the camera frame, once (with an index: those of the front faces in view and
    # of the free lines, the only ones read below, unless a failure is explained from all faces)
    Xv = geom.to_camera(T_cam_model, np.flatnonzero(fv)) if indexed and fv_all is fv else _mat3(geom.vertices, R, t)
    # candidate edges: with an index those adjacent to a front face in view (and the free lines),
    # in edge order; the others cannot pass the test below
    e_sel = geom.index.edges_of(np.flatnonzero(fv)) if indexed else _all_edges(geom)
    fv_big = fv
    if lod_min_face_px2 > 0 and len(fv):
        fv_big = fv & (projected_face_area_px2(geom, T_cam_model, K, near, Xv, fv) >= lod_min_face_px2)
    if _numpy_reference:
        from mst.pipeline.tracking.visibility_numpy import _candidate_edges_numpy as candidate_edges
    else:  # one kernel
        candidate_edges = _kc.candidate_edges
    # the edges with a front face in view (the free lines too); small_face: none of them big enough
    eid, E, small_face = candidate_edges(geom.edges, geom.edge_faces, np.ascontiguousarray(e_sel, np.int64),
                                         np.ascontiguousarray(fv, np.bool_), np.ascontiguousarray(fv_big, np.bool_))
    stats = {"candidates": int(len(E)) + sum(culled.values())}
    use_lod = bool(lod_min_line_px > 0 or lod_min_face_px2 > 0)
    bounds = (float(border_px), float(border_px), float(width - 1 - border_px), float(height - 1 - border_px))
    R_c, t_c = np.ascontiguousarray(R, np.float64), np.ascontiguousarray(t, np.float64)
    args = (np.ascontiguousarray(Xv, np.float64), np.ascontiguousarray(E, np.int64), np.ascontiguousarray(small_face),
            float(near), float(far), np.ascontiguousarray(K, np.float64), R_c, t_c, *bounds, float(step), use_lod,
            float(lod_min_line_px))
    if _numpy_reference:
        from mst.pipeline.tracking.visibility_numpy import _edge_samples_numpy

        out = _edge_samples_numpy(*args)
    else:
        edge_samples = _kc.edge_samples

        out = edge_samples(*args)
    counts, z_min, kept, pa, pb, A_model, B_model, uv, nrm, iz, Xc, edge_id = out
    eid = eid[kept]
    stats["behind"] = int(counts[0]) + culled.get("behind", 0)
    stats["z_min_m"] = None if np.isnan(z_min) else float(z_min)
    stats["beyond_far"] = int(counts[1]) + culled.get("beyond_far", 0)
    if use_lod:
        stats["lod"] = int(counts[2])
    stats["outside"] = int(counts[3]) + culled.get("outside", 0)
    stats["short"] = int(counts[4])
    X_model = None
    if hidden_lines and not geom.convex and len(uv):
        # the buffer (reused when the same pose and faces were rendered before: the previous frame's
        # evidence at the pose this frame starts from); the test, the kept samples and their model
        # points in one kernel (the erosion read at the samples only), or the numpy steps (the erosion)
        if _numpy_reference:
            from mst.pipeline.tracking.visibility_numpy import _unhidden_samples_numpy as unhidden_samples

            buf = eroded_buffer(geom, T_cam_model, K, width, height, fv, near, zbuffer_scale)[1]
        else:
            unhidden_samples = _kc.unhidden_samples

            buf = inverse_depth_buffer(geom, T_cam_model, K, width, height, fv, near, zbuffer_scale)[0]
        n_hidden, uv, nrm, Xc, edge_id, X_model = unhidden_samples(buf, uv, iz, float(zbuffer_scale), nrm, Xc, edge_id,
                                                                   R_c, t_c)
        stats["hidden"] = int(n_hidden)
    stats["visible"] = int(len(uv))  # before the cap: how much of the model the view holds
    if max_samples and len(uv) > max_samples:
        sel = np.linspace(0, len(uv) - 1, max_samples).round().astype(np.int64)
        uv, nrm, Xc, edge_id = uv[sel], nrm[sel], Xc[sel], edge_id[sel]
        X_model = None if X_model is None else X_model[sel]
    if X_model is None:
        X_model = _mat3(Xc - t, R.T)
    stats["samples"] = int(len(uv))
    if len(uv) < 6 and fv_all.any():
        # a failure to explain: the nearest front-facing face, culled or not (rare, so exact)
        vid, _ = _loops_of(geom, np.flatnonzero(fv_all))
        zf = Xv[vid, 2]
        zf = zf[zf >= near]
        if len(zf):
            stats["z_min_m"] = float(zf.min()) if stats["z_min_m"] is None else min(stats["z_min_m"], float(zf.min()))
    return Samples(uv, nrm, X_model, edge_id, A_model, B_model, np.stack([pa, pb], 1), fv, stats=stats, model_edge=eid)
