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
from mst.core.poses import inv_T, so3_exp, so3_log


@dataclass
class AutoInitConfig:
    """Search box, scoring and refusal thresholds of :func:`auto_init`."""

    pos_sigma_m: tuple[float, float, float] = (3.0, 3.0, 5.0)
    att_sigma_deg: float = 3.0
    n_sigma: float = 3.0
    n_coarse: int = 500
    n_keep: int = 10
    refine_iters: int = 7
    refine_samples: int = 16
    dt_max_px: float = 20.0
    sample_step_px: float = 5.0
    canny_low: float = 40.0
    canny_high: float = 120.0
    min_samples: int = 30
    max_score: float = 0.35
    min_margin: float = 0.15       # second best must score >= best * (1 + min_margin) + 0.02
    min_inlier_ratio: float = 0.7  # of the tracker's refinement (robust VVS inliers / samples)
    # a converged pose puts its edge samples within ~2 px of image edges (Canny localisation ~1 px,
    # the tracker's residual ~0.2 px, a few samples on low-contrast edges): 0.12 * 20 px = 2.4 px.
    # Conservative: a model whose edges largely lack image contrast (two walls shaded alike) is
    # refused even at its true pose -- then click (`mst init --clicks`)
    max_refined_score: float = 0.12
    seed: int = 0


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


def auto_init(gray: np.ndarray, model, camera, T_cam_model_guess: np.ndarray, cfg: AutoInitConfig | None = None,
              tracker_cfg=None) -> AutoInitResult:
    """Search the pose of ``model`` in the 8-bit ``gray`` image around ``T_cam_model_guess``."""
    import cv2

    from mst.pipeline.tracking.config import TrackConfig
    from mst.pipeline.tracking.visibility import ModelGeometry, visible_samples

    cfg = cfg or AutoInitConfig()
    tc = tracker_cfg or TrackConfig()
    te = tc.edges
    H, W = gray.shape[:2]
    K = camera.K
    edges = cv2.Canny(cv2.GaussianBlur(gray, (3, 3), 0), cfg.canny_low, cfg.canny_high)
    D = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
    D = np.minimum(D, cfg.dt_max_px) / cfg.dt_max_px
    geom = ModelGeometry.from_model(model)

    from mst.pipeline.tracking.config import scene_near_m

    near_m = scene_near_m(geom.vertices, T_cam_model_guess, te.near_clip_m)  # fixed at the guess, as the tracker does

    def samples(T_cam_model):
        return visible_samples(geom, T_cam_model, K, W, H, cfg.sample_step_px, near_m, te.far_clip_m,
                               te.angle_appear_deg, te.angle_disappear_deg, None, border_px=2.0,
                               hidden_lines=te.hidden_lines, zbuffer_scale=te.zbuffer_scale)

    def score_many(T_mc: np.ndarray) -> np.ndarray:
        out = np.ones(len(T_mc))
        for i, T in enumerate(T_mc):  # one visibility pass per pose (vectorised inside)
            s = samples(inv_T(T))
            if len(s) >= cfg.min_samples:
                uv = np.clip(np.rint(s.uv).astype(np.int64), 0, [W - 1, H - 1])
                out[i] = float(D[uv[:, 1], uv[:, 0]].mean())
        return out

    T0 = inv_T(np.asarray(T_cam_model_guess, float))
    half = cfg.n_sigma * np.array([*cfg.pos_sigma_m, *([cfg.att_sigma_deg] * 3)])
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
    # refine every kept candidate with the edge tracker (moving edges + robust VVS, as on a first
    # frame) and score the refined poses: the true pose then lands on the image edges (score ~0.05),
    # a wrong basin does not; refined poses that leave the search box or are unhealthy are dropped
    from mst.pipeline.tracking import EdgeTracker

    tr = EdgeTracker(model, camera, tc)
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
        cands.append((float(score_many(Tm[None])[0]), T_r, fr))
    n_eval += len(cands)
    if not cands:
        best_raw = float(min(fscores))
        if best_raw > cfg.max_score:
            return AutoInitResult(False, None, best_raw, None, guess_score, n_eval,
                                  f"no pose near the guess matches the image edges (best score {best_raw:.2f} > "
                                  f"{cfg.max_score}: the frame may not show the model)")
        return AutoInitResult(False, None, best_raw, None, guess_score, n_eval,
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
        return AutoInitResult(False, None, best, None, guess_score, n_eval,
                              f"no pose near the guess matches the image edges (best score {best:.2f} > "
                              f"{cfg.max_score}: the frame may not show the model)", info)
    for _ in range(2):  # polish: the tracker again from its own result (its search range is limited)
        fr2 = tr.track(gray, T_best, first=True)
        if not fr2.healthy or fr2.T_cam_model is None:
            break
        s2 = float(score_many(inv_T(fr2.T_cam_model)[None])[0]) * n_max / max(fr2.n_samples, 1)
        n_eval += 1
        if s2 > best:
            break
        best, T_best = s2, fr2.T_cam_model
    if best > cfg.max_refined_score:
        return AutoInitResult(False, None, best, None, guess_score, n_eval,
                              f"the best refined pose does not sit on the image edges (score {best:.3f} > "
                              f"{cfg.max_refined_score}: mean edge distance {best * cfg.dt_max_px:.1f} px)", info)
    # the best distinct competitor: its projection differs from the best's by more than dt_max on average
    s_best = samples(T_best)
    second = None
    for f, Tc, _ in cands[1:]:
        Xc = s_best.X_model @ Tc[:3, :3].T + Tc[:3, 3]
        ok = Xc[:, 2] > 1e-6
        uv = (Xc[ok] @ K.T)[:, :2] / Xc[ok, 2:3]
        if not ok.any() or np.linalg.norm(uv - s_best.uv[ok], axis=1).mean() > cfg.dt_max_px:
            second = f
            break
    if second is not None and second < best * (1.0 + cfg.min_margin) + 0.02:
        return AutoInitResult(False, None, best, second, guess_score, n_eval,
                              f"ambiguous: a distinct pose scores {second:.3f} against the best {best:.3f} "
                              f"(need {cfg.min_margin:.0%} better)", info)
    return AutoInitResult(True, T_best, best, second, guess_score, n_eval, "", info)


def guess_from_nav(nav_path, t: float | None, mount_ypr_deg, lever_arm_m) -> tuple[np.ndarray, float]:
    """``T_cam_model`` guess from the log row nearest to ``t`` (default: the first row with a fix);
    the model frame is taken as the log's world frame (offset removed). Returns (T_cam_model, row time)."""
    from mst.pipeline.init_pose import pose_from_gps
    from mst.pipeline.navlog import read_navlog

    nav = read_navlog(nav_path)
    idx = np.flatnonzero(nav.fix)
    if not len(idx):
        raise InputError(nav_path, "no row with a GPS fix")
    i = idx[0] if t is None else idx[np.argmin(np.abs(nav.t[idx] - t))]
    if t is not None and abs(nav.t[i] - t) > 1.0:
        raise InputError(nav_path, f"no fix within 1 s of t = {t:.3f} s (nearest {nav.t[i]:.3f} s)")
    T = pose_from_gps(nav.p_world[i], *nav.ypr_deg[i], mount_ypr_deg=tuple(mount_ypr_deg), mount_offset_m=tuple(lever_arm_m))
    return T, float(nav.t[i])


def run_autoinit(model_path, camera_path, out, nav_path, image_path, *, nav_time=None, mount=(0.0, 0.0, 0.0),
                 mount_offset=(0.0, 0.0, 0.0), overlay_path=None, cfg: AutoInitConfig | None = None) -> dict:
    """The ``mst init --from-nav`` stage: guess from the log, search, refine, write ``out`` (TUM line +
    cMo comment) only when the pose is accepted; raises :class:`mst.InputError` naming the image with
    the reason otherwise."""
    import cv2

    from mst import atomic_outputs
    from mst.core.camera import read_camera
    from mst.core.trajectory import write_pose_file
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import _read_image, draw_model

    if image_path is None:
        raise InputError(None, "--from-nav needs --image (the frame to search the model in)")
    model = load_tracking_model(model_path)
    cam = read_camera(camera_path)
    img = _read_image(image_path)
    h, w = img.shape[:2]
    if cam.width and cam.height and (cam.width, cam.height) != (w, h):
        raise InputError(camera_path, f"camera is for {cam.width}x{cam.height} images but {image_path} is {w}x{h}")
    cam = cam.with_size(w, h)
    T_guess, t_row = guess_from_nav(nav_path, nav_time, mount, mount_offset)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    res = auto_init(gray, model, cam, T_guess, cfg)
    if not res.ok:
        raise InputError(image_path, f"automatic initialisation refused: {res.reason}")
    with atomic_outputs(out, overlay_path) as (tmp, tmp_ov):
        write_pose_file(tmp, res.T_cam_model, t=t_row)
        if tmp_ov is not None and not cv2.imwrite(str(tmp_ov), draw_model(img, model, res.T_cam_model, cam.K)):
            raise InputError(overlay_path, "could not write the overlay (use .png)")
    return {"source": "from-nav", "nav_time": t_row, "T_cam_model_guess": T_guess.tolist(), **res.to_json()}
