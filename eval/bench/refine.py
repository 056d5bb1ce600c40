"""Benchmark of ``mst refine``: the time of a whole command on 2,000 frames (400 keyframes).

Input: a 200-frame ``mst synth orbit`` of ``samples/building_tin.obj`` at 320x240 with depth, played
forward and backward (ping-pong links) to 2,000 frames; the trajectory to refine is the truth with a
smooth error (a drift growing to 2 % of the distance and back, 1 deg of yaw, plus 1 cm / 0.1 deg
white noise per frame), so the refinement has something to do. Reported: wall/CPU seconds, peak
RSS, the ATE before/after (position RMSE, m) and the mean C2M before/after from ``--json``; the
same with ``--frames`` (the bundle adjustment of the keyframes with KLT tie points first): its
tie points, reprojection RMS and the ATE after the BA alone as well.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mst.eval.bench.harness import mst_cmd, timed_command
from mst.eval.bench.slam import _synth, ping_pong_links

N_FRAMES = 2000
FPS = 30.0


def degraded_trajectory(T_gt: np.ndarray, dist_m: float, seed: int = 0) -> np.ndarray:
    """``T_gt`` with a slow drift (up to 2 % of ``dist_m``, 1 deg of yaw) and per-frame white noise."""
    from mst.core.poses import make_T, so3_exp

    n = len(T_gt)
    rng = np.random.default_rng(seed)
    s = np.sin(np.linspace(0, np.pi, n))[:, None]
    drift_t = s * np.array([0.02, -0.012, 0.008]) * dist_m + rng.normal(0, 0.01, (n, 3))
    drift_r = s * np.array([0.0, 0.0, np.radians(1.0)]) + rng.normal(0, np.radians(0.1), (n, 3))
    D = make_T(so3_exp(drift_r), drift_t)
    return D @ T_gt


def run(workdir: Path) -> list[dict]:
    from mst.core.trajectory import read_tum, write_tum

    workdir.mkdir(parents=True, exist_ok=True)
    orb = _synth(workdir, "orbit200", "orbit", frames=200, width=320, height=240, aa_samples=4, texture_size=512)
    ping_pong_links(orb / "depth", workdir / "long" / "depth", N_FRAMES, "*.npy")
    _, T = read_tum(orb / "gt.txt")
    order = np.array(list(range(len(T))) + list(range(len(T) - 2, 0, -1)))
    T_long = T[order[np.arange(N_FRAMES) % len(order)]]
    t = np.arange(N_FRAMES) / FPS
    write_tum(workdir / "gt_long.txt", t, T_long)
    dist = float(np.median(np.linalg.norm(T_long[:, :3, 3] - np.array([2.5, 2.0, 1.75]), axis=1)))
    write_tum(workdir / "degraded.txt", t, degraded_trajectory(T_long, dist))
    ping_pong_links(orb / "rgb", workdir / "long" / "rgb", N_FRAMES, "*.png")
    rows = []
    for extra in ([], ["--frames", workdir / "long" / "rgb"]):
        r = timed_command(mst_cmd("refine", "--traj", workdir / "degraded.txt", "--model", orb / "model.obj",
                                  "--camera", orb / "camera.json", "--depth", workdir / "long" / "depth", "--fps", FPS,
                                  "--gt", workdir / "gt_long.txt", "-o", workdir / "refined.txt", "--json", "-q", *extra))
        s = json.loads(r["stdout"])
        row = {"bench": f"refine {N_FRAMES} frames ({s['keyframes']} keyframes, 320x240 depth"
                        f"{', + bundle adjustment' if extra else ''})", "wall_s": r["wall_s"],
               "cpu_s": r["cpu_s"], "peak_rss_mib": r["peak_rss_mib"], "rounds": s["rounds"],
               "ate_before_m": s["ate"]["before_m"], "ate_after_m": s["ate"]["after_m"],
               "c2m_mean_before_m": s["c2m_before"]["mean_m"], "c2m_mean_after_m": s["c2m_after"]["mean_m"]}
        if "ba" in s:
            row.update(ba_points=s["ba"].get("points"), ba_reproj_px=[s["ba"].get("reproj_rms_before_px"),
                                                                     s["ba"].get("reproj_rms_after_px")],
                       ate_after_ba_m=s["ate"].get("after_ba_m"))
        rows.append(row)
    return rows
