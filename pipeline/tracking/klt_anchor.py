"""Where the hybrid tracker's KLT points sit on the model: their face planes, and their re-anchoring.

A KLT corner's model point is lifted from the inverse depth buffer at the pose of its detection, so
it carries that pose's error. Anchored there (ViSP's ``vpMbKltTracker`` keeps the points until it
detects again), every later frame is pulled towards the detection pose, and an error of that one
frame persists until the next detection (up to 30 frames). Re-anchored at every accepted pose
(:func:`reanchor_on_planes`: the tracked pixel cast onto the point's face plane), the points constrain
only the motion since the last frame, and a past error decays as the edges pull the pose back. The
tracker (``klt.reanchor mean``, the default) keeps each point at the running mean of its casts under
the detection pose and every pose output since as the model's (not under a pose the error budget
withheld, nor a map pose): each such pose counts once (README, tracking).

Every dot product is summed in a fixed order (:func:`_dot3`, no BLAS or einsum, whose order depends on
the CPU), as the tracker's other rounding-sensitive arithmetic (``mst.pipeline.tracking.exact``).
"""

from __future__ import annotations

import numpy as np

#: above this many candidate faces the nearest planes are searched among each point's nearest face
#: centres (a k-d tree) instead of every face
TREE_MIN_FACES = 20_000
#: face centres a point's plane is chosen among, on the tree path
TREE_K = 16


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a . b`` over the last axis (length 3, broadcast), summed as ``(a0 b0 + a1 b1) + a2 b2``."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def nearest_face_planes(geom, X_model: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
    """The plane of the face nearest to each point: ``(M, 4)`` rows ``(n, d)`` with ``n . X = d``
    (model frame, ``n`` the unit outward normal, ``d`` metres).

    ``X_model`` (M, 3) metres, points on the model's surface (KLT corners lifted from the depth buffer);
    ``faces`` (F,) bool, the faces to choose from (those rendered into that buffer; all when None).
    Nearest by the distance to the face's plane: at a crease both planes pass through the point, and
    coplanar faces share one plane, so the choice between them does not matter. Up to
    :data:`TREE_MIN_FACES` candidates, every one is tested (M x F distances in blocks of at most ~4M:
    ~1 ms for 300 points against the ~700 faces of a city block in view); above (a scanned or
    render-tracked mesh of small triangles, where 300 x 100k took 0.3 s), the :data:`TREE_K` faces
    whose centres are nearest the point (a k-d tree over the face centres, built once per model),
    which hold the small triangle under it.
    """
    X = np.asarray(X_model, np.float64).reshape(-1, 3)
    N, P = geom.face_normals, geom.face_point
    ids = np.arange(len(N)) if faces is None else np.flatnonzero(faces)
    if not len(X) or not len(ids):
        return np.zeros((len(X), 4))
    if len(ids) > TREE_MIN_FACES:
        best = _nearest_by_tree(geom, X, ids)
    else:
        n = N[ids]
        d = _dot3(n, P[ids])
        best = np.empty(len(X), np.int64)
        step = max(1, 4_000_000 // len(ids))  # points per block
        for i in range(0, len(X), step):
            best[i:i + step] = ids[np.argmin(np.abs(_dot3(X[i:i + step, None, :], n[None]) - d), axis=1)]
    return np.column_stack([N[best], _dot3(N[best], P[best])])


def _nearest_by_tree(geom, X: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Per point, the face of ``ids`` nearest by plane distance among its :data:`TREE_K` nearest face
    centres (all faces' centres in the tree; a point whose neighbours are all outside ``ids`` takes the
    nearest of them)."""
    from scipy.spatial import cKDTree

    tree = geom.__dict__.get("_face_center_tree")
    if tree is None:
        tree = geom.__dict__["_face_center_tree"] = cKDTree(geom.face_point)
    k = min(TREE_K, len(geom.face_point))
    _, nb = tree.query(X, k=k)
    nb = np.asarray(nb, np.int64).reshape(len(X), k)
    N, P = geom.face_normals, geom.face_point
    dist = np.abs(_dot3(N[nb], X[:, None, :]) - _dot3(N[nb], P[nb]))
    allowed = np.zeros(len(N), bool)
    allowed[ids] = True
    dist = np.where(allowed[nb], dist, np.inf)
    return nb[np.arange(len(X)), np.argmin(dist, axis=1)]


def reanchor_on_planes(uv_px: np.ndarray, planes: np.ndarray, T_cam_model: np.ndarray, K: np.ndarray,
                       X_model: np.ndarray, min_cos: float = 0.02) -> np.ndarray:
    """The model points ``(M, 3)`` seen at pixels ``uv_px`` (M, 2) under ``T_cam_model``: each pixel's
    ray (``K`` 3x3) cast onto its plane ``planes`` (M, 4) ``(n, d)``, model frame, metres.

    Where the ray meets its plane at a grazing angle (``|cos| < min_cos`` between ray and normal) or
    behind the camera, the point keeps its given model point ``X_model`` (M, 3).
    """
    uv = np.asarray(uv_px, np.float64).reshape(-1, 2)
    X_old = np.asarray(X_model, np.float64).reshape(-1, 3)
    if not len(uv):
        return X_old.copy()
    R = T_cam_model[:3, :3]
    C = -_dot3(R.T, T_cam_model[:3, 3])  # the camera centre in the model frame: -R^T t
    rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])
    D = _dot3(rays[:, None, :], R.T[None])  # R^T ray for each row: the directions in the model frame
    n, d = planes[:, :3], planes[:, 3]
    nD = _dot3(n, D)
    cos = np.abs(nD) / np.sqrt(_dot3(D, D))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (d - _dot3(n, C)) / nD
    ok = (cos >= min_cos) & (s > 0) & np.isfinite(s)
    out = X_old.copy()
    out[ok] = C + s[ok, None] * D[ok]
    return out
