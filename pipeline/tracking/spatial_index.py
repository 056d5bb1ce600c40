"""A uniform grid over a polygon model's faces for view-frustum queries, and the rule that reuses
a query's result while the camera barely moves (issue 11: a 50k-polygon city at frame rate).

Frames and units: face bounding spheres (centre, radius) in metres in the model frame;
``T_cam_model`` 4x4 model -> camera (x right, y down, z forward); ``K`` pixels.

* :class:`FaceIndex` groups the faces by the grid cell of their bounding-sphere centre and keeps a
  bounding sphere per cell that encloses every face sphere in it. A frustum query tests the cells
  (a few thousand spheres) and only the faces of the cells that pass: a face whose sphere reaches
  into the frustum always lies in a passing cell (``n . C + R >= n . c + r`` for every plane,
  since ``R >= |c - C| + r``), so the query returns a superset of the frustum faces and the exact
  per-face test on it gives the brute-force answer bit for bit.
* The reuse rule (:meth:`FaceIndex.candidates`): the query is made with every sphere inflated by
  ``2 sin(ROT/2) |c| + TRANS`` (``|c|`` the sphere centre's distance from the camera,
  ``ROT = REUSE_ROT_DEG``, ``TRANS = REUSE_TRANS_REL`` x the distance of the nearest geometry in
  view). A face centre moves in the camera frame by at most ``2 sin(theta/2) |c| + |dC|`` when the
  camera turns by ``theta`` and its centre moves by ``dC``; so while ``theta <= ROT`` and
  ``|dC| <= TRANS`` since the full query, its result still holds every face in the frustum, and it
  is reused (the exact test runs on it each time). Beyond that, or for another frustum (intrinsics,
  image size, near/far), a full query is made.

Models with fewer than ``INDEX_MIN_FACES`` faces get no index (a per-face test over all of them is
cheaper than the grid; their outputs are those of the brute-force path).
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import matmul_exact
from mst.pipeline.tracking.exact import centre as camera_centre
from mst.pipeline.tracking.exact import inverse, norm3

INDEX_MIN_FACES = 1000  #: models with fewer faces are culled face by face (no grid)
FACES_PER_CELL = 8  #: grid resolution: about this many faces per non-empty cell
REUSE_ROT_DEG = 2.0  #: a query is reused while the camera turned less than this since it was made
REUSE_TRANS_REL = 0.05  #: ... and moved less than this x the distance of the nearest geometry in view


def csr_gather(data: np.ndarray, start: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Concatenate ``data[start[i]:start[i + 1]]`` for ``i`` in ``sel`` (CSR rows, vectorised)."""
    lens = start[sel + 1] - start[sel]
    n = int(lens.sum())
    if not n:
        return data[:0]
    off = np.concatenate([[0], np.cumsum(lens)[:-1]])
    pos = np.arange(n) - np.repeat(off - start[sel], lens)
    return data[pos]


_PLANES: dict = {}


def frustum_planes(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(4, 3) inward unit normals of the side planes through the camera centre and the image
    border (pixel centres at integers: the border is at -0.5 and W - 0.5). Kept per (K, W, H):
    a tracker asks for the same few (one per pyramid level) every frame."""
    key = (np.asarray(K, np.float64).tobytes(), int(width), int(height))
    p = _PLANES.get(key)
    if p is None:
        if len(_PLANES) > 64:
            _PLANES.clear()
        p = _PLANES[key] = _frustum_planes(K, width, height)
        p.flags.writeable = False
    return p


def _frustum_planes(K: np.ndarray, width: int, height: int) -> np.ndarray:
    Kinv = inverse(K)
    corners = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1], [-0.5, height - 0.5, 1]])
    rays = matmul_exact(corners, Kinv.T)
    out = np.zeros((4, 3))
    for i in range(4):
        n = np.cross(rays[i], rays[(i + 1) % 4])
        n /= norm3(n)
        if n[2] < 0:  # n . (0, 0, 1)
            n = -n
        out[i] = n
    return out


def _to_cam(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return X[:, 0:1] * R[:, 0] + X[:, 1:2] * R[:, 1] + X[:, 2:3] * R[:, 2] + t


def _spheres_in_frustum(c: np.ndarray, r: np.ndarray, planes: np.ndarray, near: float, far: float) -> np.ndarray:
    """(N,) bool: camera-frame spheres (centre c (N,3), radius r (N,)) reaching into the frustum."""
    ok = c[:, 2] >= near - r
    if np.isfinite(far):
        ok &= c[:, 2] <= far + r
    for n in planes:
        ok &= c[:, 0] * n[0] + c[:, 1] * n[1] + c[:, 2] * n[2] >= -r
    return ok


class FaceIndex:
    """Uniform grid of face bounding spheres (see the module docstring)."""

    def __init__(self, face_center: np.ndarray, face_radius: np.ndarray, edge_faces: np.ndarray):
        F = len(face_center)
        lo, hi = face_center.min(0), face_center.max(0)
        ext = np.maximum(hi - lo, 1e-9)
        n_cells = max(1.0, F / FACES_PER_CELL)
        # cells as cubic as the extent allows; a flat city gets one layer
        side = (np.prod(ext[ext > 1e-6 * ext.max()]) / n_cells) ** (1.0 / max(1, int((ext > 1e-6 * ext.max()).sum())))
        dims = np.maximum(1, np.ceil(ext / max(side, 1e-12))).astype(np.int64)
        ijk = np.minimum(((face_center - lo) / ext * dims).astype(np.int64), dims - 1)
        cell = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        order = np.argsort(cell, kind="stable")
        cs = cell[order]
        first = np.ones(F, bool)
        first[1:] = cs[1:] != cs[:-1]
        starts = np.flatnonzero(first)
        self.cell_faces = order.astype(np.int64)  #: face ids grouped by cell
        self.cell_start = np.append(starts, F).astype(np.int64)  #: (C+1,) CSR offsets
        # each cell's sphere: centre of its faces' sphere bounds, radius enclosing every face sphere
        c, r = face_center[order], face_radius[order]
        blo = np.minimum.reduceat(c - r[:, None], starts, axis=0)
        bhi = np.maximum.reduceat(c + r[:, None], starts, axis=0)
        C = 0.5 * (blo + bhi)
        cid = np.repeat(np.arange(len(starts)), np.diff(self.cell_start))
        R = np.maximum.reduceat(np.linalg.norm(c - C[cid], axis=1) + r, starts)
        scale = float(np.abs(face_center).max() + face_radius.max()) if F else 1.0
        self.cell_center = C
        self.cell_radius = R * (1 + 1e-9) + 1e-12 * scale  #: slack for rounding: the query stays a superset
        self.face_center, self.face_radius = face_center, face_radius
        # face -> adjacent edge ids (CSR), and the free lines (no face)
        e = np.arange(len(edge_faces))
        pf = np.concatenate([edge_faces[:, 0], edge_faces[:, 1]])
        pe = np.concatenate([e, e])
        keep = pf >= 0
        pf, pe = pf[keep], pe[keep]
        o = np.lexsort((pe, pf))
        self.face_edges = pe[o]
        self.face_edge_start = np.searchsorted(pf[o], np.arange(F + 1)).astype(np.int64)
        self.free_edges = np.flatnonzero((edge_faces[:, 0] < 0) & (edge_faces[:, 1] < 0))
        self._cache: dict | None = None
        self.n_full = 0  #: full queries made (the others reused one)
        self.n_reused = 0

    # ------------------------------------------------------------------ queries
    def query(self, T_cam_model: np.ndarray, planes: np.ndarray, near: float, far: float,
              rot_deg: float = 0.0, trans_m: float = 0.0) -> np.ndarray:
        """Sorted face ids whose bounding sphere, inflated for a camera turn of up to ``rot_deg``
        and a move of up to ``trans_m`` metres, reaches into the frustum (a superset of the faces
        in the frustum at every such pose)."""
        m_rot = 2.0 * np.sin(np.radians(rot_deg) / 2.0)
        C = _to_cam(self.cell_center, T_cam_model)
        R = self.cell_radius * (1.0 + m_rot) + m_rot * np.linalg.norm(C, axis=1) + trans_m
        cells = np.flatnonzero(_spheres_in_frustum(C, R, planes, near, far))
        faces = csr_gather(self.cell_faces, self.cell_start, cells)
        if m_rot > 0 or trans_m > 0:
            c = _to_cam(self.face_center[faces], T_cam_model)
            r = self.face_radius[faces] * (1.0 + 1e-9) + m_rot * np.linalg.norm(c, axis=1) + trans_m
            faces = faces[_spheres_in_frustum(c, r, planes, near, far)]
        return np.sort(faces)

    def candidates(self, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int, near: float,
                   far: float) -> np.ndarray:
        """Sorted face ids: a superset of the faces in the frustum at ``T_cam_model``; the last
        full query's result while the reuse rule holds (module docstring)."""
        planes = frustum_planes(K, width, height)
        key = (np.round(planes, 9).tobytes(), float(near), float(far))
        R = T_cam_model[:3, :3]
        centre = camera_centre(T_cam_model)
        c = self._cache
        if c is not None and c["key"] == key:
            cos_th = (np.trace(matmul_exact(R, c["R"].T)) - 1.0) / 2.0
            th = np.degrees(np.arccos(np.clip(cos_th, -1.0, 1.0)))
            if th <= REUSE_ROT_DEG and norm3(centre - c["centre"]) <= c["trans_m"]:
                self.n_reused += 1
                return c["faces"]
        # the distance scale of the translation margin: the nearest geometry in view now
        Cc = _to_cam(self.cell_center, T_cam_model)
        inside = _spheres_in_frustum(Cc, self.cell_radius, planes, near, far)
        d_near = float(np.maximum(np.linalg.norm(Cc[inside], axis=1) - self.cell_radius[inside], near).min()) \
            if inside.any() else near
        trans_m = REUSE_TRANS_REL * d_near
        faces = self.query(T_cam_model, planes, near, far, REUSE_ROT_DEG, trans_m)
        self._cache = {"key": key, "R": R.copy(), "centre": centre, "trans_m": trans_m, "faces": faces}
        self.n_full += 1
        return faces

    def edges_of(self, faces: np.ndarray) -> np.ndarray:
        """Sorted unique edge ids adjacent to ``faces`` (face ids), with the free lines."""
        e = csr_gather(self.face_edges, self.face_edge_start, faces)
        return np.unique(np.concatenate([e, self.free_edges]))
