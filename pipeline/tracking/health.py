"""Image evidence of a pose and the calibrated health score of the edge tracker.

:class:`PoseEvidence`: what one image says about one pose (gradient polarity and orientation at
the projected model edges, the nearest moving edge, the appearance at fixed surface points);
:class:`HealthMonitor`: one score per frame against the statistics of the sequence's healthy
frames. Pixels, degrees, gray levels.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mst.pipeline.tracking.compiled import kernels as _kc  # ahead of time or numba JIT


def sobel_at(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,2) Sobel gradient (gx, gy) of ``img`` at the nearest pixels of ``uv`` (a numba kernel,
    :func:`mst.pipeline.tracking.kernels.sobel_at`: :func:`sobel_at_numpy`'s values to the bit)."""
    _kernel = _kc.sobel_at

    if img.dtype != np.uint8 and img.dtype != np.float32:
        img = img.astype(np.float32)
    return _kernel(np.ascontiguousarray(img), np.ascontiguousarray(uv, np.float64))


def sobel_at_numpy(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The numpy formulation of :func:`sobel_at` (the reference of the kernel's test)."""
    H, W = img.shape
    ix = np.clip(np.rint(uv[:, 0]).astype(np.int64), 1, W - 2)
    iy = np.clip(np.rint(uv[:, 1]).astype(np.int64), 1, H - 2)
    b = iy * W + ix
    f = img.ravel()
    p = [f[b + dy * W + dx].astype(np.float32) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    gx = (p[2] + 2 * p[5] + p[8]) - (p[0] + 2 * p[3] + p[6])
    gy = (p[6] + 2 * p[7] + p[8]) - (p[0] + 2 * p[1] + p[2])
    return np.stack([gx, gy], 1)



@dataclass
class PoseEvidence:
    """What one image says about one pose ``T_cam_model`` (see :meth:`EdgeTracker.evidence`).

    tex_idx / tex_val: the model's fixed surface points (:attr:`EdgeTracker.surf_X`) seen at this
    pose and the image there (3x3 mean, gray levels).
    edge (N,) model edge index (into ``ModelGeometry.edges``) of each visible sample, -1 for a sample of no
    model edge (a render-based edgelet, re-sampled at each render: not checked for a learned polarity, and
    counted in clusters of :data:`EDGELET_CLUSTER` as the independent units of a share); sign (N,) int8
    polarity of the image gradient along the projected model normal at the best position within
    +-1 px (0: no gradient of at least the moving-edge contrast there); oriented (N,) that gradient is
    within ``ORIENT_TOL_DEG`` of the model normal; offset_px (M,) distance along the normal to the
    nearest moving edge within the search range (NaN: none), at every k-th sample,
    k = N // :data:`EVIDENCE_SAMPLES` (at least 1).
    """

    edge: np.ndarray
    sign: np.ndarray
    oriented: np.ndarray
    offset_px: np.ndarray
    tex_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  #: visible surface points
    tex_val: np.ndarray = field(default_factory=lambda: np.zeros(0))             #: their 3x3-mean gray levels

    @property
    def n(self) -> int:
        return len(self.edge)

    @property
    def found(self) -> float:
        """Share of samples with a moving edge within the search range."""
        return float(np.isfinite(self.offset_px).mean()) if self.n else 0.0

    @property
    def residual_px(self) -> float:
        """Median distance to the nearest moving edge (px; inf without any)."""
        f = self.offset_px[np.isfinite(self.offset_px)]
        return float(np.median(np.abs(f))) if len(f) else float("inf")


#: the evidence's moving-edge search runs on every k-th visible sample, k = N // this: its share and median
#: over 100-199 samples sit well inside the signals' floors (binomial over the visible model edges, which
#: number far fewer; RESIDUAL_FLOOR_PX). Every 2nd beyond 200 samples was 0.13 ms of the L-building orbit's
#: 1.45 ms per frame at ~430 samples (issue #14)
EVIDENCE_SAMPLES = 100

#: render-based edgelets (no model edge) count as one independent unit of a share per this many: they are
#: spaced about one sampling bucket apart along the contour (render_edges: contour length / budget), so ten
#: of them span a contour stretch that shares its background and blur like a polygon edge's samples
EDGELET_CLUSTER = 10

#: spread floor of the moving-edge residual: whole-pixel positions along the normal, std 1/sqrt(12) px
RESIDUAL_FLOOR_PX = 0.29

#: orientation tolerance of a matching edge: the Sobel orientation of a straight step is within a
#: few degrees; 30 deg leaves room for blur and corners, and still rejects random texture (which
#: falls inside +-30 deg one time in three)
ORIENT_TOL_DEG = 30.0


class HealthMonitor:
    """One calibrated health score per frame, thresholds learned from the sequence's healthy frames.

    Signals (each "higher is better" after the sign flip of the residual):

    * ``match``: share of visible samples with an image edge within +-1 px of the projected model
      edge, of the model edge's orientation (``ORIENT_TOL_DEG``) and of the **polarity** that edge
      had in the healthy frames so far (bright/dark side; an edge whose polarity flips between
      healthy frames, e.g. a silhouette over a varying background, is not checked for it);
    * ``found``: share of samples with a moving edge within the search range;
    * ``residual``: the median distance (px) to the nearest moving edge (negated);
    * ``klt``: share of the tracked KLT points that agree with the pose (its robust inliers);
    * ``texture``: normalised cross-correlation of the image at the model's surface points with
      their appearance learned in the healthy frames (catches what edges alone cannot: the
      object's mirror image, a shadow or a background pattern of the object's outline).

    For each signal the reference is the median over the last ``window`` accepted frames and the
    spread 1.4826 x their MAD, floored by the signal's own sampling noise: binomial
    ``sqrt(p (1 - p) / n)`` for a share, where the samples of one model edge share its background
    and blur, so n = the number of visible model edges, and KLT points move in clusters, so n = their
    count / 10; ``RESIDUAL_FLOOR_PX`` for the residual (moving edges sit on whole pixels along the
    normal: a uniform +-0.5 px quantisation, std 0.29 px); ``(1 - r^2) / sqrt(n)`` (at least 0.02)
    for a correlation r over n points. The
    deficit ``z = (ref - value) / spread`` of the worst signal gives ``score = 1 - z / z_reject``:
    1 = a typical healthy frame, <= 0 = rejected. Until ``min_calib`` frames are accepted the
    spreads are doubled (a looser test while the statistics are young). The first frame (the
    user's pose) is accepted as the first reference.
    """

    SIGNALS = ("match", "found", "residual", "klt", "texture")

    def __init__(self, n_edges: int, n_surface: int = 0, window: int = 50, z_reject: float = 4.0, min_calib: int = 5):
        self.pol_sum = np.zeros(max(n_edges, 1))
        self.pol_n = np.zeros(max(n_edges, 1))
        self.tex_ref = np.zeros(max(n_surface, 1))
        self.tex_n = np.zeros(max(n_surface, 1))
        self.hist = {k: deque(maxlen=window) for k in self.SIGNALS}
        self.z_reject, self.min_calib = z_reject, min_calib
        self.n_learned = 0

    def features(self, ev: PoseEvidence, klt_agree: float | None = None, n_klt: int = 0) -> dict:
        """The signal values of one frame (and the sample counts behind them)."""
        has = ev.edge >= 0  # render-based edgelets (-1) have no learned polarity
        eid = np.where(has, ev.edge, 0)
        known = has & (self.pol_n[eid] >= 2)
        p = np.where(known, self.pol_sum[eid] / np.maximum(self.pol_n[eid], 1), 0.0)
        checked = known & (np.abs(p) >= 0.5)  # a stable polarity
        pol_ok = ~checked | (ev.sign == np.sign(p))
        match = float((ev.oriented & (ev.sign != 0) & pol_ok).mean()) if ev.n else 0.0
        res = ev.residual_px
        tex, n_tex = float("nan"), 0
        if len(ev.tex_idx):
            seen = self.tex_n[ev.tex_idx] > 0
            n_tex = int(seen.sum())
            if n_tex >= 20:
                a, b = ev.tex_val[seen], self.tex_ref[ev.tex_idx[seen]]
                sa, sb = a.std(), b.std()
                if sb > 1e-6:  # no correlation with a structured reference = none (a flat shadow, a blank wall)
                    tex = float(((a - a.mean()) * (b - b.mean())).mean() / (sa * sb)) if sa > 1e-6 else 0.0
        return {"match": match, "found": ev.found, "residual": -res if np.isfinite(res) else -np.inf,
                "klt": float(klt_agree) if klt_agree is not None and n_klt > 0 else float("nan"),
                "texture": tex, "n": ev.n, "n_klt": n_klt, "n_tex": n_tex,
                "n_edges": int(len(np.unique(ev.edge[has]))) + int(np.count_nonzero(~has)) // EDGELET_CLUSTER}

    def score(self, f: dict) -> tuple[float, str]:
        """``(score, worst signal)`` of a frame's features (score 1 with no history yet)."""
        worst, name = -np.inf, ""
        loose = 2.0 if self.n_learned < self.min_calib else 1.0
        for k in self.SIGNALS:
            v, h = f[k], self.hist[k]
            if not np.isfinite(v) and v != -np.inf:
                continue
            if not len(h):
                continue
            ref = _median(h)
            spread = 1.4826 * _median([abs(x - ref) for x in h])
            if k == "residual":
                floor = RESIDUAL_FLOOR_PX
            elif k == "texture":
                floor = max((1.0 - min(ref * ref, 1.0)) / np.sqrt(max(f["n_tex"], 1)), 0.02)
            else:
                n = f["n_klt"] / 10.0 if k == "klt" else f["n_edges"]
                floor = np.sqrt(max(ref * (1 - ref), 0.01) / max(n, 1))
            z = (ref - v) / (loose * max(spread, floor)) if np.isfinite(v) else np.inf
            if z > worst:
                worst, name = z, k
        if worst == -np.inf:
            return 1.0, ""
        return float(np.clip(1.0 - worst / self.z_reject, -1.0, 1.0)), name

    def learn(self, ev: PoseEvidence, f: dict) -> None:
        """Add an accepted frame: its signals and its edges' polarities."""
        for k in self.SIGNALS:
            if np.isfinite(f[k]):
                self.hist[k].append(f[k])
        s = (ev.sign != 0) & (ev.edge >= 0)
        np.add.at(self.pol_sum, ev.edge[s], ev.sign[s].astype(float))
        np.add.at(self.pol_n, ev.edge[s], 1.0)
        if len(ev.tex_idx):
            # appearance: running mean over the first 10 sightings, then an exponential one (slow light changes)
            i = ev.tex_idx
            w = 1.0 / np.minimum(self.tex_n[i] + 1.0, 10.0)
            self.tex_ref[i] += w * (ev.tex_val - self.tex_ref[i])
            self.tex_n[i] += 1.0
        self.n_learned += 1


def _median(values) -> float:
    """``float(np.median(values))`` of a short sequence of finite floats, the same value (the middle one, or the
    two middle ones' sum halved) without numpy's per-call cost: the score takes 10 per frame of at most 50 values
    (issue #14: 0.15 ms of the tea box's default-mode frame)."""
    s = sorted(float(x) for x in values)
    m = len(s) // 2
    return s[m] if len(s) % 2 else (s[m - 1] + s[m]) / 2.0


def image_noise_sigma(gray: np.ndarray) -> float:
    """Gray-level noise std of an image (Immerkaer 1996: mean |Laplacian-difference| response)."""
    import cv2

    M = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(gray.astype(np.float32), -1, M)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) / 6.0 * np.abs(r).mean()) if r.size else 0.0
