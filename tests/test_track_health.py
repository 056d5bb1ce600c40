"""The calibrated health score (``tracker.HealthMonitor``) against poses that look plausible but are
wrong, each its own test: perturbed by a few pixels or degrees, locked onto a textured background,
onto the object's shadow, onto the object's mirror image. The monitor is calibrated the way
``run_track`` calibrates it, on the sequence's own healthy frames (ground truth for the renders,
the tracked poses for the real tea box), then asked about one later frame.

Margins: the correct pose scores ~0.9 (tested > 0.5); the score reaches 0 (rejection) at about
3 px of shift and 2-3 deg of rotation on both the tea box (45 cm away) and the rendered box (18 m
away, 170 px wide; a 3 deg turn about the camera's y axis moves its corners by 3.5 px on average and
scores +0.05). The tests use 4 px and 4 deg, and far larger errors for the locked poses.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from synth_helpers import look_at, render_textured

from mst.core.camera import Camera


def _score(tracker, monitor, gray, T):
    ev = tracker.evidence(gray, T)
    return monitor.score(monitor.features(ev))[0]


def _calibrate(tracker, grays, poses):
    from mst.pipeline.tracking import HealthMonitor

    mon = HealthMonitor(len(tracker.geom.edges), len(tracker.surf_X))
    for g, T in zip(grays, poses):
        ev = tracker.evidence(g, T)
        mon.learn(ev, mon.features(ev))
    return mon


def _centre_cam(T, V):
    """Model centre in the camera frame (m)."""
    return T[:3, :3] @ V.mean(0) + T[:3, 3]


def shift_px(T, V, K, du, dv):
    """The pose moved so that the model centre moves by (du, dv) px in the image."""
    T1 = T.copy()
    z = _centre_cam(T, V)[2]
    T1[0, 3] += du * z / K[0, 0]
    T1[1, 3] += dv * z / K[1, 1]
    return T1


def rotate_deg(T, V, axis, deg):
    """The pose rotated by ``deg`` about a camera-frame axis through the model centre."""
    c = _centre_cam(T, V)
    R = cv2.Rodrigues(np.radians(deg) * np.asarray(axis, float))[0]
    T1 = T.copy()
    T1[:3, :3] = R @ T[:3, :3]
    T1[:3, 3] = R @ (T[:3, 3] - c) + c
    return T1


def mirrored(gray, T, V, K, axis):
    """The image mirrored about the column u = cx and the rigid pose that puts the model's outline
    onto the mirrored object: ``M T S`` with M the camera-frame mirror x -> -x and S the model's
    mirror symmetry about its centre plane normal to ``axis`` (a box has three)."""
    S = np.eye(4)
    S[axis, axis] = -1.0
    S[axis, 3] = 2.0 * V.mean(0)[axis]
    M = np.diag([-1.0, 1.0, 1.0, 1.0])
    img = cv2.warpAffine(gray, np.float32([[-1, 0, 2 * K[0, 2]], [0, 1, 0]]), gray.shape[::-1])
    return img, M @ T @ S


PERTURBATIONS = [("shift", (4, 0)), ("shift", (0, 4)), ("shift", (-2.83, 2.83)),
                 ("rotate", ((1, 0, 0), 4)), ("rotate", ((0, 1, 0), 4)), ("rotate", ((0, 0, 1), 4))]


def _perturb(T, V, K, kind, arg):
    return shift_px(T, V, K, *arg) if kind == "shift" else rotate_deg(T, V, *arg)


# ------------------------------------------------------------------ synthetic box (renders)
@pytest.fixture(scope="module")
def box_scene():
    from mst.meshtools.generate import box_model
    from mst.pipeline.tracking import EdgeTracker
    from mst.pipeline.tracking.config import TrackConfig

    m = box_model((10.0, 6.0, 4.0))
    cam = Camera(300, 300, 159.5, 119.5, 320, 240)
    c = m.vertices.mean(0)
    poses = []
    for k in range(14):
        a = np.radians(-50 + 1.5 * k)
        poses.append(look_at(c + [18 * np.cos(a), 18 * np.sin(a), 7.0], c))
    imgs = render_textured(m, cam, poses)
    tr = EdgeTracker(m, cam, TrackConfig())
    mon = _calibrate(tr, imgs[:12], poses[:12])
    return m, cam, tr, mon, imgs[13], poses[13]


def test_synthetic_correct_pose_accepted(box_scene):
    m, cam, tr, mon, img, T = box_scene
    assert _score(tr, mon, img, T) > 0.5  # a typical healthy frame scores near 1


@pytest.mark.parametrize("step_px", [1.0, 6.0, 12.0])
def test_evidence_search_runs_on_100_to_199_samples(box_scene, step_px):
    """The evidence's moving-edge search (its found share and median residual) runs on every k-th visible
    sample, k = N // EVIDENCE_SAMPLES (100): on 100-199 of them, or on all N when fewer; the gradient test
    (``sign``, ``oriented``) on all N. Sample steps of 1, 6 and 12 px give N above 200, in 100-199 and
    below 100 on this view."""
    import dataclasses

    from mst.pipeline.tracking import EdgeTracker
    from mst.pipeline.tracking.config import TrackConfig

    m, cam, _, _, img, T = box_scene
    cfg = TrackConfig()
    tr = EdgeTracker(m, cam, dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, sample_step_px=step_px)))
    ev = tr.evidence(img, T)
    n, k = len(ev.sign), len(ev.offset_px)
    assert len(ev.oriented) == len(ev.edge) == n > 12
    assert k == n if n < 100 else 100 <= k < 200, (n, k)
    assert (n < 100) == (step_px == 12.0) and (n >= 200) == (step_px == 1.0), n  # each branch covered


@pytest.mark.parametrize("kind,arg", PERTURBATIONS)
def test_synthetic_perturbed_pose_rejected(box_scene, kind, arg):
    m, cam, tr, mon, img, T = box_scene
    assert _score(tr, mon, img, _perturb(T, np.asarray(m.vertices), cam.K, kind, arg)) <= 0


def test_synthetic_pose_on_textured_background_rejected(box_scene):
    """Background (sky) replaced by strong random blocks; the pose moved 110 px onto them."""
    m, cam, tr, mon, img, T = box_scene
    V = np.asarray(m.vertices)
    bg_mask = render_textured(m, cam, [T], noise=0.0)[0] == 200
    rng = np.random.default_rng(3)
    tex = np.full(img.shape, 128, np.uint8)
    for _ in range(150):
        x, y = rng.integers(0, 320), rng.integers(0, 240)
        cv2.rectangle(tex, (int(x), int(y)), (int(x + rng.integers(5, 40)), int(y + rng.integers(5, 40))),
                      int(rng.integers(0, 256)), -1)
    im2 = np.where(bg_mask, tex, img).astype(np.uint8)
    T_bg = shift_px(T, V, cam.K, 0, -110)
    assert _score(tr, mon, im2, T) > 0  # the object itself is still accepted on that image
    assert _score(tr, mon, im2, T_bg) <= 0


def test_synthetic_pose_on_shadow_rejected(box_scene):
    """A shadow of exactly the object's outline on the ground, 60 px to the side, and the pose on it."""
    m, cam, tr, mon, img, T = box_scene
    V = np.asarray(m.vertices)
    T_sh = shift_px(T, V, cam.K, -60, 10)
    from mst.pipeline.render import Renderer

    V3, F3 = m.triangulate()
    r = Renderer(np.asarray(V3, float), np.asarray(F3, np.int64))
    obj, sil = r.render_face_ids(cam, T) >= 0, r.render_face_ids(cam, T_sh) >= 0
    im2 = img.astype(np.float32)
    im2[sil & ~obj] *= 0.45
    im2 = np.clip(im2, 0, 255).astype(np.uint8)
    assert _score(tr, mon, im2, T) > 0
    assert _score(tr, mon, im2, T_sh) <= 0


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_synthetic_pose_on_mirror_image_rejected(box_scene, axis):
    m, cam, tr, mon, img, T = box_scene
    im2, T_m = mirrored(img, T, np.asarray(m.vertices), cam.K, axis)
    assert _score(tr, mon, im2, T_m) <= 0


# ------------------------------------------------------------------ real tea box
@pytest.fixture(scope="module")
def teabox_scene(shared_data, tmp_path_factory):
    from mst.core.camera import read_camera
    from mst.core.poses import inv_T
    from mst.core.trajectory import read_tum, write_pose_file
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import init_from_clicks, read_clicks
    from mst.pipeline.tracking import EdgeTracker, run_track
    from mst.pipeline.tracking.config import read_tracker_xml

    t = shared_data / "visp-teabox"
    d = tmp_path_factory.mktemp("teabox_health")
    cam = read_camera(t / "teabox.xml")
    X, uv = read_clicks(t / "teabox.clicks", t / "teabox.init")
    write_pose_file(d / "p0.txt", init_from_clicks(X, uv, cam.K).T_cam_model)
    cfg = read_tracker_xml(t / "teabox.xml")
    run_track(t / "teabox.mp4", t / "teabox.cao", t / "teabox.xml", d / "p0.txt", d / "traj.txt", cfg.replace(aid="auto"),
              frames="0:32")
    ts, P = read_tum(d / "traj.txt")
    assert len(ts) == 32
    cap = cv2.VideoCapture(str(t / "teabox.mp4"))
    grays = []
    for _ in range(32):
        ok, f = cap.read()
        grays.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    model = load_tracking_model(t / "teabox.cao")
    tr = EdgeTracker(model, cam, cfg)
    poses = [inv_T(p) for p in P]
    mon = _calibrate(tr, grays[:30], poses[:30])
    return model, cam, tr, mon, grays[31], poses[31]


def test_teabox_correct_pose_accepted(teabox_scene):
    m, cam, tr, mon, img, T = teabox_scene
    assert _score(tr, mon, img, T) > 0.5


@pytest.mark.parametrize("kind,arg", PERTURBATIONS)
def test_teabox_perturbed_pose_rejected(teabox_scene, kind, arg):
    m, cam, tr, mon, img, T = teabox_scene
    assert _score(tr, mon, img, _perturb(T, np.asarray(m.vertices), cam.K, kind, arg)) <= 0


@pytest.mark.parametrize("du,dv", [(-200, 100), (180, 150)])
def test_teabox_pose_on_the_table_rejected(teabox_scene, du, dv):
    """The box moved onto the textured table and the scene behind it."""
    m, cam, tr, mon, img, T = teabox_scene
    assert _score(tr, mon, img, shift_px(T, np.asarray(m.vertices), cam.K, du, dv)) <= 0


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_teabox_pose_on_mirror_image_rejected(teabox_scene, axis):
    m, cam, tr, mon, img, T = teabox_scene
    im2, T_m = mirrored(img, T, np.asarray(m.vertices), cam.K, axis)
    assert _score(tr, mon, im2, T_m) <= 0


# ------------------------------------------------------------------ a curved mesh (render-based edges)
@pytest.fixture(scope="module")
def blob_scene(tmp_path_factory):
    """`mst synth orbit` of a blob (5,120 triangles, no symmetry), tracked by render-based edges: the monitor
    calibrated on the true poses of frames 0-11, frame 13 asked about."""
    from mst.core.camera import read_camera
    from mst.core.poses import inv_T
    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import load_tracking_model, save_triangles
    from mst.meshtools.generate import blob
    from mst.pipeline import synth
    from mst.pipeline.tracking.config import TrackConfig
    from mst.pipeline.tracking.render_edges import edge_tracker_for

    d = tmp_path_factory.mktemp("blob_health")
    V, F = blob(subdivisions=3)
    save_triangles(d / "blob.obj", V, F)
    synth.synthesize("orbit", d / "blob.obj", d / "seq", synth.SynthConfig(frames=14, width=640, height=480,
                                                                          depth=False, aa_samples=4, texture_size=256))
    cam = read_camera(d / "seq" / "camera.json")
    poses = [inv_T(T) for T in read_tum(d / "seq" / "gt.txt")[1]]
    grays = [cv2.imread(str(d / "seq" / "rgb" / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE) for k in range(14)]
    model = load_tracking_model(d / "seq" / "model.obj")
    tr, used = edge_tracker_for(model, d / "seq" / "model.obj", cam, TrackConfig(), poses[0])
    assert used == "render"
    mon = _calibrate(tr, grays[:12], poses[:12])
    return V, cam, tr, mon, grays[13], poses[13]


def test_curved_mesh_correct_pose_accepted(blob_scene):
    """Render-based edgelets have no model edge: the score reads their gradient, moving-edge share and residual
    (no learned polarity), and a typical healthy frame scores near 1 (before: no evidence, every pose 1)."""
    V, cam, tr, mon, img, T = blob_scene
    ev = tr.evidence(img, T)
    assert ev.n > 100 and (ev.edge == -1).all()
    assert _score(tr, mon, img, T) > 0.5


#: the box's perturbations that move a smooth, roundish body's contour: 4 px shifts and 4 deg about the optical
#: axis (its contour moves 2.7-3.5 px and 1.7 px at the median); 4 deg about the camera's x or y axis through
#: the blob's centre moves it 0.5 / 0.9 px at the median, no more than the fit's own noise: not a wrong pose the
#: image can show
CURVED_PERTURBATIONS = [p for p in PERTURBATIONS if p[0] == "shift" or p[1][0] == (0, 0, 1)]


@pytest.mark.parametrize("kind,arg", CURVED_PERTURBATIONS)
def test_curved_mesh_perturbed_pose_rejected(blob_scene, kind, arg):
    V, cam, tr, mon, img, T = blob_scene
    assert _score(tr, mon, img, _perturb(T, V, cam.K, kind, arg)) <= 0


@pytest.mark.parametrize("du,dv", [(-150, 40), (160, -60)])
def test_curved_mesh_pose_on_the_floor_rejected(blob_scene, du, dv):
    """The blob's pose moved onto the textured floor beside it."""
    V, cam, tr, mon, img, T = blob_scene
    assert _score(tr, mon, img, shift_px(T, V, cam.K, du, dv)) <= 0
