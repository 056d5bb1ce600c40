"""Automatic initial pose: search around a GPS/AHRS guess on an edge distance transform (``mst init --from-nav``).

Frames: ``T_cam_model`` (model -> camera, camera x right, y down, z forward), metres, degrees.

1. Edges of the image (Canny on the 8-bit gray frame) and their distance transform ``D`` (px),
   truncated at ``dt_max_px``.
2. Score of a pose: the mean of ``min(D, dt_max) / dt_max`` at the model's visible edge samples
   (:func:`mst.pipeline.tracking.visibility.visible_samples`, hidden lines removed), 1 when fewer than
   ``min_samples`` are visible. 0 = every projected edge on an image edge.
3. Coarse: ``n_coarse`` quasi-random (Halton) perturbations of the guess in the box position
   +- n_sigma * pos_sigma (model axes) and attitude +- n_sigma * att_sigma (model-frame rotation
   vector), plus the guess. Fine: the ``n_keep`` best start points, each refined by a pattern search
   with halving steps; then the best is refined by the edge tracker (moving edges + robust VVS).
   Every kept candidate is then refined by the edge tracker (kept when healthy, with >= 70 % inliers,
   inside the box) and re-scored, the score scaled by (most samples of any candidate) / (its samples)
   so that a pose showing few edges cannot win; the best refined one wins.
4. Refusal (no pose written): the best score is above ``max_score`` (the frame does not show the
   model as predicted) or, after refinement, above ``max_refined_score`` (not converged), no candidate's refinement is healthy and inside the search box, or a
   *distinct* refined candidate (its projected samples more than ``dt_max_px`` away on average)
   scores within ``min_margin`` (+0.02) of the best (ambiguous, e.g. a repetitive facade).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mst import InputError
from mst.core.config import Config, param
from mst.core.poses import inv_T, so3_exp, so3_log, transform_points


@dataclass
class AutoInitConfig(Config):
    """Search box, scoring and refusal thresholds of :func:`auto_init` (scores: mean edge distance
    / ``dt_max_px``, 0 = every sample on an image edge, 1 = none within ``dt_max_px``)."""

    pos_sigma_m: tuple[float, float, float] = param((3.0, 3.0, 5.0), min=0, help="position uncertainty of the guess, m")
    att_sigma_deg: float = param(3.0, min=0, help="attitude uncertainty of the guess, deg")
    n_sigma: float = param(3.0, min=0, min_open=True, help="search box half-size, sigmas")
    n_coarse: int = param(500, min=1, help="coarse candidates scored")
    n_keep: int = param(6, min=1, help="best candidates refined")
    refine_iters: int = param(7, min=0, help="refinement iterations per candidate")
    refine_samples: int = param(8, min=1, help="samples per refinement iteration")
    dt_max_px: float = param(20.0, min=0, min_open=True, help="edge distance transform cap, px")
    sample_step_px: float = param(5.0, min=0, min_open=True, help="model edge sampling step, px")
    canny_low: float = param(40.0, min=0, help="Canny low threshold, grey levels")
    canny_high: float = param(120.0, min=0, help="Canny high threshold, grey levels")
    min_samples: int = param(30, min=1, help="visible edge samples a candidate needs")
    max_score: float = param(0.35, min=0, min_open=True, help="refuse a best coarse score above this")
    min_margin: float = param(0.15, min=0, help="second best must score >= best * (1 + min_margin) + 0.02")
    min_inlier_ratio: float = param(0.7, min=0, max=1,
                                    help="of the tracker's refinement (robust VVS inliers / samples)")
    # a converged pose puts its edge samples within ~2 px of image edges (Canny localisation ~1 px,
    # the tracker's residual ~0.2 px, a few samples on low-contrast edges): 0.12 * 20 px = 2.4 px.
    # Conservative: a model whose edges largely lack image contrast (two walls shaded alike) is
    # refused even at its true pose -- then click (`mst init --clicks`)
    max_refined_score: float = param(0.12, min=0, min_open=True, help="refuse a refined pose scoring above this")
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

    def to_json(self) -> dict:
        return {"ok": self.ok, "reason": self.reason, "score": self.score, "second_score": self.second_score,
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


class _EdgeScorer:
    """Scores poses by the mean capped distance of their visible model-edge samples to the image's
    Canny edges (0: every sample on an edge, 1: none within ``dt_max_px``); counts the poses scored."""

    def __init__(self, gray: np.ndarray, model, camera, T_cam_model_guess: np.ndarray, cfg: AutoInitConfig, tc):
        import cv2

        from mst.pipeline.tracking.config import scene_near_m
        from mst.pipeline.tracking.visibility import ModelGeometry

        self.cfg, self.tc, self.K = cfg, tc, camera.K
        self.H, self.W = gray.shape[:2]
        edges = cv2.Canny(cv2.GaussianBlur(gray, (3, 3), 0), cfg.canny_low, cfg.canny_high)
        D = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
        self.D = np.minimum(D, cfg.dt_max_px) / cfg.dt_max_px
        self.geom = ModelGeometry.from_model(model)
        self.near_m = scene_near_m(self.geom.vertices, T_cam_model_guess, tc.edges.near_clip_m)  # fixed at the guess, as the tracker does
        self.n_eval = 0

    def samples(self, T_cam_model):
        from mst.pipeline.tracking.visibility import visible_samples

        cfg, te = self.cfg, self.tc.edges
        return visible_samples(self.geom, T_cam_model, self.K, self.W, self.H, cfg.sample_step_px, self.near_m, te.far_clip_m,
                               te.angle_appear_deg, te.angle_disappear_deg, None, border_px=2.0,
                               hidden_lines=te.hidden_lines, zbuffer_scale=te.zbuffer_scale)

    def score_many(self, T_mc: np.ndarray) -> np.ndarray:
        W, H, D = self.W, self.H, self.D
        out = np.ones(len(T_mc))
        for i, T in enumerate(T_mc):  # one visibility pass per pose (vectorised inside)
            s = self.samples(inv_T(T))
            if len(s) >= self.cfg.min_samples:
                uv = np.clip(np.rint(s.uv).astype(np.int64), 0, [W - 1, H - 1])
                out[i] = float(D[uv[:, 1], uv[:, 0]].mean())
        return out


def _coarse_search(sc_: _EdgeScorer, T0: np.ndarray, half: np.ndarray, cfg: AutoInitConfig):
    """Halton candidates in the search box, then a shrinking random search from the ``n_keep`` best.
    Returns ``(refined offsets, their scores, the guess's own score)``."""
    score_many = sc_.score_many
    dc = np.vstack([np.zeros(6), (_halton(cfg.n_coarse, 6) * 2 - 1) * half])
    sc = score_many(_perturb(T0, dc))
    n_eval = len(dc)
    guess_score = float(sc[0])
    rng = np.random.default_rng(cfg.seed)
    starts = np.argsort(sc)[: cfg.n_keep]
    finals, fscores = [], []
    for s0 in starts:
        d, best = dc[s0].copy(), sc[s0]
        step = half / 4.0
        for _ in range(cfg.refine_iters):
            cand = d + rng.uniform(-1, 1, (cfg.refine_samples, 6)) * step
            cs = score_many(_perturb(T0, cand))
            n_eval += len(cand)
            j = int(np.argmin(cs))
            if cs[j] < best:
                d, best = cand[j], cs[j]
            step = step / 2.0
        finals.append(d)
        fscores.append(best)
    sc_.n_eval += n_eval
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
    """The tracker again from its own result (its search range is limited), while the score improves."""
    for _ in range(2):
        fr2 = tr.track(gray, T_best, first=True)
        if not fr2.healthy or fr2.T_cam_model is None:
            break
        s2 = float(sc_.score_many(inv_T(fr2.T_cam_model)[None])[0]) * n_max / max(fr2.n_samples, 1)
        sc_.n_eval += 1
        if s2 > best:
            break
        best, T_best = s2, fr2.T_cam_model
    return best, T_best


def _second_best(sc_: _EdgeScorer, cands: list, T_best: np.ndarray, dt_max_px: float) -> float | None:
    """The score of the best distinct competitor: its projection differs from the best's by more
    than ``dt_max_px`` on average (None: no such candidate)."""
    K = sc_.K
    s_best = sc_.samples(T_best)
    for f, Tc, _ in cands[1:]:
        Xc = transform_points(Tc, s_best.X_model)
        ok = Xc[:, 2] > 1e-6
        uv = (Xc[ok] @ K.T)[:, :2] / Xc[ok, 2:3]  # K-matrix form, as visible_samples' uv (not Camera.project's op order)
        if not ok.any() or np.linalg.norm(uv - s_best.uv[ok], axis=1).mean() > dt_max_px:
            return f
    return None


def auto_init(gray: np.ndarray, model, camera, T_cam_model_guess: np.ndarray, cfg: AutoInitConfig | None = None,
              tracker_cfg=None) -> AutoInitResult:
    """Search the pose of ``model`` in the 8-bit ``gray`` image around ``T_cam_model_guess``."""
    from mst.pipeline.tracking.config import TrackConfig

    cfg = cfg or AutoInitConfig()
    tc = tracker_cfg or TrackConfig()
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
    if not cands:
        best_raw = float(min(fscores))
        if best_raw > cfg.max_score:
            return AutoInitResult(False, None, best_raw, None, guess_score, sc_.n_eval,
                                  f"no pose near the guess matches the image edges (best score {best_raw:.2f} > "
                                  f"{cfg.max_score}: the frame may not show the model)")
        return AutoInitResult(False, None, best_raw, None, guess_score, sc_.n_eval,
                              "the edge tracker confirms none of the best candidates (unhealthy or outside the search box)")
    # a pose that shows fewer model edges than the best-covered candidate (e.g. seen from the
    # ground, half out of view) must not win on a few well-placed samples: scores scale by n_max / n
    n_max = max(c[2].n_samples for c in cands)
    cands = [(f * n_max / max(c.n_samples, 1), T, c) for f, T, c in cands]
    cands.sort(key=lambda c: c[0])
    best, T_best, fr = cands[0]
    info = {"healthy": True, "samples": int(fr.n_samples), "inliers": int(fr.n_inliers),
            "residual_px": float(fr.residual_px) if np.isfinite(fr.residual_px) else None, "candidates_confirmed": len(cands)}
    if best > cfg.max_score:
        return AutoInitResult(False, None, best, None, guess_score, sc_.n_eval,
                              f"no pose near the guess matches the image edges (best score {best:.2f} > "
                              f"{cfg.max_score}: the frame may not show the model)", info)
    best, T_best = _polish(sc_, tr, gray, best, T_best, n_max)
    if best > cfg.max_refined_score:
        return AutoInitResult(False, None, best, None, guess_score, sc_.n_eval,
                              f"the best refined pose does not sit on the image edges (score {best:.3f} > "
                              f"{cfg.max_refined_score}: mean edge distance {best * cfg.dt_max_px:.1f} px)", info)
    second = _second_best(sc_, cands, T_best, cfg.dt_max_px)
    if second is not None and second < best * (1.0 + cfg.min_margin) + 0.02:
        return AutoInitResult(False, None, best, second, guess_score, sc_.n_eval,
                              f"ambiguous: a distinct pose scores {second:.3f} against the best {best:.3f} "
                              f"(need {cfg.min_margin:.0%} better)", info)
    return AutoInitResult(True, T_best, best, second, guess_score, sc_.n_eval, "", info)


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
        if tmp_ov is not None and not cv2.imwrite(str(tmp_ov), draw_model(img, model, res.T_cam_model, cam.K)):
            raise InputError(overlay_path, "could not write the overlay (use .png)")
    return {"source": "from-nav", "nav_time": t_row, "T_cam_model_guess": T_guess.tolist(), **res.to_json(),
            "config": cfg.to_dict()}
