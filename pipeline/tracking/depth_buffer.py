"""The inverse-depth buffer of a polygon model's faces (hidden-line removal, KLT masks, surface
values) and the vectorised helpers that the visibility steps share.

Frames and units: ``T_cam_model`` 4x4 model -> camera (x right, y down, z forward); ``K`` pixels;
``1/z`` in 1/metres (0 = empty); buffer pixels at ``scale`` x the image's.
"""

from __future__ import annotations

import struct
from typing import TYPE_CHECKING

import numpy as np

from mst.pipeline.tracking.compiled import kernels as _kc  # ahead of time or numba JIT
from mst.pipeline.tracking.compiled import zbuffer as _kz
from mst.pipeline.tracking.exact import inverse

if TYPE_CHECKING:
    from mst.pipeline.tracking.visibility import ModelGeometry


_NO_T = np.zeros(3)  #: the translation of _mat3 without one (never written)


def _mat3(X: np.ndarray, M: np.ndarray, t=None) -> np.ndarray:
    """``X @ M.T (+ t)`` for (N,3) points without BLAS: a (N,3)x(3,3) product through OpenBLAS
    took 63 ms for 92k points on a loaded 2-core machine (thread spinning), this 1-3 ms. float64
    inputs go through one kernel (:func:`mst.pipeline.tracking.kernels.mat3_kernel`, the same bits
    as :func:`_mat3_numpy`, without its four temporaries: ~10 us a call on the tracker's few hundred
    samples), others through numpy."""
    if X.dtype == np.float64 and M.dtype == np.float64 and X.ndim == 2 and X.shape[1] == 3 and M.shape == (3, 3) \
            and (t is None or np.asarray(t).dtype == np.float64):
        mat3_kernel = _kc.mat3_kernel

        out = np.empty((len(X), 3))
        # t as a C-contiguous (3,) vector, one kernel signature (np.broadcast_to took ~5 us a call)
        tt = _NO_T if t is None else np.ascontiguousarray(t, np.float64)
        if tt.shape != (3,):  # a scalar or (1,): broadcast
            tt = np.ascontiguousarray(np.broadcast_to(tt, (3,)))
        # C-contiguous operands (a pose's R = T[:3, :3] is a strided view): the one signature compiled
        # ahead of time (mst.pipeline.tracking.compiled); a copy of 9 numbers or of an already
        # contiguous array costs nothing
        mat3_kernel(np.ascontiguousarray(X), np.ascontiguousarray(M), tt, t is not None, out)
        return out
    return _mat3_numpy(X, M, t)


def _mat3_numpy(X: np.ndarray, M: np.ndarray, t=None) -> np.ndarray:
    """The numpy formulation of :func:`_mat3` (its kernel's reference)."""
    out = X[:, 0:1] * M[:, 0] + X[:, 1:2] * M[:, 1] + X[:, 2:3] * M[:, 2]
    if t is not None:
        out += t
    return out


def _loops_of(geom: ModelGeometry, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outer-loop vertex ids of the faces ``faces`` (K,) concatenated, and each loop's start."""
    ends = np.append(geom.loop_start[1:], len(geom.loop_vid))
    lens = (ends - geom.loop_start)[faces]
    start = np.concatenate([[0], np.cumsum(lens)[:-1]]).astype(np.int64)
    pos = np.arange(int(lens.sum())) - np.repeat(start - geom.loop_start[faces], lens)
    return geom.loop_vid[pos], start


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
                         faces: np.ndarray, near: float, scale: float = 0.5,
                         Xc_all: np.ndarray | None = None, _numpy_reference: bool = False) -> tuple[np.ndarray, float]:
    """Render ``1/z`` (1/metres, 0 = empty) of the given faces (``(F,)`` bool) at ``scale`` x the
    image size (``K`` the image's intrinsics, ``T_cam_model`` model -> camera).

    Each face's plane makes ``1/z`` affine in the pixel coordinates. Faces wholly behind the near
    plane ``near`` (metres) are culled, and so are faces outside the buffer (in the kernel, from
    the projected bounding box); faces wholly in front are filled by one numba scanline call
    (:func:`mst.pipeline.zbuffer_kernels.fill_faces`, holes honoured); the few that cross the near
    plane are clipped (Sutherland-Hodgman) and filled with ``cv2.fillPoly``. ``Xc_all``: the
    model vertices already in the camera frame (V,3), when the caller has them (only the numpy
    formulation ``_numpy_reference`` reads them; the set-up kernel
    :func:`mst.pipeline.tracking.kernels.zbuffer_faces` moves the few vertices it needs itself, to
    the same values).

    The last :data:`CACHE_SIZE` buffers of a model are kept (read-only) and returned again for the
    same inputs, to the bit (issue #14: a frame's evidence renders the final pose's buffer, which the
    next frame's hidden-line pass needs when it starts from that pose).
    """
    if _numpy_reference:
        return _render_buffer(geom, T_cam_model, K, width, height, faces, near, scale, Xc_all, True), scale
    return _buffer_entry(geom, T_cam_model, K, width, height, faces, near, scale).buf, scale


class _Buffer:
    """One rendered buffer and its key (the pose, intrinsics, image size, near plane, scale and faces
    it was rendered for); ``eroded``: its 3x3 erosion once computed (:func:`eroded_buffer`)."""

    __slots__ = ("key", "buf", "eroded")

    def __init__(self, key: bytes, buf: np.ndarray):
        self.key, self.buf, self.eroded = key, buf, None


#: rendered buffers kept per model (the last ones): the evidence of a frame's final pose renders the
#: buffer that the next frame's hidden-line pass needs when it starts from that pose (issue #14)
CACHE_SIZE = 2


def _key(T_cam_model, K, width, height, near, scale, faces) -> bytes:
    """Every bit of the inputs a buffer depends on, faces (F,) bool included (one bytes comparison per
    cached buffer: issue #14, the arrays' comparisons were ~10 us a lookup)."""
    return b"".join((np.ascontiguousarray(T_cam_model, np.float64).tobytes(), np.ascontiguousarray(K, np.float64).tobytes(),
                     struct.pack("<qqddq", int(width), int(height), float(near), float(scale), len(faces)), faces.tobytes()))


def _buffer_entry(geom, T_cam_model, K, width, height, faces, near, scale) -> _Buffer:
    """The cache entry of the buffer for exactly these inputs (every bit of the pose, intrinsics,
    near plane and scale, the same face set): the kept one, else rendered now and kept (read-only,
    the last :data:`CACHE_SIZE` per model)."""
    f = np.asarray(faces, bool)
    key = _key(T_cam_model, K, width, height, near, scale, f)
    cache = geom.__dict__.setdefault("_zbuffer_cache", [])
    for e in cache:
        if e.key == key:
            return e
    buf = _render_buffer(geom, T_cam_model, K, width, height, faces, near, scale, None, False)
    buf.flags.writeable = False  # shared by every caller that asks for the same buffer
    e = _Buffer(key, buf)
    cache.insert(0, e)
    del cache[CACHE_SIZE:]
    return e


def eroded_buffer(geom: ModelGeometry, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int,
                  faces: np.ndarray, near: float, scale: float = 0.5) -> tuple[np.ndarray, np.ndarray, float]:
    """``(buf, far_nb, scale)``: :func:`inverse_depth_buffer` and its 3x3 erosion (the farthest
    surface in each pixel's 3x3 neighbourhood, the hidden-line test's), both reused when the same
    buffer was rendered before."""
    import cv2

    e = _buffer_entry(geom, T_cam_model, K, width, height, faces, near, scale)
    if e.eroded is None:
        e.eroded = cv2.erode(e.buf, np.ones((3, 3), np.uint8))
        e.eroded.flags.writeable = False
    return e.buf, e.eroded, scale


#: the buffers' intrinsics and their ``numpy.linalg.inv``, by the image intrinsics' bytes and the scale
#: (issue #14: the LAPACK call was ~40 us of each render, the scaling ~10 us of numpy calls; the same
#: matrices, to the bit, for the same inputs)
_K_SCALED: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def _scaled_K(K: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``(Ks, Kinv)``: ``K`` (3, 3) for a buffer at ``scale`` x the image's pixels (pixel centres kept)
    and its inverse (never written by the callers)."""
    key = K.dtype.str.encode() + K.tobytes() + struct.pack("<d", scale)
    out = _K_SCALED.get(key)
    if out is None:
        Ks = K.copy()
        Ks[:2] *= scale
        Ks[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
        Ks[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
        Kinv = inverse(Ks)
        Kinv.flags.writeable = False
        if len(_K_SCALED) >= 64:  # a few cameras and scales in a process
            _K_SCALED.clear()
        out = _K_SCALED[key] = (Ks, Kinv)
    return out


def _render_buffer(geom, T_cam_model, K, width, height, faces, near, scale, Xc_all, _numpy_reference) -> np.ndarray:
    """The rendering of :func:`inverse_depth_buffer` (its docstring), uncached."""
    import cv2

    fill_faces = _kz.fill_faces

    W, H = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
    buf = np.zeros((H, W), np.float32)
    Ks, Kinv = _scaled_K(K, scale)
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    sel = np.flatnonzero(faces)
    if not len(sel):
        return buf
    # per-model scratch (the rasteriser reads the rows of the faces it draws and the entries of their
    # vertices only, all written below): no (F, 3) and 2 x (V,) allocations per call
    scratch = geom.__dict__.get("_zbuffer_scratch")
    if scratch is None:
        scratch = (np.zeros((len(geom.faces), 3)), np.zeros(len(geom.vertices)), np.zeros(len(geom.vertices)))
        geom.__dict__["_zbuffer_scratch"] = scratch
    coef, uu, vv = scratch
    # plane of each selected face in the camera frame: 1/z = (n_c . Kinv [u v 1]) / d
    if _numpy_reference:
        n_c = _mat3(geom.face_normals[sel], R)
        p_c = _mat3(geom.face_point[sel], R, t)
        d = np.einsum("ij,ij->i", n_c, p_c)
        with np.errstate(divide="ignore", invalid="ignore"):
            coef[sel] = _mat3(n_c, Kinv.T) / d[:, None]
    else:  # the same operations in their order, in one kernel
        zbuffer_planes = _kc.zbuffer_planes

        d = zbuffer_planes(geom.face_normals, geom.face_point, sel.astype(np.int64, copy=False), np.ascontiguousarray(R, np.float64),
                           np.ascontiguousarray(t, np.float64), Kinv, coef)
    if _numpy_reference:  # the numpy formulation (the reference of the kernel's test)
        # depth range of each face's outer loop
        Xc = geom.to_camera(T_cam_model, sel) if Xc_all is None else Xc_all
        vid, start = _loops_of(geom, sel)
        z_loop = Xc[vid, 2]
        zmin = np.minimum.reduceat(z_loop, start)
        zmax = np.maximum.reduceat(z_loop, start)
        keep = (np.abs(d) >= 1e-12) & (zmax >= near)
        inside = sel[keep & (zmin >= near)]
        crossing = sel[keep & (zmin < near)]
        if len(inside):
            # project only the vertices of the faces drawn (the kernel reads no others)
            rv = geom.face_vertices(inside)
            Xr = Xc[rv]
            z = np.where(Xr[:, 2] > 1e-12, Xr[:, 2], 1e-12)
            uu[rv] = (Ks[0, 0] * Xr[:, 0] + Ks[0, 1] * Xr[:, 1]) / z + Ks[0, 2]
            vv[rv] = Ks[1, 1] * Xr[:, 1] / z + Ks[1, 2]
    else:  # the same in one kernel, from the model vertices (the values of Xc_all, which it need not read)
        zbuffer_faces = _kc.zbuffer_faces

        loop_end = geom.__dict__.get("_loop_end")
        if loop_end is None:
            loop_end = geom.__dict__["_loop_end"] = np.append(geom.loop_start[1:], len(geom.loop_vid)).astype(np.int64)
        inside, crossing = zbuffer_faces(geom.vertices, np.ascontiguousarray(R), np.ascontiguousarray(t), Ks, float(near),
                                         sel.astype(np.int64, copy=False), np.ascontiguousarray(d, np.float64), geom.loop_vid,
                                         geom.loop_start, loop_end, geom.ring_vid, geom.face_vstart, uu, vv)
    if len(inside):
        fill_faces(buf, uu, vv, geom.ring_vid, geom.ring_start, geom.ring_len, geom.face_ring0, geom.face_nring,
                   inside.astype(np.int64), coef)
    for f in crossing:
        polys = []
        for lp in [geom.faces[f], *geom.holes[f]]:
            Pc = _mat3(geom.vertices[lp], R, t)
            Pc = _clip_poly_near(Pc, near)
            if len(Pc) < 3:
                continue
            uv = _mat3(Pc, Ks)
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
        a = coef[f]
        uu = np.arange(xa, xb + 1, dtype=np.float32)
        vv = np.arange(ya, yb + 1, dtype=np.float32)
        iz = (a[0] * uu[None, :] + a[1] * vv[:, None] + a[2]).astype(np.float32)
        roi = buf[ya:yb + 1, xa:xb + 1]
        upd = (m > 0) & (iz > roi)
        roi[upd] = iz[upd]
    return buf
