"""``mst fuse`` benchmarks: throughput at 640x480 (voxel and TSDF modes) and bounded memory.

Inputs are generated here: 24 depth frames (640x480 float32 ``.npy``, metres) rendered with Open3D's
``RaycastingScene`` from an orbit around a box on a ground plate, and longer sequences made of
symbolic links to those frames (frame k repeats frame k mod 24, with its pose), so the output cloud
stays the same size while the sequence grows: peak RSS must then not grow with the frame count.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from mst.eval.bench.harness import mst_cmd, timed_command

W, H, N_BASE = 640, 480, 24


def _scene_and_poses():
    import open3d as o3d

    from mst.core.poses import make_T

    box = o3d.geometry.TriangleMesh.create_box(1.0, 0.6, 0.8)
    box.translate((-0.5, -0.3, 0.0))
    ground = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 0.02)
    ground.translate((-2.0, -2.0, -0.02))
    mesh = box + ground
    poses = []
    for a in np.linspace(0.0, 1.5, N_BASE):
        eye = np.array([2.4 * np.cos(a), 2.4 * np.sin(a), 1.5])
        z = np.array([0.0, 0.0, 0.4]) - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        poses.append(make_T(np.stack([x, np.cross(z, x), z], axis=1), eye))
    return mesh, np.stack(poses)


def make_inputs(work: Path) -> tuple[Path, Path, np.ndarray]:
    """Render the base frames once: ``(depth folder, camera.json, T_model_cam (24, 4, 4))``."""
    import open3d as o3d

    from mst.core.camera import Camera, write_camera
    from mst.core.poses import inv_T

    base = work / "base"
    base.mkdir(parents=True, exist_ok=True)
    cam = Camera(525.0, 525.0, 319.5, 239.5, W, H)
    write_camera(work / "camera.json", cam)
    mesh, poses = _scene_and_poses()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    K = cam.K.copy()
    K[:2, 2] += 0.5  # Open3D rays go through pixel u + 0.5
    rng = np.random.default_rng(0)
    for k, T in enumerate(poses):
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            intrinsic_matrix=o3d.core.Tensor(K), extrinsic_matrix=o3d.core.Tensor(inv_T(T)), width_px=W, height_px=H)
        d = scene.cast_rays(rays)["t_hit"].numpy()
        d = np.where(np.isfinite(d), d + rng.normal(0, 0.001, d.shape), 0).astype(np.float32)  # 1 mm noise
        np.save(base / f"{k:06d}.npy", d)
    return base, work / "camera.json", poses


def make_sequence(work: Path, base: Path, poses: np.ndarray, n: int) -> tuple[Path, Path]:
    """``n`` frames as symbolic links to the base frames + the matching trajectory (t = index)."""
    from mst.core.trajectory import write_tum

    d = work / f"seq{n}"
    d.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        link = d / f"{k:06d}.npy"
        if not link.exists():
            os.symlink(base / f"{k % len(poses):06d}.npy", link)
    traj = work / f"traj{n}.txt"
    write_tum(traj, np.arange(n, dtype=float), poses[np.arange(n) % len(poses)])
    return d, traj


def _fuse(depth: Path, traj: Path, cam: Path, out: Path, *extra: str) -> dict:
    r = timed_command(mst_cmd("fuse", "--traj", traj, "--depth", depth, "--camera", cam, "-o", out,
                              "--json", "-q", *extra))
    js = json.loads(r["stdout"])
    return {"wall_s": r["wall_s"], "peak_rss_mib": r["peak_rss_mib"], **js}


def run(workdir: Path) -> list[dict]:
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    base, cam, poses = make_inputs(workdir)
    rows: list[dict] = []
    seq, traj = make_sequence(workdir, base, poses, 96)
    for name, extra in (("fuse voxel 1 cm, 96 frames 640x480", ("--voxel", "0.01")),
                        ("fuse voxel 1 cm + smooth 5 px, 96 frames 640x480", ("--voxel", "0.01", "--smooth", "5")),
                        ("fuse TSDF 1 cm, 96 frames 640x480", ("--tsdf", "--voxel", "0.01"))):
        s = _fuse(seq, traj, cam, workdir / "cloud.ply", *extra)
        rows.append({"bench": name, "fps": s["frames_per_s"], "points_per_s": s["points_per_s"],
                     "points_out": s["points_out"], "wall_s": s["wall_s"], "peak_rss_mib": s["peak_rss_mib"]})
    # memory: 100 vs 500 frames of the same views (same output cloud): peak RSS must not grow
    rss = {}
    for n in (100, 500):
        seq, traj = make_sequence(workdir, base, poses, n)
        s = _fuse(seq, traj, cam, workdir / f"long{n}.ply", "--voxel", "0.005")
        rss[n] = s
    grow = rss[500]["peak_rss_mib"] - rss[100]["peak_rss_mib"]
    rows.append({"bench": "fuse voxel 5 mm, 500 frames: peak RSS vs 100 frames",
                 "peak_rss_mib": rss[500]["peak_rss_mib"], "peak_rss_100_mib": rss[100]["peak_rss_mib"],
                 "rss_growth_mib": grow, "points_out": rss[500]["points_out"], "fps": rss[500]["frames_per_s"],
                 "wall_s": rss[500]["wall_s"], "target": "RSS growth 100 -> 500 frames < 10 % (+30 MiB)",
                 "ok": bool(grow < 0.1 * rss[100]["peak_rss_mib"] + 30)})
    return rows


if __name__ == "__main__":
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for row in run(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tmp)):
            print(json.dumps(row))
