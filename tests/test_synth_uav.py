"""Issue 11: the procedural city (``generate.city_block_model``) and the UAV scenarios of ``mst synth``
(``uav``: survey pass pitched down with a look-away stretch; ``fpv``: facade pass), geometry checked
on the ground-truth poses and on what was rendered (frames.csv), at a tiny resolution."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mst import MstError
from mst.core.trajectory import read_tum
from mst.meshtools.formats import load_model, save_model
from mst.meshtools.generate import city_block_model
from mst.pipeline.synth import SynthConfig, synthesize
from mst.pipeline.synth.scenarios_uav import AWAY_DEG, GAP_PHASES

TINY = dict(width=160, height=120, texture_size=64, aa_samples=0, depth=False, fps=10.0)


def test_city_block_model_polygons_closed_outward_deterministic():
    m = city_block_model(40, seed=3)
    # 6 faces per flat-roof box, 7 per gabled house
    assert 6 * 40 <= m.n_faces <= 7 * 40
    assert all(len(f) in (4, 5) for f in m.faces)
    assert m.vertices[:, 2].min() == 0.0  # on the ground plane
    V, F = m.triangulate()
    # closed and outward: the signed volume of each building's triangles is positive, so the total is too
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    assert vol > 0
    # every edge of the triangulation is shared by exactly two triangles (closed solids, no ground)
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    key = np.round(V[e].reshape(len(e), 6), 6)
    _, counts = np.unique(key, axis=0, return_counts=True)
    assert (counts == 2).all()
    m2 = city_block_model(40, seed=3)
    np.testing.assert_array_equal(m.vertices, m2.vertices)
    assert not np.array_equal(city_block_model(40, seed=4).vertices, m.vertices)
    assert city_block_model(40, seed=3, ground=True).n_faces == m.n_faces + 1


def test_city_block_model_50k_polygons_round_trips(tmp_path):
    m = city_block_model(7700)
    assert 49_000 <= m.n_faces <= 52_000
    p = tmp_path / "city.wrl"
    save_model(p, m)
    assert load_model(p).n_faces == m.n_faces


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    p = tmp_path_factory.mktemp("city") / "city.wrl"
    save_model(p, city_block_model(36, seed=1))
    return p


def _frames_csv(d):
    rows = [r.split(",") for r in (d / "frames.csv").read_text().splitlines()[1:]]
    return np.array([int(r[2]) for r in rows])


def test_uav_survey_pitch_altitude_and_a_stretch_without_buildings(city, tmp_path):
    out = tmp_path / "uav"
    s = synthesize("uav", city, out, SynthConfig(frames=50, distance=60.0, **TINY))
    assert s["scenario"] == "uav" and s["frames"] == 50
    _, T = read_tum(out / "gt.txt")
    fwd = T[:, :3, 2]  # the optical axis in the model frame (z up)
    pitch = np.degrees(np.arcsin(-fwd[:, 2]))
    np.testing.assert_allclose(pitch, 45.0, atol=2.0)  # the default 45 deg down (roll/sway do not tilt the axis)
    alt = T[:, 2, 3]
    np.testing.assert_allclose(alt, 60.0, atol=0.01 * 60 + 1e-9)  # +-1 % altitude wobble
    # the look-away stretch: no model pixel while the camera looks AWAY_DEG away, model in view outside it
    model_px = _frames_csv(out)
    u = np.arange(50) / 50
    away = (u > GAP_PHASES[1]) & (u < GAP_PHASES[2])
    near = (u < GAP_PHASES[0]) | (u > GAP_PHASES[3])
    assert away.any() and (model_px[away] == 0).all()
    assert (model_px[near] > 0).all()
    assert s["frames_without_model"] >= away.sum()
    yaw = np.degrees(np.arctan2(fwd[:, 1], fwd[:, 0]))
    dyaw = (yaw[away] - yaw[0] + 180) % 360 - 180
    assert np.abs(np.abs(dyaw) - AWAY_DEG).max() < 15.0  # turned away (the +-12 deg sway on top)
    # the hover: the camera moves less during the turn than before it
    v = np.linalg.norm(np.diff(T[:, :2, 3], axis=0), axis=1)
    assert v[away[1:]].max() < 0.2 * v[:5].mean()
    spec = json.loads((out / "scene.json").read_text())
    assert spec["resolved"]["pitch_deg"] == 45.0 and "gap_phases" in spec["resolved"]


def test_fpv_facade_pass_distance_and_view(city, tmp_path):
    out = tmp_path / "fpv"
    s = synthesize("fpv", city, out, SynthConfig(frames=20, distance=30.0, pitch_deg=5.0, **TINY))
    _, T = read_tum(out / "gt.txt")
    V = load_model(city).vertices
    # lateral distance from the camera to the buildings' south facades (the nearest south edge along the pass)
    y_edge = json.loads((out / "scene.json").read_text())["resolved"]["eye_y"] + 30.0
    assert V[:, 1].min() <= y_edge + 1e-9
    d = y_edge - T[:, 1, 3]
    assert (d >= 20.0).all() and (d <= 50.0).all()  # the 20-50 m band (30 m +- the 10 % S-turn)
    fwd = T[:, :3, 2]
    np.testing.assert_allclose(np.degrees(np.arcsin(-fwd[:, 2])), 5.0, atol=0.5)
    assert (_frames_csv(out) > 0).all() and s["frames_without_model"] == 0  # the facades always in view
    # forward-looking: within 60 deg of the flight direction (+x), turned toward the facades (+y)
    yaw = np.degrees(np.arctan2(fwd[:, 1], fwd[:, 0]))
    assert (yaw > 10).all() and (yaw < 60).all()


def test_h264_video(city, tmp_path):
    """H.264 through imageio-ffmpeg's libx264 (OpenCV's wheels have no H.264 encoder): OpenCV decodes it."""
    import cv2

    out = tmp_path / "h264"
    synthesize("fpv", city, out, SynthConfig(frames=3, video=True, video_codec="h264", **TINY))
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode(errors="replace")
    assert fourcc.lower() in ("avc1", "h264") and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3


def test_h264_odd_frame_size_one_error_no_folder(city, tmp_path):
    out = tmp_path / "odd"
    cfg = SynthConfig(frames=2, video=True, video_codec="h264", **{**TINY, "width": 161})
    with pytest.raises(MstError, match="even frame size"):
        synthesize("fpv", city, out, cfg)
    assert not out.exists()


def test_older_scene_json_fields_unchanged(city, tmp_path):
    """The fields added for the UAV scenarios stay out of scene.json at their defaults (old files identical)."""
    out = tmp_path / "orbit"
    synthesize("orbit", city, out, SynthConfig(frames=1, **TINY))
    cfg = json.loads((out / "scene.json").read_text())["config"]
    assert "video_codec" not in cfg and "pitch_deg" not in cfg
    assert SynthConfig.from_dict(cfg).pitch_deg is None
    assert math.isclose(SynthConfig.from_dict(cfg).fps, 10.0)
