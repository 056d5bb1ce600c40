"""``mst track``'s runner: read the inputs, run a :class:`~mst.pipeline.tracking.session.TrackingSession`
over the frames, write ``traj.txt`` / ``traj.csv`` / ``traj.cov.csv`` (and ``traj.json``) atomically,
return a typed :class:`TrackSummary`.

Frames: files hold ``T_model_cam`` (TUM); the session works in ``T_cam_model`` (ViSP cMo).
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError, atomic_outputs
from mst.core.poses import matmul_exact
from mst.errors import ConfigError
from mst.meshtools.formats import load_tracking_model
from mst.pipeline.tracking.budget import PoseBudget, is_refusal, positive_definite
from mst.pipeline.tracking.config import TrackConfig
from mst.pipeline.tracking.exact import centre, eigvalsh, rigid
from mst.pipeline.tracking.health import HealthMonitor
from mst.pipeline.tracking.runlog import RunLog
from mst.pipeline.tracking.session import OUTPUT_STATUSES, TrackingPolicy, TrackingSession

log = logging.getLogger(__name__)

#: ``traj.csv`` columns (see :meth:`FrameRecord.csv_row`)
CSV_HEADER = ["frame", "time", "status", "samples", "inliers", "residual_px", "health", "ms", "score", "aid", "reason"]

#: ``<stem>.cov.csv``: per frame the 6x6 covariance of the output pose (empty when lost): the twist
#: ``xi = (v, w)`` of the left perturbation ``T_cam_model' = exp(xi) T_cam_model`` (v metres, w radians,
#: camera frame). For an edge (VVS) pose (status ``model``, ``relocalised``) the cluster-robust covariance
#: of :mod:`mst.pipeline.tracking.covariance` (floored by ``sigma^2 (J^T W J)^-1``); for a map pose
#: (``slam``) the SLAM aid's propagated drift covariance, which grows away from the last model anchor
#: (:meth:`mst.pipeline.slam.drift.DriftBudget.sig_cov`, the uncertainty its drift budget judges); only
#: where it is symmetric positive definite as written; and derived 1-sigma values: the camera position in the model frame
#: (``std_x_m .. std_z_m``, covariance ``R^T C_vv R``) and the rotation (``std_rot_deg``, the
#: square root of the largest eigenvalue of ``C_ww``).
COV_HEADER = (["frame", "status", "std_x_m", "std_y_m", "std_z_m", "std_rot_deg"]
              + [f"c{i}{j}" for i in range(6) for j in range(6)])


# ---------------------------------------------------------------------------- model and pose checks
def check_pose_in_view(model, T_cam_model: np.ndarray, cam, path, near: float = 1e-6) -> None:
    """Raise :class:`mst.InputError` when the pose puts the model behind the camera or out of view."""
    V = np.asarray(model.vertices)
    Xc = rigid(V, T_cam_model[:3, :3], T_cam_model[:3, 3])
    cz = float(Xc[:, 2].mean())
    ext = float(np.ptp(V, axis=0).max()) if len(V) else 0.0
    c = centre(T_cam_model)
    units = (f"; the model spans {ext:.4g} units: is it in millimetres? mst expects metres" if ext > 50
             and (c > V.min(0)).all() and (c < V.max(0)).all() else "")
    if cz <= 0 or (Xc[:, 2] <= near).all():
        raise InputError(path, f"the pose puts the model behind the camera (model centre at z = {cz:.3g} m in the "
                               f"camera frame; expected a cMo / TUM camera pose looking at the model){units}")
    front = Xc[:, 2] > near
    uv = Xc[front, :2] / Xc[front, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    if cam.width and not inside.any():
        raise InputError(path, "the pose puts the whole model outside the image")


# ---------------------------------------------------------------------------- outputs
def _psd_text(cov: np.ndarray) -> list[str] | None:
    """The 36 entries of ``cov`` as written (6 significant digits; 17 where rounding to 6 would leave a
    strongly correlated covariance indefinite), or None when the written matrix would not be symmetric
    positive definite (not finite, a variance <= 0, a negative eigenvalue: no covariance is written)."""
    if not np.isfinite(cov).all():
        return None
    C = 0.5 * (cov + cov.T)
    for fmt in (".6g", ".17g"):
        txt = [f"{x:{fmt}}" for x in C.ravel()]
        if positive_definite(np.array([float(x) for x in txt]).reshape(6, 6)):
            return txt
    return None


def cov_row(idx: int, status: str, cov: np.ndarray | None, T_cam_model: np.ndarray | None) -> list:
    """One ``.cov.csv`` row (see :data:`COV_HEADER`); empty where the frame has no output pose or no
    covariance, or its covariance is not symmetric positive definite as written (:func:`_psd_text`: a singular fit
    at a re-acquisition had been written with negative variances of 1e10, which ``mst nav fuse`` refuses)."""
    txt = None if status == "lost" or cov is None or T_cam_model is None else _psd_text(np.asarray(cov, float))
    if txt is None:
        return [idx, status] + [""] * (len(COV_HEADER) - 2)
    cov = np.array([float(x) for x in txt]).reshape(6, 6)
    R = T_cam_model[:3, :3]
    C_pos = matmul_exact(matmul_exact(R.T, cov[:3, :3]), R)  # camera centre c = -R^T t moves by -R^T v
    std = np.sqrt(np.maximum(np.diag(C_pos), 0.0))
    rot = np.degrees(np.sqrt(max(float(eigvalsh(cov[3:, 3:]).max()), 0.0)))
    return [idx, status, *(f"{x:.6g}" for x in std), f"{rot:.6g}", *txt]


def _mean_or_none(vals: list[float]) -> float | None:
    """Mean of the finite values (None when there is none: JSON has no NaN)."""
    a = np.asarray(vals, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else None


@dataclass
class TrackSummary:
    """What ``mst track`` reports (``--json``): one name per quantity.

    ``frames`` processed, ``tracked`` (an output pose: model + slam + relocalised), per-status
    counts, timing (ms per frame), residual/health statistics, the aid used and its wake-ups, the
    effective ``config`` (``--config`` of it repeats the run) and the output paths. Optional parts
    (``render_edges``, ``merged_mesh`` (triangles, polygons, merge CPU ms), ``landmarks``, ``relocalisation``, ``static_world_frames``, ``map_refuted_frames``, ``aid_wake*``)
    are left out of the JSON when they do not apply. Indexable like its JSON (``s["tracked"]``).
    """

    frames: int
    tracked: int
    status_counts: dict
    first_lost_frame: int | None
    median_ms: float | None
    p95_ms: float | None
    mean_residual_px: float | None
    mean_proj_error_deg: float | None
    health_score_rejects: int
    health_score_median: float | None
    health_score_min: float | None
    aid: str
    edges: str
    traj: str
    csv: str
    cov_csv: str
    camera: dict
    config: dict
    optional: dict = field(default_factory=dict)  #: the parts that apply to this run only

    @property
    def lost(self) -> int:
        return self.status_counts["lost"]

    def to_json(self) -> dict:
        sc = self.status_counts
        d = {"frames": self.frames, "tracked": self.tracked, "lost": sc["lost"], "model": sc["model"], "slam": sc["slam"],
             "first_lost_frame": self.first_lost_frame, "median_ms": self.median_ms, "p95_ms": self.p95_ms,
             "mean_residual_px": self.mean_residual_px, "mean_proj_error_deg": self.mean_proj_error_deg,
             "status_counts": dict(sc), "health_score_rejects": self.health_score_rejects,
             "health_score_median": self.health_score_median, "health_score_min": self.health_score_min,
             "aid": self.aid, "edges": self.edges, "traj": self.traj, "csv": self.csv, "cov_csv": self.cov_csv,
             "camera": self.camera, "config": self.config}
        d.update(self.optional)
        return d

    def __getitem__(self, key: str):
        return self.to_json()[key]

    def get(self, key: str, default=None):
        return self.to_json().get(key, default)


def _summary(records: RunLog, session: TrackingSession, aid_mode: str, edges_used: str, paths, cam,
             cfg: TrackConfig, landmarks) -> TrackSummary:
    n = len(records)
    statuses = records.statuses()
    ms = records.ms[:n]
    scores = records.score[:n]
    scores = scores[np.isfinite(scores)]
    opt: dict = {}
    tracker, aid, reloc = session.tracker, session.aid, session.reloc
    if tracker.sample_provider is not None:
        opt["render_edges"] = tracker.sample_provider.stats()
    if getattr(tracker, "merge_stats", None):
        opt["merged_mesh"] = tracker.merge_stats
    if landmarks is not None:
        opt["landmarks"] = int(len(landmarks))
    if reloc is not None:
        st = reloc.stats
        opt["relocalisation"] = {"keyframes": st["keyframes"], "attempts": st["attempts"], "pnp_poses": st["pnp_poses"],
                                 "ms_per_attempt": st["ms_attempts"] / st["attempts"] if st["attempts"] else None,
                                 "ms_learn_total": st["ms_learn"]}
    fired = getattr(aid, "static_world_fired", None) if aid is not None else None
    if fired is not None:
        opt["static_world_frames"] = [int(f) for f in fired]
    refuted = getattr(aid, "map_refuted", None) if aid is not None else None
    if refuted is not None:
        # frames whose map pose the image refuted with the model in view (not output: lost)
        opt["map_refuted_frames"] = [int(f) for f in refuted]
    relocs = getattr(aid, "map_relocalisations", None) if aid is not None else None
    if relocs is not None:
        # the map's own relocalisations (ORB against its keyframes) and those its motion gate refused
        opt["map_relocalisations"] = dict(relocs)
    beyond = getattr(aid, "drift_budget_frames", None) if aid is not None else None
    if beyond is not None and aid.drift_log:
        # map poses whose propagated uncertainty exceeded the drift budget (not output: lost), and the
        # bound of every map pose: frame -> [bound / model distance, bound deg]
        opt["drift_budget_frames"] = [int(f) for f in beyond]
        opt["slam_uncertainty"] = {str(k): [float(a), float(b)] for k, (a, b) in sorted(aid.drift_log.items())}
    ref = session.policy.refusals
    if ref.budget_frames or ref.ambiguous_frames:
        # edge poses refused by the error budget (lost): their own uncertainty beyond it, or two fits
        # of the image beyond it apart (TrackingPolicy.beyond_budget / TrackingSession._ambiguous)
        opt["pose_budget_frames"] = list(ref.budget_frames)
        opt["ambiguous_frames"] = list(ref.ambiguous_frames)
    if aid is not None and "wakes" in getattr(aid, "stats", {}):
        # the default aid: how often (and where) the mono SLAM was switched on, its replay cost
        opt["aid_wakes"] = int(aid.stats["wakes"])
        opt["aid_wake_frames"] = list(aid.stats["wake_frames"])
        opt["aid_active_frames"] = int(aid.stats["frames_active"])
        opt["aid_wake_ms"] = float(aid.timing_ms["wake"])
    scores_n = len(scores)
    return TrackSummary(
        frames=n, tracked=sum(s != "lost" for s in statuses),
        status_counts={k: statuses.count(k) for k in OUTPUT_STATUSES},
        first_lost_frame=next((int(records.index[i]) for i, s in enumerate(statuses) if s == "lost"), None),
        median_ms=float(np.median(ms)) if n else None, p95_ms=float(np.percentile(ms, 95)) if n else None,
        # the CSV's rounding: the statistics are those of the written rows
        mean_residual_px=_mean_or_none(records.residual_px[:n]),
        mean_proj_error_deg=float(np.mean(records.proj_error_deg[:n])) if n else None,
        health_score_rejects=session.policy.n_score_rejects,
        health_score_median=float(np.median(scores)) if scores_n else None,
        health_score_min=float(scores.min()) if scores_n else None,
        aid=aid_mode, edges=edges_used, traj=str(paths[0]), csv=str(paths[1]), cov_csv=str(paths[2]),
        camera=cam.to_dict(), config=cfg.to_dict(), optional=opt)


def _write_outputs(paths, records: RunLog, summary: TrackSummary, landmarks, ov) -> None:
    """traj.txt, traj.csv, traj.cov.csv (+ json, landmarks, overlay), all or nothing."""
    import json

    from mst.core.poses import inv_T
    from mst.core.trajectory import format_tum

    out_traj, csv_path, cov_path, json_path, landmarks_path = paths
    n = len(records)
    statuses, T_all, ok = records.statuses(), records.poses(), records.tracked()
    times = records.time_s[:n][ok]
    poses = np.array([inv_T(T) for T in T_all[ok]])
    with atomic_outputs(out_traj, csv_path, cov_path, json_path, landmarks_path) as (tmp_traj, tmp_csv, tmp_cov, tmp_json,
                                                                                  tmp_lm):
        if tmp_lm is not None:
            from mst.pipeline.fusion import write_ply

            write_ply(tmp_lm, landmarks, comments=["mst track SLAM landmarks, model frame, metres"])
        tmp_traj.write_text("# mst track: TUM 't tx ty tz qx qy qz qw' camera pose in model frame, tracked frames only\n"
                            + (format_tum(times, poses) if ok.any() else ""))
        tmp_csv.write_text(records.csv_text(CSV_HEADER))
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COV_HEADER)
        w.writerows(cov_row(int(records.index[i]), statuses[i], records.covariance(i), T_all[i] if ok[i] else None)
                    for i in range(n))
        tmp_cov.write_text(buf.getvalue())
        if tmp_json is not None:
            tmp_json.write_text(json.dumps(summary.to_json(), indent=2,
                                           default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)) + "\n")
        if ov is not None:
            ov.close(commit=True)


# ---------------------------------------------------------------------------- the stage
def make_aid(cfg: TrackConfig, cam, depth_dir: Path | None, depth_camera, T_depth_color):
    """The SLAM aid of ``cfg.aid`` (``auto``: rgbd with depth frames, else the mono aid on standby)
    and its name in the summary; ``(None, "off")`` for ``off``."""
    mode = cfg.aid
    if mode == "off":
        return None, "off"
    if mode == "auto":
        # with depth: the rgbd aid always on; without: the mono aid on standby (see StandbyAid)
        mode = "rgbd" if depth_dir is not None else "standby"
    from mst.pipeline import slam

    aid = slam.make_aid(mode, cam, cfg.slam, depth_dir, depth_camera, T_depth_color, depth=cfg.depth)
    return aid, "mono-standby" if mode == "standby" else mode


def effective_config(cfg: TrackConfig, depth_dir) -> TrackConfig:
    """``cfg`` with ``use_klt`` resolved (None: on for the default mode, aid auto without depth:
    edges + KLT, measured best on teabox.mp4, README tracking section)."""
    if cfg.use_klt is None:
        return cfg.replace(use_klt=cfg.aid == "auto" and depth_dir is None)
    return cfg


def _check_aid_inputs(cfg: TrackConfig, depth_dir, landmarks_path) -> None:
    if depth_dir is not None and not Path(depth_dir).is_dir():
        raise InputError(depth_dir, "depth folder does not exist")
    if cfg.aid == "rgbd" and depth_dir is None:
        raise ConfigError("aid", "rgbd needs a folder of depth frames")
    if landmarks_path is not None and cfg.aid == "off":
        raise InputError(landmarks_path, "a landmark map needs a SLAM aid (mono, rgbd or auto)")
    if cfg.aid in ("off", "mono") and depth_dir is not None:
        log.info(f"the depth frames are not used with the {cfg.aid} aid")


def _no_frame_tracked(records: RunLog, policy: TrackingPolicy, init_pose_path):
    reason = policy.first_reason or "lost"
    k = records.first.index
    if "far clipping plane" in reason:
        # the setting is to blame, not the pose
        return ConfigError("edges.far_clip_m", f"no frame could be tracked: frame {k}: {reason}; raise or remove this "
                                               "setting (default: no far plane)")
    if "too small" in reason:
        hint = "the model is too far or too small for this camera"
    elif is_refusal(reason):
        # the first frame is judged by the error budget as every other: a pose its image does not
        # pin is no start to output from (Delft at 250 m, 640x480: frame 0 was 8 % off as `model`);
        # the evidence it had: its edge samples, and how many of them matched an image edge
        fr = records.first.result
        hint = (f"this image does not pin the pose within the error budget ({fr.n_inliers} of {fr.n_samples} "
                "model edge samples matched): a nearer view, a higher resolution, or a wider budget "
                "(slam.drift_budget_rel)")
    else:
        hint = "check the pose, the camera and the model units"
    return InputError(init_pose_path, f"no frame could be tracked from this initial pose (frame {k}: {reason}); {hint}")


def run_track(frames_spec: str | os.PathLike, model_path: str | os.PathLike, camera_path: str | os.PathLike,
              init_pose_path: str | os.PathLike, out_traj: str | os.PathLike, config: TrackConfig | None = None, *,
              frames: str | None = None, scale: float = 1.0, fps: float | None = None, overlay: str | None = None,
              depth_dir: str | os.PathLike | None = None, depth_camera_path=None, depth_to_color_path=None,
              landmarks_path: str | os.PathLike | None = None, write_json: bool = False, progress=None) -> TrackSummary:
    """Track a model through frames; write ``out_traj`` (TUM, tracked frames), ``.csv``, ``.cov.csv``
    (and ``.json`` with ``write_json``).

    ``config``: a :class:`TrackConfig` (its ``aid``, ``use_klt``, ``relocalise``, ``health_score``,
    ``edge_source`` and sections). ``init_pose_path``: the pose of the first selected frame (TUM line
    or 4x4 cMo). ``progress``: optional ``progress(total) -> context manager yielding advance()``
    (called after the input checks). Raises :class:`mst.InputError` / :class:`mst.errors.ConfigError`
    for bad input before anything is written.
    """
    from mst.core.camera import read_camera
    from mst.core.poses import read_rigid_transform
    from mst.core.trajectory import read_pose_file
    from mst.pipeline.frames import check_camera_size, open_frames
    from mst.pipeline.tracking.overlay import OverlayWriter

    cfg = effective_config(config or TrackConfig(), depth_dir)
    model = load_tracking_model(model_path)
    cam0 = read_camera(camera_path)
    src = open_frames(frames_spec, frames, scale, fps)
    cam = check_camera_size(src, cam0, camera_path)
    undistort_maps = _undistort_maps(cam)
    T0 = read_pose_file(init_pose_path)  # poses are metric: a --scale changes the intrinsics only
    check_pose_in_view(model, T0, cam, init_pose_path)
    depth_camera = read_camera(depth_camera_path) if depth_camera_path else None
    T_depth_color = read_rigid_transform(depth_to_color_path, "depth-to-colour file") if depth_to_color_path else None
    _check_aid_inputs(cfg, depth_dir, landmarks_path)
    aid, aid_mode = make_aid(cfg, cam, Path(depth_dir) if depth_dir else None, depth_camera, T_depth_color)
    session, edges_used = build_session(cfg, model, model_path, cam, T0, aid)
    out_traj = Path(out_traj)
    paths = (out_traj, out_traj.with_suffix(".csv"), out_traj.with_suffix(".cov.csv"),
             out_traj.with_suffix(".json") if write_json else None, landmarks_path)
    ov = OverlayWriter(Path(overlay), src.fps or 30.0) if overlay else None
    try:
        records = _track_frames(session, src, undistort_maps, ov, progress)
    except BaseException:
        if ov is not None:
            ov.close(commit=False)
        raise
    finally:
        landmarks = aid.landmarks() if aid is not None and landmarks_path is not None else None
        if aid is not None and hasattr(aid, "close"):
            aid.close()
    if not records.tracked().any():
        if ov is not None:
            ov.close(commit=False)
        raise _no_frame_tracked(records, session.policy, init_pose_path)
    summary = _summary(records, session, aid_mode, edges_used, paths, cam, cfg, landmarks)
    _write_outputs(paths, records, summary, landmarks, ov)
    return summary


def build_session(cfg: TrackConfig, model, model_path, cam, T0: np.ndarray, aid=None) -> tuple[TrackingSession, str]:
    """A :class:`TrackingSession` for ``model`` seen by ``cam`` from ``T0`` (the first frame's
    T_cam_model): the edge tracker (render-based edges per ``cfg.edge_source``), the relocaliser and
    the health monitor when on, the policy. Returns it and the edge source used (``merged``: the polygon edges
    of a polyhedral triangle mesh merged into planar polygons, :func:`render_edges.merge_polyhedral_tin`)."""
    from mst.pipeline.tracking.render_edges import edge_tracker_for

    tracker, edges_used = edge_tracker_for(model, model_path, cam, cfg, T0)
    reloc = None
    if cfg.relocalise:
        from mst.pipeline.tracking.relocalise import Relocaliser

        reloc = Relocaliser(tracker, cfg.reloc)
    monitor = HealthMonitor(len(tracker.geom.edges), len(tracker.surf_X)) if cfg.health_score else None
    budget = PoseBudget(cfg.slam.drift_budget_rel, cfg.slam.drift_budget_deg, cfg.slam.drift_sigmas)
    policy = TrackingPolicy(T0, tracker.cfg.search_range_px, cfg.edges.constant_velocity, monitor, budget)
    return TrackingSession(tracker, policy, aid, reloc), edges_used


def _undistort_maps(cam):
    """Remap tables that undistort the frames once (then tracked with the pinhole model K); None
    for a camera without distortion."""
    if not cam.has_distortion:
        return None
    import cv2

    d = np.zeros(5)
    d[: min(5, len(cam.dist))] = cam.dist[:5]
    log.info("frames undistorted with the camera's distortion coefficients before tracking")
    return cv2.initUndistortRectifyMap(cam.K, d, None, cam.K, (cam.width, cam.height), cv2.CV_16SC2)


def _track_frames(session: TrackingSession, src, undistort_maps, ov, progress) -> RunLog:
    """Every frame of ``src`` through the session (gray, undistorted), with the progress bar and the overlay."""
    import cv2

    from mst.pipeline.tracking.overlay import draw_overlay

    records = RunLog()
    bar = progress(len(src)) if progress is not None else contextlib.nullcontext(lambda n=1: None)
    from mst.pipeline.frames import prefetched

    with bar as advance:
        for idx, t_s, bgr in prefetched(src):  # the next frames decoded while this one is tracked
            if undistort_maps is not None:
                bgr = cv2.remap(bgr, *undistort_maps, cv2.INTER_LINEAR)
            rec = session.step(idx, t_s, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
            if ov is not None:
                ov.write(draw_overlay(bgr, rec.result, rec.status), idx)
            records.add(rec)  # what the outputs read (~0.5 KB a frame): memory flat in the sequence length
            advance()
    return records
