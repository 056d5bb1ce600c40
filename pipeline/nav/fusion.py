"""Offline / causal fusion of a vision trajectory with a GPS/AHRS log (``mst nav fuse``).

Inputs: the vision trajectory ``T_model_cam`` (K_v, 4, 4) at times ``t_vis`` (lost frames absent)
with per-pose 6x6 covariances, and a :class:`~mst.pipeline.nav.log.NavLog` (frames in its docstring).

Covariance convention (input side file and output ``fused.cov.csv``): order ``(x, y, z, rx, ry, rz)``;
position of the camera in the model frame [m]; rotation as a perturbation in the model frame [rad]:
``R_true = exp([r]x) @ R_est``.

Estimator, in two stages:

1. **Calibration** (batch, robust): the model-to-world transform ``T_world_model`` (4 DoF: yaw about
   up + translation; the model is z-up) by a Huber-weighted 2-D Procrustes fit of the GPS fixes to the
   vision positions of the antenna at the same times, and the camera mount ``R_body_cam`` by a Huber-
   weighted chordal mean of ``R_cam_model R_model_world R_world_body``; alternated 3 times (the lever
   arm couples them). The constant part of the GPS bias goes into ``T_world_model``; a constant AHRS
   heading bias goes into the mount yaw (they are not separable for a near-level platform).
2. **Smoothing** on the frame grid (every frame of the video, lost ones included), two linear Kalman
   filters + Rauch-Tung-Striebel smoothers (numba), decoupled (their coupling is the lever arm times
   the attitude error, millimetres):

   * attitude: measurements are the vision rotations and the AHRS attitudes mapped to camera
     attitudes in the model frame; constant-rate model with white angular acceleration. Offline: a
     batch Gauss-Newton on SO(3) (:func:`smooth_rotations_gn`), then a linear KF + RTS about that
     smooth solution (state ``[theta, dtheta/dt]``, the model-frame correction) for the covariances.
     Causal: a multiplicative EKF (nominal rotation + rate, error state) frame by frame;
   * position: state ``[p, v, a, b]`` (camera position, velocity, acceleration in the model frame,
     GPS bias random walk); constant-acceleration model with white jerk (``motion_model="ca"``, the
     default; ``"cv"``: ``[p, v, b]`` with white acceleration, which to allow a turn must be so loose
     that across a vision gap of seconds the bridge follows the GPS noise); measurements: vision
     positions, GPS fixes mapped into the model frame and moved from the antenna to the camera with
     the attitude (``H = [I, dtau I, dtau^2/2 I, I]``, ``dtau`` = fix time - frame time, so fixes
     need not fall on frames).

   Robust: every measurement whose Mahalanobis innovation exceeds ``huber_k`` is down-weighted by the
   Huber weight ``huber_k / d`` (variance inflated); offline, the smoother is re-run with Huber
   weights from the smoothed residuals. ``mode="filter"`` returns the causal filter estimates
   (each frame from the measurements up to it; only the constant calibration of stage 1 is fitted on
   the whole log), ``mode="smoother"`` the smoothed ones.

Longer than 500 lines: the smoother and the filter share one model of the states and the vision-shape rule; split by mode they would duplicate it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from mst import InputError
from mst.core.config import Config, param
from mst.core.poses import so3_exp, so3_log, transform_points
from mst.pipeline.nav.compiled import kernels as _nk  # ahead of time or numba JIT
from mst.pipeline.nav.log import NavLog, mount_ypr_deg_from_R
from mst.pipeline.nav.models import _best_noise_scale, _ca_model, _cv_model, _run_kf
from mst.pipeline.nav.reference import vision_reference_position as _vision_reference
from mst.pipeline.nav.reference import vision_reference_rotation as _vision_reference_R
from mst.pipeline.nav.reference import vision_rotation_noise_scale as _vision_noise_scale_R


@dataclass
class FusionConfig(Config):
    """Noise model and options of :func:`fuse_navigation` (units in the names). A fixed mount
    rotation or model-to-world transform (files, not settings) are arguments of the function."""

    mode: str = param("smoother", choices=("smoother", "filter"), help="smoother: offline (RTS); filter: causal")
    gps_sigma_h_m: float = param(3.0, min=0, min_open=True, help="GPS noise, each horizontal axis, m")
    gps_sigma_v_m: float = param(5.0, min=0, min_open=True, help="GPS noise, vertical, m")
    gps_bias_rw_m_per_sqrt_s: float = param(0.05, min=0, help="random walk of the GPS bias, m / sqrt(s)")
    gps_bias_sigma_m: float = param(3.0, min=0, min_open=True, help="prior of the bias left after the calibration, m")
    ahrs_sigma_deg: float = param(3.0, min=0, min_open=True, help="AHRS noise, deg")
    motion_model: str = param("ca", choices=("cv", "ca"),
                              help="position motion model: cv (white acceleration) or ca (white jerk)")
    accel_sigma_mps2: float = param(1.0, min=0, min_open=True, help="cv model: white acceleration, (m/s^2)/sqrt(Hz)")
    jerk_sigma_mps3: float = param(0.5, min=0, min_open=True, help="ca model: white jerk, (m/s^3)/sqrt(Hz)")
    ang_accel_sigma_dps2: float = param(2.0, min=0, min_open=True,
                                        help="motion model: white angular acceleration, (deg/s^2)/sqrt(Hz)")
    vision_sigma_m: float = param(0.05, min=0, min_open=True, help="vision noise when no covariance is given, m")
    vision_sigma_deg: float = param(0.3, min=0, min_open=True, help="vision noise when no covariance is given, deg")
    huber_k: float = param(3.0, min=0, min_open=True, help="Mahalanobis distance where Huber down-weighting starts")
    lever_arm_m: tuple[float, float, float] = param((0.0, 0.0, 0.0), help="camera in the body frame, m (the prior "
                                                                          "value with estimate_lever_arm)")
    estimate_lever_arm: bool = param(False, help="estimate the lever arm from the GPS where the attitude changes "
                                                 "make it observable")
    max_lever_std_m: float = param(0.05, min=0, min_open=True,
                                   help="use the estimated lever arm only when its std (each axis) is below this, m")
    max_world_yaw_std_deg: float = param(2.0, min=0, min_open=True,
                                         help="refuse when the fit cannot pin the model-to-world yaw, deg")
    min_pairs: int = param(10, min=1, help="GPS fixes with vision needed for the calibration")
    time_offset_s: float = param(0.0, min=-60, max=60, help="added to the log's times to put them on the video clock, s")
    estimate_time_offset: bool = param(False, help="estimate the clock offset (1-D search of the calibration cost "
                                                   "around time_offset_s)")
    max_time_offset_s: float = param(1.0, min=0, min_open=True, max=30,
                                     help="the search spans time_offset_s +- this, s")
    vision_reference: bool = param(True, help="smoother: estimate the position as the vision-only track (its own "
                                              "motion noise chosen by the vision's innovation likelihood) plus a "
                                              "smooth correction from the GPS, instead of smoothing the positions "
                                              "themselves (keeps a walking camera's bob that white jerk flattens)")
    vision_motion_noise: bool = param(True, help="scale the attitude model's angular-acceleration density "
                                                 "(ang_accel_sigma_dps2 x 1/16 .. x 65536 in steps of 4) to the one of "
                                                 "highest innovation likelihood of the vision rotations alone: the "
                                                 "platform's attitude dynamics as the vision sees them, also across "
                                                 "its gaps (fitted on the whole track, like the calibration)")
    adapt_motion_noise: bool = param(False, help="scale the motion models' white noise (jerk_sigma_mps3 / "
                                                "accel_sigma_mps2, ang_accel_sigma_dps2: x 1/16 .. x 65536 in steps "
                                                "of 4) to the one of highest innovation likelihood of the data")


@dataclass
class FusionResult:
    """Fused trajectory on the frame grid and the calibration."""

    t: np.ndarray                 # (K,) s
    T_model_cam: np.ndarray       # (K, 4, 4)
    cov: np.ndarray               # (K, 6, 6) convention in the module docstring
    has_vision: np.ndarray        # (K,) bool: the frame had a vision pose (else bridged by nav)
    gps_bias_m: np.ndarray        # (K, 3) GPS bias in the model frame (relative to the calibration)
    T_world_model: np.ndarray     # (4, 4)
    R_body_cam: np.ndarray        # (3, 3)
    calib: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """Calibration and counts (what ``mst nav fuse --json`` prints)."""
        return {"frames": int(len(self.t)), "vision_frames": int(self.has_vision.sum()),
                "bridged_frames": int((~self.has_vision).sum()), "T_world_model": self.T_world_model.tolist(),
                "R_body_cam": self.R_body_cam.tolist(), **self.calib, **self.stats}





# ------------------------------------------------------------------------------ calibration helpers
def _rot_mean(R: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted chordal mean of rotations (N, 3, 3)."""
    U, _, Vt = np.linalg.svd(np.einsum("n,nij->ij", w, R))
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt


def robust_rotation_mean(R: np.ndarray, sigma_rad: float, k: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Huber-weighted chordal mean of (N, 3, 3); returns (mean, weights, std of the mean [rad])."""
    w = np.ones(len(R))
    M = _rot_mean(R, w)
    for _ in range(6):
        a = np.linalg.norm(so3_log(np.swapaxes(M, -1, -2)[None] @ R), axis=1) / sigma_rad / np.sqrt(3)
        w = np.where(a > k / np.sqrt(3), (k / np.sqrt(3)) / np.maximum(a, 1e-12), 1.0)
        M = _rot_mean(R, w)
    return M, w, sigma_rad / np.sqrt(max(w.sum(), 1.0))


def fit_world_from_model_4dof(q_model: np.ndarray, g_world: np.ndarray, sig: np.ndarray, k: float
                              ) -> tuple[np.ndarray, np.ndarray, float]:
    """Huber-IRLS fit of ``g = Rz(yaw) q + t`` (4 DoF). q, g (N, 3) m; sig (3,) m. Returns
    (T_world_model 4x4, weights (N,), yaw std [rad])."""
    w = np.ones(len(q_model))
    T = np.eye(4)
    for _ in range(8):
        ws = w / w.sum()
        qc, gc = ws @ q_model, ws @ g_world
        A, B = q_model[:, :2] - qc[:2], g_world[:, :2] - gc[:2]
        Hm = np.einsum("n,ni,nj->ij", w, A, B)
        yaw = np.arctan2(Hm[0, 1] - Hm[1, 0], Hm[0, 0] + Hm[1, 1])
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = gc - R @ qc
        r = (transform_points(T, q_model) - g_world) / sig
        d = np.linalg.norm(r, axis=1)
        w = np.where(d > k, k / np.maximum(d, 1e-12), 1.0)
    spread = np.sqrt(np.sum(w * np.sum((q_model[:, :2] - (w / w.sum()) @ q_model[:, :2]) ** 2, axis=1)))
    return T, w, float(sig[0] / max(spread, 1e-12))


# ------------------------------------------------------------------------------ main entry
def frame_grid(t_vis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The regular frame grid spanning the vision times (lost frames filled in) and the grid index of
    each vision pose. Returns (t_grid (K,), idx (K_v,))."""
    if len(t_vis) < 2:
        raise InputError(None, "the vision trajectory needs at least 2 poses")
    dt = float(np.median(np.diff(t_vis)))
    if not dt > 0:
        raise InputError(None, "vision timestamps are not increasing")
    idx = np.round((t_vis - t_vis[0]) / dt).astype(np.int64)
    if (np.diff(idx) <= 0).any():
        raise InputError(None, "vision timestamps are not on a regular frame grid (two poses in one frame)")
    t = t_vis[0] + dt * np.arange(idx[-1] + 1)
    t[idx] = t_vis
    return t, idx


@dataclass
class _Aligned:
    """The vision frame grid and the nav rows inside it, with the vision interpolated at nav times."""

    t_grid: np.ndarray      #: (K,) frame times, s
    vidx: np.ndarray        #: grid index of each vision pose
    K: int
    dt_f: float             #: frame interval, s
    has_vis: np.ndarray     #: (K,) bool
    Tg: np.ndarray          #: (K, 4, 4) vision poses on the grid (identity where none)
    tn: np.ndarray          #: nav times in the grid's range
    fix: np.ndarray         #: their GPS fix flags
    R_wb: np.ndarray        #: their platform attitudes
    g_w: np.ndarray         #: their GPS positions (world)
    pair: np.ndarray        #: both neighbouring frames of the nav row tracked
    p_ci: np.ndarray        #: vision position interpolated at the nav times
    R_ci: np.ndarray        #: vision rotation interpolated at the nav times
    k_a: np.ndarray         #: nearest frame of each nav row
    dtau_a: np.ndarray      #: its time from that frame, s
    dts: np.ndarray         #: (K,) frame steps, s (0 first)


def _align(t_vis: np.ndarray, T_vis: np.ndarray, nav: NavLog, nav_name) -> _Aligned:
    """The frame grid of the vision times and the nav rows within it (refused when they do not overlap)."""
    t_grid, vidx = frame_grid(np.asarray(t_vis, float))
    K = len(t_grid)
    dt_f = float(np.median(np.diff(t_grid)))
    has_vis = np.zeros(K, bool)
    has_vis[vidx] = True
    Tg = np.tile(np.eye(4), (K, 1, 1))
    Tg[vidx] = T_vis
    lo, hi = max(t_grid[0], nav.t[0]), min(t_grid[-1], nav.t[-1])
    if hi <= lo:
        raise InputError(nav_name, f"time range {nav.t[0]:.3f}-{nav.t[-1]:.3f} s does not overlap the video "
                                   f"({t_grid[0]:.3f}-{t_grid[-1]:.3f} s); a time offset?")
    in_rng = (nav.t >= t_grid[0] - 0.5 * dt_f) & (nav.t <= t_grid[-1] + 0.5 * dt_f)
    tn, fix, R_wb = nav.t[in_rng], nav.fix[in_rng], nav.R_world_body()[in_rng]
    g_w = nav.p_world[in_rng]
    # vision interpolated at nav times (both neighbouring frames tracked)
    j = np.clip(np.searchsorted(t_grid, tn) - 1, 0, K - 2)
    a = np.clip((tn - t_grid[j]) / (t_grid[j + 1] - t_grid[j]), 0.0, 1.0)
    pair = has_vis[j] & has_vis[j + 1]
    p_ci = (1 - a)[:, None] * Tg[j, :3, 3] + a[:, None] * Tg[j + 1, :3, 3]
    dR = so3_log(np.swapaxes(Tg[j, :3, :3], -1, -2) @ Tg[j + 1, :3, :3])
    R_ci = Tg[j, :3, :3] @ so3_exp(a[:, None] * dR)
    k_a = np.clip(np.round((tn - t_grid[0]) / dt_f).astype(np.int64), 0, K - 1)
    dtau_a = tn - t_grid[k_a]
    dts = np.diff(t_grid, prepend=t_grid[0])
    return _Aligned(t_grid, vidx, K, dt_f, has_vis, Tg, tn, fix, R_wb, g_w, pair, p_ci, R_ci, k_a, dtau_a, dts)


def _noise(cfg: FusionConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """(lever arm (3,), GPS sigma per axis (3,), AHRS sigma rad) of ``cfg``."""
    lever = np.asarray(cfg.lever_arm_m, float)
    sig = np.array([cfg.gps_sigma_h_m, cfg.gps_sigma_h_m, cfg.gps_sigma_v_m])
    s_ahrs = np.radians(cfg.ahrs_sigma_deg)
    return lever, sig, s_ahrs


def _calibrate(al: _Aligned, cfg: FusionConfig, R_body_cam, T_world_model, nav_name):
    """Model-to-world transform and camera mount (fixed ones kept), robust, with their spreads."""
    pair, fix, p_ci, g_w, R_ci, R_wb = al.pair, al.fix, al.p_ci, al.g_w, al.R_ci, al.R_wb
    lever, sig, s_ahrs = _noise(cfg)
    use_g = pair & fix
    if T_world_model is None and use_g.sum() < cfg.min_pairs:
        raise InputError(nav_name, f"only {int(use_g.sum())} GPS fixes at tracked frames (need {cfg.min_pairs}) "
                                   "to estimate the model-to-world transform")
    if R_body_cam is None and pair.sum() < cfg.min_pairs:
        raise InputError(nav_name, f"only {int(pair.sum())} attitudes at tracked frames (need {cfg.min_pairs}) to estimate the mount")
    T_wm = np.eye(4) if T_world_model is None else np.asarray(T_world_model, float)
    R_bc = np.eye(3) if R_body_cam is None else np.asarray(R_body_cam, float)
    q = p_ci
    yaw_std = 0.0
    w_g = np.ones(int(use_g.sum()))
    w_a = np.ones(int(pair.sum()))
    mount_std = 0.0
    for _ in range(3):
        if T_world_model is None:
            T_wm, w_g, yaw_std = fit_world_from_model_4dof(q[use_g], g_w[use_g], sig, cfg.huber_k)
        if R_body_cam is None:
            R_cb_j = np.swapaxes(R_ci[pair], -1, -2) @ T_wm[:3, :3].T[None] @ R_wb[pair]
            R_cb, w_a, mount_std = robust_rotation_mean(R_cb_j, s_ahrs, cfg.huber_k)
            R_bc = R_cb.T
        q = p_ci - np.einsum("nij,j->ni", R_ci @ R_bc.T[None], lever)
    if T_world_model is None and np.degrees(yaw_std) > cfg.max_world_yaw_std_deg:
        raise InputError(nav_name, f"the tracked trajectory spans too little ground for the GPS noise to fix the "
                                   f"model-to-world yaw (std {np.degrees(yaw_std):.1f} deg); give the transform")
    return T_wm, R_bc, yaw_std, mount_std, w_g, w_a


def _fuse_attitude(al: _Aligned, T_vis, cov_vis, R_wm, R_bc, cfg: FusionConfig):
    """Per-frame camera rotations from vision + AHRS: batch smoother (+ KF/RTS covariances), or the
    causal multiplicative EKF. Returns ``(R (K, 3, 3), covariances, measurement weights, the scale of
    the angular-acceleration PSD chosen by adapt_motion_noise)``."""
    t_grid, vidx, K, dt_f, has_vis, Tg = al.t_grid, al.vidx, al.K, al.dt_f, al.has_vis, al.Tg
    tn, R_wb, k_a, dtau_a, dts = al.tn, al.R_wb, al.k_a, al.dtau_a, al.dts
    s_ahrs = np.radians(cfg.ahrs_sigma_deg)
    R_mc_ahrs = R_wm.T[None] @ R_wb @ R_bc[None]
    F6, Q6 = _cv_model(dts, np.radians(cfg.ang_accel_sigma_dps2) ** 2)
    steps_r = np.concatenate([vidx, k_a])
    R_meas = np.concatenate([T_vis[:, :3, :3], R_mc_ahrs])
    H_r = np.zeros((len(steps_r), 3, 6))
    H_r[:, :, :3] = np.eye(3)
    H_r[len(vidx):, :, 3:] = dtau_a[:, None, None] * np.eye(3)
    C_r = np.concatenate([cov_vis[:, 3:, 3:], np.tile(np.eye(3) * s_ahrs**2, (len(tn), 1, 1))])
    t_meas_r = t_grid[steps_r] + np.concatenate([np.zeros(len(vidx)), dtau_a])
    R0 = Tg[:, :3, :3].copy()
    if not has_vis.all():  # frames without vision: the nearest attitude measurement
        near = np.clip(np.round((tn - t_grid[0]) / dt_f).astype(np.int64), 0, K - 1)
        R_at = np.full(K, -1)
        R_at[near] = np.arange(len(tn))
        fill = ~has_vis
        src = np.where(R_at >= 0, R_at, -1)
        known = np.flatnonzero(src >= 0)
        if len(known):
            nearest = known[np.clip(np.searchsorted(known, np.arange(K)), 0, len(known) - 1)]
            R0[fill] = R_mc_ahrs[src[nearest[fill]]]
    smooth = cfg.mode == "smoother"
    sig_alpha = np.radians(cfg.ang_accel_sigma_dps2)
    x0 = np.zeros(6)
    P0 = np.diag([np.radians(10.0) ** 2] * 3 + [np.radians(10.0) ** 2] * 3)
    scale = 1.0
    R_ref = R0
    sig_alpha_cfg = sig_alpha
    if cfg.adapt_motion_noise:  # the likelihood of the linearised problem about the smooth solution
        R_ref = smooth_rotations_gn(t_grid, R0, t_meas_r, R_meas, C_r, sig_alpha, cfg.huber_k)
        z_r = so3_log(R_meas @ np.swapaxes(_interp_R(t_grid, R_ref, t_meas_r), -1, -2))
        scale = _best_noise_scale(lambda s: _cv_model(dts, s * sig_alpha**2), x0, P0, steps_r, z_r, H_r, C_r)
    elif cfg.vision_motion_noise:  # the attitude dynamics as the vision alone sees them, linearised
        # about the vision-only smooth solution (about the fused one, the AHRS noise it follows would
        # read as motion)
        R_lin = smooth_rotations_gn(t_grid, R0, t_grid[vidx], T_vis[:, :3, :3], cov_vis[:, 3:, 3:], sig_alpha,
                                    cfg.huber_k)
        scale = _vision_noise_scale_R(al, T_vis, cov_vis, R_lin, sig_alpha)
    if scale != 1.0:
        sig_alpha *= np.sqrt(scale)
        F6, Q6 = _cv_model(dts, sig_alpha**2)
    # the smooth fused solution: at the chosen density for the smoother; the filter's linearisation
    # point at the configured one (computed once: the adapted likelihood above already has it)
    if smooth and scale != 1.0:
        R_ref = smooth_rotations_gn(t_grid, R0, t_meas_r, R_meas, C_r, sig_alpha, cfg.huber_k)
    elif not cfg.adapt_motion_noise and (cfg.vision_motion_noise or smooth):
        R_ref = smooth_rotations_gn(t_grid, R0, t_meas_r, R_meas, C_r, sig_alpha_cfg, cfg.huber_k)
    keep_shape = False
    if smooth and cfg.vision_reference:
        # as for the position: the reference is the vision's own attitude track (the bob's pitch
        # kept) unless smoothing it removes only noise; the correction about it smooth
        R_ref, keep_shape = _vision_reference_R(al, T_vis, cov_vis, R_ref, sig_alpha, cfg.huber_k)
        if keep_shape and scale > 1.0:
            # the reference carries the motion (the vision's, bridged at its density); the
            # correction about it is the vision's error, a slow bias: no looser than configured
            F6, Q6 = _cv_model(dts, sig_alpha_cfg**2)
    if smooth:
        # about the smooth batch solution the linear KF + RTS is exact to first order in its (small)
        # correction; it gives the covariances
        z_r = so3_log(R_meas @ np.swapaxes(_interp_R(t_grid, R_ref, t_meas_r), -1, -2))
        xr, Pr, wr = _run_kf(F6, Q6, x0, P0, steps_r, z_r, H_r, C_r, cfg.huber_k, True, True)
        R_ref = so3_exp(xr[:, :3]) @ R_ref
    else:  # causal: multiplicative EKF, each frame from the measurements up to it
        order = np.argsort(steps_r, kind="stable")
        ptr = np.searchsorted(steps_r[order], np.arange(K + 1)).astype(np.int64)
        dtau_r = np.concatenate([np.zeros(len(vidx)), dtau_a])
        first = R_meas[order[0]]
        R_ref, _, Pr, w_o = _nk.mekf_attitude(dts, sig_alpha**2, first, ptr,
                                  np.ascontiguousarray(R_meas[order]), dtau_r[order], np.ascontiguousarray(C_r[order]),
                                  cfg.huber_k)
        wr = np.empty_like(w_o)
        wr[order] = w_o
    return R_ref, Pr, wr, scale, keep_shape


def _fuse_position(al: _Aligned, T_vis, cov_vis, R_fused, R_wm, t_wm, R_bc, cfg: FusionConfig):
    """Per-frame camera positions and the GPS bias from vision + GPS (smoother or causal filter).
    Returns ``(states (K, n), covariances, measurement weights, used GPS rows, the scale of the
    motion model's PSD chosen by adapt_motion_noise)``: ``[p, v, b]`` (n = 9)
    or, with the constant-acceleration model, ``[p, v, a, b]`` (n = 12); the bias is the last three."""
    fix, g_w, k_a, dtau_a, dts, vidx = al.fix, al.g_w, al.k_a, al.dtau_a, al.dts, al.vidx
    lever, sig, _ = _noise(cfg)
    smooth = cfg.mode == "smoother"
    gi = np.flatnonzero(fix)
    g_m = (g_w[gi] - t_wm) @ R_wm  # = R_wm^T (g - t)
    g_cam = g_m + np.einsum("nij,j->ni", R_fused[k_a[gi]] @ R_bc.T[None], lever)  # antenna -> camera
    Sg = R_wm.T @ np.diag(sig**2) @ R_wm
    q_b = cfg.gps_bias_rw_m_per_sqrt_s**2
    ca = cfg.motion_model == "ca"
    F, Q = _ca_model(dts, cfg.jerk_sigma_mps3**2, q_b) if ca else _cv_model(dts, cfg.accel_sigma_mps2**2, 1, q_b)
    n = F.shape[1]
    steps_p = np.concatenate([vidx, k_a[gi]])
    z_p = np.concatenate([T_vis[:, :3, 3], g_cam])
    H_p = np.zeros((len(steps_p), 3, n))
    H_p[:, :, :3] = np.eye(3)
    dt_g = dtau_a[gi][:, None, None]
    H_p[len(vidx):, :, 3:6] = dt_g * np.eye(3)  # the fix is dtau after the frame: p + v dtau (+ a dtau^2 / 2)
    if ca:
        H_p[len(vidx):, :, 6:9] = 0.5 * dt_g**2 * np.eye(3)
    H_p[len(vidx):, :, n - 3:] = np.eye(3)
    C_p = np.concatenate([cov_vis[:, :3, :3], np.tile(Sg, (len(gi), 1, 1))])
    x0 = np.zeros(n)
    x0[:3] = T_vis[0, :3, 3] if vidx[0] == 0 else (g_cam[0] if len(gi) else T_vis[0, :3, 3])
    P0 = np.diag([100.0**2] * 3 + [30.0**2] * 3 + ([10.0**2] * 3 if ca else []) + [cfg.gps_bias_sigma_m**2] * 3)
    scale = 1.0
    if cfg.adapt_motion_noise:
        q = cfg.jerk_sigma_mps3**2 if ca else cfg.accel_sigma_mps2**2
        scale = _best_noise_scale(lambda s: _ca_model(dts, s * q, q_b) if ca else _cv_model(dts, s * q, 1, q_b),
                                  x0, P0, steps_p, z_p, H_p, C_p)
        F, Q = _ca_model(dts, scale * q, q_b) if ca else _cv_model(dts, scale * q, 1, q_b)
    p_ref = None
    keep_shape = False
    if smooth and cfg.vision_reference:
        # the state becomes the correction p - p_ref (smooth: the motion model's white jerk suits it);
        # p_ref carries the motion the vision sees, a walking camera's 1.8 Hz bob included
        p_ref, keep_shape = _vision_reference(al, T_vis, cov_vis, cfg)
        t_m = np.concatenate([al.t_grid[vidx], al.t_grid[k_a[gi]] + dtau_a[gi]])
        z_p = z_p - np.stack([np.interp(t_m, al.t_grid, p_ref[:, i]) for i in range(3)], 1)
        x0[:3] = 0.0
    xp_, Pp_, wp = _run_kf(F, Q, x0, P0, steps_p, z_p, H_p, C_p, cfg.huber_k, smooth, smooth)
    if p_ref is not None:
        xp_[:, :3] += p_ref
    return xp_, Pp_, wp, gi, scale, keep_shape


def _shifted(nav: NavLog, delta: float, keep: np.ndarray | None = None) -> NavLog:
    """``nav`` with ``delta`` s added to its times (and only the rows ``keep``)."""
    k = slice(None) if keep is None else keep
    return NavLog(t=nav.t[k] + delta, p_world=nav.p_world[k], ypr_deg=nav.ypr_deg[k], fix=nav.fix[k], offset=nav.offset)


def fuse_navigation(t_vis: np.ndarray, T_vis: np.ndarray, cov_vis: np.ndarray | None, nav: NavLog,
                    cfg: FusionConfig | None = None, nav_name: str | os.PathLike | None = None, *,
                    R_body_cam: np.ndarray | None = None, T_world_model: np.ndarray | None = None) -> FusionResult:
    """Fuse vision poses ``T_vis`` (K_v, 4, 4) ``T_model_cam`` at ``t_vis`` (s) having covariances
    ``cov_vis`` (K_v, 6, 6) or None (then ``cfg.vision_sigma_*``) with the log ``nav``.

    ``R_body_cam`` (3, 3) / ``T_world_model`` (4, 4): a fixed camera-mount rotation / model-to-world
    transform (None: estimated). Returns the fused poses at every frame of the vision time range
    (see :class:`FusionResult`).
    Raises :class:`mst.InputError` (naming ``nav_name``) when the log does not overlap the video or
    the calibration is not observable (too few fixes, a trajectory too short to fix the yaw).
    """
    cfg = cfg or FusionConfig()
    if cov_vis is None:
        cov_vis = np.tile(np.diag([cfg.vision_sigma_m**2] * 3 + [np.radians(cfg.vision_sigma_deg) ** 2] * 3), (len(t_vis), 1, 1))
    offset, offset_std = cfg.time_offset_s, 0.0
    if cfg.estimate_time_offset:
        from mst.pipeline.nav.offset import estimate_time_offset

        offset, offset_std = estimate_time_offset(t_vis, T_vis, nav, cfg, R_body_cam, T_world_model, nav_name)
    if offset:
        nav = _shifted(nav, offset)
    al = _align(t_vis, T_vis, nav, nav_name)
    T_wm, R_bc, yaw_std, mount_std, w_g, w_a = _calibrate(al, cfg, R_body_cam, T_world_model, nav_name)
    lever_std = None
    if cfg.estimate_lever_arm:
        from dataclasses import replace

        from mst.pipeline.nav.lever import estimate_lever_arm

        ug = al.pair & al.fix
        for _ in range(2):  # lever given the calibration, the calibration given the lever
            lev, lever_std = estimate_lever_arm(al.p_ci[ug], al.R_ci[ug], al.g_w[ug], w_g, T_wm[:3, :3], R_bc,
                                                _noise(cfg)[1])
            if lever_std.max() > cfg.max_lever_std_m:
                break
            cfg = replace(cfg, lever_arm_m=tuple(float(v) for v in lev))
            T_wm, R_bc, yaw_std, mount_std, w_g, w_a = _calibrate(al, cfg, R_body_cam, T_world_model, nav_name)
    R_wm, t_wm = T_wm[:3, :3], T_wm[:3, 3]
    R_fused, Pr, wr, scale_r, shape_r = _fuse_attitude(al, T_vis, cov_vis, R_wm, R_bc, cfg)
    xp_, Pp_, wp, gi, scale_p, shape_p = _fuse_position(al, T_vis, cov_vis, R_fused, R_wm, t_wm, R_bc, cfg)
    lever = np.asarray(cfg.lever_arm_m, float)
    K, vidx, tn, t_grid, has_vis = al.K, al.vidx, al.tn, al.t_grid, al.has_vis
    T_out = np.tile(np.eye(4), (K, 1, 1))
    T_out[:, :3, :3] = R_fused
    T_out[:, :3, 3] = xp_[:, :3]
    cov = np.zeros((K, 6, 6))
    cov[:, :3, :3] = Pp_[:, :3, :3]
    cov[:, 3:, 3:] = Pr[:, :3, :3]
    w_gps = wp[len(vidx):]
    w_ahrs = wr[len(vidx):]
    calib = {
        "mode": cfg.mode,
        "world_yaw_deg": float(np.degrees(np.arctan2(R_wm[1, 0], R_wm[0, 0]))),
        "world_yaw_std_deg": float(np.degrees(yaw_std)),
        "world_offset_m": t_wm.tolist(),
        "mount_ypr_deg": mount_ypr_deg_from_R(R_bc).tolist(),
        "mount_std_deg": float(np.degrees(mount_std)),
        "lever_arm_m": lever.tolist(),
        "lever_arm_estimated": bool(lever_std is not None and lever_std.max() <= cfg.max_lever_std_m),
        "lever_arm_std_m": None if lever_std is None else lever_std.tolist(),
        "time_offset_s": float(offset),
        "time_offset_estimated": bool(cfg.estimate_time_offset),
        "time_offset_std_s": float(offset_std),
        "gps_bias_m_start_end": [xp_[0, -3:].tolist(), xp_[-1, -3:].tolist()],
        "nav_offset_enh": nav.offset.tolist(),
    }
    stats = {
        "gps_fixes_used": int(len(gi)), "gps_downweighted": int((w_gps < 0.999).sum()),
        "gps_outliers": int((w_gps < 0.5).sum()), "ahrs_rows_used": int(len(tn)),
        "ahrs_outliers": int((w_ahrs < 0.5).sum()),
        "calibration_gps_outliers": int((w_g < 0.5).sum()), "calibration_ahrs_outliers": int((w_a < 0.5).sum()),
        "pos_sigma_median_m": float(np.median(np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2)))),
        "rot_sigma_median_deg": float(np.degrees(np.median(np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2))))),
        "motion_noise_scale_position": scale_p, "motion_noise_scale_attitude": scale_r,
        "vision_shape_kept_position": shape_p, "vision_shape_kept_attitude": shape_r,
    }
    return FusionResult(t=t_grid, T_model_cam=T_out, cov=cov, has_vision=has_vis, gps_bias_m=xp_[:, -3:].copy(),
                        T_world_model=T_wm, R_body_cam=R_bc, calib=calib, stats=stats)


def smooth_rotations_gn(t_grid: np.ndarray, R_init: np.ndarray, t_meas: np.ndarray, R_meas: np.ndarray,
                        C_meas: np.ndarray, sigma_alpha: float, huber_k: float, iters: int = 4) -> np.ndarray:
    """Batch maximum-a-posteriori attitudes on the grid (Gauss-Newton on SO(3), sparse).

    Minimises sum |log(R_meas R(t_meas)^T)|^2_C (Huber-IRLS) + sum |rate change|^2 / (sigma_alpha^2 dt)
    with ``R(t)`` slerped between grid rotations, updates ``R_k <- exp(delta_k) R_k``. ``R_init``
    (K, 3, 3) may be noisy: the smoothness terms are evaluated on the current estimate, so the result
    is smooth (unlike a linear filter about a noisy reference). ``C_meas`` (L, 3, 3) rad^2,
    ``sigma_alpha`` rad/s^2/sqrt(Hz). Returns (K, 3, 3)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    K = len(t_grid)
    R = R_init.copy()
    j = np.clip(np.searchsorted(t_grid, t_meas) - 1, 0, K - 2)
    a = np.clip((t_meas - t_grid[j]) / (t_grid[j + 1] - t_grid[j]), 0.0, 1.0)
    Linv = np.linalg.inv(np.linalg.cholesky(C_meas))  # whitening: Linv @ e
    L = len(t_meas)
    dt = np.diff(t_grid)
    w = np.ones(L)
    i3 = np.arange(3)
    # measurement rows: Linv @ ((1-a) d_j + a d_j+1) = Linv @ e
    rm = (3 * np.arange(L)[:, None, None] + i3[None, :, None]).repeat(3, 2)  # (L, 3, 3) row ids
    cj = (3 * j[:, None, None] + i3[None, None, :]).repeat(3, 1)
    ks = np.arange(1, K - 1)
    nk = len(ks)
    s_k = 1.0 / (sigma_alpha * np.sqrt(0.5 * (dt[ks - 1] + dt[ks])))
    rows_s = 3 * L + 3 * np.arange(nk)[:, None] + i3[None, :]  # (nk, 3)
    for it in range(iters):
        Rj = _interp_R(t_grid, R, t_meas)
        e = so3_log(R_meas @ np.swapaxes(Rj, -1, -2))
        ew = np.einsum("lij,lj->li", Linv, e)
        if it > 0:
            d = np.linalg.norm(ew, axis=1)
            w = np.where(d > huber_k, huber_k / np.maximum(d, 1e-12), 1.0)
        sw = np.sqrt(w)[:, None, None]
        vals_m = np.concatenate([((1 - a)[:, None, None] * Linv * sw).ravel(), (a[:, None, None] * Linv * sw).ravel()])
        rows_m = np.concatenate([rm.ravel(), rm.ravel()])
        cols_m = np.concatenate([cj.ravel(), (cj + 3).ravel()])
        om = so3_log(R[1:] @ np.swapaxes(R[:-1], -1, -2)) / dt[:, None]  # (K-1, 3) rates
        b_s = -(om[ks] - om[ks - 1]) * s_k[:, None]
        c1, c0 = s_k / dt[ks], s_k / dt[ks - 1]  # d/d delta: (d_k+1 - d_k)/dt_k - (d_k - d_k-1)/dt_k-1
        rows = np.concatenate([rows_m, np.repeat(rows_s.ravel(), 3)])
        cols = np.concatenate([cols_m, np.stack([3 * (ks + 1)[:, None] + i3, 3 * ks[:, None] + i3,
                                                 3 * (ks - 1)[:, None] + i3], -1).ravel()])
        vals = np.concatenate([vals_m, np.stack([np.repeat(c1[:, None], 3, 1), -np.repeat((c1 + c0)[:, None], 3, 1),
                                                 np.repeat(c0[:, None], 3, 1)], -1).ravel()])
        A = sp.csr_matrix((vals, (rows, cols)), shape=(3 * L + 3 * nk, 3 * K))
        b = np.concatenate([(ew * np.sqrt(w)[:, None]).ravel(), b_s.ravel()])
        N = (A.T @ A + sp.identity(3 * K) * 1e-9).tocsc()
        delta = spsolve(N, A.T @ b).reshape(K, 3)
        R = so3_exp(delta) @ R
        if np.abs(delta).max() < 1e-7:
            break
    return R


def _interp_R(t_grid: np.ndarray, R: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Rotations (K, 3, 3) on the grid slerped to times ``tau`` (M,) (clipped to the grid)."""
    K = len(t_grid)
    j = np.clip(np.searchsorted(t_grid, tau) - 1, 0, K - 2)
    a = np.clip((tau - t_grid[j]) / (t_grid[j + 1] - t_grid[j]), 0.0, 1.0)
    return R[j] @ so3_exp(a[:, None] * so3_log(np.swapaxes(R[j], -1, -2) @ R[j + 1]))
