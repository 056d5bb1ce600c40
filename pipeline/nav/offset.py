"""The clock offset between a navigation log and the video (``mst nav fuse --estimate-time-offset``):
a 1-D search of the calibration cost of :mod:`mst.pipeline.nav.fusion` (GPS fixes and AHRS attitudes
against the vision trajectory interpolated at the shifted log times, calibration refitted per
candidate)."""

from __future__ import annotations

import numpy as np

from mst import InputError
from mst.core.poses import so3_log, transform_points
from mst.pipeline.nav.fusion import FusionConfig, _align, _calibrate, _noise, _shifted
from mst.pipeline.nav.log import NavLog


def _calibration_cost(t_vis, T_vis, nav: NavLog, cfg: FusionConfig, R_body_cam, T_world_model, nav_name
                      ) -> tuple[float, int]:
    """(Huber cost in chi-square units of the calibrated GPS and AHRS residuals, rows used)."""
    al = _align(t_vis, T_vis, nav, nav_name)
    T_wm, R_bc, *_ = _calibrate(al, cfg, R_body_cam, T_world_model, nav_name)
    lever, sig, s_ahrs = _noise(cfg)
    k = cfg.huber_k
    q = al.p_ci - np.einsum("nij,j->ni", al.R_ci @ R_bc.T[None], lever)
    ug = al.pair & al.fix
    d_g = np.linalg.norm((transform_points(T_wm, q[ug]) - al.g_w[ug]) / sig, axis=1)
    R_cb_j = np.swapaxes(al.R_ci[al.pair], -1, -2) @ T_wm[:3, :3].T[None] @ al.R_wb[al.pair]
    d_a = np.linalg.norm(so3_log(R_bc[None] @ R_cb_j), axis=1) / s_ahrs
    d = np.concatenate([d_g, d_a])
    return float(np.where(d < k, d**2, 2 * k * d - k**2).sum()), len(d)


def estimate_time_offset(t_vis: np.ndarray, T_vis: np.ndarray, nav: NavLog, cfg: FusionConfig, R_body_cam=None,
                         T_world_model=None, nav_name=None) -> tuple[float, float]:
    """The clock offset (s, added to the log's times) minimising the calibration cost: GPS fixes and
    AHRS attitudes against the vision trajectory interpolated at the shifted times, with the
    model-to-world transform and the mount refitted for every candidate. Grid of half a frame over
    ``time_offset_s +- max_time_offset_s`` on the rows that stay inside the video for every candidate,
    then least-squares parabolas. Returns ``(offset, std)``: the std from the fitted curvature (the
    cost is a chi-square: std = sqrt(2 / C'')). Observable only where the motion is not the same
    after a shift: on a circle at constant speed a shift is a rotation about its centre (taken up by
    the model-to-world yaw), on a straight line at constant speed a translation (the offset), a
    constant turn rate shifts the yaw by a constant (the mount): speed and turn-rate changes carry it.
    A refitted calibration keeps the fused trajectory right where the offset is not observable."""
    t_vis = np.asarray(t_vis, float)
    c0, M = cfg.time_offset_s, cfg.max_time_offset_s
    dt_f = float(np.median(np.diff(t_vis)))
    keep = (nav.t + c0 - M >= t_vis[0]) & (nav.t + c0 + M <= t_vis[-1])
    if keep.sum() < cfg.min_pairs:
        raise InputError(nav_name, f"only {int(keep.sum())} log rows lie inside the video for every time offset within "
                                   f"+-{M:g} s of {c0:g} s; a shorter search range (max_time_offset_s)?")
    h = 0.5 * dt_f
    grid = c0 + np.arange(-M, M + 0.5 * h, h)
    cost = np.array([_calibration_cost(t_vis, T_vis, _shifted(nav, d, keep), cfg, R_body_cam, T_world_model,
                                       nav_name)[0] for d in grid])
    # the cost is a parabola plus jitter at the frame scale (the vision noise of the frames each
    # candidate interpolates): least-squares quadratics, over the whole range, then over half of it
    # around the first one's vertex
    best, curv = float(grid[np.argmin(cost)]), 0.0
    for half in (M, 0.5 * M):
        sel = np.abs(grid - best) <= half + 1e-9
        if sel.sum() < 5:
            break
        a, b, _ = np.polyfit(grid[sel] - best, cost[sel], 2)
        if not a > 0:
            return float(grid[np.argmin(cost)]), float("inf")
        best, curv = float(np.clip(best - b / (2 * a), c0 - M, c0 + M)), 2 * a
    return best, (float(np.sqrt(2.0 / curv)) if curv > 0 else float("inf"))
