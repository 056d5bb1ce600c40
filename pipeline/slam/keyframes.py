"""The aid's map over time: keyframes (every few frames, on rotation, translation or lost tracks)
with their observations, the model prior (pose + 6x6 ``W``) and ORB descriptors with model points
for relocalisation; landmarks pruned to the window (retired ones exported, bounded); relocalisation
of a lost frame against the stored keyframes (ORB matching + PnP RANSAC).

:class:`KeyframeMap` is one part of :class:`mst.pipeline.slam.aid.ModelAidedSlam` (a mixin on the
aid's ``kfs``/``reloc_kfs`` windows, tracks and landmarks).
"""

from __future__ import annotations

import math

import numpy as np

from mst.core.poses import inv_T, pnp_ransac, refine_pnp, se3_log, transform_points
from mst.pipeline.slam.drift import LM_SIG_COLS, camera_centre
from mst.pipeline.slam.geometry import pose_information
from mst.pipeline.slam.state import STATUS_MODEL, Keyframe


class KeyframeMap:
    """Map maintenance, keyframes and relocalisation of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`."""

    def _maintain_map(self, k: int, gray: np.ndarray, T: np.ndarray, status: str,
                      T_prior: np.ndarray | None, W_prior: np.ndarray | None) -> np.ndarray:
        """New landmarks, new corners, keyframes and local BA for frame k with pose ``T``.

        Returns the (possibly BA-refined, for status 'slam') output pose.
        """
        if self.mode == "rgbd":
            self._lift_depth(k, T, status == STATUS_MODEL)
        else:
            self._triangulate(T, status == STATUS_MODEL)
        n_before = len(self.pts)
        self.frames_since_kf += 1
        need_kf = self._need_keyframe(T)
        if n_before < self.cfg.replenish_ratio * self.cfg.klt.max_features or need_kf:
            self._replenish(gray, T)
            if self.mode == "rgbd" and len(self.pts) > n_before:
                self._lift_depth(k, T, status == STATUS_MODEL, only_new=n_before)
        if need_kf:
            T = self._add_keyframe(k, gray, T, status, T_prior, W_prior)
        return T

    def _need_keyframe(self, T: np.ndarray) -> bool:
        cfg = self.cfg
        if not self.kfs:
            return True
        if self.frames_since_kf < cfg.kf_min_frames:
            return False
        if self.frames_since_kf >= cfg.kf_max_frames:
            return True
        last = self.kfs[-1]
        dT = T @ inv_T(last.T_cam_model)
        ang = math.degrees(np.linalg.norm(se3_log(dT)[3:]))
        C1, C0 = inv_T(T)[:3, 3], inv_T(last.T_cam_model)[:3, 3]
        if ang > cfg.kf_angle_deg or np.linalg.norm(C1 - C0) > cfg.kf_translation_rel * self.scene_depth:
            return True
        alive = np.isin(last.tids, self.tid).sum()
        return alive < cfg.kf_track_ratio * max(len(last.tids), 1)

    def _add_keyframe(self, k: int, gray: np.ndarray, T: np.ndarray, status: str,
                      T_prior: np.ndarray | None, W_prior: np.ndarray | None) -> np.ndarray:
        """Store frame k as a keyframe (with relocalisation data) and run the local BA on the window;
        returns the output pose (BA-refined for a SLAM pose)."""
        self.frames_since_kf = 0
        X = self._landmark_array(self.tid)
        kf = Keyframe(k, T.copy(), self.tid.copy(), self.pts.copy(),
                      None if T_prior is None else np.asarray(T_prior, float).copy(),
                      None if W_prior is None else W_prior.copy())
        # relocalisation data: ORB features of the keyframe with model points (rgbd: lifted from
        # depth; mono: the landmark of a track within 3 px)
        kps, desc = self._orb.detectAndCompute(gray, None)
        if desc is not None and len(kps) >= self.cfg.reloc_min_inliers:
            uv = np.array([kp.pt for kp in kps], np.float64)
            D = self._depth_frame(k) if self.mode == "rgbd" else None
            if D is not None:
                Xc = self._depth_at(D, uv)
                Xk = transform_points(inv_T(T), Xc)
                Sk = self._depth_landmark_sig(Xc)
            else:
                Xk = np.full((len(uv), 3), np.nan)
                Sk = np.full((len(uv), LM_SIG_COLS), np.inf)
                has = np.flatnonzero(np.isfinite(X[:, 0]))
                if len(has):
                    q = self.pts[has].astype(np.float64)
                    d2 = (uv**2).sum(1)[:, None] + (q**2).sum(1)[None, :] - 2.0 * uv @ q.T
                    j = np.argmin(d2, axis=1)
                    near = d2[np.arange(len(uv)), j] < 9.0
                    Xk[near] = X[has[j[near]]]
                    Sk[near] = self._landmark_sigs(self.tid[has[j[near]]])
            ok = np.isfinite(Xk[:, 0])
            if ok.sum() >= self.cfg.reloc_min_inliers:
                kf.desc, kf.X_desc, kf.sig_desc = desc[ok], Xk[ok].astype(np.float32), Sk[ok]
        evicted = self.kfs[0] if len(self.kfs) == self.kfs.maxlen else None
        self.kfs.append(kf)
        self.reloc_kfs.append(kf)
        self.stats["keyframes"] += 1
        if evicted is not None:
            # the evicted keyframe keeps only its relocalisation data (it stays in reloc_kfs)
            evicted.tids, evicted.uv = np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
            self._prune_landmarks()
        if self.use_ba and len(self.kfs) >= 3:
            T = self._local_ba(status)
        return T

    def _prune_landmarks(self) -> None:
        """Forget landmarks neither tracked nor observed in the BA window (export the mono ones)."""
        live = set(self.tid.tolist())
        for kf in self.kfs:
            live.update(kf.tids.tolist())
        dead = [t for t in self.lm if t not in live]
        if not dead:
            return
        pts = np.array([self.lm[t] for t in dead])
        for t in dead:
            del self.lm[t]
            self.lm_model.pop(t, None)
            self.lm_sig.pop(t, None)
        room = self.cfg.max_export_points - self._n_export
        if room > 0:
            self._export.append(pts[:room])
            self._n_export += min(room, len(pts))

    @property
    def map_relocalisations(self) -> dict[str, int]:
        """This map's relocalisations: ``taken``, and ``gated`` (refused by :meth:`reloc_gate_m`)."""
        return {"taken": int(self.stats["relocalisations"]), "gated": int(self.stats["reloc_gated"])}

    def reloc_gate_m(self, k: int) -> float:
        """How far (m) a relocalised camera centre of frame ``k`` may lie from the last output pose of
        the map: ``reloc_gate_rel`` x scene depth + ``reloc_gate_speed`` x the camera's speed x the
        frames since (inf before any output pose). The speed (m per frame) is the 75th percentile of
        its steps between the last 300 output poses: robust to a pose off by metres (the edge pose of
        a sliver of the model), and it remembers the cruise speed through a hover (a UAV that hovers,
        turns, is lost and flies on must be found again where it flew to)."""
        if self._last_out_k is None:
            return math.inf
        step = float(np.percentile(np.asarray(self._steps), 75)) if self._steps else 0.0
        return self.cfg.reloc_gate_rel * self.scene_depth + self.cfg.reloc_gate_speed * step * max(k - self._last_out_k, 0)

    def _relocalise(self, gray: np.ndarray, k: int | None = None) -> np.ndarray | None:
        """ORB matching against the stored keyframes (newest first) + PnP RANSAC. With ``k``, a pose
        beyond :meth:`reloc_gate_m` of the last output pose is refused (counted in
        ``stats["reloc_gated"]``) and the next keyframe tried: a camera does not jump."""
        import cv2

        cands = [kf for kf in reversed(self.reloc_kfs) if kf.desc is not None and len(kf.desc) >= self.cfg.reloc_min_inliers]
        if not cands:
            return None
        self.stats["reloc_attempts"] += 1
        kps, desc = self._orb.detectAndCompute(gray, None)
        if desc is None or len(kps) < self.cfg.reloc_min_inliers:
            return None
        uv_all = np.array([kp.pt for kp in kps], np.float64)
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        for kf in cands[:10]:
            m = bf.knnMatch(kf.desc, desc, k=2)
            good = [(a.queryIdx, a.trainIdx) for a, *b in m if b and a.distance < 0.8 * b[0].distance and a.distance < 64]
            if len(good) < self.cfg.reloc_min_inliers:
                continue
            qi, ti = np.array(good).T
            X, uv = kf.X_desc[qi].astype(np.float64), uv_all[ti]
            ok, rvec, tvec, inl = pnp_ransac(X, uv, self.K, self.dist, 200, self.cfg.pnp_reproj_px, cv2.SOLVEPNP_SQPNP)
            if not ok or inl is None or len(inl) < self.cfg.reloc_min_inliers:
                continue
            inl = inl.ravel()
            T = refine_pnp(X[inl], uv[inl], self.K, self.dist, rvec, tvec)
            if k is not None and np.linalg.norm(camera_centre(T) - self._pose_c) > self.reloc_gate_m(k):
                self.stats["reloc_gated"] += 1
                continue
            # restart the tracks from the inlier matches (new landmark ids, positions from the keyframe,
            # their sigmas as stored with it; the pose's sigma from them: :mod:`.drift`)
            S = kf.sig_desc[qi][inl] if kf.sig_desc is not None else np.full((len(inl), LM_SIG_COLS), np.inf)
            tids = self._add_tracks(uv[inl], 90.0, T)
            for t, x, s in zip(tids, X[inl], S):
                self.lm[int(t)] = x
                self.lm_model[int(t)] = False
                self.lm_sig[int(t)] = tuple(float(v) for v in s)
            Xc = transform_points(T, X[inl])
            self._reloc_sig = self._pnp_sig(tids, pose_information(self.K, Xc), None, T)
            self.first_sig[-len(tids):] = self._reloc_sig[:2]
            self.first_C[-len(tids):] = self._reloc_sig[2]
            self.stats["relocalisations"] += 1
            return T
        return None
