"""The one KLT front end (mst.core.klt): the same result as OpenCV called the way each user did
before #10, bit for bit (the tracker's hybrid KLT with OpenCV's default criteria, the SLAM's with
10 iterations, a guess and the backward pass from the original points)."""

from __future__ import annotations

import numpy as np

from mst.core.klt import KltConfig, to_gray, track_forward_backward


def _pair():
    import cv2

    rng = np.random.default_rng(1)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.uint8), (0, 0), 2)
    M = np.float32([[1, 0, 1.7], [0, 1, -0.8]])
    b = cv2.warpAffine(a, M, (320, 240), borderMode=cv2.BORDER_REFLECT)
    pts = cv2.goodFeaturesToTrack(a, 200, 0.01, 8).reshape(-1, 2)
    return a, b, pts


def test_the_slams_settings_match_its_former_calls():
    import cv2

    a, b, pts = _pair()
    from mst.pipeline.slam import slam_klt_config

    cfg = slam_klt_config()
    guess = (pts + [1.5, -0.5]).astype(np.float32)
    lk = dict(winSize=(11, 11), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.01))
    p0 = pts.reshape(-1, 1, 2).astype(np.float32)
    p1, s1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, guess.reshape(-1, 1, 2).copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    pb, s2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    fb = np.linalg.norm(pb.reshape(-1, 2) - pts.astype(np.float32), axis=1)
    ok = (s1.ravel() == 1) & (s2.ravel() == 1) & (fb < 1.0)
    q1, q_ok, q_fb = track_forward_backward(a, b, pts, cfg, guess)
    assert np.array_equal(q1, p1.reshape(-1, 2)) and np.array_equal(q_ok, ok) and np.array_equal(q_fb, fb)
    assert ok.mean() > 0.9 and np.allclose(np.median(q1[ok] - pts[ok], 0), [1.7, -0.8], atol=0.05)


def test_the_default_criteria_are_opencvs():
    """The tracker's KLT (no criteria given before): OpenCV's default (30 iterations, 0.01)."""
    import cv2

    a, b, pts = _pair()
    cfg = KltConfig(window_px=11, fb_max_px=0.5, backward_from_start=False)
    p0 = pts.reshape(-1, 1, 2).astype(np.float32)
    p1, s1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(11, 11), maxLevel=3)
    pb, s2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, winSize=(11, 11), maxLevel=3)
    fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
    q1, q_ok, _ = track_forward_backward(a, b, pts, cfg)
    assert np.array_equal(q1, p1.reshape(-1, 2))
    assert np.array_equal(q_ok, (s1.ravel() == 1) & (s2.ravel() == 1) & (fb < 0.5))


def test_to_gray():
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 255
    g = to_gray(bgr)
    assert g.shape == (4, 5) and g.dtype == np.uint8 and g[0, 0] == 76   # 0.299 x 255, red
    assert to_gray(np.full((2, 2), 300.0))[0, 0] == 255
