"""Navigation fusion on simulated logs: accuracy against vision-only and GPS-only, calibration, gap bridging.

Budget (all tests): a 60 s UAV orbit at 30 fps (tests/nav_helpers.py), vision = ground truth + white
noise 0.3 m / 0.5 deg per axis (3-D RMS 0.52 m / 0.87 deg) with a 6 s loss; GPS at 5 Hz, sigma 3 m
horizontal / 5 m vertical (3-D RMS 6.6 m) + 0.05 m/sqrt(s) bias walk + 2 % multipath of 15-40 m;
AHRS 3 deg; mount 60 deg pan, 20 deg down, lever 0.18 m; the model frame rotated 30 deg and shifted
~110 m from the world frame. Motion model of the fusion: 1 m/s^2 and 0.5 deg/s^2 white (the path's
own accelerations are ~0.6 m/s^2 and < 0.5 deg/s^2); the position uses the default constant-
acceleration model (white jerk 0.5 m/s^3/sqrt(Hz)).
"""

from __future__ import annotations

import numpy as np
import pytest
from nav_helpers import flight, noisy_vision

from mst import InputError
from mst.core.poses import inv_T, so3_log
from mst.pipeline.nav.fusion import FusionConfig, _rot_mean, fuse_navigation
from mst.pipeline.nav.log import (
    NavSimConfig,
    R_from_ypr_deg,
    interpolate_poses,
    mount_ypr_deg_from_R,
    simulate_nav,
)
from mst.pipeline.nav.run import format_cov_csv, read_cov_csv

LEVER = (0.10, 0.0, -0.15)


def _cfg(**kw) -> FusionConfig:
    return FusionConfig(lever_arm_m=LEVER, ang_accel_sigma_dps2=0.5, **kw)


def _sim(t, T, **kw):
    base = dict(seed=3, world_yaw_deg=30.0, world_offset_m=(100.0, -50.0, 10.0), lever_arm_m=LEVER)
    base.update(kw)
    return simulate_nav(t, T, NavSimConfig(**base))


def _pos_err(T_est, T_ref):
    return np.linalg.norm(T_est[:, :3, 3] - T_ref[:, :3, 3], axis=1)


def _rot_err_deg(T_est, T_ref):
    return np.degrees(np.linalg.norm(so3_log(T_est[:, :3, :3] @ np.swapaxes(T_ref[:, :3, :3], 1, 2)), axis=1))


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def _true_antenna_world(sim, t, T):
    return (sim.T_world_model @ interpolate_poses(t, T, sim.nav.t) @ inv_T(sim.T_body_cam))[:, :3, 3]


def _gps_only_rmse(sim, t, T):
    """GPS fixes taken to the camera with the true calibration, against the truth (the best GPS-only can do)."""
    nav = sim.nav
    T_gt = interpolate_poses(t, T, nav.t)
    T_wb = sim.T_world_model @ T_gt @ inv_T(sim.T_body_cam)
    p_cam_w = nav.p_world + np.einsum("nij,j->ni", T_wb[:, :3, :3], sim.T_body_cam[:3, 3])
    p_cam_m = (p_cam_w - sim.T_world_model[:3, 3]) @ sim.T_world_model[:3, :3]
    return _rms(np.linalg.norm(p_cam_m - T_gt[:, :3, 3], axis=1)[nav.fix])


@pytest.fixture(scope="module")
def scene():
    t, T = flight()
    t_v, T_v, C_v, keep, e = noisy_vision(t, T, gap=(20.0, 26.0))
    return t, T, t_v, T_v, C_v, keep, e


def test_fused_beats_vision_and_gps_and_bridges_the_vision_gap(scene):
    t, T, t_v, T_v, C_v, keep, e = scene
    sim = _sim(t, T)
    res = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg())
    assert np.allclose(res.t, t) and np.array_equal(res.has_vision, keep)
    ep, er = _pos_err(res.T_model_cam, T), _rot_err_deg(res.T_model_cam, T)
    vision_rmse = _rms(np.linalg.norm(e[keep, :3], axis=1))
    gps_rmse = _gps_only_rmse(sim, t, T)
    assert vision_rmse < gps_rmse
    # on the frames that have vision (the gap is bounded below): across seeds 0.18-0.21x
    assert _rms(ep[keep]) <= 0.5 * min(vision_rmse, gps_rmse), (_rms(ep[keep]), vision_rmse, gps_rmse)
    assert _rms(er) <= 0.5, _rms(er)
    # the 6 s vision gap is bridged by GPS/AHRS with an error below the GPS sigma everywhere
    assert ep[~keep].max() <= 3.0, ep[~keep].max()
    # the covariances are not over-confident: the RMS error stays below 2x the predicted sigma,
    # with vision and in the gap (across seeds the ratio is 0.3-1.1)
    for sel in (keep, ~keep):
        pred = np.sqrt(np.mean(np.trace(res.cov[sel, :3, :3], axis1=1, axis2=2)))
        assert _rms(ep[sel]) < 2 * pred, (_rms(ep[sel]), pred)
    # calibration: model-to-world yaw and shift (GPS 3 m over a 120 m wide orbit: yaw std ~0.1 deg)
    assert abs(res.calib["world_yaw_deg"] - 30.0) < 0.5
    assert np.linalg.norm(np.array(res.calib["world_offset_m"]) - [100.0, -50.0, 10.0]) < 1.5
    # the multipath fixes are found: every one whose offset is > 8 sigma (Mahalanobis) gets a Huber
    # weight < 0.5 (d > 2 huber_k = 6 with the noise), and few clean fixes do (false alarms <= 2 %)
    off = (sim.nav.p_world - _true_antenna_world(sim, t, T) - sim.gps_bias_m) / [3.0, 3.0, 5.0]
    big = sim.outlier & (np.linalg.norm(off, axis=1) > 8.0)
    assert big.sum() <= res.stats["gps_outliers"] <= sim.outlier.sum() + 0.02 * sim.nav.fix.sum()


def test_mount_yaw_within_half_a_degree():
    # no AHRS heading bias: the estimated mount is the true one. 300 AHRS rows of 3 deg per axis: std
    # of the mean 0.17 deg per axis; yaw within 0.5 deg (3 sigma), the 3-D angle within 0.75 deg
    # (chi-square, 3 dof, 99.9 %: 4.0 sigma = 0.7 deg)
    t, T = flight()
    t_v, T_v, C_v, _, _ = noisy_vision(t, T, gap=None, seed=2)
    sim = _sim(t, T, ahrs_yaw_bias_deg=0.0, seed=7)
    res = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg())
    dR = R_from_ypr_deg(np.array(res.calib["mount_ypr_deg"])).T @ R_from_ypr_deg(np.array([60.0, -20.0, 0.0]))
    assert np.degrees(np.linalg.norm(so3_log(dR))) < 0.75, res.calib["mount_ypr_deg"]
    assert abs(res.calib["mount_ypr_deg"][0] - 60.0) < 0.5


def test_heading_bias_goes_into_the_mount_and_attitude_stays_accurate(scene):
    # a constant 2 deg AHRS heading bias cannot be told from a mount yaw for a near-level platform:
    # the estimate is the mount the biased AHRS implies (computed from the truth here); the fused
    # attitude stays within the budget
    t, T, t_v, T_v, C_v, keep, _ = scene
    sim = _sim(t, T, ahrs_yaw_bias_deg=2.0, seed=11)
    res = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg())
    T_gt = interpolate_poses(t, T, sim.nav.t)
    Rz = R_from_ypr_deg(np.array([2.0, 0.0, 0.0]))
    R_wb_biased = Rz @ (sim.T_world_model @ T_gt @ inv_T(sim.T_body_cam))[:, :3, :3]
    R_cb_j = np.swapaxes(T_gt[:, :3, :3], 1, 2) @ sim.T_world_model[:3, :3].T @ R_wb_biased
    R_cb = _rot_mean(R_cb_j, np.ones(len(R_cb_j)))
    d = np.degrees(np.linalg.norm(so3_log(res.R_body_cam @ R_cb)))
    assert d < 0.75, d  # budget as in test_mount_yaw_within_half_a_degree
    assert abs(res.calib["mount_ypr_deg"][0] - mount_ypr_deg_from_R(R_cb.T)[0]) < 0.5
    assert _rms(_rot_err_deg(res.T_model_cam, T)) <= 0.5


def test_gps_dropout_bridged_by_vision_without_jump(scene):
    t, T, *_ = scene
    t_v, T_v, C_v, _, _ = noisy_vision(t, T, gap=None, seed=5)
    sim = _sim(t, T, dropouts=1, dropout_s=(12.0, 14.0), seed=8)
    nofix = ~sim.nav.fix
    t_lost, t_back = sim.nav.t[nofix][0], sim.nav.t[nofix][-1] + 0.2
    assert t_back - t_lost >= 10.0
    res = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg())
    ep = res.T_model_cam[:, :3, 3] - T[:, :3, 3]
    inside = (t >= t_lost) & (t < t_back)
    # during the dropout vision carries the pose at its own accuracy (0.52 m RMS raw)
    assert _rms(np.linalg.norm(ep[inside], axis=1)) <= 0.5 * 0.52
    # no jump at the return: mean error 1 s before vs 1 s after differs by far less than the GPS
    # sigma (the bias walks 0.05*sqrt(14) = 0.19 m over the dropout; vision averages to < 0.1 m)
    before = ep[(t >= t_back - 1.0) & (t < t_back)].mean(axis=0)
    after = ep[(t >= t_back) & (t < t_back + 1.0)].mean(axis=0)
    assert np.linalg.norm(after - before) < 0.3, (before, after)
    # frame-to-frame steps at the return are no larger than the steps elsewhere
    steps = np.linalg.norm(np.diff(res.T_model_cam[:, :3, 3], 2, axis=0), axis=1)
    k = int(np.searchsorted(t, t_back))
    assert steps[k - 3:k + 3].max() <= 2 * np.percentile(steps, 99)


def _all_frames_seeds(seeds):
    """The issue's bound on ALL frames (the 6 s vision gap included: 10 % of the frames) for 8 seeds
    of vision and GPS noise. With the former constant-velocity model (white acceleration 1 m/s^2,
    loose enough for the 0.6 m/s^2 turn) the gap bridge followed the 3 m GPS noise (gap RMSE
    0.4-1.0 m) and 2-4 of 8 seeds broke the bound; the constant-acceleration model (white jerk
    0.5 m/s^3/sqrt(Hz): the acceleration may change by 1.2 m/s^2 over the gap, 3x what the flight's
    turn does) carries the turn through the gap. Across these seeds the ratio is 0.3-0.65."""
    t, T = flight()
    ratio, e_ca, e_cv = [], [], []
    for s in seeds:
        t_v, T_v, C_v, keep, e = noisy_vision(t, T, seed=s + 1, gap=(20.0, 26.0))
        sim = _sim(t, T, seed=s + 3)
        res = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg())
        cv = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg(motion_model="cv"))
        bound = 0.5 * min(_rms(np.linalg.norm(e[keep, :3], axis=1)), _gps_only_rmse(sim, t, T))
        e_ca.append(_rms(_pos_err(res.T_model_cam, T)))
        e_cv.append(_rms(_pos_err(cv.T_model_cam, T)))
        ratio.append(e_ca[-1] / bound)
    assert max(ratio) <= 1.0, np.round(ratio, 2)
    # the default is at least as good as the simpler model, seed by seed
    assert all(a <= b for a, b in zip(e_ca, e_cv)), (np.round(e_ca, 3), np.round(e_cv, 3))


def test_fused_rmse_on_all_frames_seeds_the_cv_model_failed():
    _all_frames_seeds([2, 7])


@pytest.mark.slow
def test_fused_rmse_on_all_frames_over_8_seeds():
    _all_frames_seeds(range(8))


def test_filter_mode_is_causal_and_the_smoother_is_at_least_as_good(scene):
    t, T, t_v, T_v, C_v, keep, _ = scene
    sim = _sim(t, T)
    sm = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg())
    fl = fuse_navigation(t_v, T_v, C_v, sim.nav, _cfg(mode="filter"))
    e_s, e_f = _rms(_pos_err(sm.T_model_cam, T)), _rms(_pos_err(fl.T_model_cam, T))
    assert e_s <= e_f
    assert e_f <= _gps_only_rmse(sim, t, T) / 2  # the filter alone still beats the GPS by 2x
    # causal: the filter's estimate at frame k ignores what comes later
    k = 400
    cut = fuse_navigation(t_v[t_v <= t[k]], T_v[t_v <= t[k]], C_v[t_v <= t[k]], sim.nav, _cfg(mode="filter"))
    # (the calibration is fitted on the whole log in both runs; with less data it differs slightly)
    assert np.abs(cut.T_model_cam[k, :3, 3] - fl.T_model_cam[k, :3, 3]).max() < 0.5
    assert _rot_err_deg(cut.T_model_cam[k:k + 1], fl.T_model_cam[k:k + 1])[0] < 0.5


def _varying_speed_flight(duration_s: float = 60.0, fps: float = 30.0):
    """The orbit of nav_helpers.flight with the speed swinging between ~0 and ~18 m/s (a survey
    flight's stops and dashes): a time shift is then not a rotation or translation of the path."""
    from mst.core.poses import look_at

    t = np.arange(0.0, duration_s, 1.0 / fps)
    th = 0.1 * t + 0.8 * np.sin(0.25 * t)
    P = np.stack([60 * np.cos(th), 42 * np.sin(th), 40 + 3 * np.sin(0.2 * t)], 1)
    return t, np.stack([look_at(p, np.zeros(3)) for p in P])


@pytest.mark.parametrize("seed", [0, pytest.param(2, marks=pytest.mark.slow)])
def test_time_offset_estimated(seed):
    """A log 0.3 s late (GPS/AHRS clock). Budget: 300 fixes of 3 m on a path of ~8 m/s mean speed
    change: the GPS alone pins the offset to ~3 / (8 sqrt(300)) = 0.02 s; the reported std must be
    honest (|error| <= 3 std) and <= 0.05 s. The fused positions with the estimate: within 1.25x of
    a log on the right clock; ignoring the offset is worse (a 0.3 s lag at 8 m/s is 2.4 m)."""
    t, T = _varying_speed_flight()
    t_v, T_v, C_v, _, _ = noisy_vision(t, T, seed=seed + 1, gap=(20.0, 26.0))
    late = _sim(t, T, seed=seed + 3, time_offset_s=0.3).nav
    est = fuse_navigation(t_v, T_v, C_v, late, _cfg(estimate_time_offset=True))
    c = est.calib
    assert c["time_offset_estimated"] and 0 < c["time_offset_std_s"] <= 0.05
    assert abs(c["time_offset_s"] - 0.3) <= 3 * c["time_offset_std_s"], (c["time_offset_s"], c["time_offset_std_s"])
    right = fuse_navigation(t_v, T_v, C_v, _sim(t, T, seed=seed + 3).nav, _cfg())
    ignored = fuse_navigation(t_v, T_v, C_v, late, _cfg())
    e_est, e_right, e_ign = (_rms(_pos_err(r.T_model_cam, T)) for r in (est, right, ignored))
    assert e_est <= 1.25 * e_right and e_est < e_ign, (e_est, e_right, e_ign)


def test_time_offset_on_a_constant_speed_orbit_is_weak_and_says_so(scene, tmp_path, mst):
    """On the constant-speed orbit a shift is nearly a rotation of the path about its centre (the
    model-to-world yaw takes it up): the reported std is ~4x larger than on the varying flight, still
    honest (|error| <= 3 std), and the refitted calibration keeps the fused positions as good as on
    the right clock (within 1.1x). Through the CLI: nav simulate --time-offset, nav fuse
    --estimate-time-offset."""
    import json

    from mst.core.trajectory import read_tum, write_tum

    t, T, t_v, T_v, C_v, _, _ = scene
    write_tum(tmp_path / "gt.txt", t, T)
    write_tum(tmp_path / "traj.txt", t_v, T_v)
    (tmp_path / "traj.cov.csv").write_text(format_cov_csv(t_v, C_v))
    mst("nav", "simulate", "--gt", tmp_path / "gt.txt", "-o", tmp_path / "nav.csv", "--world-yaw", "30",
        "--world-offset", "100", "-50", "10", "--lever", *map(str, LEVER), "--seed", "3", "--time-offset", "0.3")
    r = mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "f.txt",
            "--lever", *map(str, LEVER), "--ang-accel-sigma", "0.5", "--estimate-time-offset", "--json")
    c = json.loads(r.stdout)
    assert c["time_offset_estimated"] and c["config"]["estimate_time_offset"] is True
    assert c["time_offset_std_s"] > 0.04 and abs(c["time_offset_s"] - 0.3) <= 3 * c["time_offset_std_s"]
    _, Tf = read_tum(tmp_path / "f.txt")
    right = fuse_navigation(t_v, T_v, C_v, _sim(t, T).nav, _cfg())
    assert _rms(_pos_err(Tf, T)) <= 1.1 * _rms(_pos_err(right.T_model_cam, T))


def test_bad_inputs_are_refused_with_the_file_named(scene):
    t, T, t_v, T_v, C_v, _, _ = scene
    sim = _sim(t, T)
    late = sim.nav
    late.t = late.t + 1000.0
    with pytest.raises(InputError, match="nav.csv: time range .* does not overlap the video"):
        fuse_navigation(t_v, T_v, C_v, late, _cfg(), nav_name="nav.csv")
    # a trajectory of 2 s moves 12 m: the model-to-world yaw is not observable from 3 m GPS
    short = t_v < 2.0
    with pytest.raises(InputError, match="too little ground"):
        fuse_navigation(t_v[short], T_v[short], C_v[short], _sim(t, T).nav, _cfg(), nav_name="nav.csv")


def test_cov_side_file_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 6, 6))
    C = A @ np.swapaxes(A, 1, 2) + np.eye(6)
    p = tmp_path / "traj.cov.csv"
    p.write_text(format_cov_csv(np.arange(5) * 0.1, C, np.array(["vision"] * 5)))
    t, C2 = read_cov_csv(p)
    assert np.allclose(t, np.arange(5) * 0.1) and np.allclose(C2, C, rtol=1e-6)
    p.write_text(p.read_text().replace("vision,", "vision,-", 1))
    with pytest.raises(InputError, match="traj.cov.csv"):
        read_cov_csv(p)


def test_cli_fuse_chain_and_bad_log(tmp_path, mst, scene):
    import json

    from mst.core.trajectory import read_tum, write_tum

    t, T, t_v, T_v, C_v, keep, _ = scene
    write_tum(tmp_path / "gt.txt", t, T)
    write_tum(tmp_path / "traj.txt", t_v, T_v)
    (tmp_path / "traj.cov.csv").write_text(format_cov_csv(t_v, C_v))
    mst("nav", "simulate", "--gt", tmp_path / "gt.txt", "-o", tmp_path / "nav.csv", "--world-yaw", "30",
        "--enh-offset", "389000", "5820000", "40", "--seed", "3")
    r = mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "fused.txt",
            "--lever", *map(str, LEVER), "--ang-accel-sigma", "0.5", "--json")
    s = json.loads(r.stdout)
    tf, Tf = read_tum(tmp_path / "fused.txt")
    tc, Cf = read_cov_csv(tmp_path / "fused.cov.csv")
    assert len(tf) == len(t) == s["frames"] and np.allclose(tc, tf) and s["bridged_frames"] == int((~keep).sum())
    assert _rms(_pos_err(Tf, T)) <= 0.5 * 0.52
    assert abs(s["world_yaw_deg"] - 30.0) < 0.5
    # a bad log: one error line naming it, exit 1, no output
    bad = tmp_path / "bad.csv"
    bad.write_text((tmp_path / "nav.csv").read_text().replace(",1\n", ",nan\n", 1))
    r = mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", bad, "-o", tmp_path / "f2.txt", check=False)
    assert r.returncode == 1 and "bad.csv" in r.stderr and "NaN" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "f2.txt").exists() and not (tmp_path / "f2.cov.csv").exists()
    # settings from a --config file (the --json config of a run repeats it); an unknown key is named
    assert s["config"]["mode"] == "smoother" and s["config"]["lever_arm_m"] == list(LEVER)
    (tmp_path / "f.yaml").write_text("mode: filter\nang_accel_sigma_dps2: 0.5\nlever_arm_m: [0.10, 0.0, -0.15]\n")
    r = mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "causal.txt",
            "--config", tmp_path / "f.yaml", "--json")
    assert json.loads(r.stdout)["config"]["mode"] == "filter"
    assert "(filter)" in (tmp_path / "causal.txt").read_text().splitlines()[0]
    (tmp_path / "k.yaml").write_text("huber: 2\n")
    r = mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "f3.txt",
            "--config", tmp_path / "k.yaml", check=False)
    assert r.returncode == 1 and "huber: unknown key" in r.stderr and not (tmp_path / "f3.txt").exists()


def _lever_case(seed: int, rtk: bool):
    """60 s orbit, lever (0.5, -0.3, -0.2) m; RTK-grade GPS (5 / 8 cm, no outliers, no heading bias,
    vision 3 cm) or the default consumer GPS (3 / 5 m)."""
    t, T = flight()
    t_v, T_v, C_v, keep, _ = noisy_vision(t, T, seed=seed + 1, gap=None)
    kw = dict(seed=seed + 3, lever_arm_m=(0.5, -0.3, -0.2))
    cfg = dict(ang_accel_sigma_dps2=0.5, estimate_lever_arm=True)
    if rtk:
        T_v = T_v.copy()
        T_v[:, :3, 3] = T[keep, :3, 3] + np.random.default_rng(seed).normal(0, 0.03, (int(keep.sum()), 3))
        C_v = C_v / 100.0
        kw.update(sigma_h_m=0.05, sigma_v_m=0.08, outlier_rate=0.0, bias_rw_m_per_sqrt_s=0.002, dropouts=0,
                  ahrs_yaw_bias_deg=0.0)
        cfg.update(gps_sigma_h_m=0.05, gps_sigma_v_m=0.08, gps_bias_rw_m_per_sqrt_s=0.002, gps_bias_sigma_m=0.1)
    return fuse_navigation(t_v, T_v, C_v, _sim(t, T, **kw).nav, FusionConfig(**cfg)).calib


def _check_rtk_lever(seed):
    """Budget: the reported std is the white-noise one (GPS 5 cm, 300 fixes, yaw and translation
    free): ~2 / 1.5 / 4 cm; the GPS bias walk (0.002 m/sqrt(s), ~1.5 cm over the log) is not in it:
    within 3 std + 3 cm."""
    c = _lever_case(seed, rtk=True)
    err = np.abs(np.array(c["lever_arm_m"]) - [0.5, -0.3, -0.2])
    assert c["lever_arm_estimated"] and max(c["lever_arm_std_m"]) <= 0.05
    assert (err <= 3 * np.array(c["lever_arm_std_m"]) + 0.03).all(), (c["lever_arm_m"], c["lever_arm_std_m"])


def test_lever_arm_estimated_with_rtk_gps():
    _check_rtk_lever(1)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(8))
def test_lever_arm_estimated_with_rtk_gps_seeds(seed):
    _check_rtk_lever(seed)


def test_lever_arm_not_observable_with_consumer_gps_is_declined():
    """3 m GPS over 60 s: the lever's std is ~1 m (the tangential part turns with the orbit like a
    yaw of the model), so the given lever (0) is kept and the json says so."""
    c = _lever_case(0, rtk=False)
    assert not c["lever_arm_estimated"] and c["lever_arm_m"] == [0.0, 0.0, 0.0]
    assert min(c["lever_arm_std_m"]) > 0.3
