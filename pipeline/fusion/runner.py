"""The ``mst fuse`` runner: read the trajectory, camera(s) and frame lists, stream the frames into
:func:`~mst.pipeline.fusion.core.fuse_frames`, write the cloud atomically, return the summary."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import nullcontext

import numpy as np

from mst import InputError, atomic_output
from mst.core.camera import read_camera
from mst.core.poses import inv_T, read_rigid_transform
from mst.core.trajectory import read_tum
from mst.pipeline.depth_io import list_depth_frames, list_image_frames, read_depth
from mst.pipeline.fusion.config import FuseConfig
from mst.pipeline.fusion.core import Cloud, FuseFrame, FuseStats, fuse_frames
from mst.pipeline.fusion.ply import read_ply_points, write_ply

log = logging.getLogger(__name__)


def frame_index_of_times(t: np.ndarray, fps: float | None, traj_path: str | os.PathLike) -> np.ndarray:
    """Trajectory times (seconds, or frame indices) -> integer frame indices.

    With ``fps`` None the times must be frame indices (``mst track`` on an image sequence);
    otherwise ``k = round(t * fps)`` (``fps > 0``: a bound of :class:`FuseConfig`). Raises
    :class:`InputError` when times are not indices, or two poses fall on one frame.
    """
    t = np.asarray(t, dtype=np.float64)
    if fps is None:
        k = np.rint(t)
        if np.abs(t - k).max() > 1e-6:
            bad = t[np.argmax(np.abs(t - k))]
            raise InputError(traj_path, f"time {bad:g} is not a frame index; a trajectory timed in seconds needs the fps")
    else:
        k = np.rint(t * fps)
    if np.abs(k).max() > 1e9:
        raise InputError(traj_path, f"time {t[np.argmax(np.abs(k))]:g} is beyond a billion frames (corrupt value?)")
    k = k.astype(np.int64)
    if (k < 0).any():
        raise InputError(traj_path, f"negative frame index {int(k.min())} (time {t[np.argmin(k)]:g})")
    u, c = np.unique(k, return_counts=True)
    if (c > 1).any():
        raise InputError(traj_path, f"{int((c > 1).sum())} frame(s) have several poses (e.g. frame {int(u[c > 1][0])}); wrong fps?")
    return k


def read_extrinsic(path: str | os.PathLike) -> np.ndarray:
    """Read a 4x4 rigid transform (16 numbers, e.g. ViSP's ``depth_M_color.txt``); ``#`` comments allowed."""
    return read_rigid_transform(path, "extrinsic file")


def _color_loader(path) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(path, "cannot decode the colour image")
        return img

    return load


def _frames(files, todo, pose_of_frame, T_model_depth_all, colors, cfg: FuseConfig) -> Iterator[FuseFrame]:
    """The frames to fuse, read one at a time (a frame without a pose is not read)."""
    for k in todo:
        i = pose_of_frame.get(k)
        if i is None:
            yield FuseFrame(k, files[k], None, None)
            continue
        yield FuseFrame(k, files[k], read_depth(files[k], cfg.depth.scale), T_model_depth_all[i],
                        _color_loader(colors[k]) if colors is not None else None)


def fuse(out_path: str | os.PathLike, config: FuseConfig, traj_path: str | os.PathLike | None = None,
         depth_dir: str | os.PathLike | None = None, camera_path: str | os.PathLike | None = None,
         depth_to_color_path: str | os.PathLike | None = None, color_dir: str | os.PathLike | None = None,
         color_camera_path: str | os.PathLike | None = None, landmarks_path: str | os.PathLike | None = None,
         progress: Callable[[int], object] | None = None) -> dict:
    """Fuse depth frames with a trajectory into a point cloud (binary PLY, model frame, metres).

    ``traj_path``: TUM trajectory (``T_model_cam`` of the depth camera, or of the colour camera
    when ``depth_to_color_path`` holds ``T_depth_color``). ``depth_dir``: folder (or glob) of depth
    frames. ``camera_path``: the depth camera (image size taken from the frames when the file has
    none). ``color_dir``: colour images (same frame indices) to colour the points, seen by
    ``color_camera_path`` (default: the depth camera when there is no extrinsic, i.e. registered
    colour). ``landmarks_path``: a PLY of model-frame points (e.g. a mono SLAM map) added to the
    output, which is all the output when there is no depth. ``progress(total)`` returns a context
    manager yielding ``advance()``.

    Returns the summary dict (counts of frames and points, the effective config, timing). Writes
    ``out_path`` atomically; an empty cloud is an :class:`InputError` and writes nothing.
    """
    cfg = config
    t0 = time.perf_counter()
    if depth_dir is None and landmarks_path is None:
        raise InputError(None, "nothing to fuse: give depth frames or landmarks")
    # every input is read or checked before the first frame is fused (a bad landmarks file must not
    # fail after minutes of fusion)
    landmarks = read_ply_points(landmarks_path) if landmarks_path is not None else None
    stats = FuseStats()
    if depth_dir is None:
        cloud = fuse_frames([], None, cfg, landmarks=landmarks, stats=stats)
    else:
        cloud = _fuse_depth(cfg, stats, landmarks, traj_path, depth_dir, camera_path, depth_to_color_path,
                            color_dir, color_camera_path, progress)
    if len(cloud.X) == 0:
        where = depth_dir if depth_dir is not None else landmarks_path
        why = ("no frame had both a pose and valid depth" if stats.fused_frames == 0 and depth_dir is not None
               else "no point survived the depth range and edge filters")
        raise InputError(where, f"empty cloud: {why} ({stats.frames} frames, {stats.skipped_no_pose} without a pose)")
    comments = [f"mst fuse mode={cloud.mode} voxel={cloud.grid_m:g} frames={stats.fused_frames}", "units metres, model frame"]
    with atomic_output(out_path) as tmp:
        write_ply(tmp, cloud.X, cloud.rgb, cloud.count, comments)
    return _summary(out_path, cfg, cloud, time.perf_counter() - t0)


def _summary(out_path, cfg: FuseConfig, cloud: Cloud, el: float) -> dict:
    summary = {"output": str(out_path), "config": cfg.to_dict(), **cloud.to_json()}
    summary["elapsed_s"] = el
    summary["frames_per_s"] = cloud.stats.fused_frames / el if el > 0 else 0.0
    summary["points_per_s"] = cloud.stats.points_fused / el if el > 0 else 0.0
    return summary


def _fuse_depth(cfg, stats, landmarks, traj_path, depth_dir, camera_path, depth_to_color_path, color_dir,
                color_camera_path, progress) -> Cloud:
    if traj_path is None or camera_path is None:
        raise InputError(depth_dir, "fusing depth needs a trajectory and the depth camera")
    t, T_model_cam = read_tum(traj_path)
    k_of_pose = frame_index_of_times(t, cfg.fps, traj_path)
    files = list_depth_frames(depth_dir)
    cam = read_camera(camera_path)
    T_depth_color = read_extrinsic(depth_to_color_path) if depth_to_color_path is not None else np.eye(4)
    T_color_depth = inv_T(T_depth_color)
    # depth camera pose in the model frame: T_model_depth = T_model_cam @ T_cam_depth
    T_model_depth_all = T_model_cam @ T_color_depth
    pose_of_frame = {int(k): i for i, k in enumerate(k_of_pose)}
    stats.frames, stats.poses = len(files), len(t)
    stats.poses_without_frame = int((k_of_pose >= len(files)).sum())
    colors = color_cam = None
    if color_dir is not None:
        colors = list_image_frames(color_dir)
        if len(colors) < len(files):
            raise InputError(color_dir, f"{len(colors)} colour images for {len(files)} depth frames")
        if color_camera_path is not None:
            color_cam = read_camera(color_camera_path)
        elif depth_to_color_path is not None:
            raise InputError(depth_to_color_path, "colouring through an extrinsic needs the colour camera")
        else:
            color_cam = cam
    todo = list(range(0, len(files), cfg.stride))
    stats.skipped_stride = len(files) - len(todo)
    if stats.poses_without_frame:
        log.warning(f"{stats.poses_without_frame} pose(s) point past the last of {stats.frames} depth frames "
                    "(wrong fps, or a trajectory of another sequence?)")
    ctx = progress(len(todo)) if progress is not None else nullcontext(lambda n=1: None)
    with ctx as advance:
        return fuse_frames(_frames(files, todo, pose_of_frame, T_model_depth_all, colors, cfg), cam, cfg,
                           T_color_depth=T_color_depth, color_camera=color_cam, landmarks=landmarks,
                           advance=advance, stats=stats)
