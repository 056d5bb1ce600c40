"""``mst synth``: sequence layout, ground truth consistency, sub-pixel corners, reproducibility, scenarios, errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from mst.core.camera import read_camera
from mst.core.poses import inv_T
from mst.core.trajectory import read_pose_file, read_tum
from mst.meshtools.formats import save_triangles
from mst.meshtools.generate import box
from mst.pipeline.synth import SynthConfig, synthesize, synthesize_from_scene

SMALL = dict(width=160, height=120, texture_size=64)


@pytest.fixture(scope="module")
def boxfile(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("models") / "box.obj"
    V, F = box(size=(1.0, 0.7, 0.5), split=2)
    save_triangles(p, V, F)
    return p


@pytest.fixture(scope="module")
def orbit_seq(house, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("seq") / "orbit"
    synthesize("orbit", house, out, SynthConfig(frames=4, depth_noise="kinect", click_noise=0.0, **SMALL))
    return out


def test_layout_and_ground_truth_consistency(orbit_seq: Path, house: Path):
    d = orbit_seq
    for name in ("camera.json", "gt.txt", "clicks.txt", "model.obj", "scene.ply", "scene.json", "frames.csv"):
        assert (d / name).is_file(), name
    assert sorted(p.name for p in (d / "rgb").iterdir()) == [f"{k:06d}.png" for k in range(4)]
    assert len(list((d / "depth").glob("*.png"))) == 4 and len(list((d / "depth").glob("*.npy"))) == 4
    assert not list(d.parent.glob(".orbit.*"))  # temporary folder gone
    cam = read_camera(d / "camera.json")
    assert (cam.width, cam.height, cam.fx) == (160, 120, 525.0 * 160 / 640)
    img = cv2.imread(str(d / "rgb" / "000000.png"))
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    t, T_model_cam = read_tum(d / "gt.txt")
    np.testing.assert_allclose(t, np.arange(4) / 30.0, atol=1e-6)
    for k in range(4):
        T_cam_model = read_pose_file(d / "cMo" / f"{k:06d}.txt")
        np.testing.assert_allclose(T_cam_model, inv_T(T_model_cam[k]), atol=1e-6)
    # depth: PNG millimetres agree with the float metres; kinect holes exist but most pixels have depth
    mm = cv2.imread(str(d / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    z = np.load(d / "depth" / "000000.npy")
    assert mm.dtype == np.uint16 and z.dtype == np.float32
    ok = (z > 0) & (z < 65.5)
    assert np.array_equal(mm[ok].astype(np.int64), np.round(z[ok].astype(np.float64) * 1000).astype(np.int64))
    assert 0.5 < ok.mean() < 1.0
    # model.obj is the rendered model exactly
    from mst.meshtools.formats import load_triangles

    V0, F0 = load_triangles(house)
    V1, F1 = load_triangles(d / "model.obj")
    assert np.array_equal(V0, V1) and np.array_equal(F0, F1)
    spec = json.loads((d / "scene.json").read_text())
    assert spec["scenario"] == "orbit" and spec["resolved"]["frames"] == 4 and spec["config"]["seed"] == 0


def test_clicks_consistent_with_gt_pose(orbit_seq: Path, house: Path, tmp_path: Path):
    cam = read_camera(orbit_seq / "camera.json")
    T = read_pose_file(orbit_seq / "cMo" / "000000.txt")
    a = np.loadtxt(orbit_seq / "clicks.txt")
    assert a.shape[1] == 5 and 4 <= len(a) <= 6
    uv = cam.project(a[:, :3] @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(uv, a[:, 3:], atol=1e-3)
    # clicks are model corners (vertices of the house)
    from mst.meshtools.formats import load_triangles

    V, _ = load_triangles(house)
    assert all(np.min(np.linalg.norm(V - X, axis=1)) < 1e-8 for X in a[:, :3])
    # spread: not all in one image quadrant
    assert np.ptp(a[:, 3]) > 0.3 * cam.width and np.ptp(a[:, 4]) > 0.3 * cam.height
    # with pixel noise: same points, perturbed pixels
    out = tmp_path / "noisy"
    synthesize("orbit", house, out, SynthConfig(frames=1, depth=False, click_noise=2.0, **SMALL))
    b = np.loadtxt(out / "clicks.txt")
    assert np.array_equal(b[:, :3], a[:, :3])
    err = np.linalg.norm(b[:, 3:] - a[:, 3:], axis=1)
    assert err.max() > 0.1 and err.max() < 12.0


def test_projected_corners_match_rendered_corners_subpixel(boxfile: Path, tmp_path: Path):
    """High-contrast box against the sky, no noise: cornerSubPix at the GT projections moves < 0.5 px."""
    out = tmp_path / "box"
    synthesize("orbit", boxfile, out, SynthConfig(frames=1, depth=False, environment=False, rgb_noise=0.0,
                                                  width=320, height=240, texture_size=64, n_clicks=8))
    gray = cv2.cvtColor(cv2.imread(str(out / "rgb" / "000000.png")), cv2.COLOR_BGR2GRAY)
    a = np.loadtxt(out / "clicks.txt")
    assert len(a) >= 5
    uv = a[:, 3:].astype(np.float32)
    start = (uv + np.float32(1.2)).reshape(-1, 1, 2)  # start 1.7 px away from the true corner
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    found = cv2.cornerSubPix(gray, start.copy(), (4, 4), (-1, -1), crit).reshape(-1, 2)
    err = np.linalg.norm(found - uv, axis=1)
    assert np.median(err) < 0.25 and err.max() < 0.5, err


def test_scene_json_reproduces_identical_files(house: Path, tmp_path: Path):
    a = tmp_path / "a"
    cfg = SynthConfig(frames=3, width=96, height=72, texture_size=64, depth_noise="kinect", rgb_noise=3.0,
                      click_noise=1.5, seed=11, motion_blur=2, video=True)
    synthesize("fast", house, a, cfg)
    b = tmp_path / "b"
    synthesize_from_scene(a / "scene.json", b)
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert fa == fb and len(fa) > 15
    for rel in fa:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    # a different seed changes the images
    c = tmp_path / "c"
    synthesize("fast", house, c, SynthConfig(**{**cfg.__dict__, "seed": 12}))
    assert (a / "rgb" / "000001.png").read_bytes() != (c / "rgb" / "000001.png").read_bytes()


def test_fast_keeps_every_nth_pose(house: Path, tmp_path: Path):
    base = tmp_path / "base"
    fast = tmp_path / "fast"
    tiny = dict(width=64, height=48, texture_size=64, depth=False, aa_samples=0)
    synthesize("orbit", house, base, SynthConfig(frames=17, **tiny))
    synthesize("fast", house, fast, SynthConfig(frames=3, drop=8, **tiny))
    _, Tb = read_tum(base / "gt.txt")
    tf, Tf = read_tum(fast / "gt.txt")
    np.testing.assert_allclose(Tf, Tb[[0, 8, 16]], atol=1e-6)
    np.testing.assert_allclose(tf, np.arange(3) / 30.0, atol=1e-6)  # TUM times have 6 decimals
    # large inter-frame motion: > 8x the base step
    step_b = np.linalg.norm(Tb[1, :3, 3] - Tb[0, :3, 3])
    assert np.linalg.norm(Tf[1, :3, 3] - Tf[0, :3, 3]) > 7.5 * step_b


def test_corridor_model_leaves_view_for_40_frames(house: Path, tmp_path: Path):
    out = tmp_path / "corr"
    s = synthesize("corridor", house, out, SynthConfig(width=64, height=48, texture_size=64, aa_samples=0,
                                                       rgb_noise=0.0))
    assert s["frames"] == 150
    rows = np.loadtxt(out / "frames.csv", delimiter=",", skiprows=1)
    absent = rows[:, 2] == 0
    assert rows[0, 2] > 0 and rows[-1, 2] > 0          # in view at both ends
    # longest run without the model
    best = run = 0
    for a in absent:
        run = run + 1 if a else 0
        best = max(best, run)
    assert best >= 40
    # depth is available throughout (textured walls and floor within range)
    for k in (0, 75, 149):
        z = np.load(out / "depth" / f"{k:06d}.npy")
        assert (z > 0).mean() > 0.99 and z.max() < 4 * s["distance_m"]


def test_flyover_and_scene_ply(house: Path, tmp_path: Path):
    out = tmp_path / "fly"
    s = synthesize("flyover", house, out, SynthConfig(frames=3, width=80, height=60, texture_size=64))
    assert s["distance_m"] == 30.0
    t, T = read_tum(out / "gt.txt")
    assert (T[:, 2, 3] > 30.0).all()                       # tens of metres above the ground
    # scene.ply: model + ground, readable by Open3D, labels in the face property
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(out / "scene.ply"))
    from mst.meshtools.formats import load_triangles

    V, F = load_triangles(house)
    assert len(m.triangles) == len(F) + 2
    np.testing.assert_allclose(np.asarray(m.vertices)[: len(V)], V, atol=1e-12)


def test_up_axis_y_model(tmp_path: Path):
    """A y-up model: the environment floor is perpendicular to the model's y axis."""
    p = tmp_path / "yup.obj"
    V, F = box(size=(1.0, 0.5, 0.7), split=1)
    save_triangles(p, V[:, [0, 2, 1]] * [1, 1, -1], F[:, ::-1])  # swap axes: up is now +y
    out = tmp_path / "y"
    synthesize("orbit", p, out, SynthConfig(frames=1, up="y", width=64, height=48, texture_size=64))
    _, T = read_tum(out / "gt.txt")
    assert T[0, 1, 3] > 0.5                                 # the camera is above (along +y)


# ---------------------------------------------------------------------------- CLI and bad input
def test_cli_help_and_errors(mst, house: Path, tmp_path: Path):
    r = mst("synth", "--help")
    assert "mst synth orbit --model samples/building_tin.obj -o seq/ --frames 60 --depth" in r.stdout
    r = mst("synth", "orbit", "--model", str(tmp_path / "nope.obj"), "-o", str(tmp_path / "o1"), check=False)
    assert r.returncode == 1 and "nope.obj" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o1").exists()
    r = mst("synth", "spiral", "--model", str(house), "-o", str(tmp_path / "o2"), check=False)
    assert r.returncode != 0 and "spiral" in r.stderr
    r = mst("synth", "orbit", "--model", str(house), "-o", str(tmp_path / "o3"), "--frames", "0", check=False)
    assert r.returncode == 1 and "--frames" in r.stderr and not (tmp_path / "o3").exists()  # the option is named
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")
    r = mst("synth", "orbit", "--model", str(bad), "-o", str(tmp_path / "o4"), check=False)
    assert r.returncode == 1 and "bad.obj" in r.stderr and not (tmp_path / "o4").exists()
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("x")
    r = mst("synth", "orbit", "--model", str(house), "-o", str(full), check=False)
    assert r.returncode == 1 and "not empty" in r.stderr
    assert [p.name for p in full.iterdir()] == ["keep.txt"]
    r = mst("synth", "--from-scene", str(tmp_path / "missing.json"), "-o", str(tmp_path / "o5"), check=False)
    assert r.returncode == 1 and "missing.json" in r.stderr


def test_cli_writes_sequence_and_json(mst, house: Path, tmp_path: Path):
    out = tmp_path / "cli"
    r = mst("synth", "orbit", "--model", str(house), "-o", str(out), "--frames", "2", "--width", "64",
            "--height", "48", "--texture-size", "64", "--no-depth", "--video", "--json")
    s = json.loads(r.stdout)
    assert s["frames"] == 2 and s["depth"] is False and s["clicks"] >= 4
    assert not (out / "depth").exists() and (out / "video.mp4").stat().st_size > 0
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 2


def test_pure_core_renders_the_written_frames(house: Path, orbit_seq: Path):
    """plan_sequence + render_frame (arrays, no files) give the frames and poses the runner wrote."""
    from mst.pipeline.synth import load_model_triangles, plan_sequence, render_frame

    cfg = SynthConfig(frames=4, depth_noise="kinect", click_noise=0.0, **SMALL)
    V, F = load_model_triangles(house)
    plan = plan_sequence("orbit", cfg, V, F)
    _, T_gt = read_tum(orbit_seq / "gt.txt")
    assert np.abs(plan.T_model_cam - T_gt).max() < 1e-8  # gt.txt: 9 decimals
    fr = render_frame(plan, cfg, 2)
    assert np.array_equal(fr.bgr, cv2.imread(str(orbit_seq / "rgb" / "000002.png")))
    assert np.array_equal(fr.depth, np.load(orbit_seq / "depth" / "000002.npy"))


def test_cli_config_file_sets_a_setting(mst, house: Path, tmp_path: Path):
    """Settings from a --config YAML file take effect (explicit options override them), the --json
    summary echoes the effective config; an unknown key fails naming it, writing nothing."""
    (tmp_path / "s.yaml").write_text("frames: 2\nwidth: 64\nheight: 48\ntexture_size: 64\ndepth: false\n")
    r = mst("synth", "orbit", "--model", str(house), "-o", str(tmp_path / "a"), "--config", str(tmp_path / "s.yaml"),
            "--height", "40", "--json", "-q")
    s = json.loads(r.stdout)
    assert s["frames"] == 2 and s["width"] == 64 and s["height"] == 40 and s["depth"] is False
    assert s["config"]["texture_size"] == 64 and s["config"]["height"] == 40
    assert len(list((tmp_path / "a" / "rgb").glob("*.png"))) == 2 and not (tmp_path / "a" / "depth").exists()
    (tmp_path / "bad.yaml").write_text("frames: 2\nwidht: 64\n")
    r = mst("synth", "orbit", "--model", str(house), "-o", str(tmp_path / "b"), "--config", str(tmp_path / "bad.yaml"),
            check=False)
    assert r.returncode == 1 and "widht: unknown key" in r.stderr and "bad.yaml" in r.stderr
    assert not (tmp_path / "b").exists()


def test_kinect_depth_noise_model():
    """Structured-light model: sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 plus 1/8 px disparity steps; holes."""
    from mst.pipeline.synth import kinect_depth

    rng = np.random.default_rng(0)
    z = np.full((200, 200), 2.0, np.float32)
    z[:, 150:] = 4.0                                   # a step: holes along the discontinuity
    cos = np.ones_like(z)
    cos[:20] = 0.1                                     # grazing rows: holes
    zn = kinect_depth(z, cos, 525.0, rng)
    assert (zn[:20] == 0).all()
    assert (zn[:, 148:152] == 0).all()                 # the jump, grown by one pixel
    near = zn[20:, :140]
    near = near[near > 0]
    sig = 0.0012 + 0.0019 * 1.6**2
    q = 2.0**2 / (525.0 * 0.075 * 8)                   # disparity step in metres at 2 m
    expected = np.sqrt(sig**2 + q**2 / 12)
    assert abs(near.std() - expected) < 0.25 * expected
    assert abs(near.mean() - 2.0) < 0.003
    far = zn[20:, 160:]
    assert far[far > 0].std() > 2.5 * near.std()       # noise grows with z
    assert 0.0005 < (zn[20:, :140] == 0).mean() < 0.01  # sparse random dropouts


def test_motion_blur_smooths_moving_frames(house: Path, tmp_path: Path):
    a, b = tmp_path / "sharp", tmp_path / "blur"
    kw = dict(frames=2, width=128, height=96, texture_size=64, depth=False, rgb_noise=0.0, drop=4)
    synthesize("fast", house, a, SynthConfig(**kw))
    synthesize("fast", house, b, SynthConfig(motion_blur=4, **kw))
    ia = cv2.imread(str(a / "rgb" / "000001.png")).astype(float)
    ib = cv2.imread(str(b / "rgb" / "000001.png")).astype(float)
    assert np.abs(ia - ib).mean() > 1.0
    # blur removes high-frequency energy
    assert np.abs(cv2.Laplacian(ib, cv2.CV_64F)).mean() < 0.9 * np.abs(cv2.Laplacian(ia, cv2.CV_64F)).mean()
    # ground truth is the pose at the end of the exposure: identical files
    assert (a / "gt.txt").read_bytes() == (b / "gt.txt").read_bytes()


def test_rgb_noise_encoding_statistics():
    """8-bit encoding: BGR order, rounding, and the near-Gaussian sensor noise has mean 0 and the asked sigma."""
    from mst.pipeline.render_kernels import encode_bgr8

    rgb = np.empty((200, 300, 3), np.float32)
    rgb[:] = np.array([0.2, 0.5, 0.8], np.float32)
    out = np.empty(rgb.shape, np.uint8)
    encode_bgr8(rgb, np.zeros((0, 0, 0), np.uint32), np.float32(0.0), out)
    assert (out[0, 0] == np.array([204, 128, 51])).all() and np.ptp(out.reshape(-1, 3), axis=0).max() == 0
    bits = np.random.default_rng(0).integers(0, 2**32, rgb.shape, dtype=np.uint32)
    encode_bgr8(rgb, bits, np.float32(3.0), out)
    diff = out.astype(np.float64) - np.array([204.0, 127.5, 51.0])
    assert np.abs(diff.mean(axis=(0, 1))).max() < 0.05
    assert np.allclose(diff.std(axis=(0, 1)), np.sqrt(3.0**2 + 1 / 12), atol=0.05)  # noise + 8-bit rounding
    # near-Gaussian: |level - 204| <= 3 <=> n in [-3.5, 3.5): erf(3.5 / (3 sqrt 2)) = 0.757 for a Gaussian
    inside = np.mean(np.abs(diff[..., 0]) <= 3.0)
    assert abs(inside - 0.757) < 0.02
