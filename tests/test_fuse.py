"""``mst fuse`` on depth rendered from a known mesh with known poses (exact checks), and real cube data."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst import InputError
from mst.core.camera import Camera, write_camera
from mst.core.poses import inv_T, look_at, se3_exp
from mst.core.trajectory import read_tum, write_tum
from mst.pipeline.fusion import (
    FuseConfig,
    VoxelAccumulator,
    depth_edge_mask,
    frame_index_of_times,
    fuse,
    read_extrinsic,
    read_ply_points,
    write_ply,
)

W, H = 160, 120
CAM = Camera(140.0, 140.0, 79.5, 59.5, W, H)


def _scene():
    """Legacy Open3D mesh: a 1.0 x 0.6 x 0.8 m box standing on a 4 x 4 m ground plate (z up)."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(1.0, 0.6, 0.8)
    box.translate((-0.5, -0.3, 0.0))
    ground = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 0.02)
    ground.translate((-2.0, -2.0, -0.02))
    return box + ground


def _look_at(eye, target=(0.0, 0.0, 0.4), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_model_cam for a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    return look_at(eye, target, up)


def _poses(n: int = 6) -> np.ndarray:
    a = np.linspace(0.3, 1.8, n)
    return np.stack([_look_at((2.6 * np.cos(t), 2.6 * np.sin(t), 1.6)) for t in a])


def _render(mesh, T_model_cam: np.ndarray, cam: Camera = CAM) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    # Open3D casts pixel (u, v) through (u + 0.5, v + 0.5); mst's pixel (0, 0) is the pixel centre
    K_o3d = cam.K.copy()
    K_o3d[:2, 2] += 0.5
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        intrinsic_matrix=o3d.core.Tensor(K_o3d), extrinsic_matrix=o3d.core.Tensor(inv_T(T_model_cam)),
        width_px=cam.width, height_px=cam.height)
    d = scene.cast_rays(rays)["t_hit"].numpy()
    return np.where(np.isfinite(d), d, 0).astype(np.float32)


def _distance(mesh, X: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(X.astype(np.float32))).numpy()


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    """A rendered sequence: depth/%06d.npy + .png (mm), camera.json, traj.txt (t = index), gt30.txt (t = k/30)."""
    import cv2

    root = tmp_path_factory.mktemp("fuse_seq")
    (root / "depth").mkdir()
    mesh = _scene()
    T = _poses()
    for k, Tk in enumerate(T):
        d = _render(mesh, Tk)
        np.save(root / "depth" / f"{k:06d}.npy", d)
        cv2.imwrite(str(root / "depth" / f"{k:06d}.png"), np.rint(d * 1000).astype(np.uint16))
    write_camera(root / "camera.json", CAM)
    write_tum(root / "traj.txt", np.arange(len(T), dtype=float), T)
    write_tum(root / "gt30.txt", np.arange(len(T)) / 30.0, T)
    return {"root": root, "mesh": mesh, "T": T}


def _cfg(**kw) -> FuseConfig:
    """A config keeping every sample; ``kw``: settings by name (``depth__max_m`` for ``depth.max_m``)."""
    return FuseConfig().merged({"voxel_m": 0.0, **{k.replace("__", "."): v for k, v in kw.items()}})


def test_points_lie_on_the_mesh(seq, tmp_path):
    r = seq["root"]
    s = fuse(tmp_path / "c.ply", _cfg(), r / "traj.txt", r / "depth", r / "camera.json")
    X, rgb = read_ply_points(tmp_path / "c.ply")
    assert rgb is None and len(X) == s["points_out"] == s["points_fused"] > 5000
    assert s["fused_frames"] == 6 and s["skipped_no_pose"] == 0
    dist = _distance(seq["mesh"], X)
    assert dist.max() < 1e-3, dist.max()
    # every pose contributed: each frame adds points seen only from its viewpoint
    assert s["samples"] == s["points_fused"] + s["dropped_range"] + s["dropped_edge"] + s["dropped_grazing"]


def test_fuse_frames_pure_core_equals_the_file_runner(seq, tmp_path):
    """The core takes arrays (depth in metres, depth-camera poses) and returns a Cloud, no files:
    the same points, bit for bit, as the runner that reads the frames and writes the PLY."""
    from mst.pipeline.fusion import FuseFrame, fuse_frames

    r = seq["root"]
    cfg = _cfg(voxel_m=0.02)
    fuse(tmp_path / "runner.ply", cfg, r / "traj.txt", r / "depth", r / "camera.json")
    X_file, _ = read_ply_points(tmp_path / "runner.ply")
    _, T_file = read_tum(r / "traj.txt")  # the poses as the runner reads them (TUM: 9 decimals)
    frames = [FuseFrame(k, f"frame {k}", np.load(r / "depth" / f"{k:06d}.npy"), T) for k, T in enumerate(T_file)]
    cloud = fuse_frames(frames, CAM, cfg)
    np.testing.assert_array_equal(cloud.X, X_file)
    js = cloud.to_json()
    assert js["mode"] == "voxel" and js["fused_frames"] == 6 and js["points_out"] == len(X_file)
    assert cloud.rgb is None and cloud.count.sum() == js["points_fused"]


def test_png_millimetres_match_npy(seq, tmp_path):
    r = seq["root"]
    fuse(tmp_path / "a.ply", _cfg(), r / "traj.txt", r / "depth", r / "camera.json")
    fuse(tmp_path / "b.ply", _cfg(), r / "traj.txt", str(r / "depth" / "*.png"), r / "camera.json")
    Xa, _ = read_ply_points(tmp_path / "a.ply")
    Xb, _ = read_ply_points(tmp_path / "b.ply")
    assert abs(len(Xa) - len(Xb)) < 0.01 * len(Xa)
    assert _distance(seq["mesh"], Xb).max() < 2e-3  # 0.5 mm quantisation, magnified at grazing angles


def test_voxel_grid_averages_per_voxel(seq, tmp_path):
    r = seq["root"]
    fuse(tmp_path / "all.ply", _cfg(), r / "traj.txt", r / "depth", r / "camera.json")
    s = fuse(tmp_path / "vox.ply", _cfg(voxel_m=0.02), r / "traj.txt", r / "depth", r / "camera.json")
    X, _ = read_ply_points(tmp_path / "all.ply")
    V, _ = read_ply_points(tmp_path / "vox.ply")
    # same voxels as an independent np.unique over all samples (origin = first camera centre)
    origin = seq["T"][0][:3, 3]
    keys, inv, cnt = np.unique(np.floor((X - origin) / 0.02).astype(np.int64), axis=0, return_inverse=True,
                               return_counts=True)
    assert len(V) == len(keys) == s["points_out"]
    cent = np.stack([np.bincount(inv.ravel(), weights=X[:, i]) for i in range(3)], axis=1) / cnt[:, None]
    order = np.lexsort(np.floor((V - origin) / 0.02).astype(np.int64).T[::-1])
    np.testing.assert_allclose(V[order], cent, atol=1e-9)
    raw = (tmp_path / "vox.ply").read_bytes()
    assert b"property double x" in raw and b"property uint count" in raw


def test_voxel_accumulator_streaming_equals_batch():
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, (20000, 3))
    a, b = VoxelAccumulator(0.1), VoxelAccumulator(0.1)
    a.add(X)
    for chunk in np.array_split(X, 7):
        b.add(chunk)
    Xa, _, ca = a.result()
    Xb, _, cb = b.result()
    np.testing.assert_allclose(Xa, Xb, atol=1e-12)
    np.testing.assert_array_equal(ca, cb)
    assert ca.sum() == len(X) and len(Xa) == len(np.unique(np.floor(X / 0.1).astype(np.int64), axis=0))


def test_lost_frames_skipped_and_fps_association(seq, tmp_path):
    r = seq["root"]
    T = seq["T"]
    keep = [0, 2, 3, 5]
    write_tum(tmp_path / "lost.txt", np.array(keep, float), T[keep])
    s = fuse(tmp_path / "l.ply", _cfg(), tmp_path / "lost.txt", r / "depth", r / "camera.json")
    assert s["fused_frames"] == 4 and s["skipped_no_pose"] == 2
    s2 = fuse(tmp_path / "g.ply", _cfg(fps=30.0), r / "gt30.txt", r / "depth", r / "camera.json")
    fuse(tmp_path / "i.ply", _cfg(), r / "traj.txt", r / "depth", r / "camera.json")
    assert s2["fused_frames"] == 6
    assert (tmp_path / "g.ply").read_bytes() == (tmp_path / "i.ply").read_bytes()
    with pytest.raises(InputError, match="not a frame index.*fps"):
        fuse(tmp_path / "x.ply", _cfg(), r / "gt30.txt", r / "depth", r / "camera.json")
    s3 = fuse(tmp_path / "st.ply", _cfg(stride=2), r / "traj.txt", r / "depth", r / "camera.json")
    assert s3["fused_frames"] == 3 and s3["skipped_stride"] == 3
    assert not (tmp_path / "x.ply").exists()


def test_frame_index_of_times():
    np.testing.assert_array_equal(frame_index_of_times(np.array([0.0, 1 / 30, 0.1]), 30.0, "t"), [0, 1, 3])
    with pytest.raises(InputError, match="several poses"):
        frame_index_of_times(np.array([0.0, 0.01]), 30.0, "t")


def test_depth_to_color_extrinsic(seq, tmp_path):
    """Trajectory of a colour camera 5 cm beside the depth camera + depth_M_color gives the same cloud."""
    r = seq["root"]
    T_depth_color = se3_exp(np.array([-0.05, 0.002, 0.001, 0.01, -0.02, 0.015]))
    np.savetxt(tmp_path / "depth_M_color.txt", T_depth_color)
    T_model_color = seq["T"] @ T_depth_color  # T_model_depth @ T_depth_color
    write_tum(tmp_path / "color_traj.txt", np.arange(6, dtype=float), T_model_color)
    fuse(tmp_path / "ref.ply", _cfg(), r / "traj.txt", r / "depth", r / "camera.json")
    fuse(tmp_path / "ext.ply", _cfg(), tmp_path / "color_traj.txt", r / "depth", r / "camera.json",
         depth_to_color_path=tmp_path / "depth_M_color.txt")
    A, _ = read_ply_points(tmp_path / "ref.ply")
    B, _ = read_ply_points(tmp_path / "ext.ply")
    assert A.shape == B.shape
    np.testing.assert_allclose(A, B, atol=2e-6)  # TUM quaternions are written with 9 decimals
    # the other way round would be wrong by ~10 cm
    np.savetxt(tmp_path / "wrong.txt", inv_T(T_depth_color))
    fuse(tmp_path / "bad.ply", _cfg(), tmp_path / "color_traj.txt", r / "depth", r / "camera.json",
         depth_to_color_path=tmp_path / "wrong.txt")
    Cw, _ = read_ply_points(tmp_path / "bad.ply")
    assert np.median(_distance(seq["mesh"], Cw)) > 0.01


def test_read_extrinsic_rejects_non_rigid(tmp_path):
    np.savetxt(tmp_path / "s.txt", np.diag([2.0, 1, 1, 1]))
    with pytest.raises(InputError, match="not a rigid"):
        read_extrinsic(tmp_path / "s.txt")
    (tmp_path / "short.txt").write_text("1 0 0\n")
    with pytest.raises(InputError, match="3 numbers"):
        read_extrinsic(tmp_path / "short.txt")


def test_edge_and_grazing_filters():
    d = np.full((20, 20), 1.0, np.float32)
    d[:, 10:] = 2.0  # a step: columns 9 and 10 are at the discontinuity
    e = depth_edge_mask(d, 0.03)
    assert e[:, 9].all() and e[:, 10].all() and e.sum() == 40
    assert not depth_edge_mask(np.full((5, 5), 1.0, np.float32), 0.03).any()
    # a plane seen at 85 degrees is dropped with max angle 80, kept with 89
    from mst.pipeline.fusion import backproject, pixel_rays

    cam = Camera(100.0, 100.0, 24.5, 24.5, 50, 50)
    rays = pixel_rays(cam, 50, 50)
    n = np.array([np.sin(np.radians(85)), 0.0, -np.cos(np.radians(85))])  # normal 85 deg from the optical axis
    # plane n . X = -c through (0, 0, 1): depth along each ray = (n . X0) / (n . ray)
    depth = ((n @ np.array([0, 0, 1.0])) / (rays @ n)).astype(np.float32)
    depth[(depth < 0.1) | (depth > 10)] = 0
    _, keep80, c80, _ = backproject(depth, rays, _cfg(depth__edge_rel=0, max_angle_deg=80))
    _, keep89, c89, _ = backproject(depth, rays, _cfg(depth__edge_rel=0, max_angle_deg=89.9))
    centre = keep89[20:30, 20:30]
    assert centre.all() and not keep80[20:30, 20:30].any()
    assert c80["dropped_grazing"] > c89["dropped_grazing"]


def test_smooth_depth_denoises_keeps_steps_and_holes():
    from mst.pipeline.fusion import smooth_depth

    rng = np.random.default_rng(0)
    z = np.full((60, 80), 2.0, np.float32)
    z[:, 40:] = 2.5  # a 0.5 m step
    noisy = (z + rng.normal(0, 0.01, z.shape)).astype(np.float32)
    noisy[10:14, 10:14] = 0  # a hole
    s = smooth_depth(noisy, 7, 0.02)
    assert (s[10:14, 10:14] == 0).all() and (s[noisy > 0] > 0).all()
    inner = (noisy > 0) & (np.abs(np.arange(80) - 39.5) > 4)[None, :]
    inner[:4] = inner[-4:] = False
    assert np.std((s - z)[inner]) < 0.3 * np.std((noisy - z)[inner])  # noise down by > 3x
    # the step stays sharp: the columns next to it keep their own side's depth (no blending)
    assert np.abs(s[20:40, 39] - 2.0).max() < 0.02 and np.abs(s[20:40, 40] - 2.5).max() < 0.02
    # next to the hole, depths stay ~2 m (the hole's fill value never leaks in)
    assert np.abs(s[9:15, 8:16][noisy[9:15, 8:16] > 0] - 2.0).max() < 0.02


def test_tsdf_surface_close_to_mesh(seq, tmp_path):
    r = seq["root"]
    s = fuse(tmp_path / "t.ply", FuseConfig(tsdf=True, tsdf_voxel_m=0.02), r / "traj.txt", r / "depth", r / "camera.json")
    X, _ = read_ply_points(tmp_path / "t.ply")
    assert s["mode"] == "tsdf" and len(X) > 1000
    dist = _distance(seq["mesh"], X)
    # budget: the zero crossing is interpolated linearly between voxel centres, exact on a plane up
    # to the depth quantisation (0.5 mm): median < 1 mm; the box's edges and corners are rounded over
    # about one voxel, a band of < 5 % of the surface: 95 % within 0.4 voxel (8 mm)
    assert np.median(dist) < 0.001 and np.quantile(dist, 0.95) < 0.4 * 0.02
    assert b"property uint count" not in (tmp_path / "t.ply").read_bytes()[:400]


def test_color_points(seq, tmp_path):
    import cv2

    r = seq["root"]
    (tmp_path / "rgb").mkdir()
    for k in range(6):  # BGR image: pure red for even frames, blue for odd
        img = np.zeros((H, W, 3), np.uint8)
        img[:, :, 2 if k % 2 == 0 else 0] = 200
        cv2.imwrite(str(tmp_path / "rgb" / f"{k:06d}.png"), img)
    write_tum(tmp_path / "even.txt", np.array([0.0, 2.0, 4.0]), seq["T"][[0, 2, 4]])
    s = fuse(tmp_path / "c.ply", _cfg(), tmp_path / "even.txt", r / "depth", r / "camera.json", color_dir=tmp_path / "rgb")
    X, rgb = read_ply_points(tmp_path / "c.ply")
    assert rgb is not None and s["colored_samples"] == len(X)
    assert (rgb == [200, 0, 0]).all()
    # voxel averaging mixes red (even frames) and blue (odd frames) where both saw a voxel
    fuse(tmp_path / "v.ply", _cfg(voxel_m=0.05), r / "traj.txt", r / "depth", r / "camera.json", color_dir=tmp_path / "rgb")
    _, rgbv = read_ply_points(tmp_path / "v.ply")
    assert (rgbv[:, 1] == 0).all() and ((rgbv[:, 0] > 0) & (rgbv[:, 2] > 0)).mean() > 0.3
    assert ((rgbv[:, 0] + rgbv[:, 2]).astype(int) - 200 <= 1).all()
    # the TSDF carries colour too
    fuse(tmp_path / "t.ply", FuseConfig(tsdf=True, tsdf_voxel_m=0.03), tmp_path / "even.txt", r / "depth", r / "camera.json",
         color_dir=tmp_path / "rgb")
    _, rgbt = read_ply_points(tmp_path / "t.ply")
    assert np.median(rgbt[:, 0]) == 200 and rgbt[:, 1:].max() == 0


def test_landmarks_pass_through(tmp_path):
    rng = np.random.default_rng(1)
    L = rng.uniform(-1, 1, (500, 3)) + [445000.0, 5400000.0, 300.0]  # georeferenced-size coordinates
    write_ply(tmp_path / "lm.ply", L)
    s = fuse(tmp_path / "out.ply", _cfg(), landmarks_path=tmp_path / "lm.ply")
    X, _ = read_ply_points(tmp_path / "out.ply")
    assert s["landmarks"] == 500
    np.testing.assert_array_equal(X, L)  # double precision kept exactly


def test_landmarks_bad_ply(tmp_path):
    write_ply(tmp_path / "lm.ply", np.zeros((100, 3)))
    raw = (tmp_path / "lm.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(raw[:-50])
    with pytest.raises(InputError, match=r"cut\.ply: PLY is truncated"):
        fuse(tmp_path / "o.ply", _cfg(), landmarks_path=tmp_path / "cut.ply")
    (tmp_path / "txt.ply").write_text("hello\n")
    with pytest.raises(InputError, match="not a PLY"):
        fuse(tmp_path / "o.ply", _cfg(), landmarks_path=tmp_path / "txt.ply")
    assert not (tmp_path / "o.ply").exists()
    # ASCII PLY with colour
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                    "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                                    "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
                                    "1 2 3 255 0 0\n4 5 6 0 255 0\n")
    X, rgb = read_ply_points(tmp_path / "a.ply")
    np.testing.assert_array_equal(X, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(rgb, [[255, 0, 0], [0, 255, 0]])


def test_cli_json_and_errors(seq, tmp_path, mst):
    r = seq["root"]
    out = tmp_path / "cli.ply"
    p = mst("fuse", "--traj", r / "traj.txt", "--depth", r / "depth", "--camera", r / "camera.json",
            "--voxel", "0.01", "-o", out, "--json", "-q")
    js = json.loads(p.stdout)
    assert js["fused_frames"] == 6 and js["points_out"] == len(read_ply_points(out)[0])
    assert p.stderr == ""
    # a corrupt frame: one error line naming it, exit 1, no output
    bad = tmp_path / "bad_depth"
    bad.mkdir()
    for f in sorted((r / "depth").glob("*.npy")):
        (bad / f.name).write_bytes(f.read_bytes())
    (bad / "000003.npy").write_bytes((bad / "000003.npy").read_bytes()[:100])
    out2 = tmp_path / "bad.ply"
    p = mst("fuse", "--traj", r / "traj.txt", "--depth", bad, "--camera", r / "camera.json", "-o", out2, check=False)
    assert p.returncode == 1 and not out2.exists()
    assert p.stderr.strip().splitlines()[-1].startswith("mst fuse: error: ") and "000003.npy" in p.stderr
    # infinite max depth is allowed (no limit) and the JSON stays valid
    p = mst("fuse", "--traj", r / "traj.txt", "--depth", r / "depth", "--camera", r / "camera.json",
            "--max-depth", "inf", "-o", tmp_path / "inf.ply", "--json", "-q")
    # echoed as "inf" (JSON has no infinity), which --config reads back as no limit
    assert json.loads(p.stdout)["config"]["depth"]["max_m"] == "inf"
    p = mst("fuse", "--help")
    assert "mst fuse --traj traj.txt --depth seq/depth --camera seq/camera.json --voxel 0.01 -o cloud.ply" in p.stdout


def test_cli_config_file_sets_a_setting_and_repeats_a_run(seq, tmp_path, mst):
    """A setting from a --config YAML file takes effect; the --json config repeats the run exactly;
    an explicit option overrides the file; an unknown key fails naming it (dotted), writing nothing."""
    r = seq["root"]
    args = ["fuse", "--traj", r / "traj.txt", "--depth", r / "depth", "--camera", r / "camera.json", "--json", "-q"]
    (tmp_path / "c.yaml").write_text("stride: 2\nvoxel_m: 0.02\ndepth:\n  max_m: 2.5\n")
    js = json.loads(mst(*args, "--config", tmp_path / "c.yaml", "-o", tmp_path / "a.ply").stdout)
    assert js["fused_frames"] == 3 and js["skipped_stride"] == 3
    assert js["config"]["depth"]["max_m"] == 2.5 and js["config"]["voxel_m"] == 0.02
    full = json.loads(mst(*args, "--config", tmp_path / "c.yaml", "--set", "depth.max_m=50",
                          "-o", tmp_path / "far.ply").stdout)
    assert full["dropped_range"] < js["dropped_range"]  # the 2.5 m limit dropped samples
    (tmp_path / "echo.json").write_text(json.dumps(js["config"]))
    mst(*args, "--config", tmp_path / "echo.json", "-o", tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    js3 = json.loads(mst(*args, "--config", tmp_path / "c.yaml", "--stride", "1", "-o", tmp_path / "s1.ply").stdout)
    assert js3["fused_frames"] == 6 and js3["config"]["stride"] == 1
    (tmp_path / "bad.yaml").write_text("depth:\n  scal: 5000\n")
    p = mst(*args, "--config", tmp_path / "bad.yaml", "-o", tmp_path / "bad.ply", check=False)
    assert p.returncode == 1 and "depth.scal: unknown key" in p.stderr and "bad.yaml" in p.stderr
    assert not (tmp_path / "bad.ply").exists()
    listing = mst("fuse", "--show-config").stdout  # every setting by its dotted name, with its default
    assert "depth.scale" in listing and "tsdf_voxel_m" in listing


def test_real_cube_colour_through_extrinsic(shared_data, tmp_path):
    """Colour frames seen by the colour camera, mapped with depth_M_color (frames 0 and 5)."""
    cube = shared_data / "visp-cube-rgbd"
    write_tum(tmp_path / "id.txt", np.array([0.0, 5.0]), np.repeat(np.eye(4)[None], 2, axis=0))
    s = fuse(tmp_path / "c.ply", _cfg(voxel_m=0.004, depth__max_m=1.0), tmp_path / "id.txt", cube,
             cube / "model" / "cube_depth.xml", depth_to_color_path=cube / "depth_M_color.txt", color_dir=cube,
             color_camera_path=cube / "model" / "cube.xml")
    X, rgb = read_ply_points(tmp_path / "c.ply")
    assert s["fused_frames"] == 2 and rgb is not None
    # the colour camera (f = 615 px) sees a narrower cone than the depth camera (f = 384 px)
    frac = s["colored_samples"] / s["points_fused"]
    assert 0.3 < frac < 0.95, frac
    # the cloud is in the colour camera's frame: the cube (image centre) is straight ahead of it
    lit = X[rgb.sum(axis=1) > 0]
    assert np.abs(np.median(lit[:, 0] / lit[:, 2])) < 0.3


def test_real_cube_frames(shared_data, tmp_path, mst):
    """The 10 ViSP RealSense frames fused with one identity pose per frame (static camera)."""
    cube = shared_data / "visp-cube-rgbd"
    write_tum(tmp_path / "id.txt", np.arange(10, dtype=float), np.repeat(np.eye(4)[None], 10, axis=0))
    out = tmp_path / "cube.ply"
    p = mst("fuse", "--traj", tmp_path / "id.txt", "--depth", cube, "--camera", cube / "model" / "cube_depth.xml",
            "--max-depth", "1.0", "--voxel", "0.002", "-o", out, "--json", "-q")
    js = json.loads(p.stdout)
    assert js["fused_frames"] == 10 and js["frames"] == 10
    X, _ = read_ply_points(out)
    assert len(X) > 10000 and (X[:, 2] <= 1.0 + 1e-9).all() and (X[:, 2] >= 0.1).all()
    # identity poses: model frame = depth camera frame. Crop around the cube (image centre).
    u = 383.97 * X[:, 0] / X[:, 2] + 320.5
    v = 383.97 * X[:, 1] / X[:, 2] + 235.6
    C = X[(u > 240) & (u < 420) & (v > 170) & (v < 320)]
    assert len(C) > 2000
    # the board under the cube is the dominant plane of the crop (RANSAC, 3 mm)
    rng = np.random.default_rng(0)
    best_n, best = 0, None
    for _ in range(300):
        a, b, c = C[rng.choice(len(C), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        k = int((np.abs((C - a) @ n) < 0.003).sum())
        if k > best_n:
            best_n, best = k, (a, n)
    assert best_n > 0.4 * len(C)
    a, n = best
    if a @ n > 0:  # orient the normal towards the camera (the origin)
        n = -n
    h = (C - a) @ n
    cube = h[h > 0.01]
    assert cube.size > 300
    # the top face of the 42 mm cube
    assert 0.036 < np.quantile(cube, 0.95) < 0.048, np.quantile(cube, [0.5, 0.95, 1.0])
