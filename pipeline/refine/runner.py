"""The ``mst refine`` runner: read the trajectory, depth, camera and model; alternate a rigid ICP
of the fused keyframe cloud onto the model with a keyframe pose graph (per-keyframe ICP priors +
the tracked relative motions) while the mean cloud-to-model distance drops; write the refined
TUM trajectory (same times) atomically; return :class:`RefineSummary`."""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError, atomic_output
from mst.core.camera import read_camera
from mst.core.poses import inv_T, transform_points
from mst.core.trajectory import read_tum, write_tum
from mst.meshtools.formats import load_triangles
from mst.pipeline.depth_io import list_depth_frames, read_depth
from mst.pipeline.fusion.runner import frame_index_of_times
from mst.pipeline.refine.config import RefineConfig
from mst.pipeline.refine.geometry import ModelSurface, backproject, fused_points
from mst.pipeline.refine.graph import Prior, interpolate_corrections, solve_pose_graph

log = logging.getLogger(__name__)

#: keyframe samples kept per keyframe (seeded subsample), and for the global ICP of the fused cloud
MAX_KF_POINTS = 4000
MAX_GLOBAL_POINTS = 60_000
#: samples of a keyframe's own ICP (its prior's information is capped at prior_points_eff anyway)
MAX_ICP_POINTS = 1500


@dataclass
class C2MStats:
    """Cloud-to-model distances (m) of the fused keyframe samples that lay within the cut-off at the
    given poses (the model's part of the cloud), capped at the cut-off."""

    mean_m: float
    median_m: float
    rms_m: float
    p95_m: float
    points: int       #: samples within the cut-off
    share: float      #: of all fused samples

    def to_json(self) -> dict:
        return {"mean_m": self.mean_m, "median_m": self.median_m, "rms_m": self.rms_m, "p95_m": self.p95_m,
                "points": self.points, "share": self.share}


@dataclass
class RefineSummary:
    """What ``mst refine`` reports (``--json``): C2M (and ATE with ground truth) before/after."""

    poses: int
    keyframes: int
    priors: int                 #: keyframes whose depth found the model in the final round
    rounds: int                 #: rounds run (the last may have been rejected: no gain)
    rounds_kept: int
    c2m_before: C2MStats
    c2m_after: C2MStats
    c2m_max_m: float
    median_depth_m: float
    global_correction: dict     #: the first round's rigid ICP correction (translation m, rotation deg)
    output: str
    config: dict
    elapsed_s: float
    ate: dict = field(default_factory=dict)  #: {"before_m", "after_ba_m", "after_m", "matched"} with ground truth
    ba: dict = field(default_factory=dict)   #: the bundle adjustment's counts and reprojection RMS (when run)
    nav: dict = field(default_factory=dict)  #: the nav factors used (with --nav)

    def to_json(self) -> dict:
        d = {"poses": self.poses, "keyframes": self.keyframes, "priors": self.priors, "rounds": self.rounds,
             "rounds_kept": self.rounds_kept, "c2m_before": self.c2m_before.to_json(),
             "c2m_after": self.c2m_after.to_json(), "c2m_max_m": self.c2m_max_m,
             "median_depth_m": self.median_depth_m, "global_correction": self.global_correction,
             "output": self.output, "config": self.config, "elapsed_s": self.elapsed_s}
        if self.ate:
            d["ate"] = self.ate
        if self.ba:
            d["ba"] = self.ba
        if self.nav:
            d["nav"] = self.nav
        return d


def c2m_stats(surface: ModelSurface, X: np.ndarray, near: np.ndarray, max_m: float) -> C2MStats:
    """Distances of the samples ``near`` (chosen once, at the given poses) capped at ``max_m``: a
    sample moved away from the model counts ``max_m``, so no pose set gains by pushing samples out."""
    d = np.minimum(surface.distance(X[near]), max_m)
    if not len(d):
        return C2MStats(float("inf"), float("inf"), float("inf"), float("inf"), 0, 0.0)
    return C2MStats(float(d.mean()), float(np.median(d)), float(np.sqrt(np.mean(d**2))),
                    float(np.percentile(d, 95)), int(len(d)), float(len(d) / len(X)))


def ate_rmse(t: np.ndarray, T: np.ndarray, t_gt: np.ndarray, T_gt: np.ndarray) -> tuple[float, int]:
    """Position RMSE (m, model frame, no alignment: the model frame is the reference) of the poses
    whose time matches a ground-truth time within a quarter of its median spacing."""
    dt = np.median(np.diff(t_gt)) if len(t_gt) > 1 else 1.0
    j = np.clip(np.searchsorted(t_gt, t), 1, len(t_gt) - 1) if len(t_gt) > 1 else np.zeros(len(t), int)
    if len(t_gt) > 1:
        j = np.where(np.abs(t_gt[j - 1] - t) < np.abs(t_gt[j] - t), j - 1, j)
    ok = np.abs(t_gt[j] - t) <= 0.25 * dt
    if not ok.any():
        return float("nan"), 0
    e = np.linalg.norm(T[ok, :3, 3] - T_gt[j[ok], :3, 3], axis=1)
    return float(np.sqrt(np.mean(e**2))), int(ok.sum())


def _keyframe_clouds(cfg, files, k_of_pose, cam, sel, rng):
    """-> (keyframe pose indices, their camera-frame samples, their normals)."""
    kf, clouds, normals = [], [], []
    for i in sel:
        f = files[k_of_pose[i]]
        depth = read_depth(f, cfg.depth.scale)
        if cam.width and cam.height and depth.shape != (cam.height, cam.width):
            raise InputError(f, f"depth frame is {depth.shape[1]}x{depth.shape[0]} but the camera is for "
                                f"{cam.width}x{cam.height} images (the depth must be registered to the tracked camera)")
        P, N = backproject(depth, cam, cfg.pixel_step, cfg.depth.min_m, cfg.depth.max_m, cfg.depth.edge_rel or 1e9)
        if len(P) < cfg.min_points:
            continue
        if len(P) > MAX_KF_POINTS:
            pick = rng.choice(len(P), MAX_KF_POINTS, replace=False)
            P, N = P[pick], N[pick]
        kf.append(i)
        clouds.append(P)
        normals.append(N)
    return kf, clouds, normals


def _round(surface, cfg, clouds, normals, T_kf, Z, med):
    """One round: rigid ICP of the fused cloud, then the keyframe pose graph. -> (poses, priors, G)."""
    X, NX = fused_points(clouds, T_kf), fused_points(normals, T_kf, rotate_only=True)
    rng = np.random.default_rng(cfg.seed)
    if len(X) > MAX_GLOBAL_POINTS:
        pick = rng.choice(len(X), MAX_GLOBAL_POINTS, replace=False)
        X, NX = X[pick], NX[pick]
    dists = tuple(r * med for r in cfg.icp_max_rel)
    near = surface.near(X, dists[0])
    G, *_ = surface.icp(X[near], NX[near], np.eye(4), dists, cfg.tukey_rel * med, cfg.icp_iterations,
                        cfg.max_normal_deg)
    T_kf = G @ T_kf
    priors = []
    for i, (P, N, T) in enumerate(zip(clouds, normals, T_kf)):
        near = surface.near(transform_points(T, P), dists[0])  # the scene far from the model cannot match
        P, N = P[near], N[near]
        if len(P) > MAX_ICP_POINTS:
            pick = rng.choice(len(P), MAX_ICP_POINTS, replace=False)
            P, N = P[pick], N[pick]
        if len(P) < cfg.min_points:
            continue
        T_icp, n_in, rmse, info = surface.icp(P, N, T, dists[1:] or dists, cfg.tukey_rel * med, cfg.icp_iterations,
                                              cfg.max_normal_deg)
        if n_in < cfg.min_points:
            continue
        sigma = max(rmse, 1e-4 * med)
        priors.append(Prior(i, T_icp, info * min(1.0, cfg.prior_points_eff / n_in) / sigma**2))
    T_new = solve_pose_graph(T_kf, Z, priors, cfg.between_sigma_rel * med, np.radians(cfg.between_sigma_deg))
    return T_new, priors, G


def _keyframe_grays(frames_path, ks: np.ndarray, cam) -> list[np.ndarray]:
    """The frames ``ks`` (indices into the source) as 8-bit gray images of the camera's size."""
    from mst.core.klt import to_gray
    from mst.pipeline.frames import open_frames

    src = open_frames(frames_path)
    if cam.width and cam.height and (src.width, src.height) != (cam.width, cam.height):
        raise InputError(frames_path, f"frames are {src.width}x{src.height} but the camera is for {cam.width}x{cam.height}")
    if int(ks.max()) >= len(src):
        raise InputError(frames_path, f"{len(src)} frames, but the trajectory needs frame {int(ks.max())}")
    want = {int(k): None for k in ks}
    if src.kind == "images":
        import cv2

        for k in want:
            img = cv2.imread(str(src.files[src.indices[k]]), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(src.files[src.indices[k]], "image could not be read")
            want[k] = to_gray(src._resize(img))
    else:
        for j, (_, _, img) in enumerate(src):
            if j in want:
                want[j] = to_gray(img)
    return [want[int(k)] for k in ks]


def _keyframe_covariances(traj_path, cov_path, t_kf, T_kf, cfg: RefineConfig, med: float) -> tuple[np.ndarray, int]:
    """Prior covariances of the keyframes (model-frame position, rotation; :mod:`.ba`): ``mst
    track``'s ``traj.cov.csv`` (given, or beside the trajectory) x ``ba_prior_scale``, the fallback
    sigmas where a frame has none. Returns (C (n, 6, 6), frames with the tracker's covariance)."""
    from dataclasses import replace

    from mst.pipeline.nav.run import _is_track_cov, cov_path_for, read_track_cov

    s_t, s_r = cfg.ba_fallback_sigma_rel * med, np.radians(cfg.ba_fallback_sigma_deg)
    fallback = np.diag([s_t**2] * 3 + [s_r**2] * 3)
    cp = Path(cov_path) if cov_path else cov_path_for(traj_path)
    if not cp.is_file():
        if cov_path:
            raise InputError(cp, "covariance file does not exist")
        return np.tile(fallback, (len(t_kf), 1, 1)), 0
    if not _is_track_cov(cp):
        raise InputError(cp, "not mst track's per-frame covariance file (frame, c00..c55 columns)")
    # read_track_cov gives frames without a covariance 3x its vision sigmas: set them to the fallback
    ncfg = replace(cfg.nav, vision_sigma_m=s_t / 3.0, vision_sigma_deg=cfg.ba_fallback_sigma_deg / 3.0)
    C = read_track_cov(cp, traj_path, t_kf, T_kf, ncfg)
    is_fb = np.all(np.isclose(C, fallback[None], rtol=1e-9, atol=0), axis=(1, 2))
    C[~is_fb] *= cfg.ba_prior_scale
    return C, int((~is_fb).sum())


def _run_ba(cfg, traj_path, cov_path, frames_path, nav_path, files, k_kf, t_kf, T_kf, cam, med, t_all, T_all,
            m2w_path=None):
    """The bundle adjustment stage: -> (refined keyframe poses, BA summary, nav summary)."""
    from mst.pipeline.refine.ba import bundle_adjust, klt_tie_tracks, nav_factors

    C, n_cov = _keyframe_covariances(traj_path, cov_path, t_kf, T_kf, cfg, med)
    grays = _keyframe_grays(frames_path, k_kf, cam)
    depths = [read_depth(files[k], cfg.depth.scale) for k in k_kf]
    ties = klt_tie_tracks(grays, depths, cam, T_kf, cfg.klt, cfg.ba_min_track)
    nav_f, nav_info = None, {}
    if nav_path is not None:
        from mst.core.poses import read_rigid_transform
        from mst.pipeline.nav.fusion import fuse_navigation
        from mst.pipeline.nav.log import read_navlog

        nav = read_navlog(nav_path)
        T_wm = read_rigid_transform(m2w_path, "model-to-world file") if m2w_path is not None else None
        res = fuse_navigation(t_all, T_all, None, nav, cfg.nav, nav_name=nav_path, T_world_model=T_wm)  # calibration
        nav.t = nav.t + res.calib["time_offset_s"]
        sig = np.array([cfg.nav.gps_sigma_h_m, cfg.nav.gps_sigma_h_m, cfg.nav.gps_sigma_v_m])
        nav_f = nav_factors(t_kf, T_kf, nav, res.T_world_model, res.R_body_cam, cfg.nav.lever_arm_m, sig,
                            np.radians(cfg.nav.ahrs_sigma_deg))
        nav_info = {"gps_factors": int(nav_f.has_p.sum()), "ahrs_factors": int(nav_f.has_R.sum()),
                    "world_yaw_deg": res.calib["world_yaw_deg"], "mount_ypr_deg": res.calib["mount_ypr_deg"]}
    if len(ties.X0) == 0 and nav_f is None:
        log.info("bundle adjustment skipped: no KLT track spans %d keyframes", cfg.ba_min_track)
        return T_kf, {"points": 0, "skipped": "no tie points", "priors_from_tracker": n_cov}, nav_info
    r = bundle_adjust(T_kf, C, ties, cam, cfg.ba_sigma_px, cfg.ba_huber, nav_f, cfg.ba_iterations, cfg.ba_max_px,
                      cfg.ba_min_track)
    return r.T_kf, {**r.to_json(), "priors_from_tracker": n_cov}, nav_info


def refine(traj_path: str | os.PathLike, model_path: str | os.PathLike, camera_path: str | os.PathLike,
           depth_dir: str | os.PathLike, out_path: str | os.PathLike, config: RefineConfig | None = None,
           gt_path: str | os.PathLike | None = None, frames_path: str | os.PathLike | None = None,
           nav_path: str | os.PathLike | None = None, cov_path: str | os.PathLike | None = None,
           m2w_path: str | os.PathLike | None = None) -> RefineSummary:
    """Refine ``traj_path`` (TUM ``T_model_cam``) against the model with the depth frames; write
    ``out_path`` (TUM, the same times). With ``frames_path`` (the tracked images) and ``cfg.ba``:
    first a bundle adjustment of the keyframes (:mod:`mst.pipeline.refine.ba`; priors from
    ``cov_path`` or the trajectory's ``.cov.csv``, nav factors from ``nav_path``, its model-to-world
    transform from ``m2w_path`` or estimated). Raises
    :class:`InputError` for bad input, before writing."""
    cfg = config or RefineConfig()
    t0 = time.perf_counter()
    t, T_all = read_tum(traj_path)
    k_of_pose = frame_index_of_times(t, cfg.fps, traj_path)
    files = list_depth_frames(depth_dir)
    cam = read_camera(camera_path)
    V, F = load_triangles(model_path)
    gt = read_tum(gt_path) if gt_path is not None else None
    past = k_of_pose >= len(files)
    if past.any():
        raise InputError(traj_path, f"{int(past.sum())} of {len(t)} poses point past the last of {len(files)} depth "
                                    f"frames (e.g. time {t[np.argmax(past)]:g} -> frame {int(k_of_pose[past][0])}; "
                                    "wrong fps, or a trajectory of another sequence?)")
    has_depth = np.arange(len(t))
    sel = list(has_depth[::cfg.keyframe_every])
    if sel[-1] != has_depth[-1]:
        sel.append(int(has_depth[-1]))
    rng = np.random.default_rng(cfg.seed)
    kf, clouds, normals = _keyframe_clouds(cfg, files, k_of_pose, cam, sel, rng)
    if not kf:
        raise InputError(depth_dir, f"no keyframe has {cfg.min_points} valid depth samples "
                                    f"(depth range {cfg.depth.min_m:g}-{cfg.depth.max_m:g} m, scale {cfg.depth.scale:g})")
    kf = np.array(kf)
    med = float(np.median(np.concatenate([P[:, 2] for P in clouds])))
    surface = ModelSurface(np.asarray(V, np.float64), np.asarray(F, np.int64), cfg.model_samples, cfg.seed)
    c2m_max = cfg.c2m_max_rel * med
    T_kf0 = T_all[kf]
    best = T_kf0
    X0 = fused_points(clouds, best)
    near = surface.distance(X0) < c2m_max
    before = score = c2m_stats(surface, X0, near, c2m_max)
    if before.points == 0:
        raise InputError(depth_dir, f"no depth sample lies within {c2m_max:.3g} m of the model at the given poses "
                                    "(another model, or a trajectory of another sequence?)")
    ba_info, nav_info, T_ba = {}, {}, None
    if nav_path is not None and not (cfg.ba and frames_path is not None):
        raise InputError(nav_path, "nav factors are part of the bundle adjustment: give the frames (--frames) "
                                   "and keep ba on")
    if cfg.ba and frames_path is not None:
        T_ba, ba_info, nav_info = _run_ba(cfg, traj_path, cov_path, frames_path, nav_path, files, k_of_pose[kf], t[kf],
                                          T_kf0, cam, med, t, T_all, m2w_path)
        best = T_ba
        score = c2m_stats(surface, fused_points(clouds, best), near, c2m_max)
        log.info(f"bundle adjustment: mean C2M {before.mean_m:.4g} -> {score.mean_m:.4g} m")
    # the relative motions the pose graph keeps: the bundle-adjusted ones when run
    Z = inv_T(best[:-1]) @ best[1:]
    rounds = kept = 0
    n_priors, G0 = 0, np.eye(4)
    for r in range(cfg.rounds):
        rounds += 1
        T_new, priors, G = _round(surface, cfg, clouds, normals, best, Z, med)
        if r == 0:
            G0 = G
        s = c2m_stats(surface, fused_points(clouds, T_new), near, c2m_max)
        log.info(f"round {r + 1}: mean C2M {score.mean_m:.4g} -> {s.mean_m:.4g} m ({len(priors)}/{len(kf)} priors)")
        if not s.mean_m < score.mean_m:
            break
        gain = 1 - s.mean_m / score.mean_m
        best, score, kept, n_priors = T_new, s, kept + 1, len(priors)
        if gain < cfg.min_gain:
            break
    if T_ba is not None and not score.mean_m <= before.mean_m:  # never further from the model than the input
        log.info("the bundle adjustment and ICP rounds did not lower the mean C2M: the input poses are kept")
        best, score, T_ba = T_kf0, before, None
    changed = kept or T_ba is not None
    T_out = interpolate_corrections(k_of_pose[kf], T_kf0, best, k_of_pose, T_all) if changed else T_all
    ate = {}
    if gt is not None:
        b, m = ate_rmse(t, T_all, *gt)
        a, _ = ate_rmse(t, T_out, *gt)
        if m == 0:
            raise InputError(gt_path, "no ground-truth time matches a trajectory time")
        ate = {"before_m": b, "after_m": a, "matched": m}
        if T_ba is not None:
            ate["after_ba_m"] = ate_rmse(t, interpolate_corrections(k_of_pose[kf], T_kf0, T_ba, k_of_pose, T_all), *gt)[0]
    from mst.core.poses import rotation_angle_deg

    with atomic_output(out_path) as tmp:
        write_tum(tmp, t, T_out, header=f"mst refine of {Path(traj_path).name}: T_model_cam, metres")
    return RefineSummary(
        poses=len(t), keyframes=len(kf), priors=n_priors, rounds=rounds, rounds_kept=kept, c2m_before=before,
        c2m_after=score, c2m_max_m=c2m_max, median_depth_m=med,
        global_correction={"translation_m": float(np.linalg.norm(G0[:3, 3])),
                           "rotation_deg": float(rotation_angle_deg(G0[:3, :3]))},
        output=str(out_path), config=cfg.to_dict(), elapsed_s=time.perf_counter() - t0, ate=ate, ba=ba_info,
        nav=nav_info)
