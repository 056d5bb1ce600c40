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
    assert ((X @ T[:3, :3].T + T[:3, 3])[:, 2] > 0).all()  # the premise: every point in front of the camera
    got = reanchor_on_planes(uv, P, T, K, X_old)
    assert np.abs(got - X).max() < 1e-9
    # a plane seen edge-on (it holds the ray) and a plane 1 m behind the camera: the old point stays
    C = inv_T(T)[:3, 3]
    ray = (X[0] - C) / np.linalg.norm(X[0] - C)
    n_edge = np.cross(ray, [0.0, 0.0, 1.0])
    n_edge /= np.linalg.norm(n_edge)
    P_bad = np.array([[*n_edge, n_edge @ X[0]], [*ray, ray @ (C - ray)]])
    kept = reanchor_on_planes(uv[[0, 0]], P_bad, T, K, X_old[:2])
    assert np.array_equal(kept, X_old[:2])
    assert reanchor_on_planes(np.zeros((0, 2)), np.zeros((0, 4)), T, K, np.zeros((0, 3))).shape == (0, 3)


def _detection_error_over_frames(rule, seed: int, frames: int = 20) -> np.ndarray:
    """A still camera, exact edge matches, 200 KLT points tracked exactly but lifted under a
    detection pose ~3 mm / 0.3 deg off; each frame solved with the KLT information cap (1), then the
    points re-anchored by ``rule``: "off" (kept as lifted), "mean" (the tracker's ``klt.reanchor``:
    after the k-th frame since detection they move 1/(k+1) of the way to their pixels cast onto their
    planes, the running mean over the detection pose and the k poses since) or a constant share.
    Returns each frame's corner error over the detection pose's (image px)."""
    X, edge, A, B = _cube()
    T_true = _true_pose()
    rng = np.random.default_rng(seed)
    Xk, _ = _points_on_faces(rng, 200)
    T_det, Xk_model, uk = _lifted_under_a_wrong_pose(rng, Xk, T_true)
    planes = nearest_face_planes(_cube_geometry(), Xk_model)
    T, out = _start(T_true), []
    for k in range(1, frames + 1):
        res = solve_pose(T, K, X, edge, A, B, _project(T_true, X)[:, None, :], min_mad_px=0.3, iters=50,
                         klt_X_model=Xk_model, klt_uv=uk, klt_info_cap=1.0)
        assert res.has_pose
        T = res.T_cam_model
        out.append(_corner_px(T, T_true) / _corner_px(T_det, T_true))
        if rule != "off":
            share = 1.0 / (k + 1) if rule == "mean" else float(rule)
            Xk_model = Xk_model + share * (reanchor_on_planes(uk, planes, T, K, Xk_model) - Xk_model)
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_error_of_the_detection_pose_decays_only_when_reanchored(seed):
    """Anchored at detection (``reanchor off``, ViSP's way), about half of the detection pose's error
    stays in every frame (equal information: one half; within 0.3-0.7 for the Tukey weights and
    blocks that are not proportional), unchanged over the 30 frames a KLT set lives at most. The
    fused pose keeps the share ``rho`` of the anchor's error in each direction (``rho`` the KLT
    points' share of the information there: 1/2 where the two blocks are proportional; the bounds
    take 0.9, the largest share the three seeds come near being 0.7-0.8). As the running mean
    (``reanchor mean``) the anchor's error after the k-th frame is ``prod_j (1 - (1 - rho) / (j + 1))``
    of the first frame's (monotone): with rho = 0.9, 0.74 after 29 frames (the bound); with rho = 1/2,
    0.21 (seeds 0 and 1: 0.25, 0.21). Fully re-anchored (share 1, frame to frame), the error shrinks by
    rho a frame: 0.9^9 = 0.39 after 10 frames (the bound; the seeds: <= 0.05)."""
    kept = _detection_error_over_frames("off", seed, frames=30)
    assert (kept >= 0.3).all() and (kept <= 0.7).all(), kept
    assert abs(kept[-1] - kept[0]) < 0.02 * kept[0]  # it persists
    mean = _detection_error_over_frames("mean", seed, frames=30)
    assert abs(mean[0] - kept[0]) < 1e-12  # the first frame is the same solve
    bound = np.prod([1.0 - 0.1 / (j + 1) for j in range(1, 30)])
    assert mean[-1] <= bound * mean[0], (mean, bound)
    assert (np.diff(mean) <= 0.01 * mean[0]).all(), mean
    full = _detection_error_over_frames(1.0, seed, frames=10)
    assert full[-1] <= 0.9**9 * full[0] and (np.diff(full) <= 0.01 * full[0]).all(), full


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


@pytest.mark.parametrize("reanchor", ["mean", "off"])
def test_the_tracker_averages_the_output_poses_only(reanchor):
    """``EdgeTracker.accept``: the kept KLT points of a fit move to the running mean of their casts under
    the poses output as the model's (``anchor=True``: 1/2 of the way at the first, 1/3 at the second),
    and not at all with ``klt.reanchor off``; a pose the error budget withheld or a map pose
    (``anchor=False``, the session's withheld paths) drops them: the next fit is the edges' own, and
    no point is lifted under it (the Rotterdam 120 m survey's return, 3-4.7 sigma off from them)."""
    from mst.core.camera import Camera
    from mst.pipeline.tracking import EdgeTracker, TrackConfig

    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    cfg = TrackConfig(use_klt=True)
    tr = EdgeTracker(box_model((0.2, 0.2, 0.2), (-0.1, -0.1, -0.1)), cam, cfg.replace(klt=cfg.klt.replace(reanchor=reanchor)))
    T = _true_pose()
    gray = np.zeros((480, 640), np.uint8)
    X, _ = _points_on_faces(np.random.default_rng(4), 40)
    front = (X @ T[:3, :3].T + T[:3, 3])[:, 2] > 0
    X = X[front]
    planes = nearest_face_planes(tr.geom, X)
    uv = _project(T, X)
    X_det = X + np.random.default_rng(5).normal(0, 0.002, X.shape)  # lifted under another pose
    tr.accept(gray, T)  # a first accepted frame: the tracker's reference
    tr._klt_n0, tr._klt_age = len(X), 1

    def keep(anchor):  # the last fit kept every point (its KLT inliers), then the frame is accepted
        tr._klt_next = (tr.klt_X if tr.klt_X is not None and len(tr.klt_X) == len(X) else X_det, uv, planes)
        tr.accept(gray, T, anchor=anchor)
        return None if tr.klt_X is None else tr.klt_X.copy()

    first = keep(True)
    second = keep(True)
    if reanchor == "off":
        assert np.array_equal(first, X_det) and np.array_equal(second, X_det)
    else:  # the casts at T are X itself: half-way, then two thirds of the way
        np.testing.assert_allclose(first, X_det + (X - X_det) / 2, atol=1e-12)
        np.testing.assert_allclose(second, X_det + 2 * (X - X_det) / 3, atol=1e-12)
    assert keep(False) is None and tr.klt_pts is None  # a withheld pose: the points go
