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

Where the object is seen from a new side (turned on a table, carried round), the keyframe alone
does not match: every learned keyframe also seeds the database with views rendered from the model
with its texture, the model turned about its axis nearest the image's vertical by
+-``synth_step_deg`` x 1..``synth_steps`` (default +-30/60/90 deg; see :meth:`Relocaliser._learn_views`).
Keyframes are learned from model and relocalised frames with a health score of at least
``learn_min_score``. (``min_inliers`` scaled down with the image size, 15 at 320x240, was tried: not needed
with the rendered views, and on the demo's UAV pass it let relocalised poses in after which 75
more frames were lost.) An attempt
returns up to three PnP candidates (:meth:`Relocaliser.candidates`, most inliers first); the
session refines each (edges from the pose, then the widened coarse-to-fine search) and takes the
first that passes the health test.

Frames: ``T_cam_model`` (model -> camera); pixels; metres. Memory and matching cost: at most
``max_keyframes`` keyframes of at most ``kf_features`` descriptors (32 bytes) and model points
each; an attempt matches at most ``kf_per_attempt`` of them (the newest and, in turn, the others).
Measured at 640x480 on the loaded 2-core machine: learning a keyframe 5.5 ms (10 ms CPU; with its
six rendered views 75 ms CPU, 27 ms at 320x240), an attempt 6-13 ms with one keyframe, 25-35 ms with four.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from mst.core.config import Config, param
from mst.core.poses import inv_T, matmul_exact, se3_log
from mst.pipeline.tracking.exact import mv as matvec
from mst.pipeline.tracking.exact import norm3, rigid


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
    learn_min_score: float = param(0.2, min=-1, max=1, help="a tracked frame teaches a keyframe only with at least this health score (1: typical, 0: rejected)")
    every: int = param(2, min=1, max=1_000_000, help="while lost, try every n-th frame (bounded cost)")
    synth_step_deg: float = param(30.0, min=0, max=180, help="rendered views of a learned keyframe: turned by multiples of this about the image's vertical axis through the model, deg (0: none)")
    synth_steps: int = param(3, min=0, max=12, help="rendered views per side (3 with 30 deg: +-30, 60, 90 deg)")
    max_synth_views: int = param(12, min=0, max=10_000, help="rendered views kept (oldest dropped)")


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
        #: views rendered from the model with a keyframe's texture (same layout as ``kfs``)
        self.views: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=max(1, self.cfg.max_synth_views))
        self._last_learn = -10**9
        self.stats = {"keyframes": 0, "synth_views": 0, "attempts": 0, "pnp_poses": 0, "pnp_from_views": 0,
                      "ms_attempts": 0.0, "ms_learn": 0.0}

    # ------------------------------------------------------------------ learning
    def should_learn(self, k: int, T_cam_model: np.ndarray) -> bool:
        """A new keyframe: far enough in time from the last one and a new view direction."""
        if not self.kfs:
            return True
        if k - self._last_learn < self.cfg.kf_min_frames:
            return False
        for _, T, _, _ in self.kfs:
            if np.degrees(norm3(se3_log(matmul_exact(T_cam_model, inv_T(T)))[3:])) < self.cfg.kf_min_angle_deg:
                return False
        return True

    def _depth(self, T_cam_model: np.ndarray, W: int, H: int) -> np.ndarray:
        """(H, W) float32 inverse depth (1/m, 0: off the model) of the model's visible faces at this pose."""
        from mst.pipeline.tracking.visibility import face_visibility, inverse_depth_buffer

        tr = self.tr
        c = tr.cfg
        fv = face_visibility(tr.geom, T_cam_model, None, c.angle_appear_deg, c.angle_disappear_deg)
        return inverse_depth_buffer(tr.geom, T_cam_model, tr.K, W, H, fv, tr.near(T_cam_model), 1.0)[0]

    def _keypoints(self, gray: np.ndarray, mask: np.ndarray, iz: np.ndarray, T_cam_model: np.ndarray):
        """ORB keypoints of ``gray`` inside ``mask`` (the strongest ``kf_features``) and their model
        coordinates from the inverse depth ``iz`` at this pose; ``(desc, X_model)`` or None."""
        H, W = gray.shape
        kps, desc = self._orb.detectAndCompute(gray, mask)
        if desc is None or len(kps) < self.cfg.min_keypoints:
            return None
        order = np.argsort([-kp.response for kp in kps])[: self.cfg.kf_features]
        kps, desc = [kps[i] for i in order], desc[order]
        uv = np.array([kp.pt for kp in kps], np.float64)
        ix = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
        iy = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
        izk = iz[iy, ix].astype(np.float64)
        ok = izk > 0
        if ok.sum() < self.cfg.min_keypoints:
            return None
        K = self.tr.K
        xn = (uv[ok] - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        Xc = np.column_stack([xn, np.ones(len(xn))]) / izk[ok, None]
        X_model = rigid(Xc - T_cam_model[:3, 3], T_cam_model[:3, :3].T)
        return desc[ok], X_model.astype(np.float32)

    def learn(self, k: int, gray: np.ndarray, T_cam_model: np.ndarray) -> int:
        """Store the ORB keypoints of ``gray`` on the model's visible surfaces at this pose (and the
        rendered views of :meth:`_learn_views`); returns how many were stored (0: too few, nothing stored)."""
        import cv2

        t0 = time.perf_counter()
        H, W = gray.shape[0], gray.shape[1]
        iz = self._depth(T_cam_model, W, H)
        mask = cv2.erode((iz > 0).astype(np.uint8) * 255, np.ones((7, 7), np.uint8))  # off the outline
        got = self._keypoints(gray, mask, iz, T_cam_model)
        self._last_learn = k
        if got is None:
            self.stats["ms_learn"] += (time.perf_counter() - t0) * 1e3
            return 0
        self.kfs.append((k, T_cam_model.copy(), got[0], got[1]))
        self.stats["keyframes"] += 1
        if self.cfg.synth_step_deg > 0 and self.cfg.synth_steps > 0:
            self._learn_views(k, gray, T_cam_model, iz)
        self.stats["ms_learn"] += (time.perf_counter() - t0) * 1e3
        return len(got[0])

    def _learn_views(self, k: int, gray: np.ndarray, T_kf: np.ndarray, iz_kf: np.ndarray) -> None:
        """Views of the object from new sides, rendered from the model with the keyframe's texture.

        The keyframe's camera turned about the image's vertical axis through the model's centre by
        +-``synth_step_deg`` x 1..``synth_steps`` (the object turned on a table, carried round,
        put back on another side). Each pixel of the new view on a model face seen in the keyframe
        (its inverse depth there within 2 % of the keyframe's own: not hidden) takes the
        keyframe's gray level at the same surface point (``cv2.remap``, bilinear); faces the
        keyframe did not see stay blank and get no keypoints. The keypoints of the view, with
        their model coordinates from its depth, are matched like a keyframe's."""
        import cv2

        H, W = gray.shape
        K = self.tr.K
        V = self.tr.geom.vertices
        c_model = 0.5 * (V.min(0) + V.max(0))
        # the turn axis: the model axis nearest to the image's vertical at the keyframe (the object
        # turned on its base, as on a table or a turntable)
        up = matvec(T_kf[:3, :3].T, np.array([0.0, -1.0, 0.0]))
        axis = np.zeros(3)
        axis[int(np.argmax(np.abs(up)))] = 1.0
        n_half = self.cfg.synth_steps
        for j in [s * i for i in range(1, n_half + 1) for s in (1, -1)]:
            Rm = cv2.Rodrigues(np.radians(self.cfg.synth_step_deg * j) * axis)[0]
            Tm = np.eye(4)
            Tm[:3, :3] = Rm
            Tm[:3, 3] = c_model - matvec(Rm, c_model)
            T_v = matmul_exact(T_kf, Tm)  # the model turned about its centre, seen by the keyframe's camera
            M = matmul_exact(T_v, inv_T(T_kf))  # keyframe camera -> view camera (a rigid motion of the scene)
            R = M[:3, :3]
            iz_v = self._depth(T_v, W, H)
            ys, xs = np.nonzero(iz_v > 0)
            if len(ys) < 100:
                continue
            # the work on the model's bounding box in the view only
            y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
            iz = iz_v[y0:y1, x0:x1]
            vv, uu = np.mgrid[y0:y1, x0:x1].astype(np.float32)
            z = 1.0 / np.maximum(iz, 1e-12)
            Xv = [(uu - K[0, 2]) / K[0, 0] * z, (vv - K[1, 2]) / K[1, 1] * z, z]  # view camera frame
            d = [Xv[i] - M[i, 3] for i in range(3)]
            # the same points in the keyframe's camera: X_kf = R^T (X_v - M_t), column by column
            Xk = [R[0, i] * d[0] + R[1, i] * d[1] + R[2, i] * d[2] for i in range(3)]
            zk = Xk[2]
            good = (iz > 0) & (zk > 1e-6)
            zs = np.where(good, zk, 1.0)
            mu = (K[0, 0] * Xk[0] / zs + K[0, 2]).astype(np.float32)
            mv = (K[1, 1] * Xk[1] / zs + K[1, 2]).astype(np.float32)
            inside = good & (mu >= 0) & (mu <= W - 1) & (mv >= 0) & (mv <= H - 1)
            izk = cv2.remap(iz_kf, mu, mv, cv2.INTER_NEAREST, borderValue=0)
            seen = inside & (izk > 0) & (np.abs(izk * zs - 1.0) < 0.02)  # the same surface point, not hidden
            if seen.sum() < 100:
                continue
            img = np.zeros_like(gray)
            img[y0:y1, x0:x1] = cv2.remap(gray, mu, mv, cv2.INTER_LINEAR, borderValue=0)
            mask = np.zeros_like(gray)
            mask[y0:y1, x0:x1] = cv2.erode(seen.astype(np.uint8) * 255, np.ones((7, 7), np.uint8))
            got = self._keypoints(img, mask, iz_v, T_v)
            if got is not None:
                self.views.append((k, T_v, got[0], got[1]))
                self.stats["synth_views"] += 1

    # ------------------------------------------------------------------ search
    def _pnp(self, kps, pairs, X_kf) -> tuple[np.ndarray, int] | None:
        """RANSAC PnP on one keyframe's matches: ``(T_cam_model, inliers)``, None without enough consensus."""
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
        if not np.isfinite(T).all() or rigid(X[inl], T[:3, :3], T[:3, 3])[:, 2].min() <= 0:
            return None
        return T, len(inl)

    def relocalise(self, gray: np.ndarray) -> np.ndarray | None:
        """PnP pose ``T_cam_model`` of the object in ``gray`` from the stored keypoints (the one with
        the most inliers), or None."""
        cands = self.candidates(gray)
        return cands[0] if cands else None

    def candidates(self, gray: np.ndarray) -> list[np.ndarray]:
        """PnP poses ``T_cam_model`` of the object in ``gray``, most inliers first (at most three:
        one per best-matched keyframe or view; a partly symmetric object can give a wrong pose a
        consensus on one view while the right one has its own on another, so the caller refines
        and judges each in turn)."""
        import cv2

        if not self.kfs:
            return []
        t0 = time.perf_counter()
        self.stats["attempts"] += 1
        try:
            kps, desc = self._orb.detectAndCompute(gray, None)
            if desc is None or len(kps) < self.cfg.min_matches:
                return []
            # ratio test per keyframe (a surface point stored in several keyframes would fail it
            # against itself in one pooled database), then PnP on the best keyframes in turn
            bf = cv2.BFMatcher(cv2.NORM_HAMMING)
            cands = []
            kfs = [(kf, False) for kf in self.kfs] + [(v, True) for v in self.views]
            if len(kfs) > self.cfg.kf_per_attempt:
                # bounded cost: the newest keyframe and a round-robin share of the others (older
                # keyframes, rendered views) per attempt
                newest = len(self.kfs) - 1
                rest = kfs[:newest] + kfs[newest + 1:]
                j0 = (self.stats["attempts"] * (self.cfg.kf_per_attempt - 1)) % len(rest)
                kfs = [kfs[newest]] + [rest[(j0 + i) % len(rest)] for i in range(self.cfg.kf_per_attempt - 1)]
            for (_, _, d_kf, X_kf), is_view in kfs:
                m = bf.knnMatch(desc, d_kf, k=2)
                pairs = [(a.queryIdx, a.trainIdx) for a, *b in m
                         if b and a.distance < self.cfg.ratio * b[0].distance and a.distance < self.cfg.max_hamming]
                if len(pairs) >= self.cfg.min_matches:
                    cands.append((len(pairs), pairs, X_kf, is_view))
            cands.sort(key=lambda c: -c[0])
            # PnP on the three best-matched keyframes/views
            got = []
            for _, pairs, X_kf, is_view in cands[:3]:
                r = self._pnp(kps, pairs, X_kf)
                if r is not None:
                    got.append((r[1], is_view, r[0]))
            got.sort(key=lambda g: -g[0])
            if got:
                self.stats["pnp_poses"] += 1
                self.stats["pnp_from_views"] += int(got[0][1])
            return [g[2] for g in got]
        finally:
            self.stats["ms_attempts"] += (time.perf_counter() - t0) * 1e3
