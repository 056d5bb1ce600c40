"""A tiny shaded renderer for tracker tests (faces Lambert-shaded, a ground plane, 2x supersampling).

Used while ``mst.pipeline.synth`` is not available and for fast, small sequences: ground-truth
poses ``T_cam_model`` (model -> camera), images 8-bit BGR, pixel centres at integer coordinates.
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import inv_T
from mst.core.poses import look_at as poses_look_at


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_cam_model`` of a camera at ``eye`` looking at ``target`` (model frame z up)."""
    return inv_T(poses_look_at(eye, target, up))


def render_views(model, cam, poses, seed: int = 0, ground: float | None = 0.0, noise: float = 2.0) -> list[np.ndarray]:
    """Render ``model`` (PolygonModel) from each ``T_cam_model`` in ``poses`` -> list of BGR uint8."""
    import cv2

    from mst.core.camera import Camera
    from mst.pipeline.render import Renderer

    V, F = model.triangulate()
    V = np.asarray(V, float)
    F = np.asarray(F, np.int64)
    nb = len(F)
    if ground is not None:
        c = V.mean(0)
        s = 20 * float(np.ptp(V, axis=0).max())
        G = np.array([[c[0] - s, c[1] - s, ground], [c[0] + s, c[1] - s, ground], [c[0] + s, c[1] + s, ground],
                      [c[0] - s, c[1] + s, ground]])
        F = np.concatenate([F, np.array([[0, 1, 2], [0, 2, 3]]) + len(V)])
        V = np.concatenate([V, G - [0, 0, 1e-3]])
    r = Renderer(V, F)
    n = r.normals
    rng = np.random.default_rng(seed)
    # per-face albedo from the face's plane (coplanar triangles share it)
    key = np.round(np.concatenate([n, (n * V[F[:, 0]]).sum(1, keepdims=True)], 1), 3)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    alb = rng.uniform(0.7, 1.0, inv.max() + 1)[inv.ravel()]
    light = np.array([0.4, 0.3, 0.85])
    light /= np.linalg.norm(light)
    shade = 0.5 + 0.5 * np.abs(n @ light)
    col = np.clip(alb * shade, 0, 1) * 230 + 10
    if ground is not None:
        col[nb:] = 40.0
    cam2 = Camera(cam.fx * 2, cam.fy * 2, (cam.cx + 0.5) * 2 - 0.5, (cam.cy + 0.5) * 2 - 0.5, cam.width * 2, cam.height * 2)
    out = []
    for T in poses:
        ids = r.render_face_ids(cam2, T)
        img = np.where(ids >= 0, col[np.maximum(ids, 0)], 200.0).astype(np.float32)
        img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        img = img + rng.normal(0, noise, img.shape).astype(np.float32)
        g = np.clip(img, 0, 255).astype(np.uint8)
        out.append(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
    return out


def orbit_poses(center, radius: float, height: float, n: int, deg_per_frame: float, start_deg: float = -60.0):
    """Camera poses on a horizontal circle around ``center`` looking at it."""
    c = np.asarray(center, float)
    out = []
    for k in range(n):
        a = np.radians(start_deg + k * deg_per_frame)
        eye = c + [radius * np.cos(a), radius * np.sin(a), height]
        out.append(look_at(eye, c))
    return out


def render_textured(model, cam, poses, seed=0, noise=2.0, cell=0.06):
    """Gray renders of ``model`` with per-face shading plus a random checker texture fixed on its
    surface (a turned 3D grid of cells ``cell`` x the model size, one random gray each: corners for
    keypoints, and no symmetry, so that the mirror image differs), over a dark ground plane (z = 0) and a bright
    background; 2x supersampled. Poses ``T_cam_model``; (H, W) uint8 each."""
    import cv2

    from mst.core.camera import Camera
    from mst.pipeline.render import Renderer

    V, F = model.triangulate()
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    nb = len(F)
    c, s = V.mean(0), 20 * float(np.ptp(V, axis=0).max())
    G = np.array([[c[0] - s, c[1] - s, 0], [c[0] + s, c[1] - s, 0], [c[0] + s, c[1] + s, 0], [c[0] - s, c[1] + s, 0]])
    r = Renderer(np.r_[V, G - [0, 0, 1e-3]], np.r_[F, np.array([[0, 1, 2], [0, 2, 3]]) + len(V)])
    n = r.normals[:nb]
    rng = np.random.default_rng(seed)
    light = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
    face_col = 60 + 120 * (0.5 + 0.5 * np.abs(n @ light))
    size = float(np.ptp(V, axis=0).max())
    lut = rng.uniform(-60.0, 60.0, 4096)
    shift = rng.random(3)  # the cell grid off the face planes ...
    Rg = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # ... and turned: no cell border parallel to a model edge
    cam2 = Camera(cam.fx * 2, cam.fy * 2, (cam.cx + 0.5) * 2 - 0.5, (cam.cy + 0.5) * 2 - 0.5, cam.width * 2, cam.height * 2)
    K2 = cam2.K
    vv, uu = np.mgrid[0:cam2.height, 0:cam2.width]
    out = []
    for T in poses:
        z, ids = r.render_depth_ids(cam2, T)
        img = np.where(ids >= nb, 40.0, 200.0).astype(np.float32)
        obj = (ids >= 0) & (ids < nb)
        Xc = np.stack([(uu[obj] - K2[0, 2]) / K2[0, 0] * z[obj], (vv[obj] - K2[1, 2]) / K2[1, 1] * z[obj], z[obj]], 1)
        X = (Xc - T[:3, 3]) @ T[:3, :3]
        q = np.floor(X @ Rg.T / (cell * size) + shift).astype(np.int64)
        h = (q[:, 0] * 73856093) ^ (q[:, 1] * 19349663) ^ (q[:, 2] * 83492791)
        img[obj] = face_col[ids[obj]] + lut[h % 4096]
        img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        img += rng.normal(0, noise, img.shape).astype(np.float32)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out
