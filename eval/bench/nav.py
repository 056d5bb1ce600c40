"""Navigation benchmarks: ``mst nav fuse`` on a 10-minute log at 30 fps (target <= 10 s) and the
automatic-initialisation search (target <= 2 s).

Inputs are generated here: a 600 s UAV orbit (18,000 frames) with vision poses = truth + white noise
(0.3 m / 0.5 deg) and a 10 s loss, a 5 Hz GPS/AHRS log from :func:`mst.pipeline.nav.log.simulate_nav`;
for the search, one rendered 640x480 view of an L-shaped building from 40 m and one ``mst synth orbit``
frame of the bundled sample house (12 m, textured floor), each with a 3 m / 3 deg guess.
The fusion is timed as a whole command (files in, files out), the search in-process (median of 3).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mst.eval.bench.harness import mst_cmd, timed_command


def _flight(duration_s: float, fps: float):
    from mst.core.poses import look_at

    t = np.arange(0.0, duration_s, 1.0 / fps)
    w = 6.0 / 60.0
    P = np.stack([60 * np.cos(w * t), 42 * np.sin(w * t), 40 + 3 * np.sin(0.2 * t)], 1)
    T = np.stack([look_at(p, np.array([5 * np.sin(0.1 * ti), 0.0, 0.0])) for p, ti in zip(P, t)])
    return t, T


def run(workdir: Path) -> list[dict]:
    from mst.core.poses import so3_exp
    from mst.core.trajectory import write_tum
    from mst.pipeline.nav.log import NavSimConfig, simulate_nav, write_sim_outputs

    workdir.mkdir(parents=True, exist_ok=True)
    t, T = _flight(600.0, 30.0)
    rng = np.random.default_rng(0)
    Tv = T.copy()
    Tv[:, :3, 3] += rng.normal(0, 0.3, (len(t), 3))
    Tv[:, :3, :3] = so3_exp(rng.normal(0, np.radians(0.5), (len(t), 3))) @ T[:, :3, :3]
    keep = ~((t >= 200) & (t < 210))
    write_tum(workdir / "traj.txt", t[keep], Tv[keep])
    sim = simulate_nav(t, T, NavSimConfig(seed=1, dropouts=3))
    write_sim_outputs(sim, workdir / "nav.csv", None)
    r = timed_command(mst_cmd("nav", "fuse", "--traj", str(workdir / "traj.txt"), "--nav", str(workdir / "nav.csv"),
                              "-o", str(workdir / "fused.txt"), "-q"))
    out = [{"bench": "nav fuse 10 min @ 30 fps (18000 frames)", "wall_s": r["wall_s"], "cpu_s": r["cpu_s"],
            "peak_rss_mib": r["peak_rss_mib"], "target": "<= 10 s", "ok": r["wall_s"] <= 10.0}]

    import cv2

    from mst.core.camera import Camera
    from mst.core.poses import inv_T, look_at
    from mst.meshtools.generate import l_shape_model
    from mst.pipeline.render import Renderer

    m = l_shape_model()
    cam = Camera(500, 500, 319.5, 239.5, 640, 480)
    c = m.vertices.mean(0)
    T_mc = look_at(c + 40.0 * np.array([np.cos(0.6), -np.sin(0.6), 0.5]) / np.linalg.norm([1, 0.5]), c)
    V, F = m.triangulate()
    rdr = Renderer(np.asarray(V, float), np.asarray(F, np.int64))
    light = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
    n = rdr.normals
    # Lambert with a per-plane albedo (a function of the normal: no edges inside planar faces, contrast
    # between walls), 2x supersampled like the tests' renderer, sensor noise
    shade = (40 + 180 * np.abs(n @ light)) * (0.75 + 0.25 * np.sin(7 * n[:, 0] + 3 * n[:, 1] + 5 * n[:, 2]))
    cam2 = Camera(1000, 1000, 639.5, 479.5, 1280, 960)
    ids = rdr.render_face_ids(cam2, inv_T(T_mc))
    img = np.where(ids >= 0, shade[np.maximum(ids, 0)], 200.0).astype(np.float32)
    img = cv2.resize(img, (640, 480), interpolation=cv2.INTER_AREA) + np.random.default_rng(1).normal(0, 2, (480, 640))
    gray = np.clip(img, 0, 255).astype(np.uint8)
    G = T_mc.copy()
    G[:3, 3] += [3.0, -3.0, 3.0]
    G[:3, :3] = so3_exp(np.radians([3.0, -3.0, 2.0])) @ G[:3, :3]
    out.append(_search_row("init --from-nav search (L-building 640x480, 3 m / 3 deg guess)", gray, m, cam, G))
    # the bundled sample house (orbit, 12 m, textured floor), a guess drawn with the nav noise
    from mst.core.camera import read_camera
    from mst.core.trajectory import read_pose_file
    from mst.eval.bench.slam import SAMPLE_MODEL
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.synth import SynthConfig, synthesize

    hd = workdir / "house"
    synthesize("orbit", SAMPLE_MODEL, hd, SynthConfig(frames=1, aa_samples=4, texture_size=512, depth=False), overwrite=True)
    T_h = inv_T(read_pose_file(hd / "cMo" / "000000.txt"))
    cam_h, m_h = read_camera(hd / "camera.json"), load_tracking_model(hd / "model.obj")
    gray_h = cv2.cvtColor(cv2.imread(str(sorted((hd / "rgb").iterdir())[0])), cv2.COLOR_BGR2GRAY)
    G = T_h.copy()
    G[:3, 3] += [3.0, -3.0, 5.0]
    G[:3, :3] = so3_exp(np.radians([3.0, -3.0, 2.0])) @ G[:3, :3]
    out.append(_search_row("init --from-nav search (sample house orbit 640x480, 3/3/5 m / 3 deg guess)", gray_h, m_h,
                           cam_h, G))
    return out


def _search_row(name: str, gray, m, cam, G, repeats: int = 3) -> dict:
    """The search timed ``repeats`` times in-process (after one warm-up run: numba's cache load):
    median CPU and wall seconds; ok = converged and median CPU <= 2 s (CPU: the machine is shared)."""
    from mst.core.poses import inv_T
    from mst.pipeline.autoinit import auto_init

    auto_init(gray, m, cam, inv_T(G))
    cpu, wall = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        res = auto_init(gray, m, cam, inv_T(G))
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    c, w = float(np.median(cpu)), float(np.median(wall))
    return {"bench": name, "wall_s": w, "cpu_s": c, "converged": bool(res.ok), "poses_scored": res.evaluated,
            "target": "<= 2 s", "ok": c <= 2.0 and res.ok}
