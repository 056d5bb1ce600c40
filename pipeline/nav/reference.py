"""The vision reference of :mod:`mst.pipeline.nav.fusion` (``FusionConfig.vision_reference``): the
vision-only track on the frame grid, about which the smoother estimates a smooth GPS/AHRS correction
(a walking camera's bob is kept). ``al``: fusion's aligned grid (``_Aligned``). Metres, radians."""

from __future__ import annotations

import numpy as np

from mst.core.poses import so3_exp, so3_log
from mst.pipeline.nav.models import _best_noise_scale_blocks, _ca_model, _cv_model, _run_kf


def vision_reference_rotation(al, T_vis, cov_vis, R_smooth, sig_alpha: float, huber_k: float) -> np.ndarray:
    """Vision-only camera rotations on the frame grid (K, 3, 3): the batch smoother of the vision
    rotations alone at the angular-acceleration scale of highest innovation likelihood of the vision
    (linearised about ``R_smooth``, the smooth fused solution); frames without vision: ``R_smooth``
    turned by the difference at the gap's edges, interpolated linearly."""
    vidx, dts = al.vidx, al.dts
    R_v, C_v = T_vis[:, :3, :3], cov_vis[:, 3:, 3:]
    z = so3_log(R_v @ np.swapaxes(R_smooth[vidx], -1, -2))
    H = np.zeros((len(vidx), 3, 6))
    H[:, :, :3] = np.eye(3)
    P0 = np.diag([np.radians(10.0) ** 2] * 6)
    scale = _best_noise_scale_blocks(lambda d, sc: _cv_model(d, sc * sig_alpha**2), dts, lambda zb: np.zeros(6), P0,
                                     vidx, z, H, C_v)
    if scale == 1.0:
        return R_smooth
    from mst.pipeline.nav.fusion import smooth_rotations_gn

    R0 = R_smooth.copy()
    R0[vidx] = R_v
    R_a = smooth_rotations_gn(al.t_grid, R0, al.t_grid[vidx], R_v, C_v, sig_alpha * np.sqrt(scale), huber_k)
    d = so3_log(R_a[vidx] @ np.swapaxes(R_smooth[vidx], -1, -2))
    g = np.arange(al.K)
    d_all = np.stack([np.interp(g, vidx, d[:, i]) for i in range(3)], 1)
    out = R_a.copy()
    gap = ~al.has_vis
    out[gap] = so3_exp(d_all[gap]) @ R_smooth[gap]
    return out


def vision_reference_position(al, T_vis, cov_vis, cfg) -> np.ndarray:
    """Vision-only camera positions on the frame grid (K, 3), m: the vision frames smoothed (RTS) with
    the position motion model at the noise scale (:data:`~mst.pipeline.nav.models.MOTION_NOISE_SCALES`)
    of highest innovation likelihood of the vision alone -- small for white vision noise on a smooth
    flight (the noise is smoothed away), large for a bobbing camera tracked to a few cm (the bob is
    kept) --; frames without vision bridged by the configured model's vision-only smoother."""
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
    if len(vidx) < al.K and scale != 1.0:
        # across a gap the bridge of the configured (smooth) model, not of one that follows a bob --
        # whose edge accelerations would be carried across seconds --, shifted to meet the vision
        # track at both edges (the difference to it interpolated linearly)
        x1, _, _ = _run_kf(*model(dts, 1.0), x0, P0, vidx, z, H, C, cfg.huber_k, True, True)
        g = np.arange(al.K)
        d = np.stack([np.interp(g, vidx, p[vidx, i] - x1[vidx, i]) for i in range(3)], 1)
        gap = ~al.has_vis
        p[gap] = x1[gap, :3] + d[gap]
    return p
