"""``mst nav fuse`` on a TRACKED ``mst synth corridor`` (issue #15): a walking camera whose 1.8 Hz
bob (+-0.02 x distance = +-0.23 m vertical, +-1.2 deg of pitch) is no constant-acceleration motion.

320x240, 150 frames at 6 fps (25 s), tracked by ``mst track``'s default mode with the error budget
widened to 10 % (the model leaves the view: the rgbd map bridges it; the gap test cuts those poses
out for the nav log to bridge), a GPS/AHRS
log simulated from the truth (10 Hz, 3 m / 5 m GPS + bias walk + multipath, 3 deg AHRS, 60 deg
mount, lever 0.18 m), the model georeferenced. Last session (the track before the error budget and
the covariance rework) the vision reference (``FusionConfig.vision_reference``) kept the bob:
fused/vision 1.007-1.008 (1.15 without it). On the track of 2026-12-02 (94 of 150 frames with a
pose, vision 0.24 m RMS, 0.64 deg) it does not: 1.20x, attitude 2.0-2.1x (strict xfail below, with
the cause).

Budget: the vision error is correlated from frame to frame (lag-1 autocorrelation 0.96: a slowly
varying bias from the start, 1 m decaying to 0.1 m); the GPS is 7.5 m RMS, so averaging its 250
fixes of 25 s leaves ~0.5 m -- it cannot correct the vision (the oracle bound below: >= 0.73x);
the gap is bridged below the GPS.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from nav_helpers import M2W, tracked_sequence

FPS = 6.0


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.fixture(scope="module")
def tracked_corridor(tmp_path_factory):
    from mst.pipeline.slam.config import SlamConfig
    from mst.pipeline.tracking import TrackConfig

    # the error budget (1 %) refuses 149 of these 150 poses at 320x240 (2 sigma 2-5 %: this vision is
    # off by up to 1 m at ~12 m), which leaves the fusion nothing but GPS; widened to 10 %, as for
    # `mst refine` (tests/test_refine.py), the track keeps its biased poses for the fusion to weigh
    return tracked_sequence(tmp_path_factory, "navcorr", "corridor", FPS,
                            TrackConfig(slam=SlamConfig(drift_budget_rel=0.10)), frames=150)


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


def _fuse_seed(seq, tmp, seed, gap: bool = False):
    """Simulate the log (seed), fuse the track with and without the vision reference; the errors.
    ``gap``: the poses of the frames where the model is out of view (:func:`out_of_view`) removed first."""
    from mst.core.poses import inv_T, so3_log
    from mst.core.trajectory import read_tum
    from mst.eval.bench.slam import out_of_view
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.log import NavSimConfig, interpolate_poses, simulate_nav, write_sim_outputs
    from mst.pipeline.nav.run import fuse_nav_files

    tmp.mkdir()
    t_gt, T_gt = read_tum(seq / "gt.txt")
    scfg = NavSimConfig(seed=seed, rate_hz=10.0, world_yaw_deg=30.0, world_offset_m=(100.0, -50.0, 10.0), dropouts=0,
                        ahrs_yaw_bias_deg=0.0)
    sim = simulate_nav(t_gt, T_gt, scfg)
    write_sim_outputs(sim, tmp / "nav.csv", None)
    if gap:
        hidden = out_of_view(seq)
        rows = [ln for ln in (seq / "traj.txt").read_text().splitlines()
                if ln.startswith("#") or not hidden[round(float(ln.split()[0]) * FPS)]]
        (tmp / "traj.txt").write_text("\n".join(rows) + "\n")
    else:
        shutil.copy(seq / "traj.txt", tmp / "traj.txt")
    shutil.copy(seq / "traj.csv", tmp / "traj.csv")
    _valid_cov_only(seq / "traj.cov.csv", tmp / "traj.cov.csv")
    np.savetxt(tmp / "m2w.txt", M2W)
    t_v, T_v = read_tum(tmp / "traj.txt")
    kv = np.rint(t_v * FPS).astype(int)
    ev = T_v[:, :3, 3] - T_gt[kv, :3, 3]
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
        summ, res = fuse_nav_files(tmp / "traj.txt", tmp / "nav.csv", tmp / f"fused{ref}.txt",
                                   FusionConfig(lever_arm_m=scfg.lever_arm_m, vision_reference=ref), m2w_path=tmp / "m2w.txt")
        if ref:
            mount_yaw_err = (summ["mount_ypr_deg"][0] - scfg.mount_ypr_deg[0] + 180) % 360 - 180
        G = T_gt[np.rint(res.t * FPS).astype(int)]
        ep = np.linalg.norm(res.T_model_cam[:, :3, 3] - G[:, :3, 3], axis=1)
        er = np.degrees(np.linalg.norm(so3_log(res.T_model_cam[:, :3, :3] @ np.swapaxes(G[:, :3, :3], 1, 2)), axis=1))
        errs[ref] = (ep, er, res.has_vision)
    return dict(kv=kv, ev=ev, erv=erv, e_gps=e_gps, errs=errs, n_vis=len(t_v), truth=T_gt[kv, :3, 3],
                mount_yaw_err=mount_yaw_err)


@pytest.fixture(scope="module")
def fused_corridor(tracked_corridor, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("navcorr_fused")
    return {s: _fuse_seed(tracked_corridor, tmp / f"s{s}", s) for s in (0, 1)}


@pytest.fixture(scope="module")
def fused_corridor_gap(tracked_corridor, tmp_path_factory):
    """The track without its poses where the model is out of view: a vision gap of ~12 s. Since
    2026-12-07 the rgbd map bridges that stretch itself within the 10 % budget (147 of 150 frames
    with a pose), so the gap the log must bridge is cut from the track."""
    tmp = tmp_path_factory.mktemp("navcorr_gap")
    return {s: _fuse_seed(tracked_corridor, tmp / f"s{s}", s, gap=True) for s in (0, 1)}


@pytest.mark.slow
def test_the_corridor_gap_is_bridged_below_the_gps(fused_corridor_gap):
    """The model out of view for seconds: the log bridges it below the GPS's own error everywhere and
    within the GPS sigma (3 m) in the gap; the mount yaw is found within 0.5 deg (measured
    2026-12-02: gap max 0.70 / 1.27 m, mount yaw error -0.18 / -0.003 deg for seeds 0 / 1)."""
    for s, r in fused_corridor_gap.items():
        ep, er, hv = r["errs"][True]
        assert hv.sum() == r["n_vis"] and (~hv).sum() >= 5 * FPS, s  # a gap of >= 5 s, bridged by the log
        assert _rms(ep) <= r["e_gps"] and ep.max() <= 3.0 * r["e_gps"], (s, _rms(ep), ep.max(), r["e_gps"])
        assert ep[~hv].max() <= 3.0, (s, ep[~hv].max())  # the issue: the gap bridged within the GPS sigma
        # the issue's mount yaw within 0.5 deg: 250 AHRS rows of 3 deg, the mean's std 0.19 deg (2.6 std)
        assert abs(r["mount_yaw_err"]) <= 0.5, (s, r["mount_yaw_err"])


@pytest.mark.slow
def test_the_issues_half_of_the_vision_is_beyond_any_gps_fusion_on_the_corridor(fused_corridor):
    """The oracle Wiener bound (pipeline/nav/bound.py; see test_nav_tracked_flyover.py) of the tracked
    corridor: 0.86x the vision with GPS alone, 0.73x with the fusion's motion model at its stiffest
    scale (measured 2026-12-02; lag-1 autocorrelation of the error 0.96) -- above the issue's 0.5x
    by more than 0.15; a prior knowing the true path's spectrum (the bob) would reach 0.21x."""
    from mst.pipeline.nav.bound import tracked_fusion_bound
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.models import MOTION_NOISE_SCALES

    r = fused_corridor[0]
    ev = _rms(np.linalg.norm(r["ev"], axis=1))
    q = FusionConfig().jerk_sigma_mps3 * np.sqrt(MOTION_NOISE_SCALES.min())
    b_ca = tracked_fusion_bound(r["kv"], r["ev"], FPS, 10.0, jerk_psd=q)
    assert b_ca >= (0.5 + 0.15) * min(ev, r["e_gps"]), b_ca / ev


@pytest.mark.slow
def test_fusion_keeps_the_walking_cameras_bob(fused_corridor):
    for s, r in fused_corridor.items():
        ep, er, hv = r["errs"][True]
        ev = _rms(np.linalg.norm(r["ev"], axis=1))
        print(f"seed {s}: fused {_rms(ep[hv]):.4f} m vs vision {ev:.4f} m ({_rms(ep[hv]) / ev:.3f}x), "
              f"attitude {_rms(er[hv]):.3f} vs {_rms(r['erv']):.3f} deg, gap max {ep[~hv].max():.2f} m, GPS {r['e_gps']:.2f} m")
    for s, r in fused_corridor.items():
        ep, er, hv = r["errs"][True]
        ev = _rms(np.linalg.norm(r["ev"], axis=1))
        assert _rms(ep[hv]) <= 1.02 * ev, (s, _rms(ep[hv]), ev)
        # attitude: the bob's +-1.2 deg pitch is kept (within 10 % of the vision's; 1.21x before)
        assert _rms(er[hv]) <= 1.1 * _rms(r["erv"]), (s, _rms(er[hv]), _rms(r["erv"]))
        # and the default is at least as good as smoothing the positions themselves, within the paired
        # comparison's own noise (session 9: attitude 0.6391 vs 0.6362 deg, +0.45 %, on the track after
        # the VVS step test; the 1.21x of the defect this guards against is far outside it)
        ep0, er0, _ = r["errs"][False]
        assert _no_worse(ep[hv], ep0[hv]) and _no_worse(er[hv], er0[hv]), (s, _rms(ep[hv]), _rms(ep0[hv]),
                                                                          _rms(er[hv]), _rms(er0[hv]))


def _no_worse(a, b, k: float = 2.0) -> bool:
    """Errors ``a`` (N,) no worse than ``b`` (N,) on the same frames in the RMS sense, within ``k``
    standard errors of the paired difference of the squares (its effective sample size from its
    lag-1 autocorrelation: these errors are correlated from frame to frame)."""
    d = np.square(a) - np.square(b)
    n = len(d)
    if n < 3:
        return bool(d.mean() <= 0)
    x = d - d.mean()
    rho = float(np.clip(np.dot(x[1:], x[:-1]) / max(np.dot(x, x), 1e-300), 0.0, 0.99))
    n_eff = max(n * (1 - rho) / (1 + rho), 1.0)
    return bool(d.mean() <= k * d.std(ddof=1) / np.sqrt(n_eff))
