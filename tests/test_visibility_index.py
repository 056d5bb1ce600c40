"""Issue 11: the face grid of large models (pipeline/tracking/spatial_index.py).

* The indexed path of ``visible_samples`` gives the samples of the all-faces path bit for bit,
  along a survey-like flight (small steps that reuse a query, a turn and a jump that do not).
* The reuse rule's guarantee: at any pose within the margins of a query (turned <= REUSE_ROT_DEG,
  moved <= the translation margin) the query holds every face in the view frustum.
* The work follows the view, not the model: the candidates are within a small factor of the faces
  actually in the frustum.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synth_helpers import look_at

from mst.core.camera import Camera
from mst.core.poses import se3_exp
from mst.pipeline.tracking.spatial_index import INDEX_MIN_FACES, REUSE_ROT_DEG, frustum_planes
from mst.pipeline.tracking.visibility import (
    ModelGeometry,
    face_visibility,
    frustum_faces,
    inverse_depth_buffer,
    visible_samples,
)

CAM = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)


@pytest.fixture(scope="module")
def city():
    from mst.meshtools.generate import city_block_model

    g = ModelGeometry.from_model(city_block_model(400, seed=3))  # ~2,600 faces, ~0.7 km square
    assert g.index is not None and len(g.faces) >= INDEX_MIN_FACES
    return g


def _flight() -> list[np.ndarray]:
    """A pass 80 m up along the block at 1.5 m a frame, a 40-deg turn, then a jump across it."""
    poses = [look_at([-60.0 + 1.5 * k, -80.0, 80.0], [-60.0 + 1.5 * k + 40.0, 150.0, 0.0]) for k in range(20)]
    for a in np.radians(np.linspace(0, 40, 8)):
        poses.append(se3_exp(np.array([0, 0, 0, 0, a, 0])) @ poses[19])
    poses += [look_at([500.0, 300.0, 120.0], [300.0, 300.0, 0.0]), look_at([501.0, 300.0, 120.0], [301.0, 300.0, 0.0])]
    return poses


def test_indexed_samples_are_bit_identical_to_the_all_faces_path(city):
    brute = dataclasses.replace(city, index=None)
    full0, reused0 = city.index.n_full, city.index.n_reused
    prev_a = prev_b = None
    n_seen = 0
    for T in _flight():
        a = visible_samples(city, T, CAM.K, 640, 480, 4.0, 0.5, None, 80.0, 85.0, prev_a, max_samples=600,
                            lod_min_line_px=12.0, lod_min_face_px2=64.0)
        b = visible_samples(brute, T, CAM.K, 640, 480, 4.0, 0.5, None, 80.0, 85.0, prev_b, max_samples=600,
                            lod_min_line_px=12.0, lod_min_face_px2=64.0)
        n_seen += len(b) > 100
        for f in ("uv", "normal", "X_model", "edge", "A_model", "B_model", "edge_uv", "face_visible", "model_edge"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
        assert a.stats == b.stats
        # the depth buffer of the front faces, with the vertices projected on demand
        za, _ = inverse_depth_buffer(city, T, CAM.K, 640, 480, a.face_visible, 0.5, 0.5)
        zb, _ = inverse_depth_buffer(brute, T, CAM.K, 640, 480, b.face_visible, 0.5, 0.5)
        assert np.array_equal(za, zb)
        # the next frame's hysteresis state: the all-faces path keeps it for every face, the indexed
        # one (as the tracker does) for the faces in view
        prev_a, prev_b = a.face_visible, face_visibility(brute, T, prev_b, 80.0, 85.0)
        prev_b = prev_b & frustum_faces(brute, T, CAM.K, 640, 480, 0.5, np.inf)
    assert n_seen >= 24  # the turn looks past the block's corner
    # small steps reused a query, the turn and the jump made new ones
    assert city.index.n_reused - reused0 >= 10 and city.index.n_full - full0 >= 3


def test_a_query_holds_every_frustum_face_within_its_margins(city):
    rng = np.random.default_rng(0)
    idx = city.index
    T0 = look_at([100.0, -60.0, 90.0], [200.0, 200.0, 0.0])
    idx._cache = None
    cand = idx.candidates(T0, CAM.K, 640, 480, 0.5, np.inf)
    trans = idx._cache["trans_m"]
    assert trans > 1.0  # 5 % of the nearest geometry in view (~100 m away)
    for _ in range(40):  # poses at the edge of the margins: turned ~REUSE_ROT_DEG, moved ~trans
        w = rng.normal(size=3)
        w *= np.radians(REUSE_ROT_DEG) * 0.999 / np.linalg.norm(w)
        v = rng.normal(size=3)
        v *= trans * 0.999 / np.linalg.norm(v)
        dT = se3_exp(np.concatenate([np.zeros(3), w]))
        T = dT @ T0
        T[:3, 3] += T[:3, :3] @ (-v)  # camera centre moved by v (model frame)
        exact = np.flatnonzero(frustum_faces(city, T, CAM.K, 640, 480, 0.5, np.inf))
        assert len(exact) > 50 and np.isin(exact, cand).all()
        assert idx.candidates(T, CAM.K, 640, 480, 0.5, np.inf) is cand  # reused
    # beyond the margins: a new query
    T = se3_exp(np.array([0, 0, 0, 0, np.radians(2.5 * REUSE_ROT_DEG), 0])) @ T0
    assert idx.candidates(T, CAM.K, 640, 480, 0.5, np.inf) is not cand
    # another frustum (image size): a new query
    assert idx.candidates(T0, CAM.K, 320, 240, 0.5, np.inf) is not cand


def test_the_query_follows_the_view_not_the_model(city):
    """Candidates <= 2x the faces in the frustum (margins: 2 deg of a ~65 deg view plus 5 % of the
    distance, and the cells' extent, ~3 lots), and a small share of the model."""
    for T in (look_at([100.0, 100.0, 90.0], [160.0, 160.0, 0.0]), look_at([300.0, 300.0, 60.0], [300.0, 380.0, 0.0])):
        city.index._cache = None
        cand = city.index.candidates(T, CAM.K, 640, 480, 0.5, np.inf)
        exact = frustum_faces(city, T, CAM.K, 640, 480, 0.5, np.inf).sum()
        assert exact > 50 and len(cand) <= 2.0 * exact + 4 * 8, (len(cand), exact)
        assert len(cand) <= 0.5 * len(city.faces)
    # the planes of a frustum are kept per (K, W, H): one object per pyramid level
    assert frustum_planes(CAM.K, 640, 480) is frustum_planes(CAM.K.copy(), 640, 480)
