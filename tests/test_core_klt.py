"""The one KLT front end (mst.core.klt): its pyramidal Lucas-Kanade kernel (mst.core.klt_kernels,
issue #14: each frame's pyramid built once) tracks as OpenCV's calcOpticalFlowPyrLK called the way
each user did before, within the LK stopping step; pyramids and images give the same result."""

from __future__ import annotations

import numpy as np
import pytest

from mst.core.klt import KltConfig, build_pyramid, to_gray, track_forward_backward

SHIFT = (1.7, -0.8)


def _pair(shift=SHIFT):
    import cv2

    rng = np.random.default_rng(1)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.uint8), (0, 0), 2)
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    b = cv2.warpAffine(a, M, (320, 240), borderMode=cv2.BORDER_REFLECT)
    pts = cv2.goodFeaturesToTrack(a, 200, 0.01, 8).reshape(-1, 2)
    return a, b, pts


def _opencv_fb(a, b, pts, cfg: KltConfig, guess=None):
    """The former implementation: two OpenCV calls (each rebuilding both pyramids)."""
    import cv2

    lk = dict(winSize=(cfg.window_px,) * 2, maxLevel=cfg.pyramid_levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.max_iterations, cfg.eps_px))
    p0 = pts.reshape(-1, 1, 2).astype(np.float32)
    if guess is None:
        p1, s1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, **lk)
    else:
        p1, s1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, guess.reshape(-1, 1, 2).astype(np.float32).copy(),
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    if cfg.backward_from_start:
        pb, s2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    else:
        pb, s2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, **lk)
    fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
    return p1.reshape(-1, 2), (s1.ravel() == 1) & (s2.ravel() == 1) & (fb < cfg.fb_max_px)


def _configs():
    from mst.pipeline.slam import slam_klt_config
    from mst.pipeline.tracking.config import TrackKltConfig

    return {"slam": slam_klt_config(), "tracker": TrackKltConfig(),
            "tracker window 5": TrackKltConfig(window_px=5, max_iterations=20, eps_px=0.03)}


@pytest.mark.parametrize("name", ["slam", "tracker", "tracker window 5"])
def test_tracks_as_opencv_within_the_stopping_step(name):
    """Same points tracked, positions within the LK stopping step of OpenCV's: both stop where a
    step is below ``eps_px`` (0.01-0.03 px), so two exact implementations may differ by about
    that much (here: float64 steps from exact integer window sums against OpenCV's float32 sums,
    replicated against reflected borders): median <= eps, 95 % <= 2 eps; the shift recovered."""
    cfg = _configs()[name]
    a, b, pts = _pair()
    guess = (pts + [1.5, -0.5]) if name == "slam" else None
    c1, c_ok = _opencv_fb(a, b, pts, cfg, guess)
    q1, q_ok, q_fb = track_forward_backward(a, b, pts, cfg, guess)
    assert q1.dtype == np.float32 and q1.shape == pts.shape and q_fb.shape == (len(pts),)
    assert np.mean(q_ok == c_ok) >= 0.98  # at most 2 % decided differently (fb error at its bound)
    both = q_ok & c_ok
    d = np.linalg.norm(q1[both] - c1[both], axis=1)
    assert np.median(d) <= cfg.eps_px and np.percentile(d, 95) <= 2 * cfg.eps_px
    # the warp is a pure 1.7, -0.8 px shift: the median track within 0.05 px (bilinear warp, noise-free)
    assert q_ok.mean() > 0.9 and np.allclose(np.median(q1[q_ok] - pts[q_ok], 0), SHIFT, atol=0.05)


def test_pyramids_and_images_give_the_same_tracks():
    """A caller that keeps each frame's pyramid gets the tracks of the image call, bit for bit."""
    cfg = _configs()["tracker"]
    a, b, pts = _pair()
    r_img = track_forward_backward(a, b, pts, cfg)
    pa, pb = build_pyramid(a, cfg.pyramid_levels, cfg.window_px), build_pyramid(b, cfg.pyramid_levels, cfg.window_px)
    r_pyr = track_forward_backward(pa, pb, pts, cfg)
    for x, y in zip(r_img, r_pyr):
        assert np.array_equal(x, y)
    import cv2

    assert pa.levels == 3 and pa.image is a  # the frame itself is the base level (not copied)
    lv = a
    for o, h, w in pa.tab[1:]:  # OpenCV's pyramid (buildOpticalFlowPyramid's pyrDown), level by level
        lv = cv2.pyrDown(lv)
        assert lv.shape == (h, w) and np.array_equal(pa.buf[o:o + h * w].reshape(h, w), lv)


def test_points_that_leave_the_image_or_lack_texture_are_refused():
    """A flat patch (no gradient: the minimum-eigenvalue test) and points far outside the image
    are not tracked; an empty set gives empty results."""
    cfg = _configs()["tracker"]
    a, b, pts = _pair()
    a, b = a.copy(), b.copy()
    a[:60, :60] = b[:60, :60] = 128
    probe = np.array([[30.0, 30.0], [-50.0, 100.0], [100.0, 400.0]])
    _, ok, _ = track_forward_backward(a, b, probe, cfg)
    assert not ok.any()
    p1, ok, fb = track_forward_backward(a, b, np.zeros((0, 2)), cfg)
    assert p1.shape == (0, 2) and ok.shape == (0,) and fb.shape == (0,)


def test_large_motion_needs_the_pyramid():
    """An 12 px shift: tracked with 3 pyramid levels (the coarsest sees 1.5 px), not at the base
    level alone (an 11 px window's LK converges within about its half width)."""
    a, b, pts = _pair((12.0, 5.0))
    inner = pts[(pts[:, 0] > 30) & (pts[:, 0] < 290) & (pts[:, 1] > 30) & (pts[:, 1] < 210)]
    cfg = _configs()["tracker"]
    q1, ok, _ = track_forward_backward(a, b, inner, cfg)
    assert ok.mean() > 0.9 and np.allclose(np.median(q1[ok] - inner[ok], 0), [12.0, 5.0], atol=0.05)
    _, ok0, _ = track_forward_backward(a, b, inner, cfg.replace(pyramid_levels=0))
    assert ok0.mean() < 0.5


def test_to_gray():
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 255
    g = to_gray(bgr)
    assert g.shape == (4, 5) and g.dtype == np.uint8 and g[0, 0] == 76   # 0.299 x 255, red
    assert to_gray(np.full((2, 2), 300.0))[0, 0] == 255

