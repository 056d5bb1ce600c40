"""Depth fusion: depth frames + camera trajectory -> one point cloud in model coordinates.

Stage function :func:`fuse` (called by ``mst fuse``); the pieces are small vectorised functions.

Frames and units
----------------
* Depth pixels are z-depth in metres in the **depth camera** frame (x right, y down, z forward);
  ``K`` and distortion come from the depth camera file.
* The trajectory (TUM) holds camera poses in model coordinates, ``T_model_cam``. By default the
  trajectory's camera *is* the depth camera. When the trajectory is the **colour** camera's (what
  ``mst track`` writes when it tracks colour frames), ``T_depth_color`` (ViSP's ``depth_M_color``,
  read from ``--depth-to-color``) maps colour-camera points to depth-camera points,
  ``X_depth = T_depth_color @ X_color``, and the depth camera pose is
  ``T_model_depth = T_model_color @ inv(T_depth_color)``.
* Frame association: depth frame ``k`` is the ``k``-th file of the depth folder in natural order.
  A pose at time ``t`` belongs to frame ``k = t`` (``mst track`` on an image sequence writes the
  frame index as time), or ``k = round(t * fps)`` with ``fps`` (videos, ``mst synth``'s ``gt.txt``).
  Frames with no pose (lost while tracking) are skipped and counted.
* Output points are float64 metres in model coordinates (georeferenced coordinates keep their
  precision: all sums are taken relative to a local origin, the first fused camera centre).

Memory is bounded by the output, not by the sequence length: frames are streamed one at a time into
a voxel accumulator (sorted packed int64 voxel keys with running sums and counts, merged per frame
with ``np.unique``/``np.searchsorted``), an Open3D ``VoxelBlockGrid`` TSDF (``tsdf=True``), or, with
``voxel=0``, a list of per-frame point arrays (the output itself).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import asdict, dataclass

import numpy as np

from mst import InputError, atomic_output, require_file
from mst.core.camera import Camera, read_camera
from mst.core.poses import inv_T, read_rigid_transform
from mst.core.trajectory import read_tum
from mst.pipeline.depth_io import list_depth_frames, list_image_frames, read_depth


@dataclass
class FuseConfig:
    """Settings of :func:`fuse` (metres, degrees)."""

    depth_scale: float = 1000.0  #: raw integer depth units per metre (see :mod:`mst.pipeline.depth_io`)
    min_depth: float = 0.1  #: metres; nearer samples dropped
    max_depth: float = 50.0  #: metres; farther samples dropped
    edge_k: float = 0.03  #: drop a pixel when a 4-neighbour's depth differs by more than edge_k * z (0: off)
    max_angle_deg: float = 80.0  #: drop samples whose surface normal is more than this from the view ray (>= 90: off)
    smooth_px: int = 0  #: bilateral filter diameter (pixels) applied to each depth frame (0: off)
    smooth_rel: float = 0.02  #: bilateral range sigma, relative depth difference (0.02 = 2 % of z)
    voxel: float = 0.005  #: metres; voxel size of the down-sampling grid (0: keep every sample)
    stride: int = 1  #: fuse every stride-th depth frame
    fps: float | None = None  #: trajectory time -> frame index: k = round(t * fps); None: k = t
    tsdf: bool = False  #: fuse a TSDF (Open3D VoxelBlockGrid) and extract its surface points
    tsdf_voxel: float = 0.01  #: metres; TSDF voxel size when ``voxel`` is 0
    tsdf_trunc_voxels: float = 4.0  #: TSDF truncation distance in voxels
    tsdf_weight_threshold: float = 1.0  #: extract TSDF voxels with weight > this (Open3D's test is strict)


# ---------------------------------------------------------------------------- small functions
def pixel_rays(camera: Camera, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 rays ``(x, y, 1)`` in the camera frame for every pixel (distortion removed).

    A pixel with z-depth ``d`` (metres) is the camera-frame point ``d * ray``.
    """
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xy = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    rays = np.ones((height, width, 3))
    rays[:, :, :2] = xy.reshape(height, width, 2)
    return rays.astype(np.float32)


def depth_edge_mask(depth_m: np.ndarray, k: float) -> np.ndarray:
    """(H, W) bool: pixels at a depth discontinuity (a valid 4-neighbour differs by more than ``k * z``)."""
    d = depth_m
    jump = np.zeros(d.shape, np.float32)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        da, db = d[a], d[b]
        diff = np.where((da > 0) & (db > 0), np.abs(da - db), np.float32(0))
        np.maximum(jump[a], diff, out=jump[a])
        np.maximum(jump[b], diff, out=jump[b])
    return jump > np.float32(k) * d


def grazing_mask(points_cam: np.ndarray, valid: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """(H, W) bool: samples seen at more than ``max_angle_deg`` from their surface normal.

    ``points_cam`` is (H, W, 3) camera-frame metres; normals come from central differences over
    the 4-neighbours (samples whose neighbours are missing are never flagged).
    """
    P = points_cam
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    # n = du x dv, written out (np.cross is slow on images)
    nx = du[..., 1] * dv[..., 2] - du[..., 2] * dv[..., 1]
    ny = du[..., 2] * dv[..., 0] - du[..., 0] * dv[..., 2]
    nz = du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]
    Pc = P[1:-1, 1:-1]
    dot = nx * Pc[..., 0] + ny * Pc[..., 1] + nz * Pc[..., 2]
    nn2 = nx * nx + ny * ny + nz * nz
    pn2 = np.einsum("hwc,hwc->hw", Pc, Pc)
    c = np.float32(np.cos(np.radians(max_angle_deg))) if P.dtype == np.float32 else np.cos(np.radians(max_angle_deg))
    # |cos| < c  <=>  dot^2 < c^2 |n|^2 |P|^2 (no square roots)
    graze = (dot * dot < c * c * nn2 * pn2) & (nn2 > 0)
    ok = valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    out = np.zeros(valid.shape, bool)
    out[1:-1, 1:-1] = graze & ok
    return out


def smooth_depth(depth_m: np.ndarray, diameter_px: int, rel_sigma: float) -> np.ndarray:
    """Edge-preserving depth denoising: a bilateral filter on log-depth (range sigma ``rel_sigma``
    is then a relative depth difference, e.g. 0.02 = 2 % of z, right for depth noise that grows
    with z). Pixels without depth stay 0 and never leak into their neighbours."""
    import cv2

    valid = depth_m > 0
    if diameter_px < 2 or not valid.any():
        return depth_m
    L = np.empty(depth_m.shape, np.float32)
    L[valid] = np.log(depth_m[valid])
    # holes get a value far outside the range kernel (OpenCV's range LUT spans min..max, so a
    # modest gap keeps its resolution)
    L[~valid] = L[valid].max() + max(1.0, 50.0 * rel_sigma)
    Ls = cv2.bilateralFilter(L, int(diameter_px), float(rel_sigma), float(diameter_px) / 2.0)
    return np.where(valid, np.exp(Ls), np.float32(0)).astype(np.float32)


def backproject(depth_m: np.ndarray, rays: np.ndarray, cfg: FuseConfig) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """Filtered depth -> camera-frame points.

    Returns ``(X_cam (N, 3) float64 metres, keep (H, W) bool, counts, depth (H, W) metres)`` where
    ``counts`` holds the valid samples and how many were dropped by range, edges and grazing angle,
    and ``depth`` is the (smoothed, when ``cfg.smooth_px``) depth the points come from.
    """
    d = depth_m
    has = d > 0
    in_range = has & (d >= cfg.min_depth) & (d <= cfg.max_depth)
    if cfg.smooth_px >= 2:
        d = smooth_depth(np.where(in_range, d, np.float32(0)), cfg.smooth_px, cfg.smooth_rel)
    keep = in_range.copy()
    n_edge = n_graze = 0
    if cfg.edge_k > 0:
        e = depth_edge_mask(np.where(in_range, d, np.float32(0)), cfg.edge_k) & keep
        n_edge = int(e.sum())
        keep &= ~e
    P = rays * d[:, :, None]  # float32 camera-frame metres (rays are float32)
    if cfg.max_angle_deg < 90:
        g = grazing_mask(P, in_range, cfg.max_angle_deg) & keep
        n_graze = int(g.sum())
        keep &= ~g
    counts = {"samples": int(has.sum()), "dropped_range": int(has.sum() - in_range.sum()),
              "dropped_edge": n_edge, "dropped_grazing": n_graze}
    return P[keep].astype(np.float64), keep, counts, d


def transform_points_ew(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``T @ X`` for (N, 3) float64 points, elementwise (no BLAS call: BLAS threads stall when
    the cores are busy, and 3x3 products gain nothing from them)."""
    R, t = T[:3, :3], T[:3, 3]
    return X[:, 0:1] * R[:, 0] + X[:, 1:2] * R[:, 1] + X[:, 2:3] * R[:, 2] + t


def sample_colors(X_depth: np.ndarray, T_color_depth: np.ndarray, color_cam: Camera, image_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour of depth-camera points from a colour image (nearest pixel).

    Returns ``(rgb (N, 3) uint8, ok (N,) bool)``; points behind the colour camera or outside its
    image get ``ok = False``.
    """
    X_c = transform_points_ew(T_color_depth, X_depth)
    ok = X_c[:, 2] > 1e-6
    uv = np.full((len(X_c), 2), -1.0)
    if ok.any():
        uv[ok] = color_cam.project(X_c[ok])
    h, w = image_bgr.shape[:2]
    ui = np.rint(uv[:, 0]).astype(np.int64)
    vi = np.rint(uv[:, 1]).astype(np.int64)
    ok &= (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    rgb = np.zeros((len(X_c), 3), np.uint8)
    img = image_bgr if image_bgr.ndim == 3 else np.repeat(image_bgr[:, :, None], 3, axis=2)
    rgb[ok] = img[vi[ok], ui[ok], :3][:, ::-1]
    return rgb, ok


def frame_index_of_times(t: np.ndarray, fps: float | None, traj_path: str | os.PathLike) -> np.ndarray:
    """Trajectory times (seconds, or frame indices) -> integer frame indices.

    With ``fps`` None the times must be frame indices (``mst track`` on an image sequence);
    otherwise ``k = round(t * fps)``. Raises :class:`InputError` when times are not indices, or two
    poses fall on one frame.
    """
    t = np.asarray(t, dtype=np.float64)
    if fps is None:
        k = np.rint(t)
        if np.abs(t - k).max() > 1e-6:
            bad = t[np.argmax(np.abs(t - k))]
            raise InputError(traj_path, f"time {bad:g} is not a frame index; pass --fps for a trajectory timed in seconds")
    else:
        if not fps > 0:
            raise InputError(traj_path, f"fps must be positive, got {fps}")
        k = np.rint(t * fps)
    if np.abs(k).max() > 1e9:
        raise InputError(traj_path, f"time {t[np.argmax(np.abs(k))]:g} is beyond a billion frames (corrupt value?)")
    k = k.astype(np.int64)
    if (k < 0).any():
        raise InputError(traj_path, f"negative frame index {int(k.min())} (time {t[np.argmin(k)]:g})")
    u, c = np.unique(k, return_counts=True)
    if (c > 1).any():
        raise InputError(traj_path, f"{int((c > 1).sum())} frame(s) have several poses (e.g. frame {int(u[c > 1][0])}); wrong --fps?")
    return k


def read_extrinsic(path: str | os.PathLike) -> np.ndarray:
    """Read a 4x4 rigid transform (16 numbers, e.g. ViSP's ``depth_M_color.txt``); ``#`` comments allowed."""
    return read_rigid_transform(path, "extrinsic file")


# ---------------------------------------------------------------------------- accumulators
class VoxelAccumulator:
    """Streaming voxel-grid average: memory grows with the number of occupied voxels only.

    Points are given relative to a fixed local origin (metres). Voxel keys pack the three integer
    voxel coordinates (21 bits each, +-1,048,575 voxels, i.e. +-10 km at 1 cm) into one int64;
    the state is kept sorted by key so each frame merges with ``np.searchsorted`` (no Python loop
    per point or per voxel).
    """

    BITS = 21
    OFF = 1 << (BITS - 1)

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self.keys = np.empty(0, np.int64)
        self.sum = np.empty((0, 3))
        self.count = np.empty(0, np.int64)
        self.csum = np.empty((0, 3))
        self.ccount = np.empty(0, np.int64)

    def __len__(self) -> int:
        return len(self.keys)

    def pack(self, X_local: np.ndarray) -> np.ndarray:
        ijk = np.floor(X_local / self.voxel).astype(np.int64)
        if len(ijk) and (np.abs(ijk).max() >= self.OFF):
            raise InputError(None, f"points span more than {self.OFF * self.voxel:g} m from the first camera at "
                                   f"voxel {self.voxel:g} m; use a larger --voxel")
        ijk += self.OFF
        return (ijk[:, 0] << (2 * self.BITS)) | (ijk[:, 1] << self.BITS) | ijk[:, 2]

    def add(self, X_local: np.ndarray, rgb: np.ndarray | None = None, rgb_ok: np.ndarray | None = None) -> None:
        """Add (N, 3) float64 local points, optional (N, 3) uint8 colours with a validity mask."""
        if len(X_local) == 0:
            return
        key = self.pack(X_local)
        uk, inv = np.unique(key, return_inverse=True)
        m = len(uk)
        s = np.stack([np.bincount(inv, weights=X_local[:, i], minlength=m) for i in range(3)], axis=1)
        c = np.bincount(inv, minlength=m).astype(np.int64)
        if rgb is not None:
            okw = rgb_ok.astype(np.float64)
            cs = np.stack([np.bincount(inv, weights=rgb[:, i] * okw, minlength=m) for i in range(3)], axis=1)
            cc = np.bincount(inv, weights=okw, minlength=m).astype(np.int64)
        else:
            cs, cc = np.zeros((m, 3)), np.zeros(m, np.int64)
        pos = np.searchsorted(self.keys, uk)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == uk[found]
        p = pos[found]
        self.sum[p] += s[found]
        self.count[p] += c[found]
        self.csum[p] += cs[found]
        self.ccount[p] += cc[found]
        new = ~found
        if new.any():
            at = pos[new]
            self.keys = np.insert(self.keys, at, uk[new])
            self.sum = np.insert(self.sum, at, s[new], axis=0)
            self.count = np.insert(self.count, at, c[new])
            self.csum = np.insert(self.csum, at, cs[new], axis=0)
            self.ccount = np.insert(self.ccount, at, cc[new])

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(X_local (M, 3) centroids, rgb (M, 3) uint8 (0 where never coloured), count (M,))``."""
        X = self.sum / self.count[:, None]
        rgb = np.rint(self.csum / np.maximum(self.ccount, 1)[:, None]).clip(0, 255).astype(np.uint8)
        return X, rgb, self.count


class PointList:
    """``voxel = 0``: keep every sample (memory = the output cloud)."""

    def __init__(self) -> None:
        self.X: list[np.ndarray] = []
        self.rgb: list[np.ndarray] = []

    def __len__(self) -> int:
        return sum(len(x) for x in self.X)

    def add(self, X_local: np.ndarray, rgb: np.ndarray | None = None, rgb_ok: np.ndarray | None = None) -> None:
        self.X.append(X_local)
        self.rgb.append(rgb if rgb is not None else np.zeros((len(X_local), 3), np.uint8))

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X = np.concatenate(self.X) if self.X else np.empty((0, 3))
        rgb = np.concatenate(self.rgb) if self.rgb else np.empty((0, 3), np.uint8)
        return X, rgb, np.ones(len(X), np.int64)


class TSDFAccumulator:
    """Open3D ``t.geometry.VoxelBlockGrid`` TSDF on the CPU (``ScalableTSDFVolume`` is broken in 0.20).

    Integrates filtered depth (metres) in the local frame; :meth:`result` extracts the surface
    points (voxels with weight > ``weight_threshold``; Open3D's test is strict).
    """

    def __init__(self, voxel: float, trunc_voxels: float, depth_max: float, weight_threshold: float, with_color: bool):
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c = o3d, o3c
        self.dev = o3c.Device("CPU:0")
        self.with_color = with_color
        names = ("tsdf", "weight", "color") if with_color else ("tsdf", "weight")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(names, (o3c.float32,) * len(names), tuple([1, 1, 3][: len(names)]),
                                                 float(voxel), 16, 1000, self.dev)
        self.trunc_voxels = float(trunc_voxels)  # Open3D's trunc_voxel_multiplier (voxels, not metres)
        self.depth_max = float(depth_max)
        self.weight_threshold = float(weight_threshold)

    def __len__(self) -> int:
        return int(self.vbg.hashmap().size())

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_cam_local: np.ndarray, rgb_img: np.ndarray | None) -> None:
        o3d, o3c = self.o3d, self.o3c
        di = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth_m, np.float32)))
        # Open3D's pixel (u, v) spans [u, u + 1) (its rays go through u + 0.5); mst's pixel (0, 0) is
        # the centre of the top-left pixel, so the principal point moves by half a pixel (measured:
        # median distance to the surface 7 mm without the shift, 0.1 mm with it, at 3 m / f = 140 px)
        K_o3d = np.array(K, dtype=np.float64)
        K_o3d[:2, 2] += 0.5
        Kt = o3c.Tensor(K_o3d)
        Et = o3c.Tensor(np.ascontiguousarray(T_cam_local, np.float64))
        coords = self.vbg.compute_unique_block_coordinates(di, Kt, Et, 1.0, self.depth_max, self.trunc_voxels)
        if self.with_color:
            ci = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb_img, np.float32)))
            self.vbg.integrate(coords, di, ci, Kt, Et, 1.0, self.depth_max, self.trunc_voxels)
        else:
            self.vbg.integrate(coords, di, Kt, Et, 1.0, self.depth_max, self.trunc_voxels)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if len(self) == 0:
            return np.empty((0, 3)), np.empty((0, 3), np.uint8), np.empty(0, np.int64)
        pcd = self.vbg.extract_point_cloud(weight_threshold=self.weight_threshold)
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            return np.empty((0, 3)), np.empty((0, 3), np.uint8), np.empty(0, np.int64)
        X = pcd.point.positions.numpy().astype(np.float64)
        if self.with_color and "colors" in pcd.point:
            rgb = np.rint(pcd.point.colors.numpy() * 255).clip(0, 255).astype(np.uint8)
        else:
            rgb = np.zeros((len(X), 3), np.uint8)
        return X, rgb, np.ones(len(X), np.int64)


# ---------------------------------------------------------------------------- PLY
def write_ply(path: str | os.PathLike, X: np.ndarray, rgb: np.ndarray | None = None, count: np.ndarray | None = None,
              comments: list[str] | None = None) -> None:
    """Binary little-endian PLY: ``x y z`` as double (metres, full georeferenced precision),
    optional ``red green blue`` uchar and ``count`` uint (depth samples merged into the point)."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    props = ["property double x", "property double y", "property double z"]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    if count is not None:
        fields += [("count", "<u4")]
        props += ["property uint count"]
    a = np.empty(len(X), dtype=fields)
    a["x"], a["y"], a["z"] = X[:, 0], X[:, 1], X[:, 2]
    if rgb is not None:
        a["red"], a["green"], a["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if count is not None:
        a["count"] = np.minimum(count, np.iinfo(np.uint32).max)
    head = ["ply", "format binary_little_endian 1.0"] + [f"comment {c}" for c in (comments or [])]
    head += [f"element vertex {len(X)}", *props, "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode("ascii"))
        f.write(a.tobytes())


def read_ply_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a PLY point cloud: ``(X (N, 3) float64, rgb (N, 3) uint8 or None)``.

    Handles ASCII and binary PLY whose first element is ``vertex`` with scalar properties.
    """
    from mst.meshtools.io import PLY_TYPES

    p = require_file(path, "point cloud")
    raw = p.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(p, "not a PLY file (no 'ply' magic or no end_header)")
    nl = raw.find(b"\n", end)
    header = raw[:end].decode("ascii", "replace").splitlines()
    body = raw[nl + 1:]
    fmt, n, props, elements = None, None, [], []
    for line in header:
        w = line.split()
        if not w:
            continue
        if w[0] == "format" and len(w) > 1:
            fmt = w[1]
        elif w[0] == "element" and len(w) > 2:
            elements.append(w[1])
            if len(elements) == 1:
                try:
                    n = int(w[2])
                except ValueError:
                    raise InputError(p, f"bad element line {line!r}") from None
        elif w[0] == "property" and len(elements) == 1 and len(w) > 2:
            if w[1] == "list":
                raise InputError(p, "list properties in the vertex element are not supported")
            if w[1] not in PLY_TYPES:
                raise InputError(p, f"unknown PLY property type {w[1]!r}")
            props.append((w[2], PLY_TYPES[w[1]]))
    first = elements[0] if elements else None
    if first != "vertex" or n is None:
        raise InputError(p, "the first PLY element must be 'vertex'")
    names = [nm for nm, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise InputError(p, "PLY vertices have no x, y, z")
    if fmt == "ascii":
        try:
            rows = np.loadtxt(body.decode("ascii").splitlines()[:n], ndmin=2) if n else np.empty((0, len(props)))
        except ValueError as e:
            raise InputError(p, f"bad ASCII PLY data ({e})") from None
        if rows.shape != (n, len(props)):
            raise InputError(p, f"ASCII PLY: expected {n} vertices of {len(props)} values")
        cols = {nm: rows[:, i] for i, nm in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        e = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(nm, e + t) for nm, t in props])
        if len(body) < n * dt.itemsize:
            raise InputError(p, f"PLY is truncated: {n} vertices need {n * dt.itemsize} bytes, found {len(body)}")
        a = np.frombuffer(body, dtype=dt, count=n)
        cols = {nm: a[nm] for nm in names}
    else:
        raise InputError(p, f"unknown PLY format {fmt!r}")
    X = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    if not np.isfinite(X).all():
        raise InputError(p, "point cloud holds NaN or infinite coordinates")
    rgb = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).clip(0, 255).astype(np.uint8)
    return X, rgb


# ---------------------------------------------------------------------------- the stage
def fuse(
    out_path: str | os.PathLike,
    config: FuseConfig,
    traj_path: str | os.PathLike | None = None,
    depth_dir: str | os.PathLike | None = None,
    camera_path: str | os.PathLike | None = None,
    depth_to_color_path: str | os.PathLike | None = None,
    color_dir: str | os.PathLike | None = None,
    color_camera_path: str | os.PathLike | None = None,
    landmarks_path: str | os.PathLike | None = None,
    progress: Callable[[int], object] | None = None,
) -> dict:
    """Fuse depth frames with a trajectory into a point cloud (binary PLY, model frame, metres).

    ``traj_path``: TUM trajectory (``T_model_cam`` of the depth camera, or of the colour camera
    when ``depth_to_color_path`` holds ``T_depth_color``). ``depth_dir``: folder (or glob) of depth
    frames. ``camera_path``: the depth camera (image size taken from the frames when the file has
    none). ``color_dir``: colour images (same frame indices) to colour the points, seen by
    ``color_camera_path`` (default: the depth camera when there is no extrinsic, i.e. registered
    colour). ``landmarks_path``: a PLY of model-frame points (e.g. a mono SLAM map written by
    ``mst track --slam mono --landmarks``) added to the output, which is all the output when there
    is no depth. ``progress(total)`` returns a context manager yielding ``advance()``.

    Returns the summary dict (counts of frames and points, timing). Writes ``out_path`` atomically.
    """
    cfg = config
    t0 = time.perf_counter()
    if cfg.stride < 1:
        raise InputError(None, f"stride must be >= 1, got {cfg.stride}")
    if cfg.voxel < 0 or not np.isfinite(cfg.voxel):
        raise InputError(None, f"voxel must be >= 0, got {cfg.voxel}")
    if not (0 <= cfg.min_depth < cfg.max_depth):
        raise InputError(None, f"need 0 <= min depth < max depth, got {cfg.min_depth} and {cfg.max_depth}")
    if depth_dir is None and landmarks_path is None:
        raise InputError(None, "nothing to fuse: give depth frames (--depth) or landmarks (--landmarks)")

    summary: dict = {"output": str(out_path), "mode": "tsdf" if cfg.tsdf else ("voxel" if cfg.voxel > 0 else "points"),
                     "config": {k: (v if not isinstance(v, float) or np.isfinite(v) else None)
                                for k, v in asdict(cfg).items()}, "frames": 0, "poses": 0, "fused_frames": 0, "skipped_no_pose": 0,
                     "skipped_stride": 0, "empty_frames": 0, "poses_without_frame": 0, "samples": 0,
                     "dropped_range": 0, "dropped_edge": 0, "dropped_grazing": 0, "points_fused": 0,
                     "colored_samples": 0, "landmarks": 0}

    # every input is read or checked before the first frame is fused (a bad landmarks file must not
    # fail after minutes of fusion)
    landmarks = read_ply_points(landmarks_path) if landmarks_path is not None else None
    origin: np.ndarray | None = None
    acc = None
    if depth_dir is not None:
        if traj_path is None or camera_path is None:
            raise InputError(depth_dir, "fusing depth needs a trajectory (--traj) and the depth camera (--camera)")
        t, T_model_cam = read_tum(traj_path)
        k_of_pose = frame_index_of_times(t, cfg.fps, traj_path)
        frames = list_depth_frames(depth_dir)
        cam = read_camera(camera_path)
        T_depth_color = read_extrinsic(depth_to_color_path) if depth_to_color_path is not None else np.eye(4)
        T_color_depth = inv_T(T_depth_color)
        # depth camera pose in the model frame: T_model_depth = T_model_cam @ T_cam_depth
        T_model_depth_all = T_model_cam @ T_color_depth
        pose_of_frame = {int(k): i for i, k in enumerate(k_of_pose)}
        summary["frames"] = len(frames)
        summary["poses"] = len(t)
        summary["poses_without_frame"] = int((k_of_pose >= len(frames)).sum())
        colors = None
        color_cam = None
        if color_dir is not None:
            colors = list_image_frames(color_dir)
            if len(colors) < len(frames):
                raise InputError(color_dir, f"{len(colors)} colour images for {len(frames)} depth frames")
            if color_camera_path is not None:
                color_cam = read_camera(color_camera_path)
            elif depth_to_color_path is not None:
                raise InputError(depth_to_color_path, "colouring through an extrinsic needs the colour camera (--color-camera)")
            else:
                color_cam = cam
        todo = [k for k in range(0, len(frames), cfg.stride)]
        summary["skipped_stride"] = len(frames) - len(todo)
        rays = None
        size = None
        ctx = progress(len(todo)) if progress is not None else nullcontext(lambda n=1: None)
        with ctx as advance:
            for k in todo:
                i = pose_of_frame.get(k)
                if i is None:
                    summary["skipped_no_pose"] += 1
                    advance()
                    continue
                depth = read_depth(frames[k], cfg.depth_scale)
                h, w = depth.shape
                if size is None:
                    size = (w, h)
                    if cam.width and cam.height and (cam.width, cam.height) != size:
                        raise InputError(frames[k], f"depth frame is {w}x{h} but the depth camera says {cam.width}x{cam.height}")
                    cam = cam.with_size(w, h)
                    rays = pixel_rays(cam, w, h)
                elif (w, h) != size:
                    raise InputError(frames[k], f"depth frame is {w}x{h}, earlier frames are {size[0]}x{size[1]}")
                X_cam, keep, counts, depth = backproject(depth, rays, cfg)
                for key_, v in counts.items():
                    summary[key_] += v
                if len(X_cam) == 0:
                    summary["empty_frames"] += 1
                    advance()
                    continue
                T_model_depth = T_model_depth_all[i]
                if origin is None:
                    origin = T_model_depth[:3, 3].copy()
                T_local_depth = T_model_depth.copy()
                T_local_depth[:3, 3] -= origin
                rgb = rgb_ok = None
                if colors is not None:
                    import cv2

                    img = cv2.imread(str(colors[k]), cv2.IMREAD_COLOR)
                    if img is None:
                        raise InputError(colors[k], "cannot decode the colour image")
                    if color_cam.width == 0:
                        color_cam = color_cam.with_size(img.shape[1], img.shape[0])
                    rgb, rgb_ok = sample_colors(X_cam, T_color_depth, color_cam, img)
                    summary["colored_samples"] += int(rgb_ok.sum())
                if acc is None:
                    if cfg.tsdf:
                        acc = TSDFAccumulator(cfg.voxel if cfg.voxel > 0 else cfg.tsdf_voxel, cfg.tsdf_trunc_voxels,
                                              cfg.max_depth, cfg.tsdf_weight_threshold, colors is not None)
                    elif cfg.voxel > 0:
                        acc = VoxelAccumulator(cfg.voxel)
                    else:
                        acc = PointList()
                if cfg.tsdf:
                    d_keep = np.where(keep, depth, np.float32(0))
                    rgb_img = None
                    if rgb is not None:
                        rgb_img = np.zeros(depth.shape + (3,), np.float32)
                        rgb_img[keep] = rgb.astype(np.float32) / 255.0
                    acc.integrate(d_keep, cam.K, inv_T(T_local_depth), rgb_img)
                else:
                    X_local = transform_points_ew(T_local_depth, X_cam)
                    acc.add(X_local, rgb, rgb_ok)
                summary["points_fused"] += len(X_cam)
                summary["fused_frames"] += 1
                advance()
        if cfg.tsdf and cam.has_distortion:
            summary["warning"] = "TSDF integration ignores the depth camera's distortion"

    if acc is not None:
        X_local, rgb_out, count = acc.result()
        X = X_local + origin
    else:
        X, rgb_out, count = np.empty((0, 3)), np.empty((0, 3), np.uint8), np.empty(0, np.int64)
    with_rgb = color_dir is not None
    if landmarks is not None:
        L, L_rgb = landmarks
        summary["landmarks"] = len(L)
        if cfg.voxel > 0 and not cfg.tsdf and len(L):
            lacc = VoxelAccumulator(cfg.voxel)
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
        with_rgb = with_rgb or L_rgb is not None
    if len(X) == 0:
        where = depth_dir if depth_dir is not None else landmarks_path
        why = ("no frame had both a pose and valid depth" if summary["fused_frames"] == 0 and depth_dir is not None
               else "no point survived the depth range and edge filters")
        raise InputError(where, f"empty cloud: {why} ({summary['frames']} frames, {summary['skipped_no_pose']} without a pose)")
    summary["points_out"] = len(X)
    summary["bounds_min"] = X.min(axis=0).tolist()
    summary["bounds_max"] = X.max(axis=0).tolist()
    comments = [f"mst fuse mode={summary['mode']} voxel={cfg.voxel:g} frames={summary['fused_frames']}", "units metres, model frame"]
    with atomic_output(out_path) as tmp:
        write_ply(tmp, X, rgb_out if with_rgb else None, None if cfg.tsdf else count, comments)
    el = time.perf_counter() - t0
    summary["elapsed_s"] = el
    summary["frames_per_s"] = summary["fused_frames"] / el if el > 0 else 0.0
    summary["points_per_s"] = summary["points_fused"] / el if el > 0 else 0.0
    return summary
