"""Bundle adjustment of the keyframes of ``mst refine``: KLT tie points, the tracked poses as
priors, navigation factors.

Unknowns: per keyframe the camera position ``c`` (model frame, m) and a rotation increment ``r``
(rad, model frame: ``R = exp(r) R0``, the convention of ``traj.cov.csv`` as read by
:func:`mst.pipeline.nav.run.read_track_cov`), per tie point its model-frame position ``X`` (m).
Residuals, each whitened (so one Huber kernel of ``huber`` sigmas serves them all):

* reprojection of tie point ``j`` in keyframe ``i``: ``(pi(K, R_iᵀ (X_j - c_i)) - uv_ij) / sigma_px``;
* prior of keyframe ``i``: ``U_i (c_i - c0_i, r_i)`` with ``U_iᵀ U_i = W_i = C_i⁻¹``, ``C_i`` the
  tracker's 6x6 covariance of that frame (``W = JᵀJ`` / sigma² of its edge residuals), scaled by
  ``prior_scale``; frames without one (SLAM, relocalised) get the fallback sigmas;
* with a navigation log (calibrated by :func:`~mst.pipeline.nav.fusion.fuse_navigation`: the
  model-to-world transform and the camera mount): the GPS fix nearest in time (within half a row
  interval), moved from the antenna to the camera, ``(c_i - g_i) / sigma_gps`` per axis, and the AHRS
  attitude through the mount, ``log(R_ahrs,i R_iᵀ) / sigma_ahrs``.

Tie points: corners (``cv2.goodFeaturesToTrack``) tracked keyframe to keyframe by
:func:`mst.core.klt.track_forward_backward` (forward-backward check), replenished where tracks
ended; a track's point starts from the depth at its first observation. Tracks seen by fewer than
``min_track`` keyframes are dropped. Solved by ``scipy.optimize.least_squares`` (trf, sparse
Jacobian by finite differences on its sparsity pattern, Huber loss).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from mst.core.poses import so3_exp, so3_log

log = logging.getLogger(__name__)


@dataclass
class TieTracks:
    """Observations of tie points: keyframe ``kf`` (index into the keyframes), point ``pt``, pixel ``uv``."""

    kf: np.ndarray   #: (L,) int
    pt: np.ndarray   #: (L,) int
    uv: np.ndarray   #: (L, 2) px
    X0: np.ndarray   #: (P, 3) model-frame start positions, m


def klt_tie_tracks(grays: list[np.ndarray], depths: list[np.ndarray], cam, T_kf: np.ndarray, klt_cfg,
                   min_track: int = 3) -> TieTracks:
    """KLT tracks over the keyframe images ``grays`` (uint8) with their depth frames (m, 0 = none)
    and poses ``T_kf`` (n, 4, 4) ``T_model_cam`` (for the start positions)."""
    import cv2

    from mst.core.klt import track_forward_backward

    obs_kf, obs_pt, obs_uv = [], [], []
    starts = []  # per track: (keyframe, u, v, depth)
    active_pt = np.zeros(0, np.int64)
    active_uv = np.zeros((0, 2), np.float32)
    h, w = grays[0].shape
    for i, g in enumerate(grays):
        if i > 0 and len(active_pt):
            uv1, ok, _ = track_forward_backward(grays[i - 1], g, active_uv, klt_cfg)
            inside = (uv1[:, 0] >= 0) & (uv1[:, 0] <= w - 1) & (uv1[:, 1] >= 0) & (uv1[:, 1] <= h - 1)
            ok &= inside
            active_pt, active_uv = active_pt[ok], uv1[ok]
            obs_kf.append(np.full(len(active_pt), i))
            obs_pt.append(active_pt)
            obs_uv.append(active_uv.astype(np.float64))
        # replenish: corners away from the live tracks
        mask = np.full((h, w), 255, np.uint8)
        for u, v in np.rint(active_uv).astype(int):
            cv2.circle(mask, (int(u), int(v)), int(klt_cfg.min_distance_px), 0, -1)
        need = klt_cfg.max_features - len(active_pt)
        if need <= 0:
            continue
        c = cv2.goodFeaturesToTrack(g, need, klt_cfg.quality, klt_cfg.min_distance_px, mask=mask,
                                    blockSize=klt_cfg.block_px, useHarrisDetector=False)
        if c is None:
            continue
        c = c.reshape(-1, 2)
        ui, vi = np.rint(c[:, 0]).astype(int), np.rint(c[:, 1]).astype(int)
        z = depths[i][vi, ui]
        good = np.isfinite(z) & (z > 0)
        c, z = c[good], z[good]
        ids = len(starts) + np.arange(len(c))
        starts.extend((i, float(u), float(v), float(d)) for (u, v), d in zip(c, z))
        obs_kf.append(np.full(len(c), i))
        obs_pt.append(ids)
        obs_uv.append(c.astype(np.float64))
        active_pt = np.concatenate([active_pt, ids])
        active_uv = np.concatenate([active_uv, c.astype(np.float32)])
    if not starts:
        return TieTracks(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 3)))
    kf, pt, uv = np.concatenate(obs_kf), np.concatenate(obs_pt), np.concatenate(obs_uv)
    n_obs = np.bincount(pt, minlength=len(starts))
    keep_pt = n_obs >= min_track
    new_id = np.cumsum(keep_pt) - 1
    sel = keep_pt[pt]
    S = np.array(starts)[keep_pt]
    k0 = S[:, 0].astype(int)
    x = (S[:, 1] - cam.cx) / cam.fx * S[:, 3]
    y = (S[:, 2] - cam.cy) / cam.fy * S[:, 3]
    Pc = np.stack([x, y, S[:, 3]], 1)
    X0 = np.einsum("nij,nj->ni", T_kf[k0, :3, :3], Pc) + T_kf[k0, :3, 3]
    return TieTracks(kf[sel], new_id[pt[sel]], uv[sel], X0)


@dataclass
class NavFactors:
    """Per keyframe (NaN where none): the camera position from GPS (model frame, m) and its sigma
    per axis, the camera rotation from the AHRS through the mount (model frame)."""

    p_cam: np.ndarray        #: (n, 3)
    sigma_p: np.ndarray      #: (3,) m (the GPS sigmas rotated into the model frame: z-up, yaw only)
    R_cam: np.ndarray        #: (n, 3, 3)
    has_p: np.ndarray        #: (n,) bool
    has_R: np.ndarray        #: (n,) bool
    sigma_r: float           #: rad


def nav_factors(t_kf: np.ndarray, T_kf: np.ndarray, nav, T_world_model: np.ndarray, R_body_cam: np.ndarray,
                lever_m, sigma_gps_m, sigma_ahrs_rad: float) -> NavFactors:
    """The GPS/AHRS rows nearest each keyframe time (within half the median row interval), mapped
    to camera measurements in the model frame with the calibration."""
    j = np.clip(np.searchsorted(nav.t, t_kf), 1, len(nav.t) - 1)
    j = np.where(np.abs(nav.t[j - 1] - t_kf) < np.abs(nav.t[j] - t_kf), j - 1, j)
    dt = float(np.median(np.diff(nav.t))) if len(nav.t) > 1 else 1.0
    near = np.abs(nav.t[j] - t_kf) <= 0.5 * dt + 1e-9
    R_wm, t_wm = T_world_model[:3, :3], T_world_model[:3, 3]
    R_wb = nav.R_world_body()[j]
    R_mc_ahrs = R_wm.T[None] @ R_wb @ R_body_cam[None]
    # camera = antenna + R_world_body lever, with the body attitude of the current camera estimate
    R_wb_est = R_wm[None] @ T_kf[:, :3, :3] @ R_body_cam.T[None]
    p_w = nav.p_world[j] + np.einsum("nij,j->ni", R_wb_est, np.asarray(lever_m, float))
    p_m = (p_w - t_wm) @ R_wm
    return NavFactors(p_cam=p_m, sigma_p=np.asarray(sigma_gps_m, float), R_cam=R_mc_ahrs,
                      has_p=near & nav.fix[j], has_R=near, sigma_r=float(sigma_ahrs_rad))


@dataclass
class BAResult:
    T_kf: np.ndarray            #: (n, 4, 4) refined keyframe poses
    points: int                 #: tie points used
    observations: int
    reproj_rms_before_px: float
    reproj_rms_after_px: float
    nfev: int

    def to_json(self) -> dict:
        return {"points": self.points, "observations": self.observations,
                "reproj_rms_before_px": self.reproj_rms_before_px, "reproj_rms_after_px": self.reproj_rms_after_px,
                "nfev": self.nfev}


def _project(c, R, X, kf, pt, cam) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (L, 2) of the points ``X[pt]`` in the keyframes ``kf`` and their depths (L,)."""
    Xc = np.einsum("lji,lj->li", R[kf], X[pt] - c[kf])  # R^T (X - c)
    z = np.maximum(Xc[:, 2], 1e-6)
    return np.stack([cam.fx * Xc[:, 0] / z + cam.cx, cam.fy * Xc[:, 1] / z + cam.cy], 1), Xc[:, 2]


def _drop_outliers(ties: TieTracks, R, c, cam, max_px: float, min_track: int) -> TieTracks:
    """Observations off by more than ``max_px`` at the starting poses, or behind the camera, are
    wrong KLT matches (occlusions, repeated texture); tracks left with fewer than ``min_track``
    observations go."""
    if not len(ties.kf):
        return ties
    uv, z = _project(c, R, ties.X0, ties.kf, ties.pt, cam)
    ok = (np.linalg.norm(uv - ties.uv, axis=1) <= max_px) & (z > 0)
    keep_pt = np.bincount(ties.pt[ok], minlength=len(ties.X0)) >= min_track
    sel = ok & keep_pt[ties.pt]
    new_id = np.cumsum(keep_pt) - 1
    return TieTracks(ties.kf[sel], new_id[ties.pt[sel]], ties.uv[sel], ties.X0[keep_pt])


def bundle_adjust(T_kf: np.ndarray, C_kf: np.ndarray, ties: TieTracks, cam, sigma_px: float, huber: float,
                  nav: NavFactors | None = None, max_nfev: int = 30, max_px: float = 20.0,
                  min_track: int = 3) -> BAResult:
    """Refine keyframe poses ``T_kf`` (n, 4, 4) with their prior covariances ``C_kf`` (n, 6, 6) and
    the tie points (module docstring); observations off by more than ``max_px`` at the start are
    dropped first."""
    R0, c0 = T_kf[:, :3, :3].copy(), T_kf[:, :3, 3].copy()
    ties = _drop_outliers(ties, R0, c0, cam, max_px, min_track)
    n, P, L = len(T_kf), len(ties.X0), len(ties.kf)
    w, Q = np.linalg.eigh(0.5 * (C_kf + np.swapaxes(C_kf, 1, 2)))
    U = np.swapaxes(Q / np.sqrt(np.clip(w, 1e-18, None))[:, None, :], 1, 2)  # U C Uᵀ = I
    kf, pt, uv = ties.kf, ties.pt, ties.uv
    has_p = nav.has_p if nav is not None else np.zeros(n, bool)
    has_R = nav.has_R if nav is not None else np.zeros(n, bool)
    ip, ir = np.flatnonzero(has_p), np.flatnonzero(has_R)

    def unpack(x):
        pose = x[:6 * n].reshape(n, 6)
        return c0 + pose[:, :3], so3_exp(pose[:, 3:]) @ R0, pose, x[6 * n:].reshape(P, 3)

    def reproj(c, R, X):
        return _project(c, R, X, kf, pt, cam)[0] - uv

    def residuals(x):
        c, R, pose, X = unpack(x)
        out = [(reproj(c, R, X) / sigma_px).ravel(), np.einsum("nij,nj->ni", U, pose).ravel()]
        if len(ip):
            out.append(((c[ip] - nav.p_cam[ip]) / nav.sigma_p).ravel())
        if len(ir):
            out.append((so3_log(nav.R_cam[ir] @ np.swapaxes(R[ir], 1, 2)) / nav.sigma_r).ravel())
        return np.concatenate(out)

    # sparsity: reprojection rows touch their keyframe's 6 and their point's 3 columns
    rows, cols = [], []
    r = np.arange(2 * L).reshape(L, 2)
    for a in range(2):
        rows.append(np.repeat(r[:, a], 6))
        cols.append((6 * kf[:, None] + np.arange(6)).ravel())
        rows.append(np.repeat(r[:, a], 3))
        cols.append((6 * n + 3 * pt[:, None] + np.arange(3)).ravel())
    r0 = 2 * L
    for blk, idx in ((6, np.arange(n)), (3, ip), (3, ir)):
        rr = r0 + np.arange(blk * len(idx)).reshape(len(idx), blk)
        cc_base = 6 * idx[:, None]
        if blk == 6:
            rows.append(np.repeat(rr, 6, axis=1).ravel())
            cols.append(np.tile(cc_base + np.arange(6), (1, 6)).ravel())
        else:
            off = 0 if idx is ip else 3
            rows.append(np.repeat(rr, 3, axis=1).ravel())
            cols.append(np.tile(cc_base + off + np.arange(3), (1, 3)).ravel())
        r0 += blk * len(idx)
    S = coo_matrix((np.ones(sum(len(x) for x in rows), np.int8), (np.concatenate(rows), np.concatenate(cols))),
                   shape=(r0, 6 * n + 3 * P)).tocsr()
    x0 = np.concatenate([np.zeros(6 * n), ties.X0.ravel()])
    e0 = reproj(c0, R0, ties.X0)
    sol = least_squares(residuals, x0, jac_sparsity=S, method="trf", loss="huber", f_scale=huber, max_nfev=max_nfev,
                        x_scale="jac")
    c, R, _, X = unpack(sol.x)
    e1 = reproj(c, R, X)
    T_out = np.tile(np.eye(4), (n, 1, 1))
    T_out[:, :3, :3], T_out[:, :3, 3] = R, c
    rms = lambda e: float(np.sqrt(np.mean(np.sum(e**2, 1)))) if len(e) else 0.0  # noqa: E731
    log.info(f"bundle adjustment: {P} tie points, {L} observations, reprojection RMS {rms(e0):.3g} -> {rms(e1):.3g} px")
    return BAResult(T_out, int(P), int(L), rms(e0), rms(e1), int(sol.nfev))
