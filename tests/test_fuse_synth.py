"""``mst fuse`` on ``mst synth`` sequences: exact with ground-truth poses, and the issue's acceptance
chain (convert-model -> init -> track -> fuse -> c2m) with TRACKED poses and Kinect-like depth noise."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mst.meshtools.formats import load_triangles
from mst.pipeline.fusion import FuseConfig, fuse, read_ply_points
from mst.pipeline.synth import SynthConfig, synthesize


@pytest.fixture(scope="module")
def house(gabled_house_tin) -> Path:
    """The tests' gabled house at 0.4 x (1.6 x 1.2 m, 1.5 m high): a tabletop-size RGB-D scene."""
    return gabled_house_tin(0.4)


def _distance_to(mesh_path: Path, X: np.ndarray) -> np.ndarray:
    import open3d as o3d

    V, F = load_triangles(mesh_path)
    c = V.mean(axis=0)  # shift to keep float32 exact enough
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((V - c).astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor((X - c).astype(np.float32))).numpy()


def test_ground_truth_poses_exact(house, tmp_path):
    """Noise-free depth + gt.txt (t = k / 30 s): every fused sample within 1e-3 m of scene.ply."""
    seq = tmp_path / "seq"
    synthesize("orbit", house, seq, SynthConfig(frames=5, width=320, height=240, texture_size=64, depth_noise="none"))
    s = fuse(tmp_path / "c.ply", FuseConfig(voxel_m=0.0, fps=30.0), seq / "gt.txt", seq / "depth", seq / "camera.json")
    X, _ = read_ply_points(tmp_path / "c.ply")
    assert s["fused_frames"] == 5 and len(X) > 50_000
    d = _distance_to(seq / "scene.ply", X)
    assert d.max() < 1e-3, d.max()
    # the millimetre PNGs give the same surface within the 0.5 mm quantisation (+ grazing magnification)
    fuse(tmp_path / "p.ply", FuseConfig(voxel_m=0.0, fps=30.0), seq / "gt.txt", str(seq / "depth" / "*.png"), seq / "camera.json")
    Xp, _ = read_ply_points(tmp_path / "p.ply")
    assert np.quantile(_distance_to(seq / "scene.ply", Xp), 0.99) < 1e-3


def test_acceptance_tracked_rgbd_fusion(house, tmp_path, mst):
    """Issue 6: RGB-D fusion with tracked poses, realistic (Kinect v1) depth noise: >= 95 % of the
    fused points within 1 cm of scene.ply by `mst c2m`. Camera ~2.5 m from the house (sensor range;
    Kinect sigma there is ~1 cm per sample, so the TSDF's averaging along the rays does the work)."""
    seq = tmp_path / "seq"
    synthesize("orbit", house, seq, SynthConfig(frames=12, distance=2.5, environment=False, depth_noise="kinect",
                                                texture_size=64))
    mst("convert-model", seq / "model.obj", "-o", tmp_path / "house.wrl", "-q")
    mst("init", "--model", tmp_path / "house.wrl", "--camera", seq / "camera.json", "--clicks", seq / "clicks.txt",
        "-o", tmp_path / "pose0.txt", "-q")
    mst("track", seq / "rgb", "--model", tmp_path / "house.wrl", "--camera", seq / "camera.json",
        "--init", tmp_path / "pose0.txt", "-o", tmp_path / "traj.txt", "-q")
    r = mst("fuse", "--traj", tmp_path / "traj.txt", "--depth", seq / "depth", "--camera", seq / "camera.json",
            "--tsdf", "--voxel", "0.01", "-o", tmp_path / "cloud.ply", "--json", "-q")
    fj = json.loads(r.stdout)
    assert fj["fused_frames"] >= 11  # tracked, not lost
    r = mst("c2m", tmp_path / "cloud.ply", seq / "scene.ply", "--thresholds", "0.005,0.01,0.02", "--json")
    cj = json.loads(r.stdout)
    pct = {t["max_dist"]: t["percent"] for t in cj["thresholds"]}
    assert cj["points_total"] == fj["points_out"] > 10_000
    assert pct[0.01] >= 95.0, pct
    # the voxel grid needs the per-frame bilateral smoothing for this noise (85 % within 1 cm without)
    mst("fuse", "--traj", tmp_path / "traj.txt", "--depth", seq / "depth", "--camera", seq / "camera.json",
        "--smooth", "5", "--voxel", "0.01", "-o", tmp_path / "vox.ply", "-q")
    r = mst("c2m", tmp_path / "vox.ply", seq / "scene.ply", "--thresholds", "0.01", "--json")
    assert json.loads(r.stdout)["thresholds"][0]["percent"] >= 95.0


def test_acceptance_tracked_rgbd_fusion_in_the_textured_room(house, tmp_path, mst):
    """The same acceptance in the full scene (house + textured floor and walls, as `mst synth` renders
    by default), tracked with the RGB-D SLAM aid, depth used within 3 m (Kinect v1's accurate range;
    its noise is 2-2.6 cm at 3.5-4 m, which caps even ground-truth poses near 95 % within 1 cm):
    >= 95 % of the fused points within 1 cm of scene.ply, and the tracked poses lose at most one
    point of that share against fusion with the ground-truth poses."""
    seq = tmp_path / "seq"
    synthesize("orbit", house, seq, SynthConfig(frames=24, distance=2.5, depth_noise="kinect", texture_size=64))
    mst("convert-model", seq / "model.obj", "-o", tmp_path / "house.wrl", "-q")
    mst("init", "--model", tmp_path / "house.wrl", "--camera", seq / "camera.json", "--clicks", seq / "clicks.txt",
        "-o", tmp_path / "pose0.txt", "-q")
    r = mst("track", seq / "rgb", "--fps", "30", "--model", tmp_path / "house.wrl", "--camera", seq / "camera.json",
            "--init", tmp_path / "pose0.txt", "--depth", seq / "depth", "-o", tmp_path / "traj.txt", "--json", "-q")
    tj = json.loads(r.stdout)
    assert tj["aid"] == "rgbd" and tj["lost"] == 0

    def fused_share(traj):
        r = mst("fuse", "--traj", traj, "--fps", "30", "--depth", seq / "depth", "--camera", seq / "camera.json",
                "--tsdf", "--voxel", "0.01", "--max-depth", "3", "-o", tmp_path / "cloud.ply", "--json", "-q")
        assert json.loads(r.stdout)["fused_frames"] == 24
        r = mst("c2m", tmp_path / "cloud.ply", seq / "scene.ply", "--thresholds", "0.01,0.02", "--json", "-q")
        return {t["max_dist"]: t["percent"] for t in json.loads(r.stdout)["thresholds"]}

    tracked, truth = fused_share(tmp_path / "traj.txt"), fused_share(seq / "gt.txt")
    assert tracked[0.01] >= 95.0 and tracked[0.02] >= 99.0, tracked
    assert tracked[0.01] >= truth[0.01] - 1.0, (tracked, truth)
