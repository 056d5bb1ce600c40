"""Re-acquisition of a lost model pose without clicks (``mst track``, status ``relocalised``).

The object's appearance is learned while it is tracked: at the initial frame and at later healthy
keyframes (a new view direction, at most every ``kf_min_frames`` frames), ORB keypoints (FAST
corners, oriented BRIEF) are detected **on the model's visible surfaces only** (the mask of the
model's front surface at that pose) and get their 3D model coordinates from the model's depth at
that pose (the tracker's inverse depth buffer: the exact face plane under each pixel). When the
pose is lost, every ``every``-th frame is matched against all stored keypoints (nearest and second
nearest descriptor within one keyframe, Lowe ratio ``ratio``), and the pose is found by RANSAC PnP (``ransac_iters``
iterations, ``reproj_px`` inlier bound) when at least ``min_inliers`` matches and ``min_consensus``
of them agree, as ViSP's object-detection tutorial (FAST + ORB, ratio 0.8, 200 iterations, 20 %
consensus) and ORB-SLAM2's relocalisation (at least 15 matches to try, 50 inliers to accept; here
``min_inliers`` 25 at 640x480 because the object covers a part of the frame only). The caller then
refines the pose with the edge tracker and accepts it only through the calibrated health test
(:class:`mst.pipeline.tracking.HealthMonitor`): a wrong PnP pose is never output.

Frames: ``T_cam_model`` (model -> camera); pixels; metres. Memory and matching cost: at most
``max_keyframes`` keyframes of at most ``kf_features`` descriptors (32 bytes) and model points
each; an attempt matches at most ``kf_per_attempt`` of them (the newest and, in turn, the others).
Measured at 640x480 on the loaded 2-core machine: learning a keyframe 5.5 ms, an attempt 6-13 ms
with one keyframe, 25-35 ms with four.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from mst.core.config import Config, param
from mst.core.poses import inv_T, se3_log


@dataclass
class RelocConfig(Config):
    """Settings of the relocaliser (pixels, degrees)."""

    n_features: int = param(1000, min=1, max=100_000, help="ORB features per image (learning: on the model only)")
    ratio: float = param(0.8, min=0, max=1, min_open=True, help="Lowe ratio of the best to the second best descriptor distance")
    max_hamming: int = param(64, min=0, max=256, help="descriptor distance bound (of 256 bits)")
    min_matches: int = param(15, min=4, max=100_000, help="fewer ratio-test matches: no PnP")
    ransac_iters: int = param(200, min=1, max=1_000_000, help="RANSAC PnP iterations")
    reproj_px: float = param(4.0, min=0, min_open=True, help="RANSAC inlier bound, px")
    min_inliers: int = param(25, min=4, max=100_000, help="PnP inliers needed")
    min_consensus: float = param(0.2, min=0, max=1, help="inliers / matches needed")
    max_keyframes: int = param(12, min=1, max=10_000, help="appearance keyframes kept (oldest dropped)")
    kf_features: int = param(500, min=1, max=100_000, help="strongest keypoints stored per keyframe (bounds the matching cost)")
    kf_per_attempt: int = param(4, min=1, max=10_000, help="keyframes matched per attempt (the newest + a round-robin share)")
    kf_min_frames: int = param(5, min=0, max=1_000_000, help="frames between learned keyframes, at least")
    kf_min_angle_deg: float = param(10.0, min=0, max=180, help="learn a view only when it differs this much from every stored one, deg")
    min_keypoints: int = param(20, min=0, max=100_000, help="a view with fewer keypoints on the model is not stored")
    every: int = param(2, min=1, max=1_000_000, help="while lost, try every n-th frame (bounded cost)")


class Relocaliser:
    """Appearance database of the tracked object and the lost-pose search (see module docstring).

    ``tracker``: the :class:`mst.pipeline.tracking.EdgeTracker` (its model geometry, ``K`` and
    clipping distances are used).
    """

    def __init__(self, tracker, config: RelocConfig | None = None):
        import cv2

        self.tr = tracker
        self.cfg = config or RelocConfig()
        self._orb = cv2.ORB_create(nfeatures=self.cfg.n_features)
        self.kfs: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=max(1, self.cfg.max_keyframes))
        self._last_learn = -10**9
        self.stats = {"keyframes": 0, "attempts": 0, "pnp_poses": 0, "ms_attempts": 0.0, "ms_learn": 0.0}

    # ------------------------------------------------------------------ learning
    def should_learn(self, k: int, T_cam_model: np.ndarray) -> bool:
        """A new keyframe: far enough in time from the last one and a new view direction."""
        if not self.kfs:
            return True
        if k - self._last_learn < self.cfg.kf_min_frames:
            return False
        for _, T, _, _ in self.kfs:
            if np.degrees(np.linalg.norm(se3_log(T_cam_model @ inv_T(T))[3:])) < self.cfg.kf_min_angle_deg:
                return False
        return True

    def learn(self, k: int, gray: np.ndarray, T_cam_model: np.ndarray) -> int:
        """Store the ORB keypoints of ``gray`` on the model's visible surfaces at this pose; returns
        how many were stored (0: too few, nothing stored)."""
        import cv2

        from mst.pipeline.tracking.visibility import face_visibility, inverse_depth_buffer

        t0 = time.perf_counter()
        tr, H, W = self.tr, gray.shape[0], gray.shape[1]
        c = tr.cfg
        fv = face_visibility(tr.geom, T_cam_model, None, c.angle_appear_deg, c.angle_disappear_deg)
        iz, _ = inverse_depth_buffer(tr.geom, T_cam_model, tr.K, W, H, fv, tr.near(T_cam_model), 1.0)
        mask = cv2.erode((iz > 0).astype(np.uint8) * 255, np.ones((7, 7), np.uint8))  # off the outline
        kps, desc = self._orb.detectAndCompute(gray, mask)
        self._last_learn = k
        if desc is None or len(kps) < self.cfg.min_keypoints:
            self.stats["ms_learn"] += (time.perf_counter() - t0) * 1e3
            return 0
        order = np.argsort([-kp.response for kp in kps])[: self.cfg.kf_features]
        kps, desc = [kps[i] for i in order], desc[order]
        uv = np.array([kp.pt for kp in kps], np.float64)
        ix = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
        iy = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
        izk = iz[iy, ix].astype(np.float64)
        ok = izk > 0
        xn = (uv[ok] - tr.K[:2, 2]) / np.array([tr.K[0, 0], tr.K[1, 1]])
        Xc = np.column_stack([xn, np.ones(len(xn))]) / izk[ok, None]
        X_model = (Xc - T_cam_model[:3, 3]) @ T_cam_model[:3, :3]
        self.kfs.append((k, T_cam_model.copy(), desc[ok], X_model.astype(np.float32)))
        self.stats["keyframes"] += 1
        self.stats["ms_learn"] += (time.perf_counter() - t0) * 1e3
        return int(ok.sum())

    # ------------------------------------------------------------------ search
    def _pnp(self, kps, pairs, X_kf) -> np.ndarray | None:
        """RANSAC PnP on one keyframe's matches; None without enough consensus."""
        import cv2

        qi, ti = np.array(pairs).T
        uv = np.array([kps[i].pt for i in qi], np.float64)
        X = X_kf[ti].astype(np.float64)
        from mst.core.poses import pnp_ransac, refine_pnp

        ok, rvec, tvec, inl = pnp_ransac(X, uv, self.tr.K, None, self.cfg.ransac_iters, self.cfg.reproj_px,
                                         cv2.SOLVEPNP_EPNP)
        if not ok or inl is None:
            return None
        inl = inl.ravel()
        if len(inl) < max(self.cfg.min_inliers, self.cfg.min_consensus * len(pairs)):
            return None
        T = refine_pnp(X[inl], uv[inl], self.tr.K, None, rvec, tvec)
        if not np.isfinite(T).all() or (X[inl] @ T[:3, :3].T + T[:3, 3])[:, 2].min() <= 0:
            return None
        return T

    def relocalise(self, gray: np.ndarray) -> np.ndarray | None:
        """PnP pose ``T_cam_model`` of the object in ``gray`` from the stored keypoints, or None."""
        import cv2

        if not self.kfs:
            return None
        t0 = time.perf_counter()
        self.stats["attempts"] += 1
        try:
            kps, desc = self._orb.detectAndCompute(gray, None)
            if desc is None or len(kps) < self.cfg.min_matches:
                return None
            # ratio test per keyframe (a surface point stored in several keyframes would fail it
            # against itself in one pooled database), then PnP on the best keyframes in turn
            bf = cv2.BFMatcher(cv2.NORM_HAMMING)
            cands = []
            kfs = list(self.kfs)
            if len(kfs) > self.cfg.kf_per_attempt:
                # bounded cost: the newest keyframe and a round-robin share of the others per attempt
                rest = kfs[:-1]
                j0 = (self.stats["attempts"] * (self.cfg.kf_per_attempt - 1)) % len(rest)
                kfs = [kfs[-1]] + [rest[(j0 + i) % len(rest)] for i in range(self.cfg.kf_per_attempt - 1)]
            for _, _, d_kf, X_kf in kfs:
                m = bf.knnMatch(desc, d_kf, k=2)
                pairs = [(a.queryIdx, a.trainIdx) for a, *b in m
                         if b and a.distance < self.cfg.ratio * b[0].distance and a.distance < self.cfg.max_hamming]
                if len(pairs) >= self.cfg.min_matches:
                    cands.append((len(pairs), pairs, X_kf))
            cands.sort(key=lambda c: -c[0])
            for _, pairs, X_kf in cands[:3]:
                T = self._pnp(kps, pairs, X_kf)
                if T is not None:
                    self.stats["pnp_poses"] += 1
                    return T
            return None
        finally:
            self.stats["ms_attempts"] += (time.perf_counter() - t0) * 1e3
