"""Visibility of model edges: hidden-line removal vs ray casting, near-plane clipping, settings XML."""

from __future__ import annotations

import numpy as np
from synth_helpers import look_at

from mst.core.camera import Camera
from mst.pipeline.tracking.visibility import ModelGeometry, visible_samples


def _check_against_raycast(model, cam, T, min_agree=0.97):
    from mst.pipeline.render import Renderer

    geom = ModelGeometry.from_model(model)
    S = visible_samples(geom, T, cam.K, cam.width, cam.height, 3.0, 0.05, 1e3, 89.0, 89.5)
    # every sample projects inside the image, in front of the near plane
    Xc = S.X_model @ T[:3, :3].T + T[:3, 3]
    assert (Xc[:, 2] >= 0.05 - 1e-9).all()
    assert ((S.uv >= 0) & (S.uv <= [cam.width - 1, cam.height - 1])).all()
    # ray casting against the triangulated model: is the sample's 3D point seen?
    V, F = model.triangulate()
    r = Renderer(np.asarray(V, float), np.asarray(F))
    # nudge each point towards the camera (it lies on the surface edge)
    c = -T[:3, :3].T @ T[:3, 3]
    X = S.X_model + 1e-3 * (c - S.X_model) / np.linalg.norm(c - S.X_model, axis=1, keepdims=True)
    seen = r.visible_points(cam, T, X, rel_tol=2e-3)
    return S, seen.mean()


def test_hidden_lines_non_convex_building():
    from mst.meshtools.generate import courtyard_model, l_shape_model

    cam = Camera(300, 300, 159.5, 119.5, 320, 240)
    for model, eye in ((l_shape_model(), [-6, 20, 7]), (courtyard_model(), [35, -25, 22])):
        T = look_at(eye, model.vertices.mean(0))
        geom = ModelGeometry.from_model(model)
        assert not geom.convex
        S, agree = _check_against_raycast(model, cam, T)
        assert len(S) > 50 and agree > 0.97, agree
        # without hidden-line removal, many samples would be hidden ones
        S_all = visible_samples(geom, T, cam.K, 320, 240, 3.0, 0.05, 1e3, 89.0, 89.5, hidden_lines=False)
        assert len(S_all) > len(S) * 1.1


def test_near_plane_clipping_parts_behind_camera():
    from mst.meshtools.generate import l_shape_model

    m = l_shape_model()
    cam = Camera(160, 160, 159.5, 119.5, 320, 240)
    T = look_at([5, -3.0, 1.7], [16, 2.0, 4.0])  # inside the building's extent, looking along a wall
    Xc = m.vertices @ T[:3, :3].T + T[:3, 3]
    assert (Xc[:, 2] < 0).any()
    S, agree = _check_against_raycast(m, cam, T)
    assert len(S) > 30 and agree > 0.97


def test_settings_from_visp_xml(shared_data):
    from mst.pipeline.tracking.config import read_tracker_xml

    c = read_tracker_xml(shared_data / "visp-teabox/teabox.xml")
    e, k = c.edges, c.klt
    assert (e.mask_px, e.n_masks, e.search_range_px, e.edge_threshold, e.mu1, e.mu2, e.sample_step_px) == (5, 180, 8, 20, 0.5, 0.5, 4)
    assert (e.angle_appear_deg, e.angle_disappear_deg, e.near_clip_m, e.far_clip_m) == (70, 80, 0.1, 100)
    # ViSP's <window_size> 5 is the LK window's side (vpKltOpencv hands it to OpenCV as cv::Size(5, 5))
    assert (k.max_features, k.window_px, k.quality, k.min_distance_px, k.pyramid_levels) == (300, 5, 0.015, 8, 3)


def test_settings_bad_xml(tmp_path):
    import pytest

    from mst import InputError
    from mst.pipeline.tracking.config import read_tracker_xml

    p = tmp_path / "s.xml"
    p.write_text("<conf><ecm><range><tracking>eight</tracking></range></ecm></conf>")
    with pytest.raises(InputError, match="not a number"):
        read_tracker_xml(p)
    p.write_text("<conf><face><angle_appear>85</angle_appear><angle_disappear>80</angle_disappear></face></conf>")
    with pytest.raises(InputError, match="appear"):
        read_tracker_xml(p)
