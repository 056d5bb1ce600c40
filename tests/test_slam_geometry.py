"""Unit tests of mst.pipeline.slam.geometry and the rgbd depth sampling (no rendering, no images)."""

from __future__ import annotations

import numpy as np

from mst.core.camera import Camera
from mst.core.poses import inv_T, se3_exp
from mst.core.poses import look_at as poses_look_at
from mst.pipeline import slam

CAM = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)


def look_at(C, target=(0.0, 0.0, 0.5), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_cam_world of a camera at C looking at target."""
    return inv_T(poses_look_at(C, target, up))


def test_pose_information_matches_numeric_jacobian():
    rng = np.random.default_rng(3)
    X_cam = rng.uniform([-1, -1, 2], [1, 1, 4], (20, 3))
    T0 = np.eye(4)
    J = np.zeros((40, 6))
    proj = lambda T: ((X_cam @ T[:3, :3].T + T[:3, 3])[:, :2] / (X_cam @ T[:3, :3].T + T[:3, 3])[:, 2:]  # noqa: E731
                      * [CAM.fx, CAM.fy]).ravel()
    for i in range(6):
        e = np.zeros(6)
        e[i] = 1e-6
        J[:, i] = (proj(se3_exp(e) @ T0) - proj(se3_exp(-e) @ T0)) / 2e-6
    assert np.allclose(slam.pose_information(CAM.K, X_cam), J.T @ J, rtol=1e-4, atol=1e-3)


def test_prior_covariance_is_reordered_to_rotation_first():
    W = np.diag([1.0, 2.0, 3.0, 10.0, 20.0, 30.0])  # (v, w)
    cov = slam.prior_covariance_wv(W, sigma_px=2.0)
    assert np.allclose(np.diag(cov), 4.0 / np.array([10.0, 20.0, 30.0, 1.0, 2.0, 3.0]), rtol=1e-6)


def test_prior_covariance_of_a_rank_deficient_information_is_finite():
    """One planar face observes 3 of 6 directions: the others get a large but finite variance."""
    W = np.diag([1e4, 1e4, 0.0, 0.0, 0.0, 1e4])
    cov = slam.prior_covariance_wv(W, sigma_px=1.0)
    assert np.isfinite(cov).all() and np.allclose(cov, cov.T)
    observed = np.diag(cov)[[3, 4, 2]]   # (w, v) order: v_x, v_y, w_z
    assert observed.max() < 1e-3 and np.diag(cov)[[0, 1, 5]].min() > 1e3 * observed.max()


def test_triangulate_two_view_recovers_points():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (50, 3))
    T1, T2 = look_at([3, 0, 1]), look_at([3, 0.5, 1.2])
    x1 = (X @ T1[:3, :3].T + T1[:3, 3])
    x2 = (X @ T2[:3, :3].T + T2[:3, 3])
    Xt = slam.triangulate_two_view(T1[:3], T2[:3], x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:])
    assert np.abs(Xt - X).max() < 1e-9


def test_bilinear_depth_interpolates_and_refuses_holes():
    D = np.array([[1.0, 2.0, 3.0], [2.0, 3.0, 4.0], [0.0, 4.0, 5.0]], np.float32)
    d = slam.bilinear_depth(D, np.array([0.5, 1.0, 0.5]), np.array([0.5, 0.0, 1.5]))
    assert d[0] == 2.0 and d[1] == 2.0   # the mean of a 2x2 plane; a pixel centre exactly
    assert np.isnan(d[2])                 # one of the 4 neighbours has no depth
