"""One frame of ViSP-style model-based edge tracking (``vpMbEdgeTracker``): :class:`EdgeTracker`.

Per frame: project the model with the start pose, keep visible edges
(:mod:`mst.pipeline.tracking.visibility`), search moving edges along their normals
(:mod:`mst.pipeline.tracking.moving_edges`), then robust VVS (:mod:`mst.pipeline.tracking.vvs`);
optional KLT points inside visible faces (:func:`mst.core.klt.track_forward_backward`) join the
same optimisation. Absolute health tests (mean angle between the image gradient and the model
edge normal at the samples, ViSP's projection error; inlier ratio; sample count) and the image
evidence of the final pose (:mod:`mst.pipeline.tracking.health`) go back in a
:class:`FrameResult`. Sequence-level decisions (re-acquisition, the SLAM aid) are the session's
(:mod:`mst.pipeline.tracking.session`).

Frames: ``T_cam_model`` (ViSP cMo). Pixels, metres. One class whose methods share the per-frame state
(reference image, pose, faces, KLT points); the numeric kernels it calls live in their own modules.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from mst.core.poses import inv_T, transform_points
from mst.errors import SolveStatus
from mst.pipeline.tracking.compiled import kernels as _kc  # ahead of time or numba JIT
from mst.pipeline.tracking.config import (
    TrackConfig,
    lod_thresholds,
    retry_pyramid_levels,
    scene_near_m,
    search_range_px,
)
from mst.pipeline.tracking.health import EVIDENCE_SAMPLES, ORIENT_TOL_DEG, PoseEvidence, image_noise_sigma
from mst.pipeline.tracking.klt_anchor import nearest_face_planes, reanchor_on_planes
from mst.pipeline.tracking.moving_edges import _image

log = logging.getLogger(__name__)

#: fewer KLT points than this in a fit: no ``klt_agree`` for the health score (one cluster of the
#: monitor's noise model, :class:`mst.pipeline.tracking.health.HealthMonitor`)
KLT_SIGNAL_MIN = 10
_NO_BUFFER = np.zeros((1, 1), np.float32)  # the surface kernel's buffer argument for a convex model (not read)


@dataclass
class FrameResult:
    """Tracking result for one frame (pose ``T_cam_model``; statistics in pixels and degrees)."""

    T_cam_model: np.ndarray | None
    healthy: bool
    n_samples: int
    n_inliers: int
    residual_px: float
    proj_error_deg: float
    W: np.ndarray | None
    cov: np.ndarray | None
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    inlier: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    edge_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    klt_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    reason: str = ""
    support: float = 0.0
    evidence: PoseEvidence | None = None  #: the image evidence at the final pose
    klt_agree: float | None = None        #: share of the KLT points that are robust inliers
    n_klt: int = 0
    score: float = float("nan")           #: calibrated health score (HealthMonitor), 1 typical, <= 0 rejected
    features: dict | None = None          #: the health monitor's signal values of this frame
    n_visible: int = -1                   #: visible edge samples before the ``max_samples`` cap (-1: n_samples)


def _surface_points(model, n_points: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fixed random points on the model's faces (area-uniform): (M,3) model frame m, (M,) face index."""
    try:
        V, F, fid = model.triangulate(return_index=True)
    except (AttributeError, ValueError, TypeError):
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    V, F, fid = np.asarray(V, float), np.asarray(F, np.int64).reshape(-1, 3), np.asarray(fid, np.int64)
    if not len(F):
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    A = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    if A.sum() <= 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    t = rng.choice(len(F), n_points, p=A / A.sum())
    r1, r2 = rng.random(n_points), rng.random(n_points)
    flip = r1 + r2 > 1
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    X = V[F[t, 0]] + r1[:, None] * (V[F[t, 1]] - V[F[t, 0]]) + r2[:, None] * (V[F[t, 2]] - V[F[t, 0]])
    return X, fid[t]


def _sorted_unique(e: np.ndarray) -> np.ndarray:
    """``np.unique(e)`` of the samples' edge ids, which the samplers emit edge by edge (non-decreasing): the first
    of each run, without a sort (``np.unique`` when they are not in order)."""
    if len(e) < 2:
        return np.unique(e)
    step = e[1:] != e[:-1]
    if (e[1:] < e[:-1]).any():
        return np.unique(e)
    return e[np.concatenate(([True], step))]


class EdgeTracker:
    """ViSP-style edge (+ optional KLT) tracker for one model and camera.

    ``track(gray, T_cam_model_init)`` refines the pose on a new 8-bit gray frame; the previous
    frame and pose (kept internally) give each sample's reference contrast and polarity.
    """

    def __init__(self, model, camera, config: TrackConfig | None = None):
        from mst.pipeline.tracking.visibility import ModelGeometry

        config = config or TrackConfig()
        cfg = config.edges
        if cfg.search_range_px is None or cfg.retry_pyramid_levels is None:  # defaults from the image width
            cfg = dataclasses.replace(cfg, search_range_px=search_range_px(cfg, camera.width),
                                      retry_pyramid_levels=retry_pyramid_levels(cfg, camera.width))
        self.geom = ModelGeometry.from_model(model)
        self.cam = camera
        self.K = camera.K
        self.cfg = cfg  #: the edges section (moving edges, faces, LOD, VVS, health)
        self.klt_cfg = config.klt
        self.use_klt = bool(config.use_klt)
        self.prev_img: np.ndarray | None = None
        self.prev_T: np.ndarray | None = None
        self.prev_faces: np.ndarray | None = None
        self.klt_pts: np.ndarray | None = None  # (M,2) px in prev frame
        self.recover_min_inlier_ratio = 0.5  #: a recovery fit's inlier ratio (the policy's, per sequence)
        self.klt_X: np.ndarray | None = None  # (M,3) model frame
        self.klt_plane: np.ndarray | None = None  # (M,4) the face plane (n, d: n.X = d) of each, model frame (klt.reanchor)
        self.prev_gray: np.ndarray | None = None
        self._pyramids = None  # the KLT pyramids of the last two frames (core.klt.PyramidCache)
        self._klt_next: tuple | None = None  # the last fit's KLT inliers (model points, px, planes)
        self._klt_age = 0  # frames since the KLT corners were detected
        self._klt_n0 = 0  # corners at the last detection
        self._klt_n_mean = 1  # poses in the KLT points' running mean (klt.reanchor mean): the detection's
        self.klt_gate: tuple[np.ndarray, float] | None = None  #: texture gate of the last detection (g_min, noise sigma)
        self._fail = ""  # why the last edge pass found no pose
        self.near_m: float | None = cfg.near_clip_m  # None: set from the scene depth at the first pose
        self.lod = lod_thresholds(cfg)
        self.health_score = config.health_score  #: compute the image evidence of each final pose (HealthMonitor)
        self.surf_X, self.surf_face = _surface_points(model)  # (M,3) model frame, (M,) face index
        self.sample_provider = None  # render-based edgelets (mst.pipeline.tracking.render_edges) instead of polygon edges

    # -------------------------------------------------------------- helpers
    def near(self, T_cam_model: np.ndarray) -> float:
        """Near clipping distance (m): the configured one, else :func:`scene_near_m` at the first
        pose seen (fixed from then on)."""
        if self.near_m is None:
            self.near_m = scene_near_m(self.geom.vertices, T_cam_model)
        return self.near_m

    def _samples(self, T, K, W, H):
        from mst.pipeline.tracking.visibility import visible_samples

        if self.sample_provider is not None:
            return self.sample_provider.samples(T, K, W, H)
        c = self.cfg
        lod_line, lod_face = self.lod
        s = K[0, 0] / self.K[0, 0]  # coarse pyramid levels: the thresholds scale with the image
        return visible_samples(self.geom, T, K, W, H, c.sample_step_px, self.near(T), c.far_clip_m, c.angle_appear_deg,
                               c.angle_disappear_deg, self.prev_faces, border_px=c.mask_px // 2 + 1,
                               hidden_lines=c.hidden_lines, zbuffer_scale=c.zbuffer_scale, max_samples=c.max_samples,
                               lod_min_line_px=lod_line * s, lod_min_face_px2=lod_face * s * s)

    def explain(self, S) -> str:
        """Why the samples ``S`` of a pose are too few (see :func:`visibility.explain_no_samples`)."""
        from mst.pipeline.tracking.visibility import explain_no_samples

        if self.sample_provider is not None:
            return self.sample_provider.explain(S)
        return explain_no_samples(S.stats, self.near_m or 0.0, self.cfg.far_clip_m, self.lod)

    def _edge_pass(self, img, K, T, search_range, ref_img, ref_T, klt=None, min_mad_px=None):
        from mst.pipeline.tracking.moving_edges import canonical_normals, reference_contrast, search_edges
        from mst.pipeline.tracking.vvs import solve_pose

        c = self.cfg
        H, W = img.shape
        S = self._samples(T, K, W, H)
        if len(S) < 6:
            self._fail = self.explain(S)
            return None, S, None, None
        normal, midx = canonical_normals(S.normal, c.n_masks)
        ref = None
        if ref_img is not None:
            # the samples in the reference frame (transform_points(elementwise=True)'s bits), one kernel
            uvp = _kc.project_uv(np.ascontiguousarray(S.X_model, np.float64), np.ascontiguousarray(ref_T, np.float64),
                             float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
            ref = reference_contrast(ref_img, uvp, normal, midx, c.mask_px, c.n_masks)
        m = search_edges(img, S.uv, normal, ref, search_range=int(search_range), threshold=c.edge_threshold,
                         mu1=c.mu1, mu2=c.mu2, size=c.mask_px, n_masks=c.n_masks, n_candidates=c.n_candidates,
                         mask_idx=midx, edge=S.edge)
        if self.sample_provider is not None and ref_img is not None:  # render-based edges: contour side test
            m = self.sample_provider.filter_matches(img, K, S, m, ref_img, ref_T)
        cand = m.candidates_uv(S.uv)
        kx, ku = (None, None) if klt is None else klt[:2]
        # without a given floor: where the floor binds (the fit's own robust scale is below it), a fine
        # stage from the converged pose, same matches, a tighter floor (solve_pose's fine_mad_px). The
        # coarse floor must admit the whole inter-frame motion at the start (with the fine one from
        # the start a translating camera's samples were all rejected and it stood still). Real video
        # (MAD above the floor) skips it
        res = solve_pose(T, K, S.X_model, S.edge, S.A_model, S.B_model, cand, iters=c.vvs_iters, lm_mu=c.lm_mu,
                         min_mad_px=c.min_mad_px if min_mad_px is None else min_mad_px, tukey_c=c.tukey_c, klt_X_model=kx,
                         klt_uv=ku, klt_weight=c.klt_weight, klt_info_cap=c.klt_info_cap,
                         fine_mad_px=c.fine_mad_px if min_mad_px is None else None)
        if res.status is SolveStatus.TOO_FEW:
            n_m = int(np.isfinite(cand[..., 0]).any(axis=1).sum())
            self._fail = (f"pose solver failed: only {n_m} of {len(S)} edge samples found a moving edge within "
                          f"{int(search_range)} px (need 6; no image edge near the projected model)")
            return None, S, m, None
        if not res.has_pose:
            self._fail = "pose solver failed: the optimisation diverged (non-finite pose)"
            return None, S, m, None
        return res, S, m, cand

    # -------------------------------------------------------------- KLT (ViSP hybrid tracker)
    def _klt_points(self, gray, T):
        """Detect KLT corners inside visible faces: ``(pts (M,2) px, X (M,3) model points from the
        inverse depth buffer, planes (M,4) the nearest visible face plane of each)`` or Nones."""
        import cv2

        kc = self.klt_cfg
        H, W = gray.shape
        fv = self.prev_faces if self.prev_faces is not None else np.ones(len(self.geom.faces), bool)
        from mst.pipeline.tracking.visibility import inverse_depth_buffer

        best, _ = inverse_depth_buffer(self.geom, T, self.K, W, H, fv, self.near(T), 1.0)  # 1/z of the front surface
        mask = (best > 0).astype(np.uint8) * 255
        mask = cv2.erode(mask, np.ones((2 * kc.border_px + 1,) * 2, np.uint8))
        ys, xs = np.nonzero(mask[::8, ::8])
        if not len(xs):
            return None, None, None
        x0, x1 = max(0, xs.min() * 8 - 8), min(W, xs.max() * 8 + 9)
        y0, y1 = max(0, ys.min() * 8 - 8), min(H, ys.max() * 8 + 9)
        pts = cv2.goodFeaturesToTrack(gray[y0:y1, x0:x1], kc.max_features, kc.quality, kc.min_distance_px,
                                      mask=np.ascontiguousarray(mask[y0:y1, x0:x1]), blockSize=kc.block_px,
                                      useHarrisDetector=False, k=kc.harris_k)
        if pts is None:
            return None, None, None
        pts = pts.reshape(-1, 2)
        # texture gate: goodFeaturesToTrack's quality is relative to the strongest corner, so on a
        # textureless face it returns noise. Keep a corner only when the weakest-direction RMS
        # gradient over the KLT window clearly exceeds what the image noise alone gives there
        # (Sobel derivative of noise sigma: std 0.43 sigma per axis; 3x that)
        roi = gray[y0:y1, x0:x1]
        win = kc.window_px
        lam = cv2.cornerMinEigenVal(roi, win, 3)  # = 4 lambda_g / 255^2 (OpenCV's 8-bit scaling)
        ij = np.clip(np.rint(pts).astype(int), 0, [roi.shape[1] - 1, roi.shape[0] - 1])
        g_min = 127.5 * np.sqrt(np.maximum(lam[ij[:, 1], ij[:, 0]], 0))  # gray levels / px
        sigma = image_noise_sigma(roi)
        self.klt_gate = (g_min, sigma)
        pts = pts[g_min >= 3.0 * 0.43 * sigma]
        if not len(pts):
            return None, None, None
        pts = pts + [x0, y0]
        pts = pts.astype(np.float64)
        ix, iy = np.rint(pts[:, 0]).astype(int), np.rint(pts[:, 1]).astype(int)
        iz = best[iy, ix].astype(np.float64)
        ok = iz > 0
        pts, iz = pts[ok], iz[ok]
        xn = (pts - self.K[:2, 2]) / np.array([self.K[0, 0], self.K[1, 1]])
        Xc = np.column_stack([xn, np.ones(len(xn))]) / iz[:, None]
        X_model = transform_points(inv_T(T), Xc, elementwise=True)
        # the face planes where the points are re-anchored (klt.reanchor)
        return pts, X_model, nearest_face_planes(self.geom, X_model, fv) if kc.reanchor != "off" else None

    def _klt_track(self, gray):
        from mst.core.klt import track_forward_backward

        if self.klt_pts is None or len(self.klt_pts) < 4 or self.prev_gray is None:
            return None
        pyr = self._pyramids
        if pyr is None:
            from mst.core.klt import PyramidCache

            pyr = self._pyramids = PyramidCache(self.klt_cfg)  # each frame's pyramid built once
        # forward-backward check: drops unstable tracks (noise, occlusion boundaries)
        p1, ok, _ = track_forward_backward(pyr.get(self.prev_gray), pyr.get(gray), self.klt_pts, self.klt_cfg)
        if ok.sum() < 4:
            return None
        return self.klt_X[ok], p1[ok].astype(np.float64), None if self.klt_plane is None else self.klt_plane[ok]

    def discard_klt_matches(self) -> None:
        """Forget the KLT inliers of the last :meth:`track` call (its fit was not the one kept)."""
        self._klt_next = None

    # -------------------------------------------------------------- image evidence of a pose
    def evidence(self, gray: np.ndarray, T_cam_model: np.ndarray, S=None) -> PoseEvidence:
        """What ``gray`` (H, W) uint8 says about the pose ``T_cam_model``, without moving it.

        At the visible samples of the pose: the Sobel gradient at -1, 0, +1 px along the projected
        model normal (the strongest kept: its polarity, and whether it is at least the moving-edge
        contrast and within ``ORIENT_TOL_DEG`` of the normal), and the nearest moving edge within the
        search range (ViSP's oriented masks, no contrast reference).
        """
        from mst.pipeline.tracking.moving_edges import canonical_normals, search_edges

        c = self.cfg
        H, W = gray.shape
        prov = self.sample_provider
        if S is None and prov is not None:  # render-based: the contour of a render at this very pose
            kept, prov.cache = prov.cache, None  # (the tracker's cached render is left as it was)
            S = self._samples(T_cam_model, self.K, W, H)
            prov.cache = kept
        elif S is None:
            S = self._samples(T_cam_model, self.K, W, H)
        edgelets = S.model_edge is None and prov is not None  # render-based: no model edges
        if len(S) == 0 or (S.model_edge is None and not edgelets):
            z = np.zeros(0)
            return PoseEvidence(z.astype(np.int64), z.astype(np.int8), z.astype(bool), z)

        K = self.K
        # projection, model normals and the strongest Sobel gradient within +-1 px along them in one kernel
        uv, n, sign, good = _kc.pose_gradients(
            _image(gray), np.ascontiguousarray(S.X_model, np.float64), np.ascontiguousarray(S.A_model, np.float64),
            np.ascontiguousarray(S.B_model, np.float64), np.ascontiguousarray(S.edge, np.int64),
            np.ascontiguousarray(T_cam_model, np.float64), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
            float(K[1, 2]), float(2.0 * c.edge_threshold), float(np.cos(np.radians(ORIENT_TOL_DEG))))
        # the moving-edge search (the costly part) on every k-th sample, k = n // EVIDENCE_SAMPLES: a
        # share and a median over >= 100 samples, well within their binomial / quantisation floors
        sel = slice(None, None, max(1, len(uv) // EVIDENCE_SAMPLES))
        normal, midx = canonical_normals(n[sel], c.n_masks)
        m = search_edges(gray, uv[sel], normal, None, search_range=int(c.search_range_px), threshold=c.edge_threshold,
                         mu1=c.mu1, mu2=c.mu2, size=c.mask_px, n_masks=c.n_masks, n_candidates=c.n_candidates,
                         mask_idx=midx, edge=S.edge[sel])
        off = np.abs(m.offset)
        n_me = len(uv[sel])
        off = np.where(np.isfinite(off), off, np.inf).min(1) if off.ndim == 2 and off.shape[1] else np.full(n_me, np.inf)
        off = np.where(np.isfinite(off), off, np.nan)
        if edgelets:  # no model edge, no surface visibility of the render's samples: edges' signals only
            return PoseEvidence(np.full(len(sign), -1, np.int64), sign, good, off)
        ti, tv = self._surface_values(gray, T_cam_model, S.face_visible)
        return PoseEvidence(S.model_edge[S.edge], sign, good, off, ti, tv)

    def _surface_values(self, gray, T, face_visible):
        """Indices of the surface points seen at pose T (front faces, inside the image, not hidden)
        and the image's 3x3 mean gray level there (one kernel: :func:`kernels.surface_values`; the
        numpy formulation is :meth:`_surface_values_numpy`)."""
        if not len(self.surf_X) or face_visible is None:
            return np.zeros(0, np.int64), np.zeros(0)

        H, W = gray.shape
        buf, sc = _NO_BUFFER, 1.0
        if not self.geom.convex:
            from mst.pipeline.tracking.visibility import inverse_depth_buffer

            buf, sc = inverse_depth_buffer(self.geom, T, self.K, W, H, face_visible, self.near(T), 0.5)
        K = self.K
        return _kc.surface_values(_image(gray), self.surf_X, self.surf_face, np.ascontiguousarray(face_visible, np.bool_),
                              np.ascontiguousarray(T, np.float64), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                              float(K[1, 2]), float(self.near(T)), buf, float(sc), not self.geom.convex)

    def _surface_values_numpy(self, gray, T, face_visible):
        """The numpy formulation of :meth:`_surface_values` (the reference of its kernel's test)."""
        if not len(self.surf_X) or face_visible is None:
            return np.zeros(0, np.int64), np.zeros(0)
        H, W = gray.shape
        idx = np.flatnonzero(face_visible[self.surf_face])
        Xc = transform_points(T, self.surf_X[idx], elementwise=True)
        ok = Xc[:, 2] > self.near(T)
        idx, Xc = idx[ok], Xc[ok]
        uv = Xc[:, :2] / Xc[:, 2:3] * [self.K[0, 0], self.K[1, 1]] + self.K[:2, 2]
        ix, iy = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        ok = (ix >= 1) & (iy >= 1) & (ix < W - 1) & (iy < H - 1)
        idx, ix, iy, iz = idx[ok], ix[ok], iy[ok], 1.0 / Xc[ok, 2]
        if not self.geom.convex and len(idx):
            from mst.pipeline.tracking.visibility import inverse_depth_buffer

            buf, sc = inverse_depth_buffer(self.geom, T, self.K, W, H, face_visible, self.near(T), 0.5)
            bx = np.clip(np.round((ix + 0.5) * sc - 0.5).astype(np.int64), 0, buf.shape[1] - 1)
            by = np.clip(np.round((iy + 0.5) * sc - 0.5).astype(np.int64), 0, buf.shape[0] - 1)
            vis = iz >= buf[by, bx] * (1.0 - 1e-2)
            idx, ix, iy = idx[vis], ix[vis], iy[vis]
        f = gray.ravel()  # only the pixels read are converted (not the whole frame, every frame)
        b = iy * W + ix
        val = sum(f[b + dy * W + dx].astype(np.float32) for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9.0
        return idx, val.astype(np.float64)

    # -------------------------------------------------------------- main entry
    def track(self, gray: np.ndarray, T_init: np.ndarray, recover: bool = False, first: bool = False,
              klt: bool = True) -> FrameResult:
        """Refine ``T_init`` (T_cam_model) on ``gray`` (H, W) uint8; update the internal reference.
        ``klt`` False: this fit leaves the KLT points out (on the edges alone), as without ``use_klt``.

        A tracked frame that the search at ``pyramid_levels`` loses is searched once more
        coarse-to-fine with ``retry_pyramid_levels`` (the motion outran the range: the FPV pass at
        1080p); the retry's pose is taken only when healthy."""
        c = self.cfg
        klt = self._klt_track(gray) if klt and self.use_klt and not (first or recover) else None
        out = self._track(gray, T_init, recover, first, klt, c.pyramid_levels)
        retry = int(c.retry_pyramid_levels)
        if not out.healthy and not (first or recover) and retry > c.pyramid_levels:
            klt_next = self._klt_next
            again = self._track(gray, T_init, recover, first, klt, retry)
            self._klt_next = self._klt_next if again.healthy else klt_next
            if again.healthy:
                log.debug(f"the single-level search lost the frame ({out.reason}); coarse-to-fine with {retry} levels kept it")
                return again
        return out

    def _track(self, gray: np.ndarray, T_init: np.ndarray, recover: bool, first: bool, klt, levels: int) -> FrameResult:
        import cv2

        c = self.cfg
        img = gray  # uint8: the moving-edge gathers convert only the pixels they read
        H, W = img.shape
        T = T_init.copy()
        ref_img = None if (first or recover or self.prev_img is None) else self.prev_img
        ref_T = self.prev_T
        R = c.search_range_px * (c.recover_range_factor if recover else 1.0)
        # coarse-to-fine: a half-resolution pass first (always after a loss)
        levels = max(levels, 2 if recover else 1)
        for lev in range(levels - 1, 0, -1):
            s = 0.5**lev
            small = img
            for _ in range(lev):
                small = cv2.pyrDown(small)
            Ks = self.K.copy()
            Ks[:2] *= s
            Ks[0, 2] = (self.K[0, 2] + 0.5) * s - 0.5
            Ks[1, 2] = (self.K[1, 2] + 0.5) * s - 0.5
            ref_small = None
            res, *_ = self._edge_pass(small, Ks, T, R, ref_small, ref_T, min_mad_px=max(c.min_mad_px, R / 3.0))
            if res is not None and np.isfinite(res.T_cam_model).all():
                T = res.T_cam_model
        # first frame / after a loss: several passes, tolerant (wide robust scale) first, then tighter
        passes = 3 if (first or recover) else c.passes
        res = S = S_p = None
        self._fail = "too few visible edge samples"
        # render-based edges of a curved mesh: up to `extra_passes` more while the last pass still moved the
        # contour far (a start far from the frame's pose: render_edges.RenderEdgeProvider.unconverged)
        prov = self.sample_provider
        extra = 0 if (first or recover or prov is None) else int(getattr(prov, "extra_passes", 0))
        T_in = T
        for ps in range(passes + extra):
            if ps >= passes and not prov.unconverged(S, T_in, T):
                break
            T_in = T
            rng = R if ps == 0 else max(3, int(round(R / 2 ** ps)))
            mad = max(c.min_mad_px, rng / 3.0) if (first or recover) and ps < passes - 1 else None
            if (first or recover) and ps > 0:
                ref_img, ref_T = img, T  # later passes: contrast/polarity reference from this frame at the refined pose
            res_p, S_p, _, _ = self._edge_pass(img, self.K, T, rng, ref_img, ref_T, klt if ps >= passes - 1 else None,
                                               min_mad_px=mad)
            if res_p is None:
                break
            res, S = res_p, S_p
            T = res.T_cam_model
        if res is None:
            return FrameResult(None, False, 0 if S_p is None else len(S_p), 0, float("nan"), 90.0, None, None,
                               reason=self._fail)
        healthy, reason, uv, support, proj_err = self._absolute_health(img, S, T, res, recover)
        n_s, n_in = len(S), int(res.inlier.sum())
        if klt is not None and res.klt_inlier is not None:
            self._klt_next = tuple(None if a is None else a[res.klt_inlier] for a in klt)
        prov = self.sample_provider
        # the gauge-fixed covariance from the evidence's information, as VVSResult.cov
        cov = res.cov if prov is None else prov.gauge_cov(T, res.W_edges, res.cov, res.rms_px, res.jk_inputs)
        out = FrameResult(T, healthy, n_s, n_in, res.rms_px, proj_err, res.W, cov, uv, res.inlier,
                          S.edge_uv[_sorted_unique(S.edge)], np.zeros((0, 2)) if klt is None else klt[1], reason, support)
        out.n_visible = int((getattr(S, "stats", None) or {}).get("visible", n_s))
        if self.health_score:
            out.evidence = self.evidence(img, T, S)  # the last pass's samples, re-projected at T
        if klt is not None and res.klt_inlier is not None:
            out.n_klt = int(len(res.klt_inlier))
            # the health monitor counts KLT points in clusters of 10 (they move together): fewer
            # than one cluster is no agreement signal (one of 4 points flipping moved the score by 0.6)
            out.klt_agree = float(np.mean(res.klt_inlier)) if out.n_klt >= KLT_SIGNAL_MIN else None
        return out

    def _absolute_health(self, img, S, T, res, recover: bool):
        """The absolute health tests of a solved pose: projection error (gradient vs model normal)
        at the final pose, gradient support, inlier ratio, sample count, model in front. Returns
        ``(healthy, reason, uv (N, 2) the samples at T, support, projection error deg)``."""

        c = self.cfg
        K = self.K
        # projection, model normals, Sobel gradient, strong share and mean angle in one kernel; the
        # strength test in float32 as numpy's on the float32 gradient norm
        uv, in_front, n_strong, ang_sum = _kc.pose_health(
            _image(img), np.ascontiguousarray(S.X_model, np.float64), np.ascontiguousarray(S.A_model, np.float64),
            np.ascontiguousarray(S.B_model, np.float64), np.ascontiguousarray(S.edge, np.int64),
            np.ascontiguousarray(T, np.float64), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
            float(self.near(T) * 0.5), float(np.float32(2.0 * c.edge_threshold)))  # Sobel of a step of `threshold` is 4x it
        ok_z = bool(in_front)
        support = n_strong / len(uv) if len(uv) else 0.0
        proj_err = float(ang_sum / n_strong) if n_strong >= 3 else 90.0
        n_s = len(S)
        n_in = int(res.inlier.sum())
        ratio = n_in / max(n_s, 1)
        # a recovery (after a loss) must be convincing: stricter projection error and inlier ratio (the policy's)
        max_pe = c.max_proj_error_deg * (0.6 if recover else 1.0)
        min_ratio = max(c.min_inlier_ratio, self.recover_min_inlier_ratio) if recover else c.min_inlier_ratio
        healthy = bool(n_s >= c.min_samples and ratio >= min_ratio and proj_err <= max_pe
                       and support >= c.min_support and np.isfinite(T).all() and ok_z)
        reason = "" if healthy else ("the solved pose puts the model behind the camera" if not ok_z
                                     else self.explain(S) if n_s < c.min_samples else f"inliers {ratio:.0%}"
                                     if ratio < min_ratio else f"gradient support {support:.0%}"
                                     if support < c.min_support else f"projection error {proj_err:.1f} deg")
        return healthy, reason, uv, support, proj_err

    def accept(self, gray: np.ndarray, T_cam_model: np.ndarray, anchor: bool = True) -> None:
        """Make ``(gray, T_cam_model)`` the reference for the next frame (a good pose). ``anchor``: the
        pose is output as the model's (``model``, ``relocalised``), so the kept KLT points may be
        re-anchored on it (``klt.reanchor``); a pose the error budget withheld or a map pose is not."""
        from mst.pipeline.tracking.visibility import face_visibility, view_faces

        c = self.cfg
        self.prev_img = gray
        self.prev_T = T_cam_model.copy()
        if self.sample_provider is None or self.use_klt:
            # render-based edges take visibility from the render: the face set only masks the KLT corners
            # (a per-face test over a 15k-triangle mesh cost ~8 ms a frame, as much as the rest of the frame)
            # a model with a face index (>= 1000 faces) keeps the hysteresis state of the faces in
            # the view frustum only (a 50k-face city: 17 ms a frame for all faces, 0.3 ms for those)
            H, W = gray.shape
            among = view_faces(self.geom, T_cam_model, self.K, W, H, self.near(T_cam_model), c.far_clip_m)
            self.prev_faces = face_visibility(self.geom, T_cam_model, self.prev_faces, c.angle_appear_deg,
                                              c.angle_disappear_deg, among=among)
        if self.use_klt:
            nxt = self._klt_next
            self._klt_next = None
            self._klt_age += 1
            enough = nxt is not None and len(nxt[0]) >= max(20, 0.6 * self._klt_n0)
            if not anchor:
                # a pose not output (withheld by the error budget, a map pose): the points go; kept or
                # re-detected they tie the next fits to an unverified pose's error (README, tracking:
                # the Rotterdam 120 m return 3-4.7 sigma off). The next fit is the edges' own.
                self.klt_pts = self.klt_X = self.klt_plane = None
                self._klt_n0, self._klt_age, self._klt_n_mean = 0, 0, 1
            # re-detect when too few points survive (at most every 5 frames: textureless scenes) or every 30
            elif nxt is not None and len(nxt[0]) >= 4 and (enough or self._klt_age < 5) and self._klt_age < 30:
                # keep tracking the surviving points (ViSP keeps its KLT set)
                self.klt_X, self.klt_pts, self.klt_plane = nxt
                if self.klt_cfg.reanchor == "mean" and self.klt_plane is not None:  # over the output poses
                    X1 = reanchor_on_planes(self.klt_pts, self.klt_plane, T_cam_model, self.K, self.klt_X)
                    self._klt_n_mean += 1
                    self.klt_X = self.klt_X + (X1 - self.klt_X) / self._klt_n_mean
            else:
                self.klt_pts, self.klt_X, self.klt_plane = self._klt_points(gray, T_cam_model)
                self._klt_n0 = 0 if self.klt_pts is None else len(self.klt_pts)
                self._klt_age = 0
                self._klt_n_mean = 1
            self.prev_gray = gray
