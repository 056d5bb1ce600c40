"""Per-frame depth filters of the fusion: rays, back-projection, discontinuity / grazing masks,
bilateral smoothing, colour sampling. Pure numpy (OpenCV for the bilateral filter)."""

from __future__ import annotations

import numpy as np

from mst.core.camera import Camera
from mst.core.poses import transform_points
from mst.pipeline.fusion.config import FuseConfig


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
    in_range = has & (d >= cfg.depth.min_m) & (d <= cfg.depth.max_m)
    if cfg.smooth_px >= 2:
        d = smooth_depth(np.where(in_range, d, np.float32(0)), cfg.smooth_px, cfg.smooth_rel)
    keep = in_range.copy()
    n_edge = n_graze = 0
    if cfg.depth.edge_rel > 0:
        e = depth_edge_mask(np.where(in_range, d, np.float32(0)), cfg.depth.edge_rel) & keep
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


def sample_colors(X_depth: np.ndarray, T_color_depth: np.ndarray, color_cam: Camera, image_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour of depth-camera points from a colour image (nearest pixel).

    Returns ``(rgb (N, 3) uint8, ok (N,) bool)``; points behind the colour camera or outside its
    image get ``ok = False``.
    """
    X_c = transform_points(T_color_depth, X_depth, elementwise=True)
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
