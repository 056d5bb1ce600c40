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
from mst.pipeline.settings import NEAR_CLIP_REL, TrackerConfig, config_to_dict, lod_thresholds

#: on re-acquisition (the model back after a SLAM-only stretch) an edge pose is healthy only when its
#: gradient support is at least this fraction of its running mean over the model frames (measured
#: on the synthetic corridor at 640x480: correct poses 0.90-0.96 against a usual 0.93, poses locked
#: onto floor/texture edges 0.52-0.66; the real teabox: 0.66-0.73)
REACQUIRE_SUPPORT_RATIO = 0.8


# ---------------------------------------------------------------------------- model loading
def load_polygon_model(path: str | os.PathLike):
    """Load a polygon model with :func:`mst.meshtools.io.load_model` (fallback: a small .cao/.obj reader)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "model file does not exist")
    try:
        from mst.meshtools.io import load_model
    except ImportError:
        load_model = _fallback_load_model
    model = load_model(p)
    if not len(model.faces) and not len(getattr(model, "lines", [])):
        raise InputError(p, "model has no faces")
    model.check_finite(str(p))
    return model


def _fallback_load_model(p: Path):
    from mst.meshtools.model import PolygonModel

    text = p.read_text(errors="replace")
    if p.suffix.lower() == ".obj":
        V, F = [], []
        for line in text.splitlines():
            s = line.split()
            if not s:
                continue
            if s[0] == "v":
                V.append([float(x) for x in s[1:4]])
            elif s[0] == "f":
                F.append([int(x.split("/")[0]) - 1 for x in s[1:]])
        return PolygonModel(np.array(V), F)
    if p.suffix.lower() != ".cao":
        raise InputError(p, "model format not readable without mst.meshtools.io (use .cao or .obj)")
    toks = []
    for line in text.splitlines():
        s = line.split("#", 1)[0].strip()
        if s and not s.startswith("V1") and not s.startswith("load("):
            toks.extend(s.split())
    it = iter(toks)
    try:
        nv = int(next(it))
        V = [[float(next(it)) for _ in range(3)] for _ in range(nv)]
        nl = int(next(it))
        lines = [[int(next(it)), int(next(it))] for _ in range(nl)]
        nfl = int(next(it))
        faces = []
        for _ in range(nfl):
            k = int(next(it))
            ids = [int(next(it)) for _ in range(k)]
            faces.append([lines[i][0] for i in ids])
        nfp = int(next(it))
        for _ in range(nfp):
            k = int(next(it))
            faces.append([int(next(it)) for _ in range(k)])
    except (StopIteration, ValueError, IndexError):
        raise InputError(p, "could not parse the .cao model") from None
    return PolygonModel(np.array(V), faces)


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

    # -------------------------------------------------------------- helpers
    def near(self, T_cam_model: np.ndarray) -> float:
        """Near clipping distance (m): the configured one, else ``NEAR_CLIP_REL`` x the median depth
        of the model vertices in front of the camera at the first pose seen (fixed from then on)."""
        if self.near_m is None:
            z = self.geom.vertices @ T_cam_model[2, :3] + T_cam_model[2, 3]
            z = z[z > 0]
            self.near_m = float(NEAR_CLIP_REL * np.median(z)) if len(z) else 1e-3
            self.near_m = max(self.near_m, 1e-6)
        return self.near_m

    def _samples(self, T, K, W, H):
        from mst.pipeline.visibility import visible_samples

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
        pts = pts.reshape(-1, 2) + [x0, y0]
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
    if cz <= 0 or (Xc[:, 2] <= near).all():
        raise InputError(path, f"the pose puts the model behind the camera (model centre at z = {cz:.3g} m in the "
                               "camera frame; expected a cMo / TUM camera pose looking at the model)")
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
        mode = "rgbd" if depth_dir is not None else "mono"
    try:
        from mst.pipeline import slam
    except ImportError:
        notes.append(f"SLAM aid '{mode}' unavailable (mst.pipeline.slam not installed): edges only")
        return None, "off"
    aid = slam.make_aid(mode, cam, config_to_dict(config), depth_dir, depth_camera, T_depth_color)
    return aid, mode


def run_track(frames_spec: str | os.PathLike, model_path: str | os.PathLike, camera_path: str | os.PathLike,
              init_pose_path: str | os.PathLike, out_traj: str | os.PathLike, config: TrackerConfig | None = None, *,
              frames: str | None = None, scale: float = 1.0, fps: float | None = None, overlay: str | None = None,
              slam: str = "off", depth_dir: str | os.PathLike | None = None, depth_camera_path=None,
              depth_to_color_path=None, landmarks_path: str | os.PathLike | None = None, write_json: bool = False, progress=None, notes: list[str] | None = None) -> dict:
    """Track a model through frames; write ``out_traj`` (TUM, tracked frames), ``.csv`` and ``.json``.

    ``init_pose_path``: the pose of the first selected frame (TUM line or 4x4 cMo). Returns the
    summary dict (also written as ``<stem>.json`` when ``write_json``). ``progress``: optional
    ``progress(total) -> context manager yielding advance()`` (called after the input checks). Raises :class:`mst.InputError` for bad input before
    anything is written.
    """
    import cv2

    from mst.pipeline.camera import read_camera
    from mst.pipeline.frames import check_camera_size, open_frames
    from mst.pipeline.poses import inv_T, read_pose_file, read_rigid_transform
    from mst.pipeline.settings import validate_config

    cfg = config or TrackerConfig()
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
                T_start = T_pred if T_pred is not None else T_prev
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
                fr = tracker.track(gray, T_start, recover=lost_streak > 0, first=first)
                if reacq:
                    # also the widened search; keep the better fit (healthy, then gradient support)
                    fr_w = tracker.track(gray, T_start, recover=True)
                    if (fr_w.healthy, fr_w.support) > (fr.healthy, fr.support):
                        fr = fr_w
                        tracker._klt_next = None  # the KLT inliers were those of the discarded fit
                healthy = fr.healthy
                if healthy and reacq and support_ref is not None and fr.support < REACQUIRE_SUPPORT_RATIO * support_ref:
                    healthy = False
                    fr.reason = f"gradient support {fr.support:.0%} (usual {support_ref:.0%})"
                if aid is not None:
                    T_out, status = aid.update(idx, gray, fr.T_cam_model, fr.W, healthy)
                else:
                    T_out, status = (fr.T_cam_model, "model") if healthy else (None, "lost")
                if status == "model" and not reacq:
                    support_ref = fr.support if support_ref is None else 0.9 * support_ref + 0.1 * fr.support
                prev_status = status
                if T_out is not None and status != "lost":
                    tracker.accept(gray, T_out)
                    T_prev2 = T_prev if lost_streak == 0 and not first else None
                    T_prev = T_out
                    lost_streak = 0
                else:
                    lost_streak += 1
                    T_out, status = None, "lost"
                if first:
                    first_reason = fr.reason
                first = False
                ms = (time.perf_counter() - t0) * 1000.0
                t_frames.append(ms)
                rows.append([idx, f"{t_s:.6f}", status, fr.n_samples, fr.n_inliers,
                             f"{fr.residual_px:.4f}" if np.isfinite(fr.residual_px) else "nan",
                             f"{fr.proj_error_deg:.3f}", f"{ms:.3f}"])
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
    summary = {
        "frames": n, "tracked": n_tr, "frames_tracked": n_tr, "lost": statuses.count("lost"), "model": statuses.count("model"),
        "slam": statuses.count("slam"), "first_lost_frame": next((r[0] for r in rows if r[2] == "lost"), None),
        "median_ms": float(np.median(t_frames)) if t_frames else None,
        "p95_ms": float(np.percentile(t_frames, 95)) if t_frames else None,
        "mean_residual_px": _mean_or_none([float(r[5]) for r in rows]),
        "mean_proj_error_deg": float(np.mean([float(r[6]) for r in rows])) if rows else None,
        "aid": aid_mode, "traj": str(out_traj), "csv": str(csv_path), "cov_csv": str(cov_path), "notes": notes,
        "camera": cam.to_dict(), "config": config_to_dict(cfg),
    }
    from mst.pipeline.poses import format_tum

    if landmarks is not None:
        summary["landmarks"] = int(len(landmarks))
    with atomic_outputs(out_traj, csv_path, cov_path, json_path, landmarks_path) as (tmp_traj, tmp_csv, tmp_cov, tmp_json,
                                                                                  tmp_lm):
        if tmp_lm is not None:
            from mst.pipeline.fusion import write_ply

            write_ply(tmp_lm, landmarks, comments=["mst track SLAM landmarks, model frame, metres"])
        tmp_traj.write_text("# mst track: TUM 't tx ty tz qx qy qz qw' camera pose in model frame, tracked frames only\n"
                            + (format_tum(np.array(times), np.array(poses)) if poses else ""))
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", "time", "status", "samples", "inliers", "residual_px", "health", "ms"])
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
