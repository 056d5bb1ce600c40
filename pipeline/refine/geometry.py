"""Geometry of ``mst refine``: depth samples of a keyframe (camera frame), the model's surface
samples with normals (model frame), point-to-mesh distances (Open3D ray casting), robust
point-to-plane ICP (Tukey IRLS on a k-d tree of the model samples, built once: Open3D's
``registration_icp`` rebuilds the target's tree on every call, 14 ms for 50k samples, which was 80 %
of a 400-keyframe run).

Frames: ``T_model_cam`` maps camera-frame points (x right, y down, z forward, metres) into the
model frame. Open3D is imported inside the functions (``mst --help`` must not load it).
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import se3_exp, transform_points


def backproject(depth_m: np.ndarray, cam, step: int, min_m: float, max_m: float,
                edge_rel: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Depth image (metres, 0 = none) -> camera-frame points (n, 3) on a pixel grid of ``step`` and
    their unit surface normals (n, 3), facing the camera.

    A normal is the cross product of the central differences to the four grid neighbours; samples
    without four valid neighbours, or on a depth discontinuity (a neighbour's depth differs by more
    than ``edge_rel`` x depth x step, the slope a grazing surface may have), are dropped, as are
    depths outside [min_m, max_m]. Lens distortion (when the camera has any) is removed from the
    pixel coordinates with OpenCV.
    """
    h, w = depth_m.shape
    v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
    z = depth_m[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z >= min_m) & (z <= max_m)
    z = np.where(ok, z, 0.0)
    uf, vf = u.astype(np.float64).ravel(), v.astype(np.float64).ravel()
    if len(cam.dist) and np.any(cam.dist != 0):
        import cv2

        xy = cv2.undistortPoints(np.stack([uf, vf], 1)[:, None, :], cam.K, cam.dist)[:, 0, :]
        x, y = xy[:, 0].reshape(u.shape), xy[:, 1].reshape(u.shape)
    else:
        x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    P = np.stack([x * z, y * z, z], -1)
    # central differences on the grid (interior samples only)
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    zc = z[1:-1, 1:-1]
    nb = np.stack([z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]])
    good = ok[1:-1, 1:-1] & (nb > 0).all(0) & (np.abs(nb - zc).max(0) <= edge_rel * step * zc)
    N = np.cross(du, dv)
    nn = np.linalg.norm(N, axis=-1)
    good &= nn > 0
    Pc, N, nn = P[1:-1, 1:-1][good], N[good], nn[good]
    N = N / nn[:, None]
    N = np.where(((N * Pc).sum(1) > 0)[:, None], -N, N)  # towards the camera
    return Pc, N


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
    """The model as ICP target (sampled points + normals, a k-d tree) and as exact distance field (Open3D ray casting)."""

    def __init__(self, V: np.ndarray, F: np.ndarray, n_samples: int, seed: int):
        import open3d as o3d
        from scipy.spatial import cKDTree

        self._o3d = o3d
        self.X, self.N = sample_surface(V, F, n_samples, seed)
        self.tree = cKDTree(self.X)
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

    def near(self, X_model: np.ndarray, d: float) -> np.ndarray:
        """(n,) bool: a model sample lies within ``d`` (m) of the point (the coarse test before ICP)."""
        return np.isfinite(self.tree.query(X_model, distance_upper_bound=d)[0])

    def icp(self, P_cam: np.ndarray, N_cam: np.ndarray, T_model_cam: np.ndarray, max_dists: tuple, tukey_m: float,
            iterations: int, max_normal_deg: float = 30.0):
        """Robust point-to-plane ICP of camera-frame points onto the model, coarse to fine.

        Gauss-Newton on a left increment ``exp(xi) @ T`` (model frame, ``xi`` = (v, w) as in
        :func:`mst.core.poses.se3_exp`) with Tukey weights of width ``tukey_m``; nearest model
        samples within each of ``max_dists`` (the k-d tree of the model samples is built once),
        kept only where the sample's normal ``N_cam`` (camera frame) and the model's differ by less
        than ``max_normal_deg`` (the floor next to a wall does not pull the wall).
        Returns ``(T_model_cam, n_inliers, sigma_m, info)``: ``sigma_m`` the robust spread (1.4826
        MAD) of the final point-to-plane residuals, ``info`` = JᵀJ of the inlier residuals (unit
        weight; a view of one plane leaves the sliding directions unconstrained, as they are).
        """
        T = np.asarray(T_model_cam, np.float64)
        P_cam = np.asarray(P_cam, np.float64)
        cos_max = np.cos(np.radians(max_normal_deg))
        J = r = np.zeros((0, 6))
        for d in max_dists:
            for _ in range(iterations):
                p = transform_points(T, P_cam)
                dist, j = self.tree.query(p, distance_upper_bound=d)
                ok = np.isfinite(dist)
                ok[ok] = np.abs(((N_cam[ok] @ T[:3, :3].T) * self.N[j[ok]]).sum(1)) >= cos_max
                if ok.sum() < 6:
                    return T, 0, float("inf"), np.zeros((6, 6))
                p, q, n = p[ok], self.X[j[ok]], self.N[j[ok]]
                r = ((p - q) * n).sum(1)  # point-to-plane residuals, m
                # d r / d(v, w) of a left increment p -> p + w x p + v: (n, p x n)
                J = np.concatenate([n, np.cross(p, n)], axis=1)
                w = np.where(np.abs(r) < tukey_m, (1 - (r / tukey_m) ** 2) ** 2, 0.0)
                H = (J * w[:, None]).T @ J
                g = (J * w[:, None]).T @ r
                try:
                    xi = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
                except np.linalg.LinAlgError:
                    break
                T = se3_exp(xi) @ T
                if np.linalg.norm(xi[:3]) < 1e-6 * d and np.linalg.norm(xi[3:]) < 1e-7:
                    break
        inl = np.abs(r) < tukey_m
        if inl.sum() < 6:
            return T, 0, float("inf"), np.zeros((6, 6))
        sigma = float(1.4826 * np.median(np.abs(r[inl] - np.median(r[inl]))))
        return T, int(inl.sum()), sigma, J[inl].T @ J[inl]


def fused_points(clouds: list[np.ndarray], poses: np.ndarray, rotate_only: bool = False) -> np.ndarray:
    """The keyframes' camera-frame samples (or, ``rotate_only``, their normals) placed with ``poses``
    (T_model_cam): one model-frame array."""
    if not clouds:
        return np.zeros((0, 3))
    if rotate_only:
        return np.concatenate([P @ T[:3, :3].T for T, P in zip(poses, clouds)])
    return np.concatenate([transform_points(T, P) for T, P in zip(poses, clouds)])
