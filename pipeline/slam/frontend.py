"""The aid's front end: KLT tracks between frames (:func:`mst.core.klt.track_forward_backward`
guided by the landmarks projected at a constant-velocity pose), PnP + RANSAC on the 2D-3D tracks,
corners replenished per grid cell.

:class:`FrontEnd` is one part of :class:`mst.pipeline.slam.aid.ModelAidedSlam` (a mixin: it reads
and updates the aid's tracks ``pts``/``tid``/``first_xn``/``tri_deg``/``first_P``, landmarks ``lm``
and ``scene_depth``, documented there).
"""

from __future__ import annotations

import math

import numpy as np

from mst.core.klt import PyramidCache, track_forward_backward
from mst.core.poses import inv_T, pnp_ransac, refine_pnp, transform_points
from mst.pipeline.slam.geometry import pose_information


class FrontEnd:
    """KLT tracking, PnP and corner replenishing of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`."""

    def _constant_velocity(self, T_prev: np.ndarray | None) -> np.ndarray | None:
        if len(self.T_hist) == 2:
            T1, T0 = self.T_hist[-1], self.T_hist[-2]
            return (T1 @ inv_T(T0)) @ T1
        if self.T_hist:
            return self.T_hist[-1].copy()
        return None if T_prev is None else np.asarray(T_prev, float)

    def _project(self, T_cam_model: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model points (N,3) -> pixels (N,2) (:meth:`Camera.project`, depth clamped at 1e-9) and
        camera depth (N,)."""
        Xc = transform_points(T_cam_model, X)
        z = Xc[:, 2]
        zs = np.where(z > 1e-9, z, 1e-9)
        return self.cam.project(np.c_[Xc[:, :2], zs]), z

    def _normalised(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N,2) -> normalised image coordinates (N,2) (:meth:`Camera.unproject`: distortion removed)."""
        if len(uv) == 0:
            return np.zeros((0, 2))
        return self.cam.unproject(uv)

    def _landmark_array(self, tids: np.ndarray) -> np.ndarray:
        nan = np.full(3, np.nan)
        lm = self.lm
        return np.array([lm.get(int(t), nan) for t in tids]).reshape(-1, 3)


    def _track(self, gray: np.ndarray, T_cv: np.ndarray | None) -> None:
        """KLT prev -> gray with a forward-backward check; drops lost tracks.

        The guess: the landmarks projected at the constant-velocity pose ``T_cv`` (tracks without a
        landmark moved by the median of that flow); none (start at the old positions) without
        ``T_cv`` or with fewer than 6 landmarks."""
        p0 = self.pts.reshape(-1, 1, 2)
        guess = p0.copy()
        use_guess = False
        if T_cv is not None:
            X = self._landmark_array(self.tid)
            has = np.isfinite(X[:, 0])
            if has.sum() >= 6:
                uv, z = self._project(T_cv, X[has])
                ok = z > 0
                g = guess[has, 0]
                g[ok] = uv[ok]
                guess[has, 0] = g
                d = np.median((uv[ok] - self.pts[has][ok]), axis=0) if ok.any() else np.zeros(2)
                guess[~has, 0] += d
                use_guess = True
        guess = guess.astype(np.float32)
        if getattr(self, "_pyramids", None) is None:
            self._pyramids = PyramidCache(self.cfg.klt)  # each frame's KLT pyramid built once
        p1, keep, _ = track_forward_backward(self._pyramids.get(self.prev_gray), self._pyramids.get(gray), self.pts,
                                             self.cfg.klt, guess if use_guess else None)
        h, w = gray.shape
        keep &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
        self._keep_tracks(keep)
        self.pts = p1[keep].astype(np.float32)

    def _keep_tracks(self, keep: np.ndarray) -> None:
        self.pts = self.pts[keep]
        self.tid = self.tid[keep]
        self.first_xn = self.first_xn[keep]
        self.tri_deg = self.tri_deg[keep]
        self.first_P = self.first_P[keep]
        self.first_sig = self.first_sig[keep]
        self.first_C = self.first_C[keep]

    def _pnp(self, T_guess: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None, int]:
        """PnP + RANSAC on tracks with landmarks; drops outlier tracks' landmarks."""
        import cv2

        self._last_pnp_sig = None
        X = self._landmark_array(self.tid)
        has = np.flatnonzero(np.isfinite(X[:, 0]))
        if len(has) < max(6, self.cfg.pnp_min_inliers):
            return None, None, 0
        Xh, uvh = X[has], self.pts[has].astype(np.float64)
        ok, rvec, tvec, inl = pnp_ransac(Xh, uvh, self.K, self.dist, 100, self.cfg.pnp_reproj_px, cv2.SOLVEPNP_SQPNP)
        if not ok or inl is None or len(inl) < 6:
            return None, None, 0
        inl = inl.ravel()
        T = refine_pnp(Xh[inl], uvh[inl], self.K, self.dist, rvec, tvec)
        uv, z = self._project(T, Xh)
        err = np.linalg.norm(uv - uvh, axis=1)
        good = (err < self.cfg.pnp_reproj_px) & (z > 0)
        # outliers: the landmark is wrong or the track slipped -> drop the track
        keep = np.ones(len(self.tid), bool)
        keep[has[~good]] = False
        for t in self.tid[has[~good]]:
            self.lm.pop(int(t), None)
            self.lm_sig.pop(int(t), None)
        tids_in = self.tid[has[good]]
        self._keep_tracks(keep)
        R = np.ascontiguousarray(T[:3, :3])  # a contiguous copy, not T's view: the product's last bits as they were
        Xc = Xh[good] @ R.T + T[:3, 3]
        if len(Xc):
            self.scene_depth = float(np.median(Xc[:, 2]))
        W = pose_information(self.K, Xc)
        if len(Xc) >= 7:
            # the fit's noise: its reprojection RMS (2 residuals per point, 6 parameters)
            rms = float(np.sqrt(np.sum(err[good] ** 2) / max(2 * len(Xc) - 6, 1)))
            self._last_pnp_sig = self._pnp_sig(tids_in, W, rms, T)
        return T, W, int(good.sum())

    def _replenish(self, gray: np.ndarray, T: np.ndarray) -> None:
        """Detect new corners away from the tracked ones, at most a fair share per grid cell."""
        import cv2

        cfg = self.cfg
        n_new = cfg.klt.max_features - len(self.pts)
        if n_new <= 0:
            return
        h, w = gray.shape
        mask = np.full((h, w), 255, np.uint8)
        r = int(cfg.klt.min_distance_px)
        for x, y in self.pts.astype(np.int32):  # one small disc per track (<= max_points)
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        c = cv2.goodFeaturesToTrack(gray, maxCorners=2 * n_new + 50, qualityLevel=cfg.klt.quality,
                                    minDistance=cfg.klt.min_distance_px, mask=mask, blockSize=cfg.klt.block_px)
        if c is None:
            return
        c = c.reshape(-1, 2)
        gx, gy = cfg.grid
        cell_new = (np.minimum((c[:, 1] * gy / h).astype(int), gy - 1) * gx
                    + np.minimum((c[:, 0] * gx / w).astype(int), gx - 1))
        cell_old = (np.minimum((self.pts[:, 1] * gy / h).astype(int), gy - 1) * gx
                    + np.minimum((self.pts[:, 0] * gx / w).astype(int), gx - 1))
        cap = int(math.ceil(cfg.klt.max_features / (gx * gy)))
        room = np.maximum(cap - np.bincount(cell_old, minlength=gx * gy), 0)
        # corners come sorted by quality: rank within each cell, keep rank < room
        order = np.argsort(cell_new, kind="stable")
        cs = cell_new[order]
        start = np.searchsorted(cs, cs, side="left")
        rank = np.arange(len(cs)) - start
        sel = order[rank < room[cs]]
        if len(sel) < n_new:  # fill up with the best remaining corners anywhere
            rest = np.setdiff1d(np.arange(len(c)), sel)
            sel = np.r_[sel, rest[: n_new - len(sel)]]
        sel = np.sort(sel)[:n_new]
        self._add_tracks(c[sel].astype(np.float32), 0.0, T)

    def _add_tracks(self, uv: np.ndarray, tri_deg: float, T: np.ndarray) -> np.ndarray:
        """Start tracks at pixels ``uv`` (M, 2) seen under pose ``T`` (their first view), with the
        triangulation parallax ``tri_deg`` (0: none yet); returns their new ids."""
        m = len(uv)
        tids = np.arange(self._next_tid, self._next_tid + m)
        self._next_tid += m
        self.pts = np.r_[self.pts, uv.astype(np.float32)].astype(np.float32)
        self.tid = np.r_[self.tid, tids]
        self.first_xn = np.r_[self.first_xn, self._normalised(uv)]
        self.tri_deg = np.r_[self.tri_deg, np.full(m, tri_deg)]
        self.first_P = np.r_[self.first_P, np.broadcast_to(T[:3], (m, 3, 4))]
        self.first_sig = np.r_[self.first_sig, np.broadcast_to(np.asarray(self._pose_sig[:2], float), (m, 2))]
        self.first_C = np.r_[self.first_C, np.broadcast_to(self._pose_sig[2], (m, 6, 6))]
        return tids
