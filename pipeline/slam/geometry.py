"""Pose geometry of the SLAM aid: the 6x6 pose information of points, its prior covariance in
COLMAP's order, two-view (DLT) triangulation, the regularised 6x6 inverse.

Twists and ``W`` are in the order ``(v, w)`` (translation then rotation) as
:func:`mst.core.poses.se3_exp`; perturbations on the left: ``T = exp(delta) @ T0``.
"""

from __future__ import annotations

import numpy as np


def pose_information(K: np.ndarray, X_cam: np.ndarray) -> np.ndarray:
    """6x6 information ``J^T J`` (pixels^-2 units up to sigma^2) of a pose from points ``X_cam`` (N,3).

    ``J`` (2N x 6) is the derivative of the pixel projection with respect to a left perturbation
    ``exp(delta) @ T_cam_model``, ``delta = (v, w)``.
    """
    X = np.asarray(X_cam, float)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    iz = 1.0 / z
    fx, fy = K[0, 0], K[1, 1]
    o = np.zeros_like(z)
    # d(u)/d(X_cam) then d(X_cam)/d(delta) = [I, -[X]x]
    Ju = np.stack([fx * iz, o, -fx * x * iz**2, -fx * x * y * iz**2, fx * (1 + x * x * iz**2), -fx * y * iz], 1)
    Jv = np.stack([o, fy * iz, -fy * y * iz**2, -fy * (1 + y * y * iz**2), fy * x * y * iz**2, fy * x * iz], 1)
    return Ju.T @ Ju + Jv.T @ Jv


def vw_to_wv(M: np.ndarray) -> np.ndarray:
    """Reorder a 6x6 matrix from twist order (v, w) to (w, v) (COLMAP's prior residual order)."""
    p = [3, 4, 5, 0, 1, 2]
    return M[np.ix_(p, p)]


def prior_covariance_wv(W: np.ndarray, sigma_px: float) -> np.ndarray:
    """Covariance in COLMAP's (rotation, translation) order from an information ``W`` in (v, w) order.

    ``cov = sigma^2 (W + eps I)^-1`` with a small relative regularisation so that a rank-deficient W
    (e.g. one planar face) gives a large but finite variance in the unobserved directions.
    """
    W = 0.5 * (np.asarray(W, float) + np.asarray(W, float).T)
    eps = 1e-9 * max(np.trace(W), 1e-12)
    cov = sigma_px**2 * np.linalg.inv(W + eps * np.eye(6))
    cov = 0.5 * (cov + cov.T)
    return vw_to_wv(cov)


def triangulate_two_view(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of N points from two views.

    ``P1``/``P2``: (N, 3, 4) or (3, 4) normalised projection matrices ``[R | t]`` (model -> camera);
    ``x1``/``x2``: (N, 2) normalised image coordinates. Returns (N, 3) model points.
    """
    P1 = np.broadcast_to(P1, (len(x1), 3, 4))
    P2 = np.broadcast_to(P2, (len(x1), 3, 4))
    A = np.stack([x1[:, :1] * P1[:, 2] - P1[:, 0], x1[:, 1:2] * P1[:, 2] - P1[:, 1],
                  x2[:, :1] * P2[:, 2] - P2[:, 0], x2[:, 1:2] * P2[:, 2] - P2[:, 1]], axis=1)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:4]


def regularised_6x6(M: np.ndarray) -> np.ndarray:
    """A symmetric 6x6 matrix with a tiny relative ridge (safe to invert when rank-deficient)."""
    M = 0.5 * (M + M.T)
    return M + 1e-9 * max(float(np.trace(M)), 1e-12) * np.eye(6)
