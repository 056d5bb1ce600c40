"""The vision reference of :mod:`mst.pipeline.nav.fusion` (``FusionConfig.vision_reference``): the
vision-only track on the frame grid, about which the fusion estimates a smooth GPS/AHRS correction.
``al``: fusion's aligned grid (``_Aligned``). Metres, radians.

Vision as relative motion: at the vision frames the reference is the vision itself, unless a
vision-only smoother at the motion-noise scale of highest innovation likelihood removes nothing
but noise, i.e. its residual (vision minus smoothed, whitened by the stated covariance, per axis)
passes :func:`residual_is_noise`: no larger than the stated noise (chi-square, 0.1 %) and white
(Box-Pierce over lags 1-6, 0.1 %, and at most 10 % of its power predictable from its own past).
White vision noise on a smooth flight passes (it is smoothed away, as a motion prior should); a
walking camera's 1.8 Hz bob at 6 fps does not (its residual is 3.9x the stated noise and periodic:
lag-2/3/5 autocorrelations -0.7/0.8/-0.85): it is motion the constant-acceleration model cannot
represent, so the vision's shape is kept and the GPS/AHRS only correct it slowly (the issue's
``BetweenFactorPose3`` from the vision track). Frames without vision: the configured (smooth)
model's bridge, shifted to meet the reference at both edges."""

from __future__ import annotations

import numpy as np

from mst.core.poses import so3_exp, so3_log
from mst.pipeline.nav.models import _best_noise_scale_blocks, _ca_model, _cv_model, _run_kf

#: residual whiteness test of :func:`residual_is_noise`
NOISE_TEST_LAGS = 6
NOISE_TEST_ALPHA = 1e-3
NOISE_TEST_MAX_PREDICTABLE = 0.10


def residual_is_noise(r_w: np.ndarray, idx: np.ndarray) -> bool:
    """Whether residuals ``r_w`` (N, 3), whitened by the stated noise, at frame-grid indices ``idx``
    (N,) look like that noise: on every axis the mean square within the chi-square bound of N
    degrees of freedom at ``NOISE_TEST_ALPHA``, and the autocorrelations rho_j over grid lags
    1..``NOISE_TEST_LAGS`` (pairs of frames both present) either insignificant (Box-Pierce
    sum n_j rho_j^2 below chi-square of the lags at ``NOISE_TEST_ALPHA``) or small (sum rho_j^2,
    about the share of the power a linear predictor from the past explains, at most
    ``NOISE_TEST_MAX_PREDICTABLE``)."""
    from scipy.stats import chi2

    n = len(idx)
    if n < 2 * NOISE_TEST_LAGS:
        return True  # too few frames to tell: the motion model's smoothing, as before
    if (np.mean(r_w**2, axis=0) > chi2.ppf(1 - NOISE_TEST_ALPHA, n) / n).any():
        return False
    g = np.full((int(idx[-1]) + 1, r_w.shape[1]), np.nan)
    g[idx] = r_w
    q = np.zeros(r_w.shape[1])
    s = np.zeros(r_w.shape[1])
    for lag in range(1, NOISE_TEST_LAGS + 1):
        a, b = g[:-lag], g[lag:]
        m = np.isfinite(a[:, 0]) & np.isfinite(b[:, 0])
        if m.sum() < 2:
            continue
        rho = np.sum(a[m] * b[m], 0) / np.sqrt(np.sum(a[m] ** 2, 0) * np.sum(b[m] ** 2, 0) + 1e-300)
        q += m.sum() * rho**2
        s += rho**2
    return not ((q > chi2.ppf(1 - NOISE_TEST_ALPHA, NOISE_TEST_LAGS)) & (s > NOISE_TEST_MAX_PREDICTABLE)).any()


def vision_rotation_noise_scale(al, T_vis, cov_vis, R_lin, sig_alpha: float) -> float:
    """The scale of the angular-acceleration PSD ``sig_alpha**2`` that the vision rotations alone
    show: the larger of (a) the scale of :data:`~mst.pipeline.nav.models.MOTION_NOISE_SCALES` of
    highest innovation likelihood, linearised about ``R_lin`` (K, 3, 3), and (b) the least density
    the vision's second differences need: over three consecutive frames the second difference of
    the rotation has the variance ``2/3 q dt^3`` per axis under white angular acceleration ``q``,
    plus ``s_(k-1)^2 + 4 s_k^2 + s_(k+1)^2`` of white vision noise at the stated covariance -- what
    exceeds that noise (its mean's lower 3-standard-error bound) is motion (a 1.8 Hz bob at 6 fps, which the likelihood with a stated noise as
    large as the bob reads as noise)."""
    vidx = al.vidx
    z = so3_log(T_vis[:, :3, :3] @ np.swapaxes(R_lin[vidx], -1, -2))
    H = np.zeros((len(vidx), 3, 6))
    H[:, :, :3] = np.eye(3)
    P0 = np.diag([np.radians(10.0) ** 2] * 6)
    C = cov_vis[:, 3:, 3:]
    scale = _best_noise_scale_blocks(lambda d, sc: _cv_model(d, sc * sig_alpha**2), al.dts, lambda zb: np.zeros(6), P0,
                                     vidx, z, H, C)
    tri = np.flatnonzero((np.diff(vidx)[:-1] == 1) & (np.diff(vidx)[1:] == 1))  # frames i, i+1, i+2 consecutive
    if len(tri) >= 10:
        R = T_vis[:, :3, :3]
        w1 = so3_log(R[tri + 1] @ np.swapaxes(R[tri], -1, -2))
        w2 = so3_log(R[tri + 2] @ np.swapaxes(R[tri + 1], -1, -2))
        s2 = np.einsum("nii->ni", C)
        x = ((w2 - w1) ** 2 - (s2[tri] + 4 * s2[tri + 1] + s2[tri + 2])).ravel()
        # its lower confidence bound: 3 standard errors below the mean (the triples overlap: the
        # error of the mean taken from every third one, n / 3 independent samples)
        excess = x.mean() - 3.0 * x.std() / np.sqrt(max(len(x) / 3.0, 1.0))
        scale = max(scale, float(excess / (2.0 / 3.0 * al.dt_f**3)) / sig_alpha**2)
    return scale


def _whiten(r: np.ndarray, C: np.ndarray) -> np.ndarray:
    return r / np.sqrt(np.einsum("nii->ni", C))


def vision_reference_rotation(al, T_vis, cov_vis, R_smooth, sig_alpha: float, huber_k: float) -> tuple[np.ndarray, bool]:
    """Vision-only camera rotations on the frame grid (K, 3, 3) and whether the vision's own shape is
    kept (see the module docstring). ``R_smooth``: the smooth fused solution at the angular-
    acceleration density ``sig_alpha`` (rad/s^2/sqrt(Hz)), the vision's own (its likelihood's) scale;
    at the vision frames the reference is the vision smoothed at that density when its residual is
    noise, else the vision itself; frames without vision: ``R_smooth`` turned by the difference at
    the gap's edges, interpolated linearly."""
    from mst.pipeline.nav.fusion import smooth_rotations_gn

    vidx = al.vidx
    R_v, C_v = T_vis[:, :3, :3], cov_vis[:, 3:, 3:]
    R0 = R_smooth.copy()
    R0[vidx] = R_v
    R_a = smooth_rotations_gn(al.t_grid, R0, al.t_grid[vidx], R_v, C_v, sig_alpha, huber_k)
    keep = not residual_is_noise(_whiten(so3_log(R_v @ np.swapaxes(R_a[vidx], -1, -2)), C_v), vidx)
    R_at = R_v if keep else R_a[vidx]
    d = so3_log(R_at @ np.swapaxes(R_smooth[vidx], -1, -2))
    g = np.arange(al.K)
    d_all = np.stack([np.interp(g, vidx, d[:, i]) for i in range(3)], 1)
    out = so3_exp(d_all) @ R_smooth
    out[vidx] = R_at
    return out, keep


def vision_reference_position(al, T_vis, cov_vis, cfg) -> tuple[np.ndarray, bool]:
    """Vision-only camera positions on the frame grid (K, 3), m, and whether the vision's own shape
    is kept (see the module docstring): the vision frames smoothed (RTS) with the position motion
    model at the noise scale (:data:`~mst.pipeline.nav.models.MOTION_NOISE_SCALES`) of highest
    innovation likelihood of the vision alone, or, when that smoothing's residual is not noise, the
    vision itself; frames without vision bridged by the configured model's vision-only smoother."""
    dts, vidx = al.dts, al.vidx
    ca = cfg.motion_model == "ca"
    q = cfg.jerk_sigma_mps3**2 if ca else cfg.accel_sigma_mps2**2

    def model(d, sc):  # the position states only (no GPS bias)
        F, Q = _ca_model(d, sc * q, 0.0) if ca else _cv_model(d, sc * q)
        return np.ascontiguousarray(F[:, :n, :n]), np.ascontiguousarray(Q[:, :n, :n])

    n = 9 if ca else 6
    H = np.zeros((len(vidx), 3, n))
    H[:, :, :3] = np.eye(3)
    z = T_vis[:, :3, 3]
    C = cov_vis[:, :3, :3]

    def x0_of(zb):
        x0 = np.zeros(n)
        x0[:3] = zb[0]
        return x0

    P0 = np.diag([100.0**2] * 3 + [30.0**2] * 3 + ([10.0**2] * 3 if ca else []))
    scale = _best_noise_scale_blocks(model, dts, x0_of, P0, vidx, z, H, C)
    x0 = x0_of(z)
    x, _, _ = _run_kf(*model(dts, scale), x0, P0, vidx, z, H, C, cfg.huber_k, True, True)
    p = x[:, :3].copy()
    keep = not residual_is_noise(_whiten(z - p[vidx], C), vidx)
    if keep:
        p[vidx] = z
    if len(vidx) < al.K and (scale != 1.0 or keep):
        # across a gap the bridge of the configured (smooth) model, not of one that follows a bob --
        # whose edge accelerations would be carried across seconds --, shifted to meet the reference
        # at both edges (the difference to it interpolated linearly)
        x1, _, _ = _run_kf(*model(dts, 1.0), x0, P0, vidx, z, H, C, cfg.huber_k, True, True)
        g = np.arange(al.K)
        d = np.stack([np.interp(g, vidx, p[vidx, i] - x1[vidx, i]) for i in range(3)], 1)
        gap = ~al.has_vis
        p[gap] = x1[gap, :3] + d[gap]
    return p, keep
