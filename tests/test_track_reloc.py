"""Re-acquisition without clicks (``pipeline/relocalise.py``, status ``relocalised``).

The object is tracked, the camera is covered (black frames), and it comes back at a pose the
edge tracker cannot reach from its last pose by its widened search. With the relocaliser (default)
the pose is found again from the keypoints learned on the model's surfaces while it was tracked,
refined by the edges and accepted through the health score; without it the frames stay ``lost``.
Bounds: the issue's (every output pose within 1 % of the distance and 2 deg), re-acquired within
``RelocConfig.every`` frames of the object being back in view.
"""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest
from synth_helpers import look_at, render_textured

from mst.core.camera import Camera, write_camera
from mst.core.poses import inv_T, pose_error
from mst.core.trajectory import read_tum, write_pose_file
from mst.pipeline.tracking.relocalise import RelocConfig


def _statuses(out):
    return [r["status"] for r in csv.DictReader(open(out.with_suffix(".csv")))]


@pytest.fixture(scope="module")
def covered_box(tmp_path_factory):
    """Textured box orbit (10 frames), 3 black frames, then the camera 5 m to the side (~80 px jump)."""
    from mst.meshtools.formats import save_model
    from mst.meshtools.generate import box_model

    d = tmp_path_factory.mktemp("reloc_box")
    (d / "rgb").mkdir()
    m = box_model((10.0, 6.0, 4.0))
    cam = Camera(300, 300, 159.5, 119.5, 320, 240)
    c = m.vertices.mean(0)
    angs = [-50 + 1.5 * k for k in range(10)] + [None] * 3 + [-36.5 + 1.5 * k for k in range(8)]
    poses = []
    for k, a in enumerate(angs):
        if a is None:
            poses.append(None)
            continue
        T_model_cam = inv_T(look_at(c + [18 * np.cos(np.radians(a)), 18 * np.sin(np.radians(a)), 7.0], c))
        if k >= 13:
            T_model_cam[:3, 3] += 5.0 * T_model_cam[:3, 0]  # moved along the camera's x axis
        poses.append(inv_T(T_model_cam))
    imgs = iter(render_textured(m, cam, [p for p in poses if p is not None]))
    for k, p in enumerate(poses):
        cv2.imwrite(str(d / "rgb" / f"{k:06d}.png"), next(imgs) if p is not None else np.zeros((240, 320), np.uint8))
    save_model(d / "model.obj", m)
    write_camera(d / "camera.json", cam)
    write_pose_file(d / "p0.txt", poses[0])
    return d, poses


@pytest.mark.parametrize("slam", ["auto", "off"])
def test_synthetic_reacquired_after_covered_camera(covered_box, tmp_path, slam):
    from mst.pipeline.tracking import TrackConfig, run_track

    d, poses = covered_box
    back = 13
    out0 = tmp_path / "noreloc.txt"
    run_track(d / "rgb", d / "model.obj", d / "camera.json", d / "p0.txt", out0, TrackConfig(aid=slam, relocalise=False))
    assert all(s == "lost" for s in _statuses(out0)[back:])  # beyond the edge tracker's own recovery
    out = tmp_path / "reloc.txt"
    s = run_track(d / "rgb", d / "model.obj", d / "camera.json", d / "p0.txt", out, TrackConfig(aid=slam))
    st = _statuses(out)
    assert st[:10] == ["model"] * 10 and st[10:back] == ["lost"] * 3
    first = st.index("relocalised")
    assert back <= first < back + RelocConfig().every
    assert all(x in ("model", "relocalised") for x in st[first:])
    assert s["status_counts"]["relocalised"] >= 1 and s["relocalisation"]["keyframes"] >= 1
    t, P = read_tum(out)
    dt, dr = pose_error(P, np.array([inv_T(poses[int(k)]) for k in t]))
    dist = 18.0
    assert dt.max() < 0.01 * dist and dr.max() < 2.0  # every output pose (the bound)


def test_teabox_reacquired_after_jump(shared_data, tmp_path):
    """Real video: frames 0-38, 4 black frames, then frames 0-11 again (the camera 'jumps back')."""
    from mst.core.camera import read_camera
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import init_from_clicks, read_clicks
    from mst.pipeline.tracking import run_track
    from mst.pipeline.tracking.config import read_tracker_xml

    t = shared_data / "visp-teabox"
    from mst.pipeline.frames import open_frames

    frames = [bgr for _, _, bgr in open_frames(t / "teabox.mp4")]
    seq = frames + [np.zeros_like(frames[0])] * 4 + frames[:12]
    (tmp_path / "rgb").mkdir()
    for i, f in enumerate(seq):
        cv2.imwrite(str(tmp_path / "rgb" / f"{i:06d}.png"), f)
    cam = read_camera(t / "teabox.xml")
    X, uv = read_clicks(t / "teabox.clicks", t / "teabox.init")
    write_pose_file(tmp_path / "p0.txt", init_from_clicks(X, uv, cam.K).T_cam_model)
    cfg = read_tracker_xml(t / "teabox.xml")
    out = tmp_path / "traj.txt"
    s = run_track(tmp_path / "rgb", t / "teabox.cao", t / "teabox.xml", tmp_path / "p0.txt", out, cfg.replace(aid="off"))
    st = _statuses(out)
    n, back = len(frames), len(frames) + 4
    assert st[:n] == ["model"] * n and st[n:back] == ["lost"] * 4
    first = st.index("relocalised")
    assert back <= first < back + RelocConfig().every
    assert all(x in ("model", "relocalised") for x in st[first:])
    # the re-acquired poses equal those of the first pass over the same images: within one pixel
    # (the pixel size; forward-backward consistency on this video is 0.2-0.3 px)
    ts, P = read_tum(out)
    by_t = {int(round(k)): inv_T(p) for k, p in zip(ts, P)}
    K, V = cam.K, np.asarray(load_tracking_model(t / "teabox.cao").vertices, float)

    def corners(T):
        Xc = V @ T[:3, :3].T + T[:3, 3]
        return Xc[:, :2] / Xc[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]

    err = [np.linalg.norm(corners(by_t[k]) - corners(by_t[k - back]), axis=1).mean() for k in range(first, len(seq))]
    assert max(err) < 1.0, err
    assert s["relocalisation"]["attempts"] >= 1


@pytest.fixture(scope="module")
def turned_box():
    """The textured box seen from azimuth -50 deg (learned), then turned by 30, 60 and 90 deg
    (the camera orbits it: the sides the learned keyframe sees at a grazing angle come to face it)."""
    from mst.meshtools.generate import box_model

    m = box_model((10.0, 6.0, 4.0))
    cam = Camera(300, 300, 159.5, 119.5, 320, 240)
    c = m.vertices.mean(0)
    angs = [-50, -20, 10, 40]
    poses = [look_at(c + [18 * np.cos(np.radians(a)), 18 * np.sin(np.radians(a)), 7.0], c) for a in angs]
    return m, cam, poses, render_textured(m, cam, poses)


def _corner_px(cam, V, T_a, T_b):
    """Mean image distance (px) of the model's vertices projected with two poses."""
    def uv(T):
        Xc = V @ T[:3, :3].T + T[:3, 3]
        return Xc[:, :2] / Xc[:, 2:3] * [cam.fx, cam.fy]
    return float(np.linalg.norm(uv(T_a) - uv(T_b), axis=1).mean())


@pytest.mark.parametrize("k", [1, 2, 3])
def test_rendered_views_find_a_new_side(turned_box, k):
    """Keypoints of views rendered from the model with the keyframe's texture (the model turned
    by +-30/60/90 deg about its axis nearest the image's vertical) find the box turned by 30-90
    deg; the keyframe alone does not. Bound: a PnP candidate must bring the model inside the edge
    tracker's search range (the session refines each candidate and accepts it only through the
    health score): its mean vertex reprojection error below ``search_range_px``. All views are
    matched in the one attempt here (``kf_per_attempt``; the default shares them out over
    consecutive attempts)."""
    from mst.pipeline.tracking import EdgeTracker, TrackConfig
    from mst.pipeline.tracking.relocalise import Relocaliser

    m, cam, poses, imgs = turned_box
    cfg = TrackConfig()
    tr = EdgeTracker(m, cam, cfg)
    V = np.asarray(m.vertices, float)
    R = tr.cfg.search_range_px  # the default, resolved for this camera
    plain = Relocaliser(tr, RelocConfig(synth_steps=0, kf_per_attempt=20))
    plain.learn(0, imgs[0], poses[0])
    views = Relocaliser(tr, RelocConfig(kf_per_attempt=20))
    views.learn(0, imgs[0], poses[0])
    assert views.stats["synth_views"] >= 4 and plain.stats["synth_views"] == 0
    assert all(_corner_px(cam, V, T, poses[k]) > R for T in plain.candidates(imgs[k]))
    err = [_corner_px(cam, V, T, poses[k]) for T in views.candidates(imgs[k])]
    assert err and min(err) < R, err
