"""Geometry of ``mst refine``: depth samples of a keyframe (camera frame), the model's surface
samples with normals (model frame), point-to-mesh distances, robust point-to-plane ICP (Open3D).

Frames: ``T_model_cam`` maps camera-frame points (x right, y down, z forward, metres) into the
model frame. Open3D is imported inside the functions (``mst --help`` must not load it).
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import transform_points


def backproject(depth_m: np.ndarray, cam, step: int, min_m: float, max_m: float) -> np.ndarray:
    """Depth image (metres, 0 = none) -> (n, 3) camera-frame points on a pixel grid of ``step``.

    Pixels with a depth outside [min_m, max_m] are dropped; lens distortion (when the camera has
    any) is removed from the pixel coordinates with OpenCV.
    """
    h, w = depth_m.shape
    v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
    z = depth_m[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z >= min_m) & (z <= max_m)
    u, v, z = u[ok].astype(np.float64), v[ok].astype(np.float64), z[ok]
    if len(cam.dist) and np.any(cam.dist != 0):
        import cv2

        xy = cv2.undistortPoints(np.stack([u, v], 1)[:, None, :], cam.K, cam.dist)[:, 0, :]
        x, y = xy[:, 0], xy[:, 1]
    else:
        x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    return np.stack([x * z, y * z, z], 1)


def sample_surface(V: np.ndarray, F: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly by area on the triangles (model frame) and their face normals."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cr = np.cross(B - A, C - A)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    keep = area > 0
    A, B, C, cr, area = A[keep], B[keep], C[keep], cr[keep], area[keep]
    rng = np.random.default_rng(seed)
    f = rng.choice(len(area), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    X = (1 - s)[:, None] * A[f] + (s * (1 - r2))[:, None] * B[f] + (s * r2)[:, None] * C[f]
    N = cr[f] / (2 * area[f])[:, None]
    return X, N


class ModelSurface:
    """The model as ICP target (sampled points + normals) and as exact distance field (ray casting)."""

    def __init__(self, V: np.ndarray, F: np.ndarray, n_samples: int, seed: int):
        import open3d as o3d

        self._o3d = o3d
        X, N = sample_surface(V, F, n_samples, seed)
        self.target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(X))
        self.target.normals = o3d.utility.Vector3dVector(N)
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(np.asarray(V, np.float32))
        mesh.triangle.indices = o3d.core.Tensor(np.asarray(F, np.int32))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)

    def distance(self, X_model: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) of each model-frame point to the nearest triangle."""
        if not len(X_model):
            return np.zeros(0)
        q = self._o3d.core.Tensor(np.asarray(X_model, np.float32))
        return self.scene.compute_distance(q).numpy().astype(np.float64)

    def icp(self, P_cam: np.ndarray, T_model_cam: np.ndarray, max_dists: tuple, tukey_m: float, iterations: int):
        """Robust point-to-plane ICP of camera-frame points onto the model, coarse to fine.

        Returns ``(T_model_cam, fitness, n_inliers, rmse_m, info)``: ``rmse_m`` of the final
        point-to-plane residuals, ``info`` = JᵀJ of those residuals for a left increment
        ``exp(xi) @ T`` in the model frame, ordered (v, w) like :func:`mst.core.poses.se3_exp` (unit
        weight; a view of one plane leaves the sliding directions unconstrained, as they are).
        """
        o3d = self._o3d
        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P_cam))
        est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=tukey_m))
        crit = reg.ICPConvergenceCriteria(max_iteration=iterations)
        T = np.asarray(T_model_cam, np.float64)
        res = None
        for d in max_dists:
            res = reg.registration_icp(src, self.target, d, T, est, crit)
            T = np.asarray(res.transformation)
        corr = np.asarray(res.correspondence_set, dtype=np.int64).reshape(-1, 2)
        p = transform_points(T, P_cam[corr[:, 0]])
        q = np.asarray(self.target.points)[corr[:, 1]]
        n = np.asarray(self.target.normals)[corr[:, 1]]
        r = ((p - q) * n).sum(1)  # point-to-plane residuals, m
        # d r / d(v, w) of a left increment p -> p + w x p + v: (n, p x n)
        J = np.concatenate([n, np.cross(p, n)], axis=1)
        info = J.T @ J
        n_in = len(corr)
        # robust spread (1.4826 MAD): the scene next to the model leaves a few far correspondences
        rmse = float(1.4826 * np.median(np.abs(r - np.median(r)))) if n_in else float("inf")
        return T, float(res.fitness), n_in, rmse, info


def fused_points(clouds: list[np.ndarray], poses: np.ndarray) -> np.ndarray:
    """The keyframes' camera-frame samples placed with ``poses`` (T_model_cam): one model-frame cloud."""
    if not clouds:
        return np.zeros((0, 3))
    return np.concatenate([transform_points(T, P) for T, P in zip(poses, clouds)])
