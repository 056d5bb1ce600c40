"""The one KLT front end: pyramidal Lucas-Kanade tracking with a forward-backward check.

Both KLT users call it: the tracker's hybrid edges+KLT mode (ViSP's ``<klt>`` settings: corners
inside the model's silhouette, lifted onto the model) and the SLAM aid (grid-replenished corners
with landmarks). They differ in their settings only (:class:`KltConfig`; each stage keeps its own
section with its own defaults), not in code.

Pixels throughout: ``(N, 2)`` float arrays of (u, v) in the image of the frame they belong to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mst.core.config import Config, param


@dataclass
class KltConfig(Config):
    """KLT corner detection and tracking (pixels; ViSP ``<klt>`` names in brackets)."""

    window_px: int = param(11, min=3, max=255, odd=True, help="side of the square LK window, px [2 window_size + 1]")
    pyramid_levels: int = param(3, min=0, max=8, help="pyramid levels above the base image [pyramid_lvl]")
    fb_max_px: float = param(1.0, min=0, min_open=True, help="forward-backward error bound, px")
    backward_from_start: bool = param(True, help="start the backward pass at the original points (else at the tracked ones)")
    max_iterations: int = param(30, min=1, max=1000, help="LK iterations per pyramid level, at most (OpenCV's default 30)")
    eps_px: float = param(0.01, min=0, help="LK stops when the window moves less than this, px (OpenCV's default 0.01)")
    max_features: int = param(300, min=1, max=100_000, help="corners detected per image [max_features]")
    quality: float = param(0.015, min=0, max=1, min_open=True, help="goodFeaturesToTrack quality level [quality]")
    min_distance_px: float = param(8.0, min=0, help="minimum distance between corners, px [min_distance]")
    harris_k: float = param(0.01, min=0, max=1, help="Harris k [harris]")
    block_px: int = param(3, min=1, max=31, help="corner detector block size, px [size_block]")
    border_px: int = param(5, min=0, max=1000, help="corners at least this far inside the mask, px [mask_border]")


def track_forward_backward(prev_gray: np.ndarray, gray: np.ndarray, pts_px: np.ndarray, cfg: KltConfig,
                           guess_px: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track ``pts_px`` (N, 2) from ``prev_gray`` to ``gray`` (H, W uint8) and back.

    ``guess_px`` (N, 2): initial positions in ``gray`` (e.g. the landmarks projected at a predicted
    pose); ``None`` starts from ``pts_px``. Returns ``(pts1_px (N, 2) float32, ok (N,) bool,
    fb_px (N,))``: the tracked positions, whether both passes converged with a forward-backward
    error below ``cfg.fb_max_px``, and that error (px).
    """
    import cv2

    p0 = np.ascontiguousarray(np.asarray(pts_px, np.float32).reshape(-1, 1, 2))
    lk = dict(winSize=(cfg.window_px, cfg.window_px), maxLevel=cfg.pyramid_levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.max_iterations, cfg.eps_px))
    if guess_px is None:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, p0, None, **lk)
    else:
        g = np.ascontiguousarray(np.asarray(guess_px, np.float32).reshape(-1, 1, 2))
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, p0, g, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    if cfg.backward_from_start:
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev_gray, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    else:
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev_gray, p1, None, **lk)
    fb = np.linalg.norm(pb.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_max_px)
    return p1.reshape(-1, 2), ok, fb


def to_gray(img: np.ndarray) -> np.ndarray:
    """A frame as the 8-bit single-channel image KLT and ORB work on (BGR/BGRA converted, other
    dtypes clipped to 0..255); an 8-bit gray image is returned as is."""
    import cv2

    a = np.asarray(img)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.dtype != np.uint8:
        a = np.clip(a, 0, 255).astype(np.uint8)
    return a
