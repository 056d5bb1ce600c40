"""The aid's landmarks in model coordinates: lifted from depth frames (rgbd: depth camera
intrinsics and ``T_depth_color`` honoured, bilinear depth, discontinuities dropped) or triangulated
from two views with known poses (mono: parallax and reprojection checks, refined while the parallax
grows).

:class:`Landmarks` is one part of :class:`mst.pipeline.slam.aid.ModelAidedSlam` (a mixin on the
aid's tracks, landmarks ``lm``/``lm_model``, depth files and ``depth`` section).
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import inv_T, transform_points
from mst.pipeline.depth_io import read_depth
from mst.pipeline.slam.geometry import triangulate_two_view


def bilinear_depth(D: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Depth image ``D`` (H, W) in metres (0/NaN = none) at sub-pixel positions ``u, v`` (N,) (pixel
    centres at integers): bilinear over the 4 neighbours, NaN where one of them has no depth.

    The nearest pixel's depth applied to a sub-pixel ray is off by up to half a pixel of depth
    gradient: centimetres on a wall or floor seen at a grazing angle, and the rounding of ``x.5``
    made the lifted map (and the drift carried on it) depend on the last bits of the pose."""
    h, w = D.shape
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    a = np.clip(u - u0, 0.0, 1.0)
    b = np.clip(v - v0, 0.0, 1.0)
    d00, d01 = D[v0, u0].astype(float), D[v0, u0 + 1].astype(float)
    d10, d11 = D[v0 + 1, u0].astype(float), D[v0 + 1, u0 + 1].astype(float)
    d = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    ok = (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)   # False for NaN too
    return np.where(ok, d, np.nan)


class Landmarks:
    """Depth lifting (rgbd) and two-view triangulation (mono) of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`."""

    def _lift_depth(self, k: int, T: np.ndarray, model_pose: bool, only_new: int | None = None) -> None:
        """rgbd: give tracks without a landmark (and, under a model pose, the tracks whose landmark
        was anchored under a SLAM pose or less certainly than this pose places it) a model point
        from depth frame k."""
        if k >= len(self._depth_files):
            return
        if only_new is not None:
            idx = np.arange(only_new, len(self.tid))
        else:
            if model_pose and self.cfg.rgbd_reset_on_model:
                # the SLAM is reset to the model pose (RGB-D paper): re-lift every track (below: where
                # this pose places it more certainly), which also cancels the slow drift of KLT tracks
                # against their landmarks
                need = np.ones(len(self.tid), bool)
            else:
                need = ~np.isfinite(self._landmark_array(self.tid)[:, 0])
            idx = np.flatnonzero(need)
        if len(idx) == 0:
            return
        X_cam = self._depth_at(self._depth_frame(k), self.pts[idx])
        ok = np.isfinite(X_cam[:, 0])
        if not ok.any():
            return
        sig = self._depth_landmark_sig(X_cam[ok])
        if model_pose and only_new is None:
            # a landmark lifted under an earlier model pose that placed it more certainly (common and
            # own error together) keeps its place: the last model pose before a gap is often the
            # weakest (the model leaving the view), and re-lifting the whole map under it passed its
            # uncertainty to every map pose of the gap (640x480 corridor: 2 sigma 1.1-1.6 % of the
            # distance, 71 of 76 map poses withheld, measured error <= 0.07 %)
            old = self._landmark_sigs(self.tid[idx[ok]], model_only=True)
            better = np.hypot(sig[:, 0], sig[:, 1]) < np.hypot(old[:, 0], old[:, 1])
            ok[np.flatnonzero(ok)[~better]] = False
            sig = sig[better]
            if not ok.any():
                return
        T_model_cam = inv_T(T)
        X_model = transform_points(T_model_cam, X_cam[ok])
        for t, x, s in zip(self.tid[idx[ok]], X_model, sig):
            self.lm[int(t)] = x
            self.lm_model[int(t)] = model_pose
            self.lm_sig[int(t)] = tuple(float(v) for v in s)


    def _depth_frame(self, k: int) -> np.ndarray | None:
        """Depth frame k (metres, 0 = none), cached; None past the end of the depth list."""
        if k >= len(self._depth_files):
            return None
        if self._depth_k != k:
            self._depth = read_depth(self._depth_files[k], self.depth.scale)
            self._depth_k = k
            h, w = self._depth.shape
            if not self._depth_camera_given and self.cam.width and w != self.cam.width:
                # registered depth at another resolution (e.g. colour frames resized by --scale)
                self.K_depth = self.cam.scaled(w / self.cam.width).K
        return self._depth

    def _depth_at(self, D: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Colour pixels (N,2) -> colour-camera points (N,3) (NaN where no valid depth).

        The depth image lives in the depth camera (``K_depth``, ``T_depth_color``); the depth along
        each colour ray is found by fixed-point iteration on the depth image (exact when registered).
        """
        dcfg = self.depth
        xn = self._normalised(uv)
        r_c = np.c_[xn, np.ones(len(xn))]                          # colour ray, z = 1
        R, t = self.T_depth_color[:3, :3], self.T_depth_color[:3, 3]
        Kd = self.K_depth
        h, w = D.shape
        Rr = r_c @ R.T                                             # ray direction in the depth frame
        z = np.full(len(xn), max(self.scene_depth, dcfg.min_m))
        valid = np.ones(len(xn), bool)
        for _ in range(3 if np.any(t != 0) or np.any(R != np.eye(3)) else 1):
            P_d = z[:, None] * Rr + t
            zd = np.where(P_d[:, 2] > 1e-6, P_d[:, 2], 1e-6)
            uf = Kd[0, 0] * P_d[:, 0] / zd + Kd[0, 2]
            vf = Kd[1, 1] * P_d[:, 1] / zd + Kd[1, 2]
            u, v = np.rint(uf).astype(int), np.rint(vf).astype(int)
            inside = (u >= 1) & (v >= 1) & (u < w - 1) & (v < h - 1)
            uc, vc = np.clip(u, 1, w - 2), np.clip(v, 1, h - 2)
            dm = bilinear_depth(D, uf, vf)
            valid = inside & np.isfinite(dm) & (dm > dcfg.min_m) & (dm < dcfg.max_m)
            dz = np.where(np.abs(Rr[:, 2]) > 1e-9, Rr[:, 2], 1e-9)
            z = np.where(valid, (dm - t[2]) / dz, z)
        # depth discontinuity test on the 3x3 neighbourhood
        nb = np.stack([D[vc + dv, uc + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], 1).astype(float)
        nb_ok = np.all(np.isfinite(nb) & (nb > 0), axis=1)
        spread = np.where(nb_ok, nb.max(1) - nb.min(1), np.inf)
        valid &= spread < dcfg.edge_rel * np.maximum(dm, 1e-6)
        valid &= (z > dcfg.min_m) & (z < dcfg.max_m)
        X = z[:, None] * r_c
        X[~valid] = np.nan
        return X

    def _triangulate(self, T: np.ndarray, model_pose: bool) -> None:
        """mono: triangulate tracks from their first view and this one once the parallax is enough,
        and re-triangulate young landmarks while their parallax keeps growing (depth error ~ pose
        error / baseline: a landmark from a 1 deg baseline is refined at 1.5, 2.25, ... deg)."""
        cfg = self.cfg
        if not len(self.tid):
            return
        has = np.array([int(t) in self.lm for t in self.tid], bool)
        self.tri_deg[~has] = 0.0
        cand = np.flatnonzero(self.tri_deg < cfg.tri_refine_deg)
        if len(cand) == 0:
            return
        x1 = self.first_xn[cand]
        P1 = self.first_P[cand]
        x2 = self._normalised(self.pts[cand])
        # parallax: angle between the two bearing rays in the model frame
        r1 = np.einsum("nji,nj->ni", P1[:, :, :3], np.c_[x1, np.ones(len(x1))])
        r2 = np.c_[x2, np.ones(len(x2))] @ T[:3, :3]
        cosang = np.sum(r1 * r2, 1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
        ang = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
        ok = (ang > cfg.tri_min_angle_deg) & (ang > 1.5 * self.tri_deg[cand])
        if not ok.any():
            return
        cand, x1, P1, x2, ang = cand[ok], x1[ok], P1[ok], x2[ok], ang[ok]
        X = triangulate_two_view(P1, T[:3], x1, x2)
        # checks: finite, in front of both cameras, reprojection in both views
        X1c = np.einsum("nij,nj->ni", P1[:, :, :3], X) + P1[:, :, 3]
        X2c = transform_points(T, X)
        f = self.K[0, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            e1 = np.linalg.norm(X1c[:, :2] / X1c[:, 2:3] - x1, axis=1) * f
            e2 = np.linalg.norm(X2c[:, :2] / X2c[:, 2:3] - x2, axis=1) * f
        # no far bound: the parallax test above already bounds the depth error (depth.max_m is the
        # depth sensor's range; a 50 m cap rejected every landmark of a 200 m UAV flyover)
        good = (np.isfinite(X).all(1) & (X1c[:, 2] > cfg.tri_min_depth_m) & (X2c[:, 2] > cfg.tri_min_depth_m)
                & (e1 < cfg.tri_max_reproj_px) & (e2 < cfg.tri_max_reproj_px))
        self.tri_deg[cand[good]] = ang[good]
        cg = cand[good]
        sig = self._landmark_sig(X1c[good], X2c[good], self.first_sig[cg], self.first_C[cg], ang[good])
        for t, x, s in zip(self.tid[cand[good]], X[good], sig):
            self.lm[int(t)] = x
            self.lm_model[int(t)] = model_pose
            self.lm_sig[int(t)] = tuple(float(v) for v in s)
