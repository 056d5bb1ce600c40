"""``mst nav fuse`` on a TRACKED ``mst synth corridor`` (issue #15): a walking camera whose 1.8 Hz
bob (+-0.02 x distance = +-0.23 m vertical, +-1.2 deg of pitch) is no constant-acceleration motion.

320x240, 150 frames at 6 fps (25 s), tracked by ``mst track``'s default mode (the model leaves the
view for 76 frames: lost, bridged by the nav log), a GPS/AHRS log simulated from the truth (10 Hz,
3 m / 5 m GPS + bias walk + multipath, 3 deg AHRS, 60 deg mount, lever 0.18 m), the model
georeferenced. Before the vision reference (``FusionConfig.vision_reference``) the smoother
flattened the bob: fused/vision position RMSE 1.15 on the tracked frames (1.23-1.50 at 4-8 fps in
the previous session), attitude 0.86 vs 0.71 deg. Measured 2026-12-02, seeds 0-1: 1.007-1.008,
attitude 0.75 deg.

Budget: the tracked vision is 0.29 m RMS, its error correlated from frame to frame (lag-1
autocorrelation 0.88: a slowly varying bias from the start, 1 m decaying to 0.1 m); the GPS is
7.5 m RMS, so averaging its 250 fixes of 25 s leaves ~0.5 m -- it cannot correct the vision, and the
fusion must keep it: within 2 % (the GPS-driven correction's own noise) on the tracked frames,
and below the GPS everywhere.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from mst.eval.bench.slam import SAMPLE_MODEL

FPS = 6.0
M2W = np.array([[np.cos(np.radians(30)), -np.sin(np.radians(30)), 0, 100.0],
                [np.sin(np.radians(30)), np.cos(np.radians(30)), 0, -50.0], [0, 0, 1, 10.0], [0, 0, 0, 1.0]])


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.fixture(scope="module")
def tracked_corridor(tmp_path_factory):
    from mst.pipeline.synth import SynthConfig, synthesize
    from mst.pipeline.tracking import TrackConfig, run_track

    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    out = tmp_path_factory.mktemp("navcorr") / "corridor"
    synthesize("corridor", SAMPLE_MODEL, out, SynthConfig(width=320, height=240, frames=150, fps=FPS, aa_samples=4,
                                                          texture_size=512))
    run_track(out / "rgb", out / "model.obj", out / "camera.json", out / "cMo" / "000000.txt", out / "traj.txt",
              TrackConfig(), depth_dir=out / "depth", fps=FPS)
    return out


def _valid_cov_only(src, dst):
    """traj.cov.csv with the rows whose covariance is not positive definite emptied (read as 'no
    covariance': 3 x --vision-sigma). mst track wrote one such row at a re-acquisition (frame 111:
    negative variances, 1e10) on 2026-12-02 -- a tracker defect, reported; nav fuse itself refuses it."""
    lines = src.read_text().splitlines()
    out = [lines[0]]
    for ln in lines[1:]:
        f = ln.split(",")
        try:
            C = np.array([float(x) for x in f[6:]]).reshape(6, 6)
            ok = np.isfinite(C).all() and np.linalg.eigvalsh(0.5 * (C + C.T)).min() > 0
        except ValueError:
            ok = False
        out.append(ln if ok else ",".join(f[:2] + [""] * (len(f) - 2)))
    dst.write_text("\n".join(out) + "\n")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_fusion_keeps_the_walking_cameras_bob(tracked_corridor, tmp_path, seed):
    from mst.core.poses import inv_T, so3_log
    from mst.core.trajectory import read_tum
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.log import NavSimConfig, interpolate_poses, simulate_nav, write_sim_outputs
    from mst.pipeline.nav.run import fuse_nav_files

    seq = tracked_corridor
    t_gt, T_gt = read_tum(seq / "gt.txt")
    scfg = NavSimConfig(seed=seed, rate_hz=10.0, world_yaw_deg=30.0, world_offset_m=(100.0, -50.0, 10.0), dropouts=0,
                        ahrs_yaw_bias_deg=0.0)
    sim = simulate_nav(t_gt, T_gt, scfg)
    write_sim_outputs(sim, tmp_path / "nav.csv", None)
    shutil.copy(seq / "traj.txt", tmp_path / "traj.txt")
    shutil.copy(seq / "traj.csv", tmp_path / "traj.csv")
    _valid_cov_only(seq / "traj.cov.csv", tmp_path / "traj.cov.csv")
    np.savetxt(tmp_path / "m2w.txt", M2W)
    t_v, T_v = read_tum(seq / "traj.txt")
    kv = np.rint(t_v * FPS).astype(int)
    ev = np.linalg.norm(T_v[:, :3, 3] - T_gt[kv, :3, 3], axis=1)
    erv = np.degrees(np.linalg.norm(so3_log(T_v[:, :3, :3] @ np.swapaxes(T_gt[kv, :3, :3], 1, 2)), axis=1))
    # GPS-only: the fixes taken to the camera with the true calibration (the best GPS alone can do)
    nav = sim.nav
    Tn = interpolate_poses(t_gt, T_gt, nav.t)
    T_wb = sim.T_world_model @ Tn @ inv_T(sim.T_body_cam)
    p_cam = nav.p_world + np.einsum("nij,j->ni", T_wb[:, :3, :3], sim.T_body_cam[:3, 3])
    p_cam_m = (p_cam - sim.T_world_model[:3, 3]) @ sim.T_world_model[:3, :3]
    e_gps = _rms(np.linalg.norm(p_cam_m - Tn[:, :3, 3], axis=1)[nav.fix])
    errs = {}
    for ref in (True, False):
        _, res = fuse_nav_files(tmp_path / "traj.txt", tmp_path / "nav.csv", tmp_path / f"fused{ref}.txt",
                                FusionConfig(lever_arm_m=scfg.lever_arm_m, vision_reference=ref),
                                m2w_path=tmp_path / "m2w.txt")
        G = T_gt[np.rint(res.t * FPS).astype(int)]
        ep = np.linalg.norm(res.T_model_cam[:, :3, 3] - G[:, :3, 3], axis=1)
        er = np.degrees(np.linalg.norm(so3_log(res.T_model_cam[:, :3, :3] @ np.swapaxes(G[:, :3, :3], 1, 2)), axis=1))
        errs[ref] = (ep, er, res.has_vision)
    ep, er, hv = errs[True]
    assert hv.sum() == len(t_v) and (~hv).sum() >= 5 * FPS  # a gap of >= 5 s, bridged by the log
    assert _rms(ep[hv]) <= 1.02 * _rms(ev), (_rms(ep[hv]), _rms(ev))
    assert _rms(ep) <= e_gps and ep.max() <= 3.0 * e_gps, (_rms(ep), ep.max(), e_gps)
    # attitude: the bob's +-1.2 deg pitch is kept (within 10 % of the vision's; 1.21x before)
    assert _rms(er[hv]) <= 1.1 * _rms(erv), (_rms(er[hv]), _rms(erv))
    # and the default is at least as good as smoothing the positions themselves (1.15x the vision)
    ep0, er0, _ = errs[False]
    assert _rms(ep[hv]) <= _rms(ep0[hv]) and _rms(er[hv]) <= _rms(er0[hv])
