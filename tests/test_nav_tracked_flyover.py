"""Issue 15's fusion checks on REAL tracked vision: ``mst synth flyover`` of the sample house
(320x240, 60 frames at 2 fps = 30 s, 0.8 m/s, 6 m above the roof: the camera ~9-10 m from the
house, with depth), tracked by ``mst track`` in its default mode (with depth: the RGB-D aid), then
``mst nav fuse`` with a GPS/AHRS log simulated from the truth (``mst nav simulate``'s default error
model at 10 Hz: GPS 3 m / 5 m white + 0.05 m/sqrt(s) bias walk + 2 % multipath, AHRS 3 deg, 60 deg
mount, lever 0.18 m; one GPS dropout of 10-11 s; the model georeferenced: its model-to-world transform
given, as for a surveyed building). A 6 s vision gap is cut from the tracked trajectory in the half
of the flight away from the dropout (the tracker's error budget refuses 7 of the 60 poses by itself,
frames 2-6 and 15-16: 2 sigma 0.5-1.0 % against its 1 %, 0.5 x after a refusal).

Budgets: GPS sigma 3 m horizontal; the tracked vision here is 3.9 cm / 0.19 deg RMS (its
covariances in traj.cov.csv are optimistic: NEES 8.4 for 3, measured last session). Seeds 0-7
re-measured 2026-12-02 on the track with the error budget (load ~5): fused/vision position RMSE on
the tracked frames 0.999-1.001 (the issue's 0.5 x min(vision, GPS) is NOT reached, and no GPS
fusion can reach it: the oracle Wiener bound is 0.955-0.97x, test below: the tracker's error is a
slow bias, lag-1 autocorrelation 0.97, and the 6.6 m GPS averaged over 30 s is still ~0.4 m per
axis); attitude RMSE 0.19 deg on the tracked frames, 0.51-0.75 deg over all frames (the 6 s gap,
20 % of the frames, is bridged by the 3 deg AHRS alone); mount yaw error <= 0.24 deg; gap error
<= 2.05 m; at the GPS's return the error changes by 1-10 mm against 7-11 mm RMS per frame.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from nav_helpers import M2W, tracked_sequence

FPS = 2.0
SEEDS = (0, 1, 2, 3)
GPS_SIGMA_H_M = 3.0


@pytest.fixture(scope="session")
def tracked_flyover(tmp_path_factory):
    from mst.pipeline.tracking import TrackConfig

    return tracked_sequence(tmp_path_factory, "navfly", "flyover", FPS, TrackConfig(), frames=60, speed=0.8,
                            distance=6.0)


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def _fuse_seed(seq, tmp, seed):
    """Simulate the log, cut the vision gap, fuse. Returns a dict of the measured quantities."""
    from mst.core.poses import so3_log
    from mst.core.trajectory import format_tum, read_tum
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.log import NavSimConfig, simulate_nav, write_sim_outputs
    from mst.pipeline.nav.run import fuse_nav_files

    d = tmp / f"s{seed}"
    d.mkdir()
    t_gt, T_gt = read_tum(seq / "gt.txt")
    scfg = NavSimConfig(seed=seed, rate_hz=10.0, world_yaw_deg=30.0, world_offset_m=(100.0, -50.0, 10.0), dropouts=1,
                        dropout_s=(10.0, 11.0), ahrs_yaw_bias_deg=0.0)
    sim = simulate_nav(t_gt, T_gt, scfg)
    write_sim_outputs(sim, d / "nav.csv", None)
    drop_t = sim.nav.t[~sim.nav.fix]
    gap = (3.0, 9.0) if drop_t.mean() > 15.0 else (21.0, 27.0)
    t_v, T_v = read_tum(seq / "traj.txt")
    keep = ~((t_v >= gap[0]) & (t_v < gap[1]))
    (d / "traj.txt").write_text(format_tum(t_v[keep], T_v[keep]))
    for ext in (".csv", ".cov.csv"):  # mst track's per-frame status and covariances beside it
        shutil.copy(seq / f"traj{ext}", d / f"traj{ext}")
    np.savetxt(d / "m2w.txt", M2W)
    summ, res = fuse_nav_files(d / "traj.txt", d / "nav.csv", d / "fused.txt", FusionConfig(lever_arm_m=scfg.lever_arm_m),
                               m2w_path=d / "m2w.txt")
    G = T_gt[np.rint(res.t * FPS).astype(int)]
    ep = np.linalg.norm(res.T_model_cam[:, :3, 3] - G[:, :3, 3], axis=1)
    er = np.degrees(np.linalg.norm(so3_log(res.T_model_cam[:, :3, :3] @ np.swapaxes(G[:, :3, :3], 1, 2)), axis=1))
    kv = np.rint(t_v[keep] * FPS).astype(int)
    ev = np.linalg.norm(T_v[keep, :3, 3] - T_gt[kv, :3, 3], axis=1)
    fix_f = np.interp(res.t, sim.nav.t, sim.nav.fix.astype(float)) > 0.5
    back = np.flatnonzero(~fix_f[:-1] & fix_f[1:])  # last frame of the dropout
    de = np.linalg.norm(np.diff(res.T_model_cam[:, :3, 3] - G[:, :3, 3], axis=0), axis=1)  # error increments
    return dict(res=res, ep=ep, er=er, ev=ev, hv=res.has_vision, fix=fix_f, back=back, de=de, summ=summ,
                mount_yaw_err=(summ["mount_ypr_deg"][0] - scfg.mount_ypr_deg[0] + 180) % 360 - 180)


@pytest.fixture(scope="module")
def fused(tracked_flyover, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("navfly_fused")
    return {s: _fuse_seed(tracked_flyover, tmp, s) for s in SEEDS}


def test_fusion_keeps_the_tracked_vision_and_bridges_a_vision_gap(fused):
    for s, r in fused.items():
        hv, ep = r["hv"], r["ep"]
        assert (~hv).sum() >= 5.0 * FPS, s  # a gap of >= 5 s
        # the 7 m GPS cannot improve 4 cm of correlated vision error; the fusion must not spoil it:
        # within 1.1x of the vision on its frames (measured 0.93x)
        assert _rms(ep[hv]) <= 1.1 * _rms(r["ev"]), (s, _rms(ep[hv]), _rms(r["ev"]))
        # the vision gap is bridged by GPS/AHRS with an error below the GPS sigma everywhere
        assert ep[~hv].max() <= GPS_SIGMA_H_M, (s, ep[~hv].max())
        # attitude on the tracked frames within 0.5 deg (the vision's is 0.18 deg RMS)
        assert _rms(r["er"][hv]) <= 0.5, (s, _rms(r["er"][hv]))


def test_gps_dropout_is_bridged_by_the_vision_without_a_jump_at_its_return(fused):
    for s, r in fused.items():
        fix, hv, ep, de = r["fix"], r["hv"], r["ep"], r["de"]
        assert (~fix).sum() >= 10.0 * FPS - 1 and len(r["back"]) == 1, s  # one dropout of >= 10 s
        drop = ~fix
        # bridged by the vision: on the dropout's frames the error is that of the vision frames
        # with GPS (within 2x, + 1 cm for the few frames)
        assert ep[drop & hv].max() <= 2 * ep[fix & hv].max() + 0.01, (s, ep[drop & hv].max(), ep[fix & hv].max())
        # no jump when the GPS returns: the error changes by no more than its usual frame-to-frame
        # change (3 x the RMS increment between tracked frames with GPS)
        k = r["back"][0]
        usual = _rms(de[(fix & hv)[1:] & (fix & hv)[:-1]])
        assert de[k] <= 3 * usual, (s, de[k], usual)


def test_mount_yaw_within_half_a_degree(fused):
    # 300 AHRS rows (10 Hz, 30 s; the issue's logs are 1-10 Hz) of 3 deg: the mean's std 0.17 deg,
    # the issue's 0.5 deg is 3 std (at 5 Hz it would be 2 std: one seed in 20 outside); the vision's
    # attitude error adds little (0.2 deg RMS, correlated). The issue's bound on every seed
    for s, r in fused.items():
        assert abs(r["mount_yaw_err"]) <= 0.5, (s, r["summ"]["mount_ypr_deg"])


def _refine(seq, tmp, nav: bool):
    from mst.pipeline.refine import RefineConfig, refine

    np.savetxt(tmp / "m2w.txt", M2W)
    if nav and not (tmp / "nav.csv").exists():
        from mst.core.trajectory import read_tum
        from mst.pipeline.nav.log import NavSimConfig, simulate_nav, write_sim_outputs

        t_gt, T_gt = read_tum(seq / "gt.txt")
        write_sim_outputs(simulate_nav(t_gt, T_gt, NavSimConfig(seed=0, world_yaw_deg=30.0,
                                                                world_offset_m=(100.0, -50.0, 10.0))), tmp / "nav.csv", None)
    from mst.pipeline.nav.fusion import FusionConfig

    return refine(seq / "traj.txt", seq / "model.obj", seq / "camera.json", seq / "depth", tmp / f"r{int(nav)}.txt",
                  RefineConfig(fps=FPS, keyframe_every=2, nav=FusionConfig(lever_arm_m=(0.10, 0.0, -0.15))), gt_path=seq / "gt.txt",
                  frames_path=seq / "rgb", nav_path=tmp / "nav.csv" if nav else None, m2w_path=tmp / "m2w.txt")


def test_refine_with_nav_factors_on_the_flyover(tracked_flyover, tmp_path):
    """mst refine with the bundle adjustment (KLT tie points) and the nav factors on the tracked
    flyover: the GPS/AHRS enter the BA, and the refined trajectory is better than the tracked one.
    Budget: the tracked poses are off by ~4-6 cm at ~10 m with exact depth of the model's planes:
    the ICP pins them to mm; >= 30 % lower ATE is the issue's bound for refine."""
    s = _refine(tracked_flyover, tmp_path, nav=True)
    assert s.nav["gps_factors"] >= 0.5 * s.keyframes and s.nav["ahrs_factors"] >= 0.8 * s.keyframes, s.nav
    assert s.ba["points"] >= 50 and s.ba["reproj_rms_after_px"] < s.ba["reproj_rms_before_px"], s.ba
    assert s.ate["after_m"] <= 0.7 * s.ate["before_m"], s.ate


@pytest.mark.slow
def test_refine_nav_factors_do_not_spoil_centimetre_poses(tracked_flyover, tmp_path):
    # the 3 m GPS has nothing to say to cm-level poses: with nav within 1.1x (+1 mm) of without
    with_nav, without = _refine(tracked_flyover, tmp_path, True), _refine(tracked_flyover, tmp_path, False)
    assert with_nav.ate["after_m"] <= 1.1 * without.ate["after_m"] + 0.001, (with_nav.ate, without.ate)
    assert with_nav.ate["after_ba_m"] <= 1.1 * without.ate["after_ba_m"] + 0.001, (with_nav.ate, without.ate)


def _vision_errors(seq):
    """Frame indices, position errors (N, 3) and 3-D RMSE of the whole tracked trajectory (no gap cut)."""
    from mst.core.trajectory import read_tum

    t_gt, T_gt = read_tum(seq / "gt.txt")
    t_v, T_v = read_tum(seq / "traj.txt")
    k = np.rint(t_v * FPS).astype(int)
    e = T_v[:, :3, 3] - T_gt[k, :3, 3]
    return k, e, T_gt[k, :3, 3], float(np.sqrt(np.mean(np.sum(e**2, 1))))


def test_the_issues_half_of_the_vision_is_beyond_any_gps_fusion(tracked_flyover):
    """Why the issue's "fused RMSE <= 0.5 x min(vision, GPS)" is not met here: the oracle Wiener bound
    (pipeline/nav/bound.py: an ideal linear smoother that knows the realised spectrum of the vision
    error, the GPS noise's -- 3/3/5 m at 10 Hz + 0.05 m/sqrt(s) walk -- and, for the motion prior, the
    fusion's constant-acceleration model at its stiffest scale) stays above 0.5 x the vision (the
    better of the two: 4 cm against 6.6 m). Measured 2026-12-02: 0.97x with GPS alone, 0.955x with
    the motion prior (the error is a slow bias, lag-1 autocorrelation 0.97); only a prior that knew
    the true path's own spectrum (the straight line) would reach 0.49x. Margin: the bound must
    exceed 0.5x by 0.2 (white vision errors of the same RMS give 0.54x: the correlation, not the
    size, of the error is what no GPS averaging removes)."""
    from mst.pipeline.nav.bound import tracked_fusion_bound
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.models import MOTION_NOISE_SCALES

    k, e, _, ev = _vision_errors(tracked_flyover)
    q = FusionConfig().jerk_sigma_mps3 * np.sqrt(MOTION_NOISE_SCALES.min())
    b_gps = tracked_fusion_bound(k, e, FPS, 10.0)
    b_ca = tracked_fusion_bound(k, e, FPS, 10.0, jerk_psd=q)
    # more information never hurts the oracle: against the vision alone on the same grids (short holes
    # filled linearly, each run weighted by its poses: the bound with no GPS information), not against
    # the poses' own RMS ``ev`` (session 8's track: grid 0.0407 m against 0.0404 m on the poses)
    b_vis = tracked_fusion_bound(k, e, FPS, 10.0, sigma_m=(1e12, 1e12, 1e12), walk_m_per_sqrt_s=0.0)
    assert b_ca <= b_gps <= b_vis * (1 + 1e-9), (b_ca, b_gps, b_vis)
    assert abs(b_vis - ev) <= 0.05 * ev  # the filled grid is the track (a few 1-3 frame holes)
    assert b_ca >= (0.5 + 0.2) * ev, (b_gps / ev, b_ca / ev)
    # the same RMS as white noise: the motion prior alone would smooth half of it away (0.54x)
    w = np.random.default_rng(0).normal(size=e.shape) * ev / np.sqrt(3)
    assert tracked_fusion_bound(k, w, FPS, 10.0, jerk_psd=q) < 0.75 * ev


@pytest.mark.xfail(strict=True, reason="the issue's 0.5 x min(vision, GPS): the fused/vision RMSE is ~1.0 on the "
                   "tracked flyover; the oracle Wiener bound of any fusion with this GPS and motion model is 0.955-0.97x "
                   "(test_the_issues_half_of_the_vision_is_beyond_any_gps_fusion)")
def test_fused_rmse_half_the_better_of_vision_and_gps(fused):
    for s, r in fused.items():
        assert _rms(r["ep"][r["hv"]]) <= 0.5 * _rms(r["ev"]), s
