"""Where the hybrid tracker's KLT points sit (:mod:`mst.pipeline.tracking.klt_anchor`): their face
planes, their re-anchoring at an accepted pose, and what re-anchoring does to an error of the
detection pose (the 20 cm cube of ``test_vvs``, exact edge matches, the solver itself)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_vvs import K, _corner_px, _cube, _lifted_under_a_wrong_pose, _project, _start, _true_pose  # noqa: E402

from mst.core.poses import inv_T  # noqa: E402
from mst.meshtools.generate import box_model  # noqa: E402
from mst.pipeline.tracking.klt_anchor import nearest_face_planes, reanchor_on_planes  # noqa: E402
from mst.pipeline.tracking.visibility import ModelGeometry  # noqa: E402
from mst.pipeline.tracking.vvs import solve_pose  # noqa: E402


def _cube_geometry():
    return ModelGeometry.from_model(box_model((0.2, 0.2, 0.2), (-0.1, -0.1, -0.1)))


def _points_on_faces(rng, n):
    """``n`` points on the 20 cm cube's faces (model frame) and the axis of each one's face."""
    X = rng.uniform(-0.09, 0.09, (n, 3))
    axis = rng.integers(0, 3, n)
    X[np.arange(n), axis] = rng.choice([-0.1, 0.1], n)
    return X, axis


def test_each_point_gets_the_plane_of_its_face():
    g = _cube_geometry()
    X, axis = _points_on_faces(np.random.default_rng(0), 50)
    P = nearest_face_planes(g, X)
    assert P.shape == (50, 4)
    # the plane holds the point, its normal is the face's outward axis
    assert np.abs(np.einsum("mk,mk->m", P[:, :3], X) - P[:, 3]).max() < 1e-12
    want = np.zeros((50, 3))
    want[np.arange(50), axis] = np.sign(X[np.arange(50), axis])
    assert np.abs(P[:, :3] - want).max() < 1e-12
    # only the faces offered are chosen from: with the +x face alone every plane is x = 0.1
    only = np.abs(g.face_normals[:, 0] - 1.0) < 1e-9
    P1 = nearest_face_planes(g, X, only)
    assert np.allclose(P1, [1.0, 0.0, 0.0, 0.1])
    assert nearest_face_planes(g, np.zeros((0, 3))).shape == (0, 4)


def test_reanchoring_casts_the_pixel_onto_the_plane():
    """At the pose where a point is seen, its pixel cast onto its plane is the point itself, whatever
    model point it carried before; a ray that grazes its plane or meets it behind the camera keeps
    the old point."""
    g = _cube_geometry()
    X, _ = _points_on_faces(np.random.default_rng(1), 60)
    T = _true_pose()
    P = nearest_face_planes(g, X)
    uv = _project(T, X)
    X_old = X + np.random.default_rng(2).normal(0, 0.003, X.shape)  # lifted under another pose
    front = (X @ T[:3, :3].T + T[:3, 3])[:, 2] > 0
    got = reanchor_on_planes(uv, P, T, K, X_old)
    assert np.abs(got - X).max() < 1e-9
    # a plane seen edge-on (it holds the ray) and a plane 1 m behind the camera: the old point stays
    C = inv_T(T)[:3, 3]
    ray = (X[0] - C) / np.linalg.norm(X[0] - C)
    n_edge = np.cross(ray, [0.0, 0.0, 1.0])
    n_edge /= np.linalg.norm(n_edge)
    P_bad = np.array([[*n_edge, n_edge @ X[0]], [*ray, ray @ (C - ray)]])
    kept = reanchor_on_planes(uv[[0, 0]], P_bad, T, K, X_old[:2])
    assert np.array_equal(kept, X_old[:2]) and front.all()
    assert reanchor_on_planes(np.zeros((0, 2)), np.zeros((0, 4)), T, K, np.zeros((0, 3))).shape == (0, 3)


def _detection_error_over_frames(alpha: float, seed: int, frames: int = 20) -> np.ndarray:
    """A still camera, exact edge matches, 200 KLT points tracked exactly but lifted under a
    detection pose ~3 mm / 0.3 deg off; each frame solved with the KLT information cap (1) and the
    points then moved ``alpha`` of the way to their re-anchored position (the tracker's
    ``klt.reanchor``). Returns each frame's corner error over the detection pose's (image px)."""
    X, edge, A, B = _cube()
    T_true = _true_pose()
    rng = np.random.default_rng(seed)
    Xk, _ = _points_on_faces(rng, 200)
    T_det, Xk_model, uk = _lifted_under_a_wrong_pose(rng, Xk, T_true)
    planes = nearest_face_planes(_cube_geometry(), Xk_model)

    def corner_px(T):
        return _corner_px(T, T_true)

    T, out = _start(T_true), []
    for _ in range(frames):
        res = solve_pose(T, K, X, edge, A, B, _project(T_true, X)[:, None, :], min_mad_px=0.3, iters=50,
                         klt_X_model=Xk_model, klt_uv=uk, klt_info_cap=1.0)
        assert res.has_pose
        T = res.T_cam_model
        out.append(corner_px(T) / corner_px(T_det))
        if alpha > 0:
            X1 = reanchor_on_planes(uk, planes, T, K, Xk_model)
            Xk_model = Xk_model + alpha * (X1 - Xk_model)
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_error_of_the_detection_pose_decays_only_when_reanchored(seed):
    """Anchored at detection (``reanchor`` 0, ViSP's way), about half of the detection pose's error
    stays in every frame (equal information: one half; within 0.3-0.7 for the Tukey weights and
    blocks that are not proportional), unchanged over 40 frames. Re-anchored by ``a`` a frame, the
    anchor moves ``a`` of the way to the fused pose, which keeps the share ``rho`` of the anchor's
    error in each direction (``rho`` the KLT points' share of the information there: 1/2 where the
    two blocks are proportional, at most 0.8 here): the error shrinks by ``1 - a (1 - rho)`` a frame
    or faster, monotonically. Bounds from rho = 0.8: with a = 0.2, 0.96^39 = 0.2 of the first
    frame's after 40 frames (bound 0.25); fully re-anchored (the frame-to-frame case), 0.8^9 = 0.13
    after 10 frames (bound 0.15)."""
    kept = _detection_error_over_frames(0.0, seed, frames=40)
    assert (kept >= 0.3).all() and (kept <= 0.7).all(), kept
    assert abs(kept[-1] - kept[0]) < 0.02 * kept[0]  # it persists
    leaky = _detection_error_over_frames(0.2, seed, frames=40)
    assert abs(leaky[0] - kept[0]) < 1e-12  # the first frame is the same solve
    assert leaky[-1] <= 0.25 * leaky[0], leaky
    assert (np.diff(leaky) <= 0.01 * leaky[0]).all(), leaky
    full = _detection_error_over_frames(1.0, seed, frames=10)
    assert full[-1] <= 0.15 * full[0] and (np.diff(full) <= 0.01 * full[0]).all(), full


def test_the_tree_search_of_a_fine_mesh_finds_the_plane_under_each_point(monkeypatch):
    """A mesh of many small triangles (the 20 cm cube cut into 1,536 triangles, each face a flat
    lattice) takes the k-d tree path (its threshold lowered to 100 faces for the test): each point's
    plane holds it, with its face's outward normal, as the exhaustive search finds; points offered
    no face near them take the nearest allowed one."""
    import mst.pipeline.tracking.klt_anchor as ka
    from mst.meshtools.generate import model_to_tin
    from mst.meshtools.model import PolygonModel

    V, F = model_to_tin(box_model((0.2, 0.2, 0.2), (-0.1, -0.1, -0.1)), split=16)
    g = ModelGeometry.from_model(PolygonModel(V, [f for f in F]))
    assert len(g.faces) > 1000
    X, axis = _points_on_faces(np.random.default_rng(3), 80)
    exhaustive = nearest_face_planes(g, X)
    monkeypatch.setattr(ka, "TREE_MIN_FACES", 100)
    tree = nearest_face_planes(g, X)
    assert np.abs(np.einsum("mk,mk->m", tree[:, :3], X) - tree[:, 3]).max() < 1e-12
    assert np.abs(tree - exhaustive).max() < 1e-9
    want = np.zeros((80, 3))
    want[np.arange(80), axis] = np.sign(X[np.arange(80), axis])
    assert np.abs(tree[:, :3] - want).max() < 1e-12
