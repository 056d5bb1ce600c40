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

from mst.core.aot import Kernels
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


@dataclass(frozen=True)
class Pyramid:
    """One frame's image pyramid for :func:`track_forward_backward` (built once per frame by
    :func:`build_pyramid`; a frame-to-frame tracker keeps the previous frame's). ``image``: the
    base level (H, W) uint8 (the frame itself, not copied); ``buf``: the coarser levels' pixels
    (uint8, row-major, one after the other); ``tab`` (L + 1, 3) int64: each level's offset (in
    ``buf``; 0 for the base level, read from ``image``), height and width."""

    image: np.ndarray
    buf: np.ndarray
    tab: np.ndarray

    @property
    def levels(self) -> int:
        """Levels above the base image."""
        return len(self.tab) - 1


def build_pyramid(gray: np.ndarray, levels: int, window_px: int = 3) -> Pyramid:
    """The pyramid of ``gray`` (H, W) uint8: ``levels`` halvings (``cv2.pyrDown``, as OpenCV's
    ``buildOpticalFlowPyramid``), fewer where a level would be no larger than ``window_px``."""
    import cv2

    img = np.ascontiguousarray(to_gray(gray))
    shapes = [img.shape]
    while len(shapes) <= levels:
        h, w = shapes[-1]
        if (h + 1) // 2 <= window_px or (w + 1) // 2 <= window_px:
            break
        shapes.append(((h + 1) // 2, (w + 1) // 2))
    tab = np.zeros((len(shapes), 3), np.int64)
    tab[:, 1:] = shapes
    tab[2:, 0] = np.cumsum(tab[1:, 1] * tab[1:, 2])[:-1]
    buf = np.empty(int(tab[-1, 0] + tab[-1, 1] * tab[-1, 2]) if len(shapes) > 1 else 0, np.uint8)
    lv = [img] + [buf[o:o + h * w].reshape(h, w) for o, h, w in tab[1:]]
    for k in range(1, len(lv)):  # each level written in place into the flat buffer
        cv2.pyrDown(lv[k - 1], dst=lv[k], dstsize=(int(tab[k, 2]), int(tab[k, 1])))
    return Pyramid(img, buf, tab)


class PyramidCache:
    """The pyramids of the last two images seen (by identity): a frame-to-frame tracker asks for
    the previous and the current frame's, and each frame's is built once. The images must not be
    modified in place while cached (the trackers keep their frames unchanged)."""

    def __init__(self, cfg: KltConfig):
        self.cfg = cfg
        self._items: list[tuple[np.ndarray, Pyramid]] = []

    def get(self, gray: np.ndarray) -> Pyramid:
        for img, pyr in self._items:
            if img is gray:
                return pyr
        pyr = build_pyramid(gray, self.cfg.pyramid_levels, self.cfg.window_px)
        self._items = [*self._items[-1:], (gray, pyr)]
        return pyr


#: the LK kernels (:mod:`mst.core.klt_kernels`): compiled ahead of time when current, numba's JIT otherwise
_KLT_KERNELS = Kernels("mst.core.klt_kernels")

#: OpenCV's default minimum eigenvalue (1e-4 of its gradient matrix over the window area, which
#: holds the Scharr derivatives unnormalised (32 x gray levels / px) scaled by 2^-20): in (gray
#: levels / px)^2 of the mean gradient matrix
MIN_EIG = 1e-4 * 1024.0


def _lk(prev: Pyramid, cur: Pyramid, p0: np.ndarray, guess: np.ndarray | None, cfg: KltConfig):
    lk_track, lk_track_5, lk_track_11 = _KLT_KERNELS.lk_track, _KLT_KERNELS.lk_track_5, _KLT_KERNELS.lk_track_11
    n = len(p0)
    out, st = np.empty((n, 2)), np.empty(n, np.uint8)
    g = p0 if guess is None else np.ascontiguousarray(guess, np.float64)
    args = (prev.image.reshape(-1), prev.buf, prev.tab, cur.image.reshape(-1), cur.buf, cur.tab, p0, g, guess is not None)
    rest = (int(min(cfg.pyramid_levels, prev.levels, cur.levels)), int(cfg.max_iterations), float(cfg.eps_px), MIN_EIG,
            out, st)
    win = int(cfg.window_px)
    if win == 5:
        lk_track_5(*args, *rest)
    elif win == 11:
        lk_track_11(*args, *rest)
    else:
        lk_track(*args, win, *rest)
    return out, st.astype(bool)


def track_forward_backward(prev_gray: np.ndarray | Pyramid, gray: np.ndarray | Pyramid, pts_px: np.ndarray,
                           cfg: KltConfig, guess_px: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track ``pts_px`` (N, 2) from ``prev_gray`` to ``gray`` (H, W uint8 images, or their
    pyramids, :class:`Pyramid`: a caller that tracks frame to frame builds each frame's once) and back.

    ``guess_px`` (N, 2): initial positions in ``gray`` (e.g. the landmarks projected at a predicted
    pose); ``None`` starts from ``pts_px``. Returns ``(pts1_px (N, 2) float32, ok (N,) bool,
    fb_px (N,))``: the tracked positions, whether both passes converged with a forward-backward
    error below ``cfg.fb_max_px``, and that error (px).
    """
    prev = prev_gray if isinstance(prev_gray, Pyramid) else build_pyramid(prev_gray, cfg.pyramid_levels, cfg.window_px)
    cur = gray if isinstance(gray, Pyramid) else build_pyramid(gray, cfg.pyramid_levels, cfg.window_px)
    # float32 positions throughout (OpenCV's point type, which the callers were written for)
    p0 = np.ascontiguousarray(np.asarray(pts_px, np.float32).reshape(-1, 2), np.float64)
    if not len(p0):
        return np.zeros((0, 2), np.float32), np.zeros(0, bool), np.zeros(0)
    g = None if guess_px is None else np.asarray(guess_px, np.float32).reshape(-1, 2)
    p1, st1 = _lk(prev, cur, p0, g, cfg)
    p1 = p1.astype(np.float32)
    p1d = p1.astype(np.float64)
    pb, st2 = _lk(cur, prev, p1d, p0 if cfg.backward_from_start else None, cfg)
    pb = pb.astype(np.float32)
    fb = np.linalg.norm(pb - p0.astype(np.float32), axis=1)
    ok = st1 & st2 & (fb < cfg.fb_max_px)
    return p1, ok, fb


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
