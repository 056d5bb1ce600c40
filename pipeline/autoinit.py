"""Automatic initial pose: search around a GPS/AHRS guess on an edge distance transform (``mst init --from-nav``).

Frames: ``T_cam_model`` (model -> camera, camera x right, y down, z forward), metres, degrees.

1. Image edges: the straight line segments (LSD) at least ``min_line_px`` long (a model's edges are
   long straight lines; ground, grass or gravel texture gives short curved edges -- with every Canny
   edge, on the textured ground of the sample house a random pose of the search box scored better
   than the true one), in ``orient_bins`` bins of their normal's orientation; one distance transform
   ``D`` per bin (px), capped at ``dt_max_px``.
2. Score of a pose: the mean of ``min(D_bin, dt_max) / dt_max`` at the model's visible edge samples
   (:func:`mst.pipeline.tracking.visibility.visible_samples`, hidden lines removed), each read in
   the bin of its projected normal; samples short of ``n_ref`` (the typical visible count in the
   box) count as misses, so a pose showing a small part of the model cannot win by chance; 1 when
   fewer than ``min_samples`` are visible. 0 = every projected edge on an image edge.
3. Coarse: ``n_coarse`` quasi-random (Halton) positions and rolls in the box position
   +- n_sigma * pos_sigma (model axes), roll +- n_sigma * att_sigma, plus the guess; each pose is
   moved by its best image similarity (scale +-``coarse_scale_step``, roll +-``coarse_roll_step_deg``)
   and image shift on a grid (``coarse_shift_px``) spanning the attitude box -- the camera's pitch
   and yaw move the image nearly rigidly, so they are searched exhaustively in 2-D (numba kernel,
   on distance transforms eroded by half a grid step, then refined on the plain ones) instead of
   sampled in 3-D: the basin of the true pose in a +-9/9/15 m, +-9 deg box is ~1e-4 of its volume.
   Fine: the ``n_keep`` best, each refined by a shrinking random search over position and roll,
   every candidate again at its best shift. Every kept candidate is then refined by the edge
   tracker (its moving-edge threshold lowered to ``refine_edge_threshold``: a grey wall against grey
   ground is evidence too; kept when healthy, with >= ``min_inlier_ratio`` inliers, inside the box)
   and re-scored, the score scaled by (most samples of any candidate) / (its samples); the best
   refined one is polished by the tracker until it stops moving.
4. Refusal (no pose written), calibrated on the frame: the best score is above ``max_null_ratio``
   times the frame's null score -- the median over the coarse candidates of their best scores,
   nearly all of them wrong poses: what a wrong pose reaches on this frame's texture (a blank frame:
   1 everywhere) --, no candidate's refinement is healthy and inside the search box, or a *distinct*
   refined candidate (its projected samples more than ``distinct_px`` = 1 px away on average:
   candidates of one pose agree to ~0.1 px) scores within ``min_margin`` (+0.02) of the best
   (ambiguous: e.g. a repetitive facade, or a pose a few % off along a direction the image barely
   fixes), or fewer than ``min_agree`` refined candidates land on the best pose (within
   ``dt_max_px``; a lone basin: generic scene lines such as
   a room's corner matched by a pose with most of the model out of view). The tracker's inlier
   share does not separate right from wrong (sample house at its true pose: 50-55 %, the moving
   edges find no contrast along the wall's foot; wrong L-building poses: up to 90 %).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mst import InputError
from mst.core.aot import Kernels
from mst.core.config import Config, param
from mst.core.poses import inv_T, so3_exp, so3_log, transform_points

#: the search kernels (:mod:`mst.pipeline.autoinit_kernels`): ahead of time when built, else numba's JIT
_AK = Kernels("mst.pipeline.autoinit_kernels")


@dataclass
class AutoInitConfig(Config):
    """Search box, scoring and refusal thresholds of :func:`auto_init` (scores: mean edge distance
    / ``dt_max_px``, 0 = every sample on an image edge, 1 = none within ``dt_max_px``)."""

    pos_sigma_m: tuple[float, float, float] = param((3.0, 3.0, 5.0), min=0, help="position uncertainty of the guess, m")
    att_sigma_deg: float = param(3.0, min=0, help="attitude uncertainty of the guess, deg")
    n_sigma: float = param(3.0, min=0, min_open=True, help="search box half-size, sigmas")
    n_coarse: int = param(500, min=1, help="coarse candidates scored")
    n_keep: int = param(6, min=1, help="best candidates refined")
    coarse_scale_step: float = param(0.1, min=0, max=0.5, help="image scale step of the coarse similarity search")
    coarse_roll_step_deg: float = param(4.0, min=0, help="roll step of the coarse similarity search, deg")
    coarse_shift_px: float = param(8.0, min=0, min_open=True, help="image shift grid step of the coarse search, px")
    shift_samples: int = param(100, min=1, help="edge samples per pose in the image shift search")
    refine_iters: int = param(7, min=0, help="refinement iterations per candidate")
    refine_samples: int = param(8, min=1, help="samples per refinement iteration")
    dt_max_px: float = param(20.0, min=0, min_open=True, help="edge distance transform cap, px")
    sample_step_px: float = param(5.0, min=0, min_open=True, help="model edge sampling step, px")
    min_line_px: float = param(15.0, min=0, help="image edges: straight segments (LSD) at least this long, px (0: every Canny edge)")
    blur_sigma_px: float = param(1.5, min=0, help="Gaussian blur before Canny, px (0: none)")
    canny_low: float = param(10.0, min=0, help="Canny low threshold, Sobel units (4 x grey-level step)")
    canny_high: float = param(30.0, min=0, help="Canny high threshold, Sobel units (4 x grey-level step)")
    orient_bins: int = param(8, min=1, max=16, help="edge orientation bins of the chamfer score (1: orientation ignored)")
    min_samples: int = param(30, min=1, help="visible edge samples a candidate needs")
    max_null_ratio: float = param(0.6, min=0, min_open=True,
                                  help="refuse a best score above this x the frame's null score (median of the coarse candidates')")
    min_margin: float = param(0.15, min=0, help="second best must score >= best * (1 + min_margin) + 0.02")
    distinct_px: float = param(1.0, min=0, min_open=True,
                               help="a refined candidate whose projection lies more than this from the best's (mean, px) "
                                    "is a distinct pose for min_margin")
    refine_edge_threshold: float = param(10.0, min=0, min_open=True,
                                         help="moving-edge contrast threshold of the tracker's refinement (at most the tracker's own)")
    min_agree: int = param(2, min=1, help="refined candidates (of n_keep) that must land on the best pose")
    min_inlier_ratio: float = param(0.4, min=0, max=1,
                                    help="of the tracker's refinement (robust VVS inliers / samples)")
    seed: int = param(0, help="seed of the candidate sampling")


@dataclass
class AutoInitResult:
    """Best pose and the evidence for it (``ok`` False: refused, ``reason`` says why)."""

    ok: bool
    T_cam_model: np.ndarray | None
    score: float
    second_score: float | None
    guess_score: float
    evaluated: int
    reason: str = ""
    tracker: dict = field(default_factory=dict)
    #: the frame's null score: median over the search box of the candidates' best scores (mostly wrong poses)
    null_score: float | None = None

    def to_json(self) -> dict:
        return {"ok": self.ok, "reason": self.reason, "score": self.score, "second_score": self.second_score,
                "null_score": self.null_score,
                "guess_score": self.guess_score, "evaluated": self.evaluated, "tracker": self.tracker,
                "T_cam_model": None if self.T_cam_model is None else self.T_cam_model.tolist()}


def _halton(n: int, d: int, skip: int = 1) -> np.ndarray:
    """(n, d) Halton points in [0, 1)."""
    primes = [2, 3, 5, 7, 11, 13, 17, 19][:d]
    idx = np.arange(skip, skip + n)
    out = np.zeros((n, d))
    for j, b in enumerate(primes):
        f, i, r = 1.0, idx.copy(), np.zeros(n)
        while (i > 0).any():
            f /= b
            r += f * (i % b)
            i //= b
        out[:, j] = r
    return out


def _perturb(T_model_cam0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Camera poses (N, 4, 4) T_model_cam: position + d[:, :3] (m), rotation exp(d[:, 3:] deg) R."""
    T = np.tile(T_model_cam0, (len(d), 1, 1))
    T[:, :3, 3] += d[:, :3]
    T[:, :3, :3] = so3_exp(np.radians(d[:, 3:])) @ T_model_cam0[:3, :3]
    return T


def _edge_pixels(gray: np.ndarray, cfg: AutoInitConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image edge pixels ``(row, col, normal orientation mod pi rad)``: with ``min_line_px`` > 0 those
    of the straight line segments (LSD) at least that long -- a model's edges are long straight lines,
    ground or foliage texture gives short curved ones --, else every Canny edge pixel."""
    import cv2

    H, W = gray.shape[:2]
    if cfg.min_line_px > 0:
        L = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(gray)[0]
        L = np.zeros((0, 4)) if L is None else L.reshape(-1, 4).astype(np.float64)
        d = L[:, 2:] - L[:, :2]
        ln = np.hypot(d[:, 0], d[:, 1])
        L, d, ln = L[ln >= cfg.min_line_px], d[ln >= cfg.min_line_px], ln[ln >= cfg.min_line_px]
        k = np.ceil(2 * ln).astype(np.int64) + 1  # points every <= 0.5 px along each segment
        seg = np.repeat(np.arange(len(L)), k)
        t = (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k)) / np.repeat(np.maximum(k - 1, 1), k)
        p = L[seg, :2] + t[:, None] * d[seg]
        ix = np.clip(np.rint(p[:, 0]).astype(np.int64), 0, W - 1)
        iy = np.clip(np.rint(p[:, 1]).astype(np.int64), 0, H - 1)
        ang = np.mod(np.arctan2(d[seg, 0], -d[seg, 1]), np.pi)  # normal (-dy, dx) ~ (dy, -dx) mod pi
        return iy, ix, ang
    blur = cv2.GaussianBlur(gray, (0, 0), cfg.blur_sigma_px) if cfg.blur_sigma_px > 0 else gray
    edges = cv2.Canny(blur, cfg.canny_low, cfg.canny_high) > 0
    gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3)[edges]
    gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3)[edges]
    iy, ix = np.nonzero(edges)
    return iy, ix, np.mod(np.arctan2(gy, gx), np.pi).astype(np.float64)


class _EdgeScorer:
    """Scores poses by the mean capped distance of their visible model-edge samples to the image's
    Canny edges (0: every sample on an edge, 1: none within ``dt_max_px``); counts the poses scored."""

    def __init__(self, gray: np.ndarray, model, camera, T_cam_model_guess: np.ndarray, cfg: AutoInitConfig, tc):
        import cv2

        from mst.pipeline.tracking.config import scene_near_m
        from mst.pipeline.tracking.visibility import ModelGeometry

        self.cfg, self.tc, self.K = cfg, tc, camera.K
        self.H, self.W = gray.shape[:2]
        self.n_bins = B = max(int(cfg.orient_bins), 1)
        iy, ix, ang = _edge_pixels(gray, cfg)
        x = ang / (np.pi / B)  # edge normal orientation mod 180 deg, in B bins; each pixel also in its nearest neighbour bin
        lab = np.minimum(x.astype(np.int64), B - 1)
        nb = np.where(x - lab >= 0.5, lab + 1, lab - 1) % B if B > 1 else lab
        self.D = np.empty((B, self.H, self.W), np.float32)
        for k in range(B):  # one distance transform per orientation bin (B <= 16, each a few ms)
            free = np.ones((self.H, self.W), np.uint8)
            m = (lab == k) | (nb == k)
            free[iy[m], ix[m]] = 0
            D = cv2.distanceTransform(free, cv2.DIST_L2, 3)
            self.D[k] = np.minimum(D, cfg.dt_max_px) / cfg.dt_max_px
        r = int(round(cfg.coarse_shift_px / 2))
        ker = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        self.D_coarse = np.stack([cv2.erode(d, ker) for d in self.D])
        self.geom = ModelGeometry.from_model(model)
        self.near_m = scene_near_m(self.geom.vertices, T_cam_model_guess, tc.edges.near_clip_m)  # fixed at the guess, as the tracker does
        self.n_eval = 0
        self.null_score = 1.0  #: median best score of the coarse candidates (set by the coarse search)
        self.n_ref = 0  #: typical visible sample count in the search box (set by the coarse search)

    def samples(self, T_cam_model):
        from mst.pipeline.tracking.visibility import visible_samples

        cfg, te = self.cfg, self.tc.edges
        return visible_samples(self.geom, T_cam_model, self.K, self.W, self.H, cfg.sample_step_px, self.near_m, te.far_clip_m,
                               te.angle_appear_deg, te.angle_disappear_deg, None, border_px=2.0,
                               hidden_lines=te.hidden_lines, zbuffer_scale=te.zbuffer_scale)

    def bins(self, normal: np.ndarray) -> np.ndarray:
        """Orientation bin of each projected edge normal (N, 2)."""
        B = self.n_bins
        if B == 1:
            return np.zeros(len(normal), np.int64)
        x = np.mod(np.arctan2(normal[:, 1], normal[:, 0]), np.pi) / (np.pi / B)
        return np.minimum(x.astype(np.int64), B - 1)

    def raw_many(self, T_mc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mean capped distance (1 below ``min_samples``), visible sample count) of each pose."""
        W, H, D = self.W, self.H, self.D
        out, n = np.ones(len(T_mc)), np.zeros(len(T_mc), np.int64)
        for i, T in enumerate(T_mc):  # one visibility pass per pose (vectorised inside)
            s = self.samples(inv_T(T))
            n[i] = len(s)
            if len(s) >= self.cfg.min_samples:
                uv = np.clip(np.rint(s.uv).astype(np.int64), 0, [W - 1, H - 1])
                out[i] = float(D[self.bins(s.normal), uv[:, 1], uv[:, 0]].mean())
        return out, n

    def sim_scores(self, s, shifts: np.ndarray, sims: np.ndarray, coarse: bool) -> np.ndarray:
        """Scores (k, M) of the samples ``s`` under each image similarity ``sims`` (k, 2) = (scale about
        the samples' image centroid, rotation about the principal point, rad) followed by each image
        shift (M, 2) px (or (k, M, 2): a shift set per similarity); at most ``shift_samples`` samples, evenly spaced; a sample moved out of the
        image is a miss. ``coarse``: on the distance transforms eroded by half the coarse grid step
        (a grid node then scores as well as the best position within its cell)."""
        sim_own_shift_means, sim_shift_means = _AK.sim_own_shift_means, _AK.sim_shift_means

        D = self.D_coarse if coarse else self.D
        idx = np.linspace(0, len(s) - 1, min(len(s), self.cfg.shift_samples)).astype(np.int64)
        uv = np.ascontiguousarray(s.uv[idx], np.float64)
        kern = sim_own_shift_means if shifts.ndim == 3 else sim_shift_means  # (k, M, 2): a shift set per similarity
        m = kern(D, uv, np.ascontiguousarray(s.normal[idx], np.float64), uv.mean(0),
                 np.ascontiguousarray(self.K[:2, 2], np.float64), np.ascontiguousarray(sims, np.float64),
                 np.ascontiguousarray(shifts, np.float64), self.n_bins)
        n = len(s)
        return (m * n + max(self.n_ref - n, 0)) / max(n, self.n_ref, 1)

    def score_many(self, T_mc: np.ndarray) -> np.ndarray:
        """Mean capped distance, the samples short of ``n_ref`` counted as misses (1 each): the minimum
        over many poses of a mean over few samples is low by chance alone (selection bias towards
        poses that show a small part of the model)."""
        m, n = self.raw_many(T_mc)
        if not self.n_ref:
            return m
        return (m * n + np.maximum(self.n_ref - n, 0)) / np.maximum(n, self.n_ref)


def _turn(T_mc: np.ndarray, rot_cam: np.ndarray) -> np.ndarray:
    """Camera poses (N, 4, 4) T_model_cam turned about their own centres by the camera-frame rotation
    vectors ``rot_cam`` (N, 3), rad."""
    R = so3_exp(rot_cam)                        # camera_new <- camera
    out = T_mc.copy()
    out[:, :3, :3] = T_mc[:, :3, :3] @ np.transpose(R, (0, 2, 1))
    return out


def _shift_rot(K: np.ndarray, shift_px: np.ndarray) -> np.ndarray:
    """Camera-frame rotation vectors (N, 3) that move the image by ``shift_px`` (N, 2) (u right, v down)
    at the principal point: about +y for +u, about -x for +v."""
    return np.stack([-np.arctan(shift_px[:, 1] / K[1, 1]), np.arctan(shift_px[:, 0] / K[0, 0]),
                     np.zeros(len(shift_px))], 1)


def _grid(r: float, step: float) -> np.ndarray:
    """(M, 2) image shifts on a square grid of half-size ``r`` px."""
    g = np.arange(-np.floor(r / step), np.floor(r / step) + 1) * step
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def _search_shifts(sc_: _EdgeScorer, T_mc: np.ndarray, shifts: np.ndarray, sims: np.ndarray | None = None,
                   fine: np.ndarray | None = None, samples: list | None = None):
    """Each pose (N, 4, 4) T_model_cam moved by its best image similarity and shift: ``(moved poses,
    scores)``. ``sims`` (k, 2) (scale, roll rad; default identity) and ``shifts`` are searched on the
    eroded distance transforms when ``fine`` (shifts around the best coarse one, on the plain
    transforms) is given, else on the plain ones. A scale s moves the camera along its ray to the
    samples' 3-D centroid to 1/s of its distance; a roll turns it about its optical axis."""
    sims = np.array([[1.0, 0.0]]) if sims is None else sims
    out, scores = T_mc.copy(), np.ones(len(T_mc))
    rot = np.zeros((len(T_mc), 3))
    for i, T in enumerate(T_mc):
        s = sc_.samples(inv_T(T)) if samples is None else samples[i]
        if len(s) < sc_.cfg.min_samples:
            continue
        sc = sc_.sim_scores(s, shifts, sims, coarse=fine is not None)
        if fine is not None:  # each similarity's 3 best coarse shifts, refined on the plain transforms
            top = np.argsort(sc, 1)[:, :3]
            cand = (shifts[top][:, :, None] + fine[None, None]).reshape(len(sims), -1, 2)
            f2 = sc_.sim_scores(s, cand, sims, coarse=False)
            k = int(np.argmin(f2.min(1)))  # the first similarity reaching the minimum, its first shift
            j2 = int(np.argmin(f2[k]))
            scores[i], sh = f2[k, j2], cand[k, j2]
        else:
            k, j = np.unravel_index(int(np.argmin(sc)), sc.shape)
            scores[i], sh = sc[k, j], shifts[j]
        scale, roll = sims[k]
        if scale != 1.0:
            Xc = s.X_model.mean(0)
            out[i, :3, 3] = Xc + (T[:3, 3] - Xc) / scale
        rot[i] = _shift_rot(sc_.K, sh[None])[0] + np.array([0.0, 0.0, roll])
    sc_.n_eval += len(T_mc)
    return _turn(out, rot), scores


def _coarse_search(sc_: _EdgeScorer, T0: np.ndarray, half: np.ndarray, cfg: AutoInitConfig):
    """Coarse: Halton positions and rolls (about the optical axis) in the search box, each turned by
    its best image shift on a grid covering the attitude box (pitch/yaw of the camera move the image
    nearly rigidly: searched exhaustively in 2-D on the distance transforms instead of sampled in 3-D).
    Fine: a shrinking random search over position and roll from the ``n_keep`` best, each candidate
    again turned by its best shift on a finer grid. Returns ``(refined offsets, their scores, the
    guess's own score)`` (offsets: position m, model-frame rotation vector deg, as :func:`_perturb`)."""
    K = sc_.K
    f = 0.5 * (K[0, 0] + K[1, 1])
    h = np.vstack([np.zeros(4), _halton(cfg.n_coarse, 4) * 2 - 1])
    P = np.tile(T0, (len(h), 1, 1))
    P[:, :3, 3] += h[:, :3] * half[:3]
    P = _turn(P, np.c_[np.zeros((len(h), 2)), np.radians(h[:, 3] * half[3])])
    # typical visible sample count in the box, for the penalty of poses that show less of the model
    S = [sc_.samples(inv_T(T)) for T in P]
    n = np.array([len(x) for x in S])
    ok = n >= cfg.min_samples
    sc_.n_ref = int(np.median(n[ok])) if ok.any() else 0
    guess_score = float(sc_.score_many(T0[None])[0])
    r_px = f * np.tan(np.radians(min(half[3], 60.0)))
    st = cfg.coarse_shift_px
    sims = np.array([(sc, np.radians(r)) for sc in (1 - cfg.coarse_scale_step, 1.0, 1 + cfg.coarse_scale_step)
                     for r in (-cfg.coarse_roll_step_deg, 0.0, cfg.coarse_roll_step_deg)])
    P, sc = _search_shifts(sc_, P, _grid(r_px, st), sims, _grid(st / 2, st / 6), S)
    # what a pose of the box reaches on this frame at its best image similarity: nearly all of them are
    # wrong, so their median calibrates the refusal on the frame's own texture (dense ground texture
    # lets wrong poses score low too; a blank frame scores 1 everywhere)
    sc_.null_score = float(np.median(sc))
    rng = np.random.default_rng(cfg.seed)
    fine = _grid(st / 2, st / 6)
    finals, fscores = [], []
    for s0 in np.argsort(sc)[: cfg.n_keep]:
        T, best = P[s0], sc[s0]
        step = np.r_[half[:3], half[3]] / 4.0
        for _ in range(cfg.refine_iters):
            d = rng.uniform(-1, 1, (cfg.refine_samples, 4)) * step
            C = np.tile(T, (len(d), 1, 1))
            C[:, :3, 3] += d[:, :3]
            C = _turn(C, np.c_[np.zeros((len(d), 2)), np.radians(d[:, 3])])
            C, cs = _search_shifts(sc_, np.vstack([T[None], C]), fine)
            j = int(np.argmin(cs))
            if cs[j] < best:
                T, best = C[j], cs[j]
            step = step / 2.0
        finals.append(np.r_[T[:3, 3] - T0[:3, 3], np.degrees(so3_log(T[:3, :3] @ T0[:3, :3].T))])
        fscores.append(best)
    return finals, fscores, guess_score


def _confirm(sc_: _EdgeScorer, tr, gray, finals, T0: np.ndarray, half: np.ndarray, cfg: AutoInitConfig) -> list:
    """``(score, T_cam_model, tracker frame)`` of the candidates the edge tracker refines healthily
    without leaving the search box."""
    cands = []
    for d in finals:
        T_c = inv_T(_perturb(T0, d[None])[0])
        fr = tr.track(gray, T_c, first=True)
        if not fr.healthy or fr.T_cam_model is None or fr.n_inliers < cfg.min_inlier_ratio * max(fr.n_samples, 1):
            continue
        T_r = fr.T_cam_model
        Tm = inv_T(T_r)
        dp = Tm[:3, 3] - T0[:3, 3]
        da = np.degrees(np.linalg.norm(so3_log(Tm[:3, :3] @ T0[:3, :3].T)))
        if (np.abs(dp) > half[:3] * 1.2).any() or da > np.sqrt(3) * half[3] * 1.2:
            continue
        cands.append((float(sc_.score_many(Tm[None])[0]), T_r, fr))
    sc_.n_eval += len(cands)
    return cands


def _polish(sc_: _EdgeScorer, tr, gray, best: float, T_best: np.ndarray, n_max: int) -> tuple[float, np.ndarray]:
    """The tracker again from its own result (its search range is limited) until it stops moving
    (< 1e-4 of the distance and 0.01 deg), up to 4 times, unless its score gets clearly worse (by
    more than 0.01: the scores are read at whole pixels of the distance transforms, so equal poses
    differ by ~0.001)."""
    from mst.core.poses import pose_error

    for _ in range(4):
        fr2 = tr.track(gray, T_best, first=True)
        if not fr2.healthy or fr2.T_cam_model is None:
            break
        s2 = float(sc_.score_many(inv_T(fr2.T_cam_model)[None])[0]) * n_max / max(fr2.n_samples, 1)
        sc_.n_eval += 1
        if s2 > best + 0.01:
            break
        dt, dr = pose_error(inv_T(fr2.T_cam_model), inv_T(T_best))
        best, T_best = min(best, s2), fr2.T_cam_model
        if dt < 1e-4 * np.linalg.norm(inv_T(T_best)[:3, 3] - sc_.geom.vertices.mean(0)) and dr < 0.01:
            break
    return best, T_best


def _second_best(sc_: _EdgeScorer, cands: list, T_best: np.ndarray, distinct_px: float,
                 agree_px: float) -> tuple[float | None, int]:
    """``(score of the best distinct competitor -- its projection differs from the best's by more than
    ``distinct_px`` on average -- or None, how many candidates land on the best pose -- within
    ``agree_px`` --, itself included)``. Refined from different starts, candidates of one pose
    agree to ~0.1 px; two more than a pixel apart are two answers, and when both score alike the image
    does not choose between them (sample house flyover at 22 m: a pose 3.5 % / 1.8 deg off, 1.3 px
    from five candidates within 0.5 %, scored 0.35 against their 0.39)."""
    K = sc_.K
    s_best = sc_.samples(T_best)
    second, agree = None, 1
    for f, Tc, _ in cands[1:]:
        Xc = transform_points(Tc, s_best.X_model)
        ok = Xc[:, 2] > 1e-6
        uv = (Xc[ok] @ K.T)[:, :2] / Xc[ok, 2:3]  # K-matrix form, as visible_samples' uv (not Camera.project's op order)
        d = np.linalg.norm(uv - s_best.uv[ok], axis=1).mean() if ok.any() else np.inf
        if d > distinct_px:
            second = f if second is None else second
        if d <= agree_px:
            agree += 1
    return second, agree


def auto_init(gray: np.ndarray, model, camera, T_cam_model_guess: np.ndarray, cfg: AutoInitConfig | None = None,
              tracker_cfg=None) -> AutoInitResult:
    """Search the pose of ``model`` in the 8-bit ``gray`` image around ``T_cam_model_guess``."""
    import dataclasses

    from mst.pipeline.tracking.config import TrackConfig

    cfg = cfg or AutoInitConfig()
    tc = tracker_cfg or TrackConfig()
    # one still frame: a low-contrast model edge (a grey wall against grey ground) is evidence too;
    # at the tracker's threshold 20 the moving edges skip it and latch onto the texture beside it
    # (sample house flyover, 22 m, tracked from the TRUE pose: 0.79 % / 0.48 deg at 20, 0.40 % / 0.24 deg at 10)
    tc = dataclasses.replace(tc, edges=dataclasses.replace(
        tc.edges, edge_threshold=min(tc.edges.edge_threshold, cfg.refine_edge_threshold)))
    sc_ = _EdgeScorer(gray, model, camera, T_cam_model_guess, cfg, tc)
    T0 = inv_T(np.asarray(T_cam_model_guess, float))
    half = cfg.n_sigma * np.array([*cfg.pos_sigma_m, *([cfg.att_sigma_deg] * 3)])
    finals, fscores, guess_score = _coarse_search(sc_, T0, half, cfg)
    # refine every kept candidate with the edge tracker (moving edges + robust VVS, as on a first
    # frame) and score the refined poses: the true pose then lands on the image edges (score ~0.05),
    # a wrong basin does not; refined poses that leave the search box or are unhealthy are dropped
    from mst.pipeline.tracking import EdgeTracker

    tr = EdgeTracker(model, camera, tc)
    cands = _confirm(sc_, tr, gray, finals, T0, half, cfg)
    null, ratio = sc_.null_score, cfg.max_null_ratio

    def _no_match(score, info=None):
        return AutoInitResult(False, None, score, None, guess_score, sc_.n_eval,
                              f"no pose near the guess matches the image edges clearly better than a wrong pose does "
                              f"(best score {score:.3f} > {ratio} x {null:.3f}, the frame's median over the search box:"
                              f" the frame may not show the model)", info or {}, null)

    if not cands:
        best_raw = float(min(fscores))
        if best_raw > ratio * null:
            return _no_match(best_raw)
        return AutoInitResult(False, None, best_raw, None, guess_score, sc_.n_eval,
                              "the edge tracker confirms none of the best candidates (unhealthy or outside the search box)",
                              {}, null)
    # a pose that shows fewer model edges than the best-covered candidate (e.g. seen from the
    # ground, half out of view) must not win on a few well-placed samples: scores scale by n_max / n
    n_max = max(c[2].n_samples for c in cands)
    cands = [(f * n_max / max(c.n_samples, 1), T, c) for f, T, c in cands]
    cands.sort(key=lambda c: c[0])
    best, T_best, fr = cands[0]
    info = {"healthy": True, "samples": int(fr.n_samples), "inliers": int(fr.n_inliers),
            "residual_px": float(fr.residual_px) if np.isfinite(fr.residual_px) else None, "candidates_confirmed": len(cands)}
    best, T_best = _polish(sc_, tr, gray, best, T_best, n_max)
    if best > ratio * null:
        return _no_match(best, info)
    second, agree = _second_best(sc_, cands, T_best, cfg.distinct_px, cfg.dt_max_px)
    info["candidates_agreeing"] = agree
    if second is not None and second < best * (1.0 + cfg.min_margin) + 0.02:
        return AutoInitResult(False, None, best, second, guess_score, sc_.n_eval,
                              f"ambiguous: a distinct pose scores {second:.3f} against the best {best:.3f} "
                              f"(need {cfg.min_margin:.0%} better)", info, null)
    if agree < cfg.min_agree:
        # a lone basin: an isolated match of generic scene lines (a room's corner under a pose with most
        # of the model out of view) is found from one start; the true pose from several (house orbit:
        # 2-5 of 6, flyover and L-building: 6 of 6)
        return AutoInitResult(False, None, best, second, guess_score, sc_.n_eval,
                              f"only {agree} of the {len(cands)} refined candidates land on the best pose "
                              f"(need {cfg.min_agree}): an isolated match", info, null)
    return AutoInitResult(True, T_best, best, second, guess_score, sc_.n_eval, "", info, null)


def guess_from_nav(nav_path, t: float | None, mount_ypr_deg, lever_arm_m) -> tuple[np.ndarray, float]:
    """``T_cam_model`` guess from the log row nearest to ``t`` (default: the first row with a fix);
    the model frame is taken as the log's world frame (offset removed). Returns (T_cam_model, row time)."""
    from mst.pipeline.init_pose import pose_from_gps
    from mst.pipeline.nav.log import read_navlog

    nav = read_navlog(nav_path)
    idx = np.flatnonzero(nav.fix)
    if not len(idx):
        raise InputError(nav_path, "no row with a GPS fix")
    i = idx[0] if t is None else idx[np.argmin(np.abs(nav.t[idx] - t))]
    if t is not None and abs(nav.t[i] - t) > 1.0:
        raise InputError(nav_path, f"no fix within 1 s of t = {t:.3f} s (nearest {nav.t[i]:.3f} s)")
    T = pose_from_gps(nav.p_world[i], *nav.ypr_deg[i], mount_ypr_deg=tuple(mount_ypr_deg), mount_offset_m=tuple(lever_arm_m))
    return T, float(nav.t[i])


def run_autoinit(model_path, camera_path, out, nav_path, image_path, *, nav_time=None, overlay_path=None,
                 cfg=None) -> dict:
    """The ``mst init --from-nav`` stage: guess from the log, search, refine, write ``out`` (TUM line +
    cMo comment) only when the pose is accepted; raises :class:`mst.InputError` naming the image with
    the reason otherwise. ``cfg``: :class:`mst.pipeline.init_pose.InitConfig` (the camera mount and
    the search settings ``cfg.auto``)."""
    import cv2

    from mst import atomic_outputs
    from mst.core.camera import read_camera
    from mst.core.trajectory import write_pose_file
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import InitConfig, _read_image, draw_model

    cfg = cfg or InitConfig()
    if image_path is None:
        raise InputError(None, "searching the pose needs the image (the frame to search the model in)")
    model = load_tracking_model(model_path)
    cam = read_camera(camera_path)
    img = _read_image(image_path)
    h, w = img.shape[:2]
    if cam.width and cam.height and (cam.width, cam.height) != (w, h):
        raise InputError(camera_path, f"camera is for {cam.width}x{cam.height} images but {image_path} is {w}x{h}")
    cam = cam.with_size(w, h)
    T_guess, t_row = guess_from_nav(nav_path, nav_time, cfg.mount_ypr_deg, cfg.mount_offset_m)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    res = auto_init(gray, model, cam, T_guess, cfg.auto)
    if not res.ok:
        raise InputError(image_path, f"automatic initialisation refused: {res.reason}")
    with atomic_outputs(out, overlay_path) as (tmp, tmp_ov):
        write_pose_file(tmp, res.T_cam_model, t=t_row)
        if tmp_ov is not None and not cv2.imwrite(str(tmp_ov), draw_model(img, model, res.T_cam_model, cam.K,
                                                                          model_path=model_path)):
            raise InputError(overlay_path, "could not write the overlay (use .png)")
    return {"source": "from-nav", "nav_time": t_row, "T_cam_model_guess": T_guess.tolist(), **res.to_json(),
            "config": cfg.to_dict()}
