"""The local bundle adjustment of the SLAM aid (pycolmap / pyceres), guarded by the model priors.

At each keyframe the last ``ba_window`` keyframes and the landmarks seen by at least two of them
are adjusted: first unconstrained (reference reprojection RMSE ``e0``, gauge held by the two oldest
keyframes), then with ``AbsolutePosePriorCost`` priors from the keyframes' model poses (covariance
``sigma_e^2 W^-1``). The constrained result is kept only when its RMSE stays below
``ba_guard_ratio * e0 + ba_guard_px`` (Lhuillier's scheme); else the priors are down-weighted
(x100) and, failing that, dropped. Keyframes with few observations in the window keep their pose.

:class:`LocalBA` is one part of :class:`mst.pipeline.slam.aid.ModelAidedSlam` (a mixin on its
keyframe window ``kfs`` and landmarks ``lm``); the pycolmap steps are module functions.
"""

from __future__ import annotations

import numpy as np

from mst.pipeline.slam.geometry import prior_covariance_wv
from mst.pipeline.slam.state import STATUS_SLAM, Keyframe


def _colmap_camera(cam, K: np.ndarray, dist: np.ndarray | None):
    """The colour camera as a pycolmap camera (PINHOLE, or OPENCV with the first 4 coefficients)."""
    import pycolmap

    if dist is None:
        return pycolmap.Camera(model="PINHOLE", width=cam.width or 640, height=cam.height or 480,
                               params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=1)
    d = np.zeros(4)
    d[: min(4, len(dist))] = dist[:4]
    return pycolmap.Camera(model="OPENCV", width=cam.width or 640, height=cam.height or 480,
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d], camera_id=1)


def _build(cam, kfs: list[Keyframe], u: np.ndarray, lm: dict[int, np.ndarray]):
    """A reconstruction of the window: one image per keyframe, the landmarks ``u``, their observations."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    obs_idx = []
    for i, kf in enumerate(kfs):
        sel = np.flatnonzero(np.isin(kf.tids, u))
        obs_idx.append(sel)
        img = pycolmap.Image(name=f"{i}", points2D=pycolmap.Point2DList(
            [pycolmap.Point2D(xy) for xy in kf.uv[sel].astype(np.float64)]), camera_id=1, image_id=i + 1)
        T = kf.T_cam_model
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy()))
    pid_of = {}
    for t in u:
        pid_of[int(t)] = rec.add_point3D(lm[int(t)], pycolmap.Track())
    for i, kf in enumerate(kfs):
        for j, t in enumerate(kf.tids[obs_idx[i]]):
            pid = pid_of[int(t)]
            rec.add_observation(pid, pycolmap.TrackElement(i + 1, j))
    return rec, pid_of


def _options(cfg):
    import pycolmap

    bo = pycolmap.BundleAdjustmentOptions()
    bo.refine_focal_length = False
    bo.refine_principal_point = False
    bo.refine_extra_params = False
    bo.print_summary = False
    bo.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    bo.ceres.loss_function_scale = cfg.ba_loss_px
    bo.ceres.solver_options.max_num_iterations = cfg.ba_iterations
    bo.ceres.solver_options.num_threads = 1
    return bo


def _rmse(rec, cfg) -> float:
    rec.update_point_3d_errors()
    errs = np.array([p.error for p in rec.points3D.values()])
    # robust: ignore gross outliers (they are removed afterwards)
    errs = errs[errs < 4 * cfg.ba_max_error_px]
    return float(np.sqrt(np.mean(errs**2))) if len(errs) else np.inf


def _solve(rec, n_kfs: int, priors: list[tuple[int, np.ndarray, np.ndarray]], fixed: list[int], weak: set[int], cfg) -> None:
    """Adjust ``rec`` in place: keyframes ``fixed`` and ``weak`` held, ``priors`` (index, covariance
    in COLMAP's (rotation, translation) order, model pose) as pose prior costs."""
    import pyceres
    import pycolmap
    import pycolmap.cost_functions as cf

    bo = _options(cfg)
    bc = pycolmap.BundleAdjustmentConfig()
    for i in range(n_kfs):
        bc.add_image(i + 1)
    bc.set_constant_cam_intrinsics(1)
    for i in sorted(set(fixed) | weak):
        bc.set_constant_rig_from_world_pose(i + 1)
    ba = pycolmap.create_default_ceres_bundle_adjuster(bo, bc, rec)
    prob = ba.problem
    for i, cov, Tp in priors:
        prob.add_residual_block(cf.AbsolutePosePriorCost(cov, pycolmap.Rigid3d(
            pycolmap.Rotation3d(Tp[:3, :3]), Tp[:3, 3].copy())), None, [rec.frame(i + 1).rig_from_world.params])
    summ = pyceres.SolverSummary()
    pyceres.solve(bo.ceres.create_solver_options(bc, prob), prob, summ)


def _window_landmarks(kfs: list[Keyframe], lm: dict[int, np.ndarray], max_points: int) -> np.ndarray:
    """Landmark ids seen by >= 2 window keyframes (the ``max_points`` most observed)."""
    all_t = np.concatenate([kf.tids for kf in kfs])
    u, cnt = np.unique(all_t, return_counts=True)
    u = u[cnt >= 2]
    u = np.array([t for t in u if int(t) in lm], np.int64)
    if len(u) > max_points:
        c2 = cnt[np.isin(np.unique(all_t), u)]
        u = np.sort(u[np.argsort(-c2, kind="stable")[: max_points]])
    return u


class LocalBA:
    """The guarded, model-constrained local BA of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`."""

    def _local_ba(self, status: str) -> np.ndarray:
        """Guarded, model-constrained local BA over the keyframe window; returns the current pose."""
        import time

        t0 = time.perf_counter()
        try:
            return self._local_ba_impl(status)
        except (RuntimeError, ValueError, np.linalg.LinAlgError):  # a degenerate window: skip this BA
            self.stats["ba_errors"] += 1
            return self.kfs[-1].T_cam_model.copy()
        finally:
            self.timing_ms["ba"] += (time.perf_counter() - t0) * 1e3
            self.stats["ba_runs"] += 1

    def _local_ba_impl(self, status: str) -> np.ndarray:
        import pycolmap

        cfg = self.cfg
        kfs = list(self.kfs)
        cur = kfs[-1]
        T_in = cur.T_cam_model.copy()   # this frame's output pose before the BA
        u = _window_landmarks(kfs, self.lm, cfg.ba_max_points)
        if len(u) < 10:
            return cur.T_cam_model
        cam = _colmap_camera(self.cam, self.K, self.dist)
        # keyframes with few observations in this BA are held (a free, weakly observed pose wanders)
        n_obs = [int(np.isin(kf.tids, u).sum()) for kf in kfs]
        weak = {i for i, n in enumerate(n_obs) if n < cfg.ba_min_observations}
        # 1) unconstrained BA, gauge fixed by the two oldest keyframes (scale too, for mono)
        rec_init, pid_of = _build(cam, kfs, u, self.lm)
        rec0 = pycolmap.Reconstruction(rec_init)
        _solve(rec0, len(kfs), [], [0, 1], weak, cfg)
        e0 = _rmse(rec0, cfg)
        # 2) constrained BA with the model priors
        priors = [(i, prior_covariance_wv(kf.prior_W, cfg.edge_sigma_px), kf.prior_T_cam_model)
                  for i, kf in enumerate(kfs) if kf.prior_W is not None and kf.prior_T_cam_model is not None]
        result = rec0
        if priors:
            # two or more 6-DoF priors fix the gauge (scale included); with one, the oldest
            # keyframe keeps the scale
            fixed = [] if len(priors) >= 2 else [0]
            bound = cfg.ba_guard_ratio * e0 + cfg.ba_guard_px
            for scale, key in ((1.0, "ba_prior_accepted"), (100.0, "ba_prior_downweighted")):
                rec1 = pycolmap.Reconstruction(rec_init)
                _solve(rec1, len(kfs), [(i, c * scale, Tp) for i, c, Tp in priors], fixed, weak, cfg)
                if _rmse(rec1, cfg) <= bound:
                    result = rec1
                    self.stats[key] += 1
                    break
            else:
                self.stats["ba_prior_dropped"] += 1
        # write back: keyframe poses, landmarks; drop landmarks with large errors
        for i, kf in enumerate(kfs):
            kf.T_cam_model = np.eye(4)
            kf.T_cam_model[:3] = result.image(i + 1).cam_from_world().matrix()
        result.update_point_3d_errors()
        for t, pid in pid_of.items():
            p = result.point3D(pid)
            if p.error > cfg.ba_max_error_px or not np.isfinite(p.xyz).all():
                self.lm.pop(t, None)
                self.lm_sig.pop(t, None)
            else:
                self.lm[t] = np.asarray(p.xyz, float).copy()
        if status != STATUS_SLAM:
            return T_in  # under a model pose the output stays the (fused) model pose
        return cur.T_cam_model.copy()
