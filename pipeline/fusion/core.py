"""The pure fusion core: depth frames with their poses + camera + config -> :class:`Cloud`.

:func:`fuse_frames` reads no file: the frames come as :class:`FuseFrame` objects (depth in metres,
the depth camera's pose in the model frame), one at a time, so memory stays bounded by the output.
Points are summed relative to a local origin (the first fused camera centre), so georeferenced
coordinates keep their precision.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from mst import InputError
from mst.core.camera import Camera
from mst.core.poses import inv_T, transform_points
from mst.pipeline.fusion.accumulators import PointList, TSDFAccumulator, VoxelAccumulator
from mst.pipeline.fusion.config import FuseConfig
from mst.pipeline.fusion.filters import backproject, pixel_rays, sample_colors

log = logging.getLogger(__name__)


@dataclass
class FuseFrame:
    """One depth frame: its index, its file (named in errors), depth and the depth camera's pose.

    ``T_model_depth`` None: the frame has no pose (lost while tracking); it is skipped and counted,
    and ``depth_m`` may be None. ``color`` loads the frame's colour image (BGR) when it is needed.
    """

    index: int
    source: str | os.PathLike
    depth_m: np.ndarray | None
    T_model_depth: np.ndarray | None
    color: Callable[[], np.ndarray] | None = None


@dataclass
class FuseStats:
    """Counts of one fusion (frames, samples and why they were dropped, points)."""

    frames: int = 0                 #: depth frames in the input
    poses: int = 0                  #: poses in the trajectory
    fused_frames: int = 0
    skipped_no_pose: int = 0
    skipped_stride: int = 0
    empty_frames: int = 0           #: frames with a pose but no sample left by the filters
    poses_without_frame: int = 0    #: poses past the last depth frame
    samples: int = 0                #: depth pixels with a value
    dropped_range: int = 0
    dropped_edge: int = 0
    dropped_grazing: int = 0
    points_fused: int = 0           #: samples that went into the grid
    colored_samples: int = 0
    landmarks: int = 0


@dataclass
class Cloud:
    """The fused cloud: float64 model-frame metres, colours and merged-sample counts."""

    X: np.ndarray                   #: (N, 3) float64, model frame, metres
    rgb: np.ndarray | None          #: (N, 3) uint8 (black where nothing coloured it); None without colour
    count: np.ndarray | None        #: (N,) samples merged per point; None for a TSDF
    mode: str                       #: tsdf | voxel | points
    grid_m: float                   #: the grid the cloud was made on (0: none)
    stats: FuseStats = field(default_factory=FuseStats)
    warning: str | None = None

    def to_json(self) -> dict:
        out = {"mode": self.mode, **dataclasses.asdict(self.stats)}
        if self.warning:
            out["warning"] = self.warning
        out["points_out"] = len(self.X)
        if len(self.X):
            out["bounds_min"] = self.X.min(axis=0).tolist()
            out["bounds_max"] = self.X.max(axis=0).tolist()
        return out


class _Fusion:
    """The state of one fusion: the accumulator, the local origin and the frame size."""

    def __init__(self, camera: Camera, cfg: FuseConfig, T_color_depth: np.ndarray | None,
                 color_camera: Camera | None, stats: FuseStats):
        self.cam, self.cfg, self.stats = camera, cfg, stats
        self.T_color_depth = np.eye(4) if T_color_depth is None else T_color_depth
        self.color_cam = color_camera
        self.acc = None
        self.origin: np.ndarray | None = None
        self.size: tuple[int, int] | None = None
        self.rays: np.ndarray | None = None
        self.seen = False

    def _rays_for(self, frame: FuseFrame, depth: np.ndarray) -> np.ndarray:
        h, w = depth.shape
        if self.size is None:
            self.size = (w, h)
            cam = self.cam
            if cam.width and cam.height and (cam.width, cam.height) != self.size:
                raise InputError(frame.source, f"depth frame is {w}x{h} but the depth camera says {cam.width}x{cam.height}")
            self.cam = cam.with_size(w, h)
            self.rays = pixel_rays(self.cam, w, h)
        elif (w, h) != self.size:
            raise InputError(frame.source, f"depth frame is {w}x{h}, earlier frames are {self.size[0]}x{self.size[1]}")
        return self.rays

    def _new_accumulator(self):
        cfg = self.cfg
        if cfg.tsdf:
            return TSDFAccumulator(cfg.tsdf_voxel_m, cfg.tsdf_trunc_voxels, cfg.depth.max_m, cfg.tsdf_weight_threshold,
                                   self.color_cam is not None)
        return VoxelAccumulator(cfg.voxel_m) if cfg.voxel_m > 0 else PointList()

    def add(self, frame: FuseFrame) -> None:
        cfg, st = self.cfg, self.stats
        self.seen = True
        if frame.T_model_depth is None:
            st.skipped_no_pose += 1
            return
        rays = self._rays_for(frame, frame.depth_m)
        X_cam, keep, counts, depth = backproject(frame.depth_m, rays, cfg)
        for key_, v in counts.items():
            setattr(st, key_, getattr(st, key_) + v)
        if len(X_cam) == 0:
            st.empty_frames += 1
            return
        T_model_depth = frame.T_model_depth
        if self.origin is None:
            self.origin = T_model_depth[:3, 3].copy()
        T_local_depth = T_model_depth.copy()
        T_local_depth[:3, 3] -= self.origin
        rgb = rgb_ok = None
        if frame.color is not None:
            img = frame.color()
            if self.color_cam.width == 0:
                self.color_cam = self.color_cam.with_size(img.shape[1], img.shape[0])
            rgb, rgb_ok = sample_colors(X_cam, self.T_color_depth, self.color_cam, img)
            st.colored_samples += int(rgb_ok.sum())
        if self.acc is None:
            self.acc = self._new_accumulator()
        if cfg.tsdf:
            d_keep = np.where(keep, depth, np.float32(0))
            rgb_img = None
            if rgb is not None:
                rgb_img = np.zeros(depth.shape + (3,), np.float32)
                rgb_img[keep] = rgb.astype(np.float32) / 255.0
            self.acc.integrate(d_keep, self.cam.K, inv_T(T_local_depth), rgb_img)
        else:
            self.acc.add(transform_points(T_local_depth, X_cam, elementwise=True), rgb, rgb_ok)
        st.points_fused += len(X_cam)
        st.fused_frames += 1

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.acc is None:
            return np.empty((0, 3)), np.empty((0, 3), np.uint8), np.empty(0, np.int64)
        X_local, rgb_out, count = self.acc.result()
        return X_local + self.origin, rgb_out, count


def _with_landmarks(X, rgb_out, count, landmarks, origin, cfg: FuseConfig):
    """The cloud with the landmark points appended (voxel-merged on their own in voxel mode)."""
    L, L_rgb = landmarks
    if cfg.voxel_m > 0 and not cfg.tsdf and len(L):
        lacc = VoxelAccumulator(cfg.voxel_m)
        lo = L[0].copy() if origin is None else origin
        lacc.add(L - lo, L_rgb, None if L_rgb is None else np.ones(len(L), bool))
        L, L_rgb2, L_count = lacc.result()
        L = L + lo
        L_rgb = L_rgb2 if L_rgb is not None else None
    else:
        L_count = np.ones(len(L), np.int64)
    X = np.concatenate([X, L])
    rgb_out = np.concatenate([rgb_out, L_rgb if L_rgb is not None else np.zeros((len(L), 3), np.uint8)])
    count = np.concatenate([count, L_count])
    return X, rgb_out, count, L_rgb is not None


def fuse_frames(frames: Iterable[FuseFrame], camera: Camera | None, cfg: FuseConfig, *,
                T_color_depth: np.ndarray | None = None, color_camera: Camera | None = None,
                landmarks: tuple[np.ndarray, np.ndarray | None] | None = None,
                advance: Callable[[], object] | None = None, stats: FuseStats | None = None) -> Cloud:
    """Fuse depth frames into one cloud in the model frame.

    ``camera``: the depth camera (its size is taken from the first frame when it has none; None
    only without frames).
    ``T_color_depth`` maps depth-camera points into the colour camera ``color_camera`` (given iff
    the frames carry colour). ``landmarks``: ``(X (M, 3) model-frame points, rgb or None)`` added
    to the output. ``advance()`` is called after each frame; ``stats`` (the file-level counts of
    the caller) is filled in and returned in the cloud. An empty cloud is returned, not refused.
    """
    stats = FuseStats() if stats is None else stats
    fusion = _Fusion(camera, cfg, T_color_depth, color_camera, stats)
    for frame in frames:
        fusion.add(frame)
        if advance is not None:
            advance()
    warning = None
    if fusion.seen and cfg.tsdf and camera.has_distortion:
        warning = "TSDF integration ignores the depth camera's distortion"
        log.warning(warning)
    X, rgb_out, count = fusion.result()
    with_rgb = color_camera is not None
    if landmarks is not None:
        stats.landmarks = len(landmarks[0])
        X, rgb_out, count, lm_rgb = _with_landmarks(X, rgb_out, count, landmarks, fusion.origin, cfg)
        with_rgb = with_rgb or lm_rgb
    return Cloud(X, rgb_out if with_rgb else None, None if cfg.tsdf else count, cfg.mode, cfg.grid_m, stats, warning)
