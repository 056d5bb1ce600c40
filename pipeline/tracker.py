"""``mst track``: model-based edge tracking (ViSP's ``vpMbEdgeTracker``) over a frame source.

Per frame: project the model with the previous (or the SLAM aid's predicted) pose, keep visible
edges (:mod:`mst.pipeline.visibility`), search moving edges along their normals
(:mod:`mst.pipeline.moving_edges`), then robust VVS (:mod:`mst.pipeline.vvs`); optional KLT points
inside visible faces join the same optimisation (``use_klt``). A health test (mean angle between
the image gradient and the model edge normal at the samples, ViSP's projection error; inlier
ratio; sample count) marks a frame ``lost`` instead of drifting; the next frame restarts from the
last good pose with a widened, coarse-to-fine search.

Frames: ``T_cam_model`` (ViSP cMo) internally; files hold ``T_model_cam`` (TUM). Pixels, metres.
"""

from __future__ import annotations

import csv
import io
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError, atomic_outputs
from mst.pipeline.overlay import OverlayWriter, draw_overlay
from mst.pipeline.settings import TrackerConfig, config_to_dict, lod_thresholds, scene_near_m

#: on re-acquisition (the model back after a SLAM-only stretch) an edge pose is healthy only when its
#: gradient support is at least this fraction of its running mean over the model frames (measured
#: on the synthetic corridor at 640x480: correct poses 0.90-0.96 against a usual 0.93, poses locked
#: onto floor/texture edges 0.52-0.66; the real teabox: 0.66-0.73)
REACQUIRE_SUPPORT_RATIO = 0.8


# ---------------------------------------------------------------------------- model loading
def load_polygon_model(path: str | os.PathLike):
    """Load a polygon model with :func:`mst.meshtools.io.load_model` and check it can be tracked.

    Raises :class:`mst.InputError` naming the file for a missing file, a model without faces or
    lines, non-finite vertices, or degenerate geometry (all vertices at one point or on one line:
    no edge of it constrains a pose)."""
    from mst.meshtools.io import load_model

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "model file does not exist")
    model = load_model(p)
    if not len(model.faces) and not len(getattr(model, "lines", [])):
        raise InputError(p, "model has no faces")
    model.check_finite(str(p))
    V = np.asarray(model.vertices, float).reshape(-1, 3)
    used = np.unique(np.concatenate([np.asarray(f, np.int64).ravel() for f in model.faces]
                                    + [np.asarray(getattr(model, "lines", []), np.int64).ravel()]))
    X = V[used[(used >= 0) & (used < len(V))]]
    ext = float(np.ptp(X, axis=0).max()) if len(X) else 0.0
    # rank of the centred vertices: 0 = one point, 1 = one line (relative to the model's size)
    sv = np.linalg.svd(X - X.mean(0), compute_uv=False) if len(X) >= 2 else np.zeros(1)
    if ext <= 0.0 or sv.size < 2 or sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise InputError(p, "model is degenerate: its vertices lie at one point or on one line")
    return model


# ---------------------------------------------------------------------------- one-frame tracker
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


def _sobel_at(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,2) Sobel gradient (gx, gy) of ``img`` at the nearest pixels of ``uv``."""
    H, W = img.shape
    ix = np.clip(np.rint(uv[:, 0]).astype(np.int64), 1, W - 2)
    iy = np.clip(np.rint(uv[:, 1]).astype(np.int64), 1, H - 2)
    b = iy * W + ix
    f = img.ravel()
    p = [f[b + dy * W + dx].astype(np.float32) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    gx = (p[2] + 2 * p[5] + p[8]) - (p[0] + 2 * p[3] + p[6])
    gy = (p[6] + 2 * p[7] + p[8]) - (p[0] + 2 * p[1] + p[2])
    return np.stack([gx, gy], 1)


@dataclass
class PoseEvidence:
    """What one image says about one pose ``T_cam_model`` (see :meth:`EdgeTracker.evidence`).

    tex_idx / tex_val: the model's fixed surface points (:attr:`EdgeTracker.surf_X`) seen at this
    pose and the image there (3x3 mean, gray levels).
    edge (N,) model edge index (into ``ModelGeometry.edges``) of each visible sample; sign (N,) int8
    polarity of the image gradient along the projected model normal at the best position within
    +-1 px (0: no gradient of at least the moving-edge contrast there); oriented (N,) that gradient is
    within ``ORIENT_TOL_DEG`` of the model normal; offset_px (M,) distance along the normal to the
    nearest moving edge within the search range (NaN: none), at every sample or, beyond 200
    samples, every 2nd.
    """

    edge: np.ndarray
    sign: np.ndarray
    oriented: np.ndarray
    offset_px: np.ndarray
    tex_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  #: visible surface points
    tex_val: np.ndarray = field(default_factory=lambda: np.zeros(0))             #: their 3x3-mean gray levels

    @property
    def n(self) -> int:
        return len(self.edge)

    @property
    def found(self) -> float:
        """Share of samples with a moving edge within the search range."""
        return float(np.isfinite(self.offset_px).mean()) if self.n else 0.0

    @property
    def residual_px(self) -> float:
        """Median distance to the nearest moving edge (px; inf without any)."""
        f = self.offset_px[np.isfinite(self.offset_px)]
        return float(np.median(np.abs(f))) if len(f) else float("inf")


#: spread floor of the moving-edge residual: whole-pixel positions along the normal, std 1/sqrt(12) px
RESIDUAL_FLOOR_PX = 0.29

#: orientation tolerance of a matching edge: the Sobel orientation of a straight step is within a
#: few degrees; 30 deg leaves room for blur and corners, and still rejects random texture (which
#: falls inside +-30 deg one time in three)
ORIENT_TOL_DEG = 30.0


class HealthMonitor:
    """One calibrated health score per frame, thresholds learned from the sequence's healthy frames.

    Signals (each "higher is better" after the sign flip of the residual):

    * ``match``: share of visible samples with an image edge within +-1 px of the projected model
      edge, of the model edge's orientation (``ORIENT_TOL_DEG``) and of the **polarity** that edge
      had in the healthy frames so far (bright/dark side; an edge whose polarity flips between
      healthy frames, e.g. a silhouette over a varying background, is not checked for it);
    * ``found``: share of samples with a moving edge within the search range;
    * ``residual``: the median distance (px) to the nearest moving edge (negated);
    * ``klt``: share of the tracked KLT points that agree with the pose (its robust inliers);
    * ``texture``: normalised cross-correlation of the image at the model's surface points with
      their appearance learned in the healthy frames (catches what edges alone cannot: the
      object's mirror image, a shadow or a background pattern of the object's outline).

    For each signal the reference is the median over the last ``window`` accepted frames and the
    spread 1.4826 x their MAD, floored by the signal's own sampling noise: binomial
    ``sqrt(p (1 - p) / n)`` for a share, where the samples of one model edge share its background
    and blur, so n = the number of visible model edges, and KLT points move in clusters, so n = their
    count / 10; ``RESIDUAL_FLOOR_PX`` for the residual (moving edges sit on whole pixels along the
    normal: a uniform +-0.5 px quantisation, std 0.29 px); ``(1 - r^2) / sqrt(n)`` (at least 0.02)
    for a correlation r over n points. The
    deficit ``z = (ref - value) / spread`` of the worst signal gives ``score = 1 - z / z_reject``:
    1 = a typical healthy frame, <= 0 = rejected. Until ``min_calib`` frames are accepted the
    spreads are doubled (a looser test while the statistics are young). The first frame (the
    user's pose) is accepted as the first reference.
    """

    SIGNALS = ("match", "found", "residual", "klt", "texture")

    def __init__(self, n_edges: int, n_surface: int = 0, window: int = 50, z_reject: float = 4.0, min_calib: int = 5):
        from collections import deque

        self.pol_sum = np.zeros(max(n_edges, 1))
        self.pol_n = np.zeros(max(n_edges, 1))
        self.tex_ref = np.zeros(max(n_surface, 1))
        self.tex_n = np.zeros(max(n_surface, 1))
        self.hist = {k: deque(maxlen=window) for k in self.SIGNALS}
        self.z_reject, self.min_calib = z_reject, min_calib
        self.n_learned = 0

    def features(self, ev: PoseEvidence, klt_agree: float | None = None, n_klt: int = 0) -> dict:
        """The signal values of one frame (and the sample counts behind them)."""
        known = self.pol_n[ev.edge] >= 2
        p = np.where(known, self.pol_sum[ev.edge] / np.maximum(self.pol_n[ev.edge], 1), 0.0)
        checked = known & (np.abs(p) >= 0.5)  # a stable polarity
        pol_ok = ~checked | (ev.sign == np.sign(p))
        match = float((ev.oriented & (ev.sign != 0) & pol_ok).mean()) if ev.n else 0.0
        res = ev.residual_px
        tex, n_tex = float("nan"), 0
        if len(ev.tex_idx):
            seen = self.tex_n[ev.tex_idx] > 0
            n_tex = int(seen.sum())
            if n_tex >= 20:
                a, b = ev.tex_val[seen], self.tex_ref[ev.tex_idx[seen]]
                sa, sb = a.std(), b.std()
                if sb > 1e-6:  # no correlation with a structured reference = none (a flat shadow, a blank wall)
                    tex = float(((a - a.mean()) * (b - b.mean())).mean() / (sa * sb)) if sa > 1e-6 else 0.0
        return {"match": match, "found": ev.found, "residual": -res if np.isfinite(res) else -np.inf,
                "klt": float(klt_agree) if klt_agree is not None and n_klt > 0 else float("nan"),
                "texture": tex, "n": ev.n, "n_edges": int(len(np.unique(ev.edge))), "n_klt": n_klt, "n_tex": n_tex}

    def score(self, f: dict) -> tuple[float, str]:
        """``(score, worst signal)`` of a frame's features (score 1 with no history yet)."""
        worst, name = -np.inf, ""
        loose = 2.0 if self.n_learned < self.min_calib else 1.0
        for k in self.SIGNALS:
            v, h = f[k], self.hist[k]
            if not np.isfinite(v) and v != -np.inf:
                continue
            if not len(h):
                continue
            a = np.asarray(h, float)
            ref = float(np.median(a))
            spread = 1.4826 * float(np.median(np.abs(a - ref)))
            if k == "residual":
                floor = RESIDUAL_FLOOR_PX
            elif k == "texture":
                floor = max((1.0 - min(ref * ref, 1.0)) / np.sqrt(max(f["n_tex"], 1)), 0.02)
            else:
                n = f["n_klt"] / 10.0 if k == "klt" else f["n_edges"]
                floor = np.sqrt(max(ref * (1 - ref), 0.01) / max(n, 1))
            z = (ref - v) / (loose * max(spread, floor)) if np.isfinite(v) else np.inf
            if z > worst:
                worst, name = z, k
        if worst == -np.inf:
            return 1.0, ""
        return float(np.clip(1.0 - worst / self.z_reject, -1.0, 1.0)), name

    def learn(self, ev: PoseEvidence, f: dict) -> None:
        """Add an accepted frame: its signals and its edges' polarities."""
        for k in self.SIGNALS:
            if np.isfinite(f[k]):
                self.hist[k].append(f[k])
        s = ev.sign != 0
        np.add.at(self.pol_sum, ev.edge[s], ev.sign[s].astype(float))
        np.add.at(self.pol_n, ev.edge[s], 1.0)
        if len(ev.tex_idx):
            # appearance: running mean over the first 10 sightings, then an exponential one (slow light changes)
            i = ev.tex_idx
            w = 1.0 / np.minimum(self.tex_n[i] + 1.0, 10.0)
            self.tex_ref[i] += w * (ev.tex_val - self.tex_ref[i])
            self.tex_n[i] += 1.0
        self.n_learned += 1


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


def image_noise_sigma(gray: np.ndarray) -> float:
    """Gray-level noise std of an image (Immerkaer 1996: mean |Laplacian-difference| response)."""
    import cv2

    M = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(gray.astype(np.float32), -1, M)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) / 6.0 * np.abs(r).mean()) if r.size else 0.0


class EdgeTracker:
    """ViSP-style edge (+ optional KLT) tracker for one model and camera.

    ``track(gray, T_cam_model_init)`` refines the pose on a new 8-bit gray frame; the previous
    frame and pose (kept internally) give each sample's reference contrast and polarity.
    """

    def __init__(self, model, camera, cfg: TrackerConfig):
        from mst.pipeline.visibility import ModelGeometry

        self.geom = ModelGeometry.from_model(model)
        self.cam = camera
        self.K = camera.K
        self.cfg = cfg
        self.prev_img: np.ndarray | None = None
        self.prev_T: np.ndarray | None = None
        self.prev_faces: np.ndarray | None = None
        self.klt = None
        self.klt_pts: np.ndarray | None = None  # (M,2) px in prev frame
        self.klt_X: np.ndarray | None = None  # (M,3) model frame
        self.prev_gray: np.ndarray | None = None
        self.near_m: float | None = cfg.near_clip  # None: set from the scene depth at the first pose
        self.lod = lod_thresholds(cfg)
        self.health_score = True  #: compute the image evidence of each final pose (HealthMonitor)
        self.surf_X, self.surf_face = _surface_points(model)  # (M,3) model frame, (M,) face index
        self.sample_provider = None  # render-based edgelets (mst.pipeline.render_edges) instead of polygon edges

    # -------------------------------------------------------------- helpers
    def near(self, T_cam_model: np.ndarray) -> float:
        """Near clipping distance (m): the configured one, else :func:`scene_near_m` at the first
        pose seen (fixed from then on)."""
        if self.near_m is None:
            self.near_m = scene_near_m(self.geom.vertices, T_cam_model)
        return self.near_m

    def _samples(self, T, K, W, H):
        from mst.pipeline.visibility import visible_samples

        if self.sample_provider is not None:
            return self.sample_provider.samples(T, K, W, H)
        c = self.cfg
        lod_line, lod_face = self.lod
        s = K[0, 0] / self.K[0, 0]  # coarse pyramid levels: the thresholds scale with the image
        return visible_samples(self.geom, T, K, W, H, c.sample_step, self.near(T), c.far_clip, c.angle_appear,
                               c.angle_disappear, self.prev_faces, border_px=c.mask_size // 2 + 1,
                               hidden_lines=c.hidden_lines, zbuffer_scale=c.zbuffer_scale, max_samples=c.max_samples,
                               lod_min_line_px=lod_line * s, lod_min_face_px2=lod_face * s * s)

    def explain(self, S) -> str:
        """Why the samples ``S`` of a pose are too few (see :func:`visibility.explain_no_samples`)."""
        from mst.pipeline.visibility import explain_no_samples

        return explain_no_samples(S.stats, self.near_m or 0.0, self.cfg.far_clip, self.lod)

    def _edge_pass(self, img, K, T, search_range, ref_img, ref_T, klt=None, min_mad_px=None):
        from mst.pipeline.moving_edges import canonical_normals, reference_contrast, search_edges
        from mst.pipeline.vvs import solve_pose

        c = self.cfg
        H, W = img.shape
        S = self._samples(T, K, W, H)
        if len(S) < 6:
            self._fail = self.explain(S)
            return None, S, None, None
        normal, midx = canonical_normals(S.normal, c.n_masks)
        ref = None
        if ref_img is not None:
            Xc = S.X_model @ ref_T[:3, :3].T + ref_T[:3, 3]
            z = np.maximum(Xc[:, 2], 1e-9)
            uvp = np.stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]], 1)
            ref = reference_contrast(ref_img, uvp, normal, midx, c.mask_size, c.n_masks)
        m = search_edges(img, S.uv, normal, ref, search_range=int(search_range), threshold=c.edge_threshold,
                         mu1=c.mu1, mu2=c.mu2, size=c.mask_size, n_masks=c.n_masks, n_candidates=c.n_candidates,
                         mask_idx=midx, edge=S.edge)
        cand = m.candidates_uv(S.uv)
        kx, ku = (None, None) if klt is None else klt
        try:
            res = solve_pose(T, K, S.X_model, S.edge, S.A_model, S.B_model, cand, iters=c.vvs_iters, lm_mu=c.lm_mu,
                             min_mad_px=c.min_mad_px if min_mad_px is None else min_mad_px, tukey_c=c.tukey_c, klt_X_model=kx, klt_uv=ku,
                             klt_weight=c.klt_weight)
        except ValueError:
            n_m = int(np.isfinite(cand[..., 0]).any(axis=1).sum())
            self._fail = (f"pose solver failed: only {n_m} of {len(S)} edge samples found a moving edge within "
                          f"{int(search_range)} px (need 6; no image edge near the projected model)")
            return None, S, m, None
        if (min_mad_px is None and c.fine_mad_px < c.min_mad_px and res.sigma_px <= c.min_mad_px
                and np.isfinite(res.T_cam_model).all()):
            # the floor binds (the fit's own robust scale is below it): a fine stage from the
            # converged pose, same matches, a tighter floor. The coarse floor must admit the whole
            # inter-frame motion at the start (with the fine one from the start a translating
            # camera's samples were all rejected and it stood still). Real video (MAD above the
            # floor) skips it
            try:
                fine = solve_pose(res.T_cam_model, K, S.X_model, S.edge, S.A_model, S.B_model, cand, iters=c.vvs_iters,
                                  lm_mu=c.lm_mu, min_mad_px=c.fine_mad_px, tukey_c=c.tukey_c, klt_X_model=kx,
                                  klt_uv=ku, klt_weight=c.klt_weight)
                if np.isfinite(fine.T_cam_model).all() and np.isfinite(fine.W).all():
                    res = fine
            except ValueError:
                pass
        if not np.isfinite(res.T_cam_model).all() or not np.isfinite(res.W).all():
            self._fail = "pose solver failed: the optimisation diverged (non-finite pose)"
            return None, S, m, None
        return res, S, m, cand

    # -------------------------------------------------------------- KLT (ViSP hybrid tracker)
    def _klt_points(self, gray, T):
        """Detect KLT corners inside visible faces; their model points from the face plane."""
        import cv2

        c = self.cfg
        H, W = gray.shape
        fv = self.prev_faces if self.prev_faces is not None else np.ones(len(self.geom.faces), bool)
        from mst.pipeline.visibility import inverse_depth_buffer

        best, _ = inverse_depth_buffer(self.geom, T, self.K, W, H, fv, self.near(T), 1.0)  # 1/z of the front surface
        mask = (best > 0).astype(np.uint8) * 255
        mask = cv2.erode(mask, np.ones((2 * c.klt_border + 1,) * 2, np.uint8))
        ys, xs = np.nonzero(mask[::8, ::8])
        if not len(xs):
            return None, None
        x0, x1 = max(0, xs.min() * 8 - 8), min(W, xs.max() * 8 + 9)
        y0, y1 = max(0, ys.min() * 8 - 8), min(H, ys.max() * 8 + 9)
        pts = cv2.goodFeaturesToTrack(gray[y0:y1, x0:x1], c.klt_max_features, c.klt_quality, c.klt_min_distance,
                                      mask=np.ascontiguousarray(mask[y0:y1, x0:x1]), blockSize=c.klt_block,
                                      useHarrisDetector=False, k=c.klt_harris)
        if pts is None:
            return None, None
        pts = pts.reshape(-1, 2)
        # texture gate: goodFeaturesToTrack's quality is relative to the strongest corner, so on a
        # textureless face it returns noise. Keep a corner only when the weakest-direction RMS
        # gradient over the KLT window clearly exceeds what the image noise alone gives there
        # (Sobel derivative of noise sigma: std 0.43 sigma per axis; 3x that)
        roi = gray[y0:y1, x0:x1]
        win = 2 * c.klt_window + 1
        lam = cv2.cornerMinEigenVal(roi, win, 3)  # = 4 lambda_g / 255^2 (OpenCV's 8-bit scaling)
        ij = np.clip(np.rint(pts).astype(int), 0, [roi.shape[1] - 1, roi.shape[0] - 1])
        g_min = 127.5 * np.sqrt(np.maximum(lam[ij[:, 1], ij[:, 0]], 0))  # gray levels / px
        sigma = image_noise_sigma(roi)
        self._klt_gate = (g_min, sigma)
        pts = pts[g_min >= 3.0 * 0.43 * sigma]
        if not len(pts):
            return None, None
        pts = pts + [x0, y0]
        pts = pts.astype(np.float64)
        ix, iy = np.rint(pts[:, 0]).astype(int), np.rint(pts[:, 1]).astype(int)
        iz = best[iy, ix].astype(np.float64)
        ok = iz > 0
        pts, iz = pts[ok], iz[ok]
        xn = (pts - self.K[:2, 2]) / np.array([self.K[0, 0], self.K[1, 1]])
        Xc = np.column_stack([xn, np.ones(len(xn))]) / iz[:, None]
        X_model = (Xc - T[:3, 3]) @ T[:3, :3]
        return pts, X_model

    def _klt_track(self, gray):
        import cv2

        if self.klt_pts is None or len(self.klt_pts) < 4 or self.prev_gray is None:
            return None
        c = self.cfg
        p0 = self.klt_pts.astype(np.float32).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(self.prev_gray, gray, p0, None, winSize=(2 * c.klt_window + 1,) * 2,
                                             maxLevel=c.klt_pyramid)
        # forward-backward check: drops unstable tracks (noise, occlusion boundaries)
        p0r, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self.prev_gray, p1, None, winSize=(2 * c.klt_window + 1,) * 2,
                                               maxLevel=c.klt_pyramid)
        fb = np.linalg.norm((p0r - p0).reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb < 0.5)
        if ok.sum() < 4:
            return None
        return self.klt_X[ok], p1.reshape(-1, 2)[ok].astype(np.float64)

    # -------------------------------------------------------------- image evidence of a pose
    def evidence(self, gray: np.ndarray, T_cam_model: np.ndarray, S=None) -> PoseEvidence:
        """What ``gray`` (H, W) uint8 says about the pose ``T_cam_model``, without moving it.

        At the visible samples of the pose: the Sobel gradient at -1, 0, +1 px along the projected
        model normal (the strongest kept: its polarity, and whether it is at least the moving-edge
        contrast and within ``ORIENT_TOL_DEG`` of the normal), and the nearest moving edge within the
        search range (ViSP's oriented masks, no contrast reference).
        """
        from mst.pipeline.moving_edges import canonical_normals, search_edges

        c = self.cfg
        H, W = gray.shape
        if S is None:
            S = self._samples(T_cam_model, self.K, W, H)
        if len(S) == 0 or S.model_edge is None:
            z = np.zeros(0)
            return PoseEvidence(z.astype(np.int64), z.astype(np.int8), z.astype(bool), z)
        Xc = S.X_model @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
        z = np.maximum(Xc[:, 2], 1e-9)
        uv = np.stack([self.K[0, 0] * Xc[:, 0] / z + self.K[0, 2], self.K[1, 1] * Xc[:, 1] / z + self.K[1, 2]], 1)
        Ae = S.A_model @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
        Be = S.B_model @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
        f = np.array([self.K[0, 0], self.K[1, 1]])
        d = (Be[:, :2] / Be[:, 2:3] - Ae[:, :2] / Ae[:, 2:3]) * f
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        n = np.stack([-d[:, 1], d[:, 0]], 1)[S.edge]  # fixed by the model edge's direction A -> B
        g = np.stack([_sobel_at(gray, uv + k * n) for k in (-1.0, 0.0, 1.0)])  # (3, N, 2)
        proj = (g * n[None]).sum(2)
        j = np.argmax(np.abs(proj), axis=0)
        ii = np.arange(len(uv))
        pb, gb = proj[j, ii], g[j, ii]
        strong = np.abs(pb) >= 2.0 * c.edge_threshold
        oriented = np.abs(pb) >= np.cos(np.radians(ORIENT_TOL_DEG)) * np.linalg.norm(gb, axis=1)
        sign = np.where(strong, np.sign(pb), 0).astype(np.int8)
        # the moving-edge search (the costly part) on every 2nd sample beyond 200: a share and a
        # median over >= 100 samples, well within their binomial / quantisation floors
        sel = slice(None, None, 2) if len(uv) > 200 else slice(None)
        normal, midx = canonical_normals(n[sel], c.n_masks)
        m = search_edges(gray, uv[sel], normal, None, search_range=int(c.search_range), threshold=c.edge_threshold,
                         mu1=c.mu1, mu2=c.mu2, size=c.mask_size, n_masks=c.n_masks, n_candidates=c.n_candidates,
                         mask_idx=midx, edge=S.edge[sel])
        off = np.abs(m.offset)
        n_me = len(uv[sel])
        off = np.where(np.isfinite(off), off, np.inf).min(1) if off.ndim == 2 and off.shape[1] else np.full(n_me, np.inf)
        off = np.where(np.isfinite(off), off, np.nan)
        ti, tv = self._surface_values(gray, T_cam_model, S.face_visible)
        return PoseEvidence(S.model_edge[S.edge], sign, oriented & strong, off, ti, tv)

    def _surface_values(self, gray, T, face_visible):
        """Indices of the surface points seen at pose T (front faces, inside the image, not hidden)
        and the image's 3x3 mean gray level there."""
        if not len(self.surf_X) or face_visible is None:
            return np.zeros(0, np.int64), np.zeros(0)
        H, W = gray.shape
        idx = np.flatnonzero(face_visible[self.surf_face])
        Xc = self.surf_X[idx] @ T[:3, :3].T + T[:3, 3]
        ok = Xc[:, 2] > self.near(T)
        idx, Xc = idx[ok], Xc[ok]
        uv = Xc[:, :2] / Xc[:, 2:3] * [self.K[0, 0], self.K[1, 1]] + self.K[:2, 2]
        ix, iy = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        ok = (ix >= 1) & (iy >= 1) & (ix < W - 1) & (iy < H - 1)
        idx, ix, iy, iz = idx[ok], ix[ok], iy[ok], 1.0 / Xc[ok, 2]
        if not self.geom.convex and len(idx):
            from mst.pipeline.visibility import inverse_depth_buffer

            buf, sc = inverse_depth_buffer(self.geom, T, self.K, W, H, face_visible, self.near(T), 0.5)
            bx = np.clip(np.round((ix + 0.5) * sc - 0.5).astype(np.int64), 0, buf.shape[1] - 1)
            by = np.clip(np.round((iy + 0.5) * sc - 0.5).astype(np.int64), 0, buf.shape[0] - 1)
            vis = iz >= buf[by, bx] * (1.0 - 1e-2)
            idx, ix, iy = idx[vis], ix[vis], iy[vis]
        f = gray.ravel().astype(np.float32)
        b = iy * W + ix
        val = sum(f[b + dy * W + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9.0
        return idx, val.astype(np.float64)

    # -------------------------------------------------------------- main entry
    def track(self, gray: np.ndarray, T_init: np.ndarray, recover: bool = False, first: bool = False) -> FrameResult:
        """Refine ``T_init`` (T_cam_model) on ``gray`` (H, W) uint8; update the internal reference."""
        import cv2

        c = self.cfg
        img = gray  # uint8: the moving-edge gathers convert only the pixels they read
        H, W = img.shape
        T = T_init.copy()
        ref_img = None if (first or recover or self.prev_img is None) else self.prev_img
        ref_T = self.prev_T
        R = c.search_range * (c.recover_range_factor if recover else 1.0)
        klt = self._klt_track(gray) if c.use_klt and not (first or recover) else None
        # coarse-to-fine: a half-resolution pass first (always after a loss)
        levels = max(c.pyramid_levels, 2 if recover else 1)
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
        for ps in range(passes):
            rng = R if ps == 0 else max(3, int(round(R / 2 ** ps)))
            mad = max(c.min_mad_px, rng / 3.0) if (first or recover) and ps < passes - 1 else None
            if (first or recover) and ps > 0:
                ref_img, ref_T = img, T  # later passes: contrast/polarity reference from this frame at the refined pose
            res_p, S_p, _, _ = self._edge_pass(img, self.K, T, rng, ref_img, ref_T, klt if ps == passes - 1 else None,
                                               min_mad_px=mad)
            if res_p is None:
                break
            res, S = res_p, S_p
            T = res.T_cam_model
        if res is None:
            return FrameResult(None, False, 0 if S_p is None else len(S_p), 0, float("nan"), 90.0, None, None,
                               reason=self._fail)
        # health: projection error (gradient vs model normal) at the final pose, inlier ratio
        Xc = S.X_model @ T[:3, :3].T + T[:3, 3]
        ok_z = Xc[:, 2] > self.near(T) * 0.5
        z = np.where(ok_z, Xc[:, 2], 1.0)
        uv = np.stack([self.K[0, 0] * Xc[:, 0] / z + self.K[0, 2], self.K[1, 1] * Xc[:, 1] / z + self.K[1, 2]], 1)
        Ae = S.A_model @ T[:3, :3].T + T[:3, 3]
        Be = S.B_model @ T[:3, :3].T + T[:3, 3]
        pa = Ae[:, :2] / Ae[:, 2:3] * [self.K[0, 0], self.K[1, 1]] + self.K[:2, 2]
        pb = Be[:, :2] / Be[:, 2:3] * [self.K[0, 0], self.K[1, 1]] + self.K[:2, 2]
        d = pb - pa
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        n = np.stack([-d[:, 1], d[:, 0]], 1)[S.edge]
        g = _sobel_at(img, uv)
        gn = np.linalg.norm(g, axis=1)
        cosang = np.abs((g * n).sum(1)) / np.maximum(gn, 1e-9)
        ang = np.degrees(np.arccos(np.clip(cosang, 0, 1)))
        strong = gn >= 2.0 * c.edge_threshold  # Sobel of a step of `threshold` gray levels is 4x it
        support = float(strong.mean()) if len(strong) else 0.0
        proj_err = float(ang[strong].mean()) if strong.sum() >= 3 else 90.0
        n_s = len(S)
        n_in = int(res.inlier.sum())
        ratio = n_in / max(n_s, 1)
        # a recovery (after a loss) must be convincing: stricter projection error and inlier ratio
        max_pe = c.max_proj_error_deg * (0.6 if recover else 1.0)
        min_ratio = max(c.min_inlier_ratio, 0.5) if recover else c.min_inlier_ratio
        healthy = bool(n_s >= c.min_samples and ratio >= min_ratio and proj_err <= max_pe
                       and support >= c.min_support and np.isfinite(T).all() and ok_z.all())
        reason = "" if healthy else ("the solved pose puts the model behind the camera" if not ok_z.all()
                                     else self.explain(S) if n_s < c.min_samples else f"inliers {ratio:.0%}"
                                     if ratio < min_ratio else f"gradient support {support:.0%}"
                                     if support < c.min_support else f"projection error {proj_err:.1f} deg")
        if klt is not None and res.klt_inlier is not None:
            self._klt_next = (klt[0][res.klt_inlier], klt[1][res.klt_inlier])
        out = FrameResult(T, healthy, n_s, n_in, res.rms_px, proj_err, res.W, res.cov, uv, res.inlier,
                          S.edge_uv[np.unique(S.edge)], np.zeros((0, 2)) if klt is None else klt[1], reason, support)
        if self.health_score:
            out.evidence = self.evidence(img, T, S)  # the last pass's samples, re-projected at T
        if klt is not None and res.klt_inlier is not None:
            out.klt_agree, out.n_klt = float(np.mean(res.klt_inlier)), int(len(res.klt_inlier))
        return out

    def accept(self, gray: np.ndarray, T_cam_model: np.ndarray) -> None:
        """Make ``(gray, T_cam_model)`` the reference for the next frame (a good pose)."""
        from mst.pipeline.visibility import face_visibility

        c = self.cfg
        self.prev_img = gray
        self.prev_T = T_cam_model.copy()
        self.prev_faces = face_visibility(self.geom, T_cam_model, self.prev_faces, c.angle_appear, c.angle_disappear)
        if c.use_klt:
            nxt = getattr(self, "_klt_next", None)
            self._klt_next = None
            self._klt_age = getattr(self, "_klt_age", 0) + 1
            enough = nxt is not None and len(nxt[0]) >= max(20, 0.6 * getattr(self, "_klt_n0", 0))
            # re-detect when too few points survive (at most every 5 frames: textureless scenes) or every 30
            if nxt is not None and len(nxt[0]) >= 4 and (enough or self._klt_age < 5) and self._klt_age < 30:
                self.klt_X, self.klt_pts = nxt  # keep tracking the surviving points (ViSP keeps its KLT set)
            else:
                pts, X = self._klt_points(gray, T_cam_model)
                self.klt_pts, self.klt_X = pts, X
                self._klt_n0 = 0 if pts is None else len(pts)
                self._klt_age = 0
            self.prev_gray = gray


# ---------------------------------------------------------------------------- checks
def check_pose_in_view(model, T_cam_model: np.ndarray, cam, path, near: float = 1e-6) -> None:
    """Raise :class:`mst.InputError` when the pose puts the model behind the camera or out of view."""
    V = np.asarray(model.vertices)
    Xc = V @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
    cz = float(Xc[:, 2].mean())
    ext = float(np.ptp(V, axis=0).max()) if len(V) else 0.0
    units = (f"; the model spans {ext:.4g} units: is it in millimetres? mst expects metres" if ext > 50
             and (-T_cam_model[:3, :3].T @ T_cam_model[:3, 3] > V.min(0)).all()
             and (-T_cam_model[:3, :3].T @ T_cam_model[:3, 3] < V.max(0)).all() else "")
    if cz <= 0 or (Xc[:, 2] <= near).all():
        raise InputError(path, f"the pose puts the model behind the camera (model centre at z = {cz:.3g} m in the "
                               f"camera frame; expected a cMo / TUM camera pose looking at the model){units}")
    front = Xc[:, 2] > near
    uv = Xc[front, :2] / Xc[front, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    if cam.width and not inside.any():
        raise InputError(path, "the pose puts the whole model outside the image")


# ---------------------------------------------------------------------------- the stage
def _shift_px(tracker: EdgeTracker, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Largest image displacement (px) between two poses of up to ~200 model vertices in front of
    both cameras (all of them when fewer)."""
    V = tracker.geom.vertices
    V = V[:: max(1, len(V) // 200)]
    K = tracker.K
    uv = []
    for T in (T_a, T_b):
        Xc = V @ T[:3, :3].T + T[:3, 3]
        uv.append(Xc)
    ok = (uv[0][:, 2] > 0) & (uv[1][:, 2] > 0)
    if not ok.any():
        return float("inf")
    p = [X[ok, :2] / X[ok, 2:3] * [K[0, 0], K[1, 1]] for X in uv]
    return float(np.linalg.norm(p[0] - p[1], axis=1).max())


#: ``<stem>.cov.csv``: per frame the 6x6 covariance of the edge (VVS) pose, for frames whose output
#: pose is the edge pose (status ``model``; empty otherwise): the twist ``xi = (v, w)`` of the left
#: perturbation ``T_cam_model' = exp(xi) T_cam_model`` (v metres, w radians, camera frame),
#: ``sigma^2 (J^T W J)^-1``; and derived 1-sigma values: the camera position in the model frame
#: (``std_x_m .. std_z_m``, covariance ``R^T C_vv R``) and the rotation (``std_rot_deg``, the
#: square root of the largest eigenvalue of ``C_ww``).
COV_HEADER = (["frame", "status", "std_x_m", "std_y_m", "std_z_m", "std_rot_deg"]
              + [f"c{i}{j}" for i in range(6) for j in range(6)])


def _cov_row(idx: int, status: str, cov: np.ndarray | None, T_cam_model: np.ndarray | None) -> list:
    """One ``.cov.csv`` row (see :data:`COV_HEADER`)."""
    if status != "model" or cov is None or T_cam_model is None or not np.isfinite(cov).all():
        return [idx, status] + [""] * (len(COV_HEADER) - 2)
    R = T_cam_model[:3, :3]
    C_pos = R.T @ cov[:3, :3] @ R  # camera centre c = -R^T t moves by -R^T v
    std = np.sqrt(np.maximum(np.diag(C_pos), 0.0))
    rot = np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(0.5 * (cov[3:, 3:] + cov[3:, 3:].T)).max()), 0.0)))
    return [idx, status, *(f"{x:.6g}" for x in std), f"{rot:.6g}", *(f"{x:.6g}" for x in cov.ravel())]


def _mean_or_none(vals: list[float]) -> float | None:
    """Mean of the finite values (None when there is none: JSON has no NaN)."""
    a = np.asarray(vals, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else None


def _make_aid(mode: str, cam, config: TrackerConfig, depth_dir, depth_camera, T_depth_color, notes: list[str]):
    if mode == "off":
        return None, "off"
    if mode == "auto":
        # with depth: the rgbd aid always on; without: the mono aid on standby (see StandbyAid)
        mode = "rgbd" if depth_dir is not None else "standby"
    try:
        from mst.pipeline import slam
    except ImportError:
        notes.append(f"SLAM aid '{mode}' unavailable (mst.pipeline.slam not installed): edges only")
        return None, "off"
    # TrackerConfig has no slam section yet: the aid's defaults (H3's TrackConfig passes cfg.slam, cfg.depth)
    aid = slam.make_aid(mode, cam, {}, depth_dir, depth_camera, T_depth_color)
    return aid, "mono-standby" if mode == "standby" else mode


def run_track(frames_spec: str | os.PathLike, model_path: str | os.PathLike, camera_path: str | os.PathLike,
              init_pose_path: str | os.PathLike, out_traj: str | os.PathLike, config: TrackerConfig | None = None, *,
              frames: str | None = None, scale: float = 1.0, fps: float | None = None, overlay: str | None = None,
              slam: str = "off", depth_dir: str | os.PathLike | None = None, depth_camera_path=None,
              depth_to_color_path=None, landmarks_path: str | os.PathLike | None = None, write_json: bool = False, progress=None, notes: list[str] | None = None,
              klt: bool | None = None, health_score: bool = True, relocalise: bool = True,
              edges: str = "auto") -> dict:
    """Track a model through frames; write ``out_traj`` (TUM, tracked frames), ``.csv`` and ``.json``.

    ``slam``: ``'auto'`` = ``'rgbd'`` with ``depth_dir``, else edges + KLT with the mono aid on
    standby (:class:`mst.pipeline.slam.StandbyAid`); ``klt``: KLT points in the edge optimisation
    (None: on for that default, else ``config.use_klt``). ``health_score``: reject poses whose
    calibrated :class:`HealthMonitor` score is <= 0 (on top of the absolute tests). ``relocalise``:
    learn the object's keypoints and re-acquire a lost pose without clicks
    (:mod:`mst.pipeline.relocalise`, status ``relocalised``).
    ``init_pose_path``: the pose of the first selected frame (TUM line or 4x4 cMo). Returns the
    summary dict (also written as ``<stem>.json`` when ``write_json``). ``progress``: optional
    ``progress(total) -> context manager yielding advance()`` (called after the input checks). Raises :class:`mst.InputError` for bad input before
    anything is written.
    """
    import cv2

    from mst.core.camera import read_camera
    from mst.core.poses import inv_T, read_pose_file, read_rigid_transform
    from mst.pipeline.frames import check_camera_size, open_frames
    from mst.pipeline.settings import validate_config

    cfg = config or TrackerConfig()
    if klt is None and slam == "auto" and depth_dir is None:
        klt = True  # the default mode: edges + KLT (measured best on teabox.mp4, README tracking section)
    if klt is not None:
        cfg = cfg.updated(use_klt=bool(klt))
    validate_config(cfg)
    notes = notes if notes is not None else []
    model = load_polygon_model(model_path)
    cam0 = read_camera(camera_path)
    src = open_frames(frames_spec, frames, scale, fps)
    cam = check_camera_size(src, cam0, camera_path)
    undistort_maps = None
    if cam.has_distortion:
        # frames are undistorted once (remap tables), then tracked with the pinhole model K
        d = np.zeros(5)
        d[: min(5, len(cam.dist))] = cam.dist[:5]
        undistort_maps = cv2.initUndistortRectifyMap(cam.K, d, None, cam.K, (cam.width, cam.height), cv2.CV_16SC2)
        notes.append("frames undistorted with the camera's distortion coefficients before tracking")
    T0 = read_pose_file(init_pose_path)
    if scale != 1.0:
        pass  # poses are metric; only the intrinsics scale
    check_pose_in_view(model, T0, cam, init_pose_path)
    depth_camera = read_camera(depth_camera_path) if depth_camera_path else None
    T_depth_color = read_rigid_transform(depth_to_color_path, "depth-to-colour file") if depth_to_color_path else None
    if depth_dir is not None and not Path(depth_dir).is_dir():
        raise InputError(depth_dir, "depth folder does not exist")
    if slam == "rgbd" and depth_dir is None:
        raise InputError(None, "--slam rgbd needs --depth DIR")
    if landmarks_path is not None and slam == "off":
        raise InputError(landmarks_path, "--landmarks needs a SLAM aid (--slam mono or rgbd)")
    if slam in ("off", "mono") and depth_dir is not None:
        notes.append(f"--depth is not used with --slam {slam}")
    aid, aid_mode = _make_aid(slam, cam, cfg, Path(depth_dir) if depth_dir else None, depth_camera, T_depth_color, notes)

    tracker = EdgeTracker(model, cam, cfg)
    from mst.pipeline.render_edges import attach_render_edges

    edges_used = attach_render_edges(tracker, model, model_path, edges, T0, notes)  # --edges auto|polygon|render
    out_traj = Path(out_traj)
    csv_path = out_traj.with_suffix(".csv")
    cov_path = out_traj.with_suffix(".cov.csv")
    cov_rows: list[list] = []
    json_path = out_traj.with_suffix(".json") if write_json else None
    rows, times, poses = [], [], []
    ov = OverlayWriter(Path(overlay), src.fps or 30.0) if overlay else None
    T_prev = T0
    T_prev2 = None
    first_reason = ""
    lost_streak = 0
    first = True
    prev_status = "model"
    support_ref: float | None = None  # running mean of the gradient support of model frames
    tracker.health_score = health_score
    reloc = None
    if relocalise:
        from mst.pipeline.relocalise import Relocaliser

        reloc = Relocaliser(tracker)
    monitor = HealthMonitor(len(tracker.geom.edges), len(tracker.surf_X)) if health_score else None
    n_score_rejects = 0
    T_hint = None

    def judge(fr: FrameResult, first_frame: bool) -> FrameResult:
        """The calibrated health score on top of the tracker's absolute tests."""
        nonlocal n_score_rejects
        if monitor is None or fr.evidence is None:
            return fr
        fr._feat = monitor.features(fr.evidence, fr.klt_agree, fr.n_klt)
        fr.score, worst = monitor.score(fr._feat)
        if fr.healthy and not first_frame and fr.score <= 0:
            fr.healthy = False
            fr.reason = f"health score {fr.score:.2f} ({worst})"
            n_score_rejects += 1
        return fr
    t_frames = []
    import contextlib

    bar = progress(len(src)) if progress is not None else contextlib.nullcontext(lambda n=1: None)
    try:
        with bar as advance:
            for idx, t_s, bgr in src:
                if undistort_maps is not None:
                    bgr = cv2.remap(bgr, *undistort_maps, cv2.INTER_LINEAR)
                gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
                t0 = time.perf_counter()
                T_pred = aid.predict(idx, gray, T_prev) if aid is not None else None
                if T_pred is None and cfg.constant_velocity and T_prev2 is not None and lost_streak == 0:
                    T_pred = (T_prev @ inv_T(T_prev2)) @ T_prev  # constant velocity (camera-frame motion)
                T_start = T_pred if T_pred is not None else (T_hint if T_hint is not None else T_prev)
                T_hint = None
                if (aid is not None and T_pred is not None and prev_status == "model" and lost_streak == 0
                        and not first and _shift_px(tracker, T_pred, T_prev) < 0.5 * cfg.search_range):
                    # slow motion: the edges' own last pose is inside the search range already; the
                    # SLAM pose (its map triangulated from earlier edge poses) would only pass its
                    # error on along the edges' weakly observed direction (250 m flyover: 2.5-3.9 m
                    # predictions, the edges followed). The aid predicts where the motion is large
                    T_start = T_prev
                # re-acquisition: the model comes back after a SLAM-only stretch (or after a loss).
                # The SLAM prediction has drifted (mono: ~1 deg = several pixels), the previous image
                # holds no model edges to take contrasts from: widened coarse-to-fine search, and the
                # pose must look like a full fit (gradient support near its usual value), since a
                # pose locked onto floor/texture edges passes the absolute tests
                reacq = aid is not None and prev_status == "slam" and lost_streak == 0 and not first
                fr = judge(tracker.track(gray, T_start, recover=lost_streak > 0, first=first), first)
                if aid is not None and getattr(aid, "standby", False) and not first and aid.needs_wake(fr.healthy, fr.W):
                    # the default aid wakes on a weak or unhealthy edge pose: its prediction may
                    # rescue this frame (fast motion), else the edge pose goes to its gate as usual
                    T_wake = aid.wake(idx, gray, T_prev)
                    if T_wake is not None and not fr.healthy:
                        fr_s = judge(tracker.track(gray, T_wake, recover=lost_streak > 0), False)
                        if fr_s.healthy:
                            fr = fr_s
                if reacq:
                    # also the widened search; keep the better fit (healthy, then gradient support)
                    fr_w = judge(tracker.track(gray, T_start, recover=True), False)
                    if (fr_w.healthy, fr_w.support) > (fr.healthy, fr.support):
                        fr = fr_w
                        tracker._klt_next = None  # the KLT inliers were those of the discarded fit
                relocalised = False
                if (reloc is not None and lost_streak > 0 and not fr.healthy
                        and (lost_streak - 1) % reloc.cfg.every == 0):
                    # lost: search the learned keypoints, refine with the edges, accept only if healthy
                    T_r = reloc.relocalise(gray)
                    if T_r is not None:
                        fr_r = judge(tracker.track(gray, T_r, first=True), False)  # no contrast reference, no coarse pass
                        if fr_r.healthy:
                            fr, relocalised = fr_r, True
                            tracker._klt_next = None
                healthy = fr.healthy
                # the same guard after a loss (edges only, or the aid lost too): a pose found by the
                # widened search on its first frame back has too little history for the health score
                # (few edges in view: wide binomial floors) and can lock onto texture edges
                recovering = reacq or lost_streak > 0
                if healthy and recovering and support_ref is not None and fr.support < REACQUIRE_SUPPORT_RATIO * support_ref:
                    healthy = False
                    fr.reason = f"gradient support {fr.support:.0%} (usual {support_ref:.0%})"
                if aid is not None:
                    # an edge pose refused only by the health score still says where the image
                    # puts the object: the aid outputs no map pose that contradicts it
                    weak = (fr.T_cam_model if not healthy and fr.T_cam_model is not None
                            and (fr.reason or "").startswith("health score") else None)
                    T_out, status = aid.update(idx, gray, fr.T_cam_model, fr.W, healthy, weak_edge_pose=weak)
                else:
                    T_out, status = (fr.T_cam_model, "model") if healthy else (None, "lost")
                if status == "model" and not recovering:
                    support_ref = fr.support if support_ref is None else 0.9 * support_ref + 0.1 * fr.support
                if relocalised and status == "model":
                    status = "relocalised"
                    if aid is not None and getattr(aid, "standby", None) is False:
                        aid.close()  # the default's map belongs to the lost stretch: back to standby
                prev_status = status
                if monitor is not None and status in ("model", "relocalised") and healthy and fr.evidence is not None:
                    monitor.learn(fr.evidence, fr._feat)
                if (reloc is not None and status == "model" and healthy and (first or fr.score >= 0.5)
                        and reloc.should_learn(idx, fr.T_cam_model)):
                    reloc.learn(idx, gray, fr.T_cam_model)
                if T_out is not None and status != "lost":
                    tracker.accept(gray, T_out)
                    T_prev2 = T_prev if lost_streak == 0 and not first else None
                    T_prev = T_out
                    lost_streak = 0
                else:
                    lost_streak += 1
                    T_out, status = None, "lost"
                    if fr.healthy and fr.T_cam_model is not None:
                        # a healthy edge pose the aid refused (it contradicts the map): not output,
                        # but where the object is; the next frame starts there
                        T_hint = fr.T_cam_model
                if first:
                    first_reason = fr.reason
                first = False
                ms = (time.perf_counter() - t0) * 1000.0
                t_frames.append(ms)
                aid_state = "" if aid is None else ("standby" if getattr(aid, "standby", False) else "on")
                fired = getattr(aid, "static_world_fired", None) if aid is not None else None
                if fired and fired[-1] == idx:
                    aid_state = "static-world-broken"  # the map's world moved against the object here
                rows.append([idx, f"{t_s:.6f}", status, fr.n_samples, fr.n_inliers,
                             f"{fr.residual_px:.4f}" if np.isfinite(fr.residual_px) else "nan",
                             f"{fr.proj_error_deg:.3f}", f"{ms:.3f}",
                             f"{fr.score:.3f}" if np.isfinite(fr.score) else "nan", aid_state,
                             "" if status in ("model", "relocalised") else (fr.reason or "edge pose not used")])
                cov_rows.append(_cov_row(idx, status, fr.cov, T_out))
                if T_out is not None:
                    times.append(t_s)
                    poses.append(inv_T(T_out))
                if ov is not None:
                    ov.write(draw_overlay(bgr, fr, status), idx)
                advance()
    except BaseException:
        if ov is not None:
            ov.close(commit=False)
        raise
    finally:
        landmarks = aid.landmarks() if aid is not None and landmarks_path is not None else None
        if aid is not None and hasattr(aid, "close"):
            aid.close()
    n = len(rows)
    n_tr = len(poses)
    if n_tr == 0:
        if ov is not None:
            ov.close(commit=False)
        reason = first_reason or "lost"
        if "far clipping plane" in reason:
            # the setting is to blame, not the pose
            raise InputError(cfg.source, f"no frame could be tracked: frame {rows[0][0]}: {reason}; raise or remove "
                                         "<far_clipping> (default: no far plane)")
        hint = ("the model is too far or too small for this camera" if "too small" in reason
                else "check the pose, the camera and the model units")
        raise InputError(init_pose_path, f"no frame could be tracked from this initial pose (frame {rows[0][0]}: "
                                         f"{reason}); {hint}")
    statuses = [r[2] for r in rows]
    scores = np.array([float(r[8]) for r in rows])
    scores = scores[np.isfinite(scores)]
    summary = {
        "frames": n, "tracked": n_tr, "frames_tracked": n_tr, "lost": statuses.count("lost"), "model": statuses.count("model"),
        "slam": statuses.count("slam"), "first_lost_frame": next((r[0] for r in rows if r[2] == "lost"), None),
        "median_ms": float(np.median(t_frames)) if t_frames else None,
        "p95_ms": float(np.percentile(t_frames, 95)) if t_frames else None,
        "mean_residual_px": _mean_or_none([float(r[5]) for r in rows]),
        "mean_proj_error_deg": float(np.mean([float(r[6]) for r in rows])) if rows else None,
        "status_counts": {k: statuses.count(k) for k in ("model", "slam", "relocalised", "lost")},
        "health_score_rejects": n_score_rejects,
        "health_score_median": float(np.median(scores)) if len(scores) else None,
        "health_score_min": float(scores.min()) if len(scores) else None,
        "aid": aid_mode, "edges": edges_used, "traj": str(out_traj), "csv": str(csv_path), "cov_csv": str(cov_path), "notes": notes,
        "camera": cam.to_dict(), "config": config_to_dict(cfg),
    }
    from mst.core.poses import format_tum

    if tracker.sample_provider is not None:
        summary["render_edges"] = tracker.sample_provider.stats()
    if landmarks is not None:
        summary["landmarks"] = int(len(landmarks))
    if reloc is not None:
        st = reloc.stats
        summary["relocalisation"] = {"keyframes": st["keyframes"], "attempts": st["attempts"], "pnp_poses": st["pnp_poses"],
                                     "ms_per_attempt": st["ms_attempts"] / st["attempts"] if st["attempts"] else None,
                                     "ms_learn_total": st["ms_learn"]}
    fired = getattr(aid, "static_world_fired", None) if aid is not None else None
    if fired is not None:
        summary["static_world_frames"] = [int(f) for f in fired]
    if aid is not None and "wakes" in getattr(aid, "stats", {}):
        # the default aid: how often (and where) the mono SLAM was switched on, its replay cost
        summary["aid_wakes"] = int(aid.stats["wakes"])
        summary["aid_wake_frames"] = list(aid.stats["wake_frames"])
        summary["aid_active_frames"] = int(aid.stats["frames_active"])
        summary["aid_wake_ms"] = float(aid.timing_ms["wake"])
    with atomic_outputs(out_traj, csv_path, cov_path, json_path, landmarks_path) as (tmp_traj, tmp_csv, tmp_cov, tmp_json,
                                                                                  tmp_lm):
        if tmp_lm is not None:
            from mst.pipeline.fusion import write_ply

            write_ply(tmp_lm, landmarks, comments=["mst track SLAM landmarks, model frame, metres"])
        tmp_traj.write_text("# mst track: TUM 't tx ty tz qx qy qz qw' camera pose in model frame, tracked frames only\n"
                            + (format_tum(np.array(times), np.array(poses)) if poses else ""))
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", "time", "status", "samples", "inliers", "residual_px", "health", "ms", "score", "aid",
                    "reason"])
        w.writerows(rows)
        tmp_csv.write_text(buf.getvalue())
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COV_HEADER)
        w.writerows(cov_rows)
        tmp_cov.write_text(buf.getvalue())
        if tmp_json is not None:
            import json

            tmp_json.write_text(json.dumps(summary, indent=2, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)) + "\n")
        if ov is not None:
            ov.close(commit=True)
    return summary
