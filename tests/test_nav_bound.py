"""The oracle Wiener bound of a vision + GPS fusion (pipeline/nav/bound.py) against closed forms.

Budget: 300 frames at 5 fps, GPS 10 Hz (2 rows per frame: per-frame variance sigma^2 / 2). The
bound reads the realised vision spectrum, so it scatters about the expected value by the periodogram's
chi-square(2) spread, averaged over ~450 bins per axis: a few %; the bounds below allow 10 %.
"""

from __future__ import annotations

import numpy as np
import pytest

from mst.pipeline.nav.bound import gps_frame_noise_power, oracle_fusion_rmse, tracked_fusion_bound

N, FPS, RATE, SIG = 300, 5.0, 10.0, (3.0, 3.0, 5.0)


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(np.square(e), 1))))


@pytest.mark.parametrize("sv", [0.3, 1.0, 3.0])
def test_white_vision_matches_the_closed_form(sv):
    # white vision sv and white GPS s^2 / 2 per frame: per axis 1 / (1 / sv^2 + 2 / s^2)
    e = np.random.default_rng(1).normal(0.0, sv, (N, 3))
    expect = np.sqrt(sum(1.0 / (1.0 / sv**2 + 2.0 / s**2) for s in SIG))
    assert abs(oracle_fusion_rmse(e, FPS, RATE, SIG, 0.0) / expect - 1.0) < 0.1


def test_a_constant_bias_is_averaged_by_all_the_fixes():
    # a 0.3 m constant bias against the mean of 600 fixes (3 m): 1 / (1 / 0.09 + 600 / 9) per x
    e = np.tile([0.3, 0.0, 0.0], (N, 1))
    expect = np.sqrt(1.0 / (1.0 / 0.09 + 600 / 9.0))
    assert abs(oracle_fusion_rmse(e, FPS, RATE, SIG, 0.0) / expect - 1.0) < 0.1


def test_a_slow_bias_is_beyond_the_gps_and_a_white_error_is_not():
    rng = np.random.default_rng(2)
    slow = np.cumsum(rng.normal(0.0, 0.02, (N, 3)), 0)  # a random walk: its power in the lowest bins
    slow *= 0.3 / _rms(slow)
    white = rng.normal(0.0, 0.3 / np.sqrt(3), (N, 3))
    # the GPS averaged over the 60 s (600 fixes, 0.15 m per axis) barely touches 0.3 m of slow bias
    assert oracle_fusion_rmse(slow, FPS, RATE, SIG, 0.05) > 0.85 * 0.3
    # the same RMS as white noise: a smooth motion prior removes most of it
    assert oracle_fusion_rmse(white, FPS, RATE, SIG, 0.05, jerk_psd=0.5) < 0.7 * 0.3
    # more information never raises the bound
    assert oracle_fusion_rmse(slow, FPS, RATE, SIG, 0.05, jerk_psd=0.5) <= oracle_fusion_rmse(slow, FPS, RATE, SIG, 0.05)


def test_gps_power_and_tracked_runs():
    P = gps_frame_noise_power(N, FPS, RATE, SIG, 0.0, draws=400)
    # white: the bins' mean power is the per-frame variance sigma^2 / 2 (400 draws: ~0.4 % scatter)
    assert np.allclose(P.mean(0), np.square(SIG) / 2, rtol=0.05)
    with pytest.raises(ValueError):
        gps_frame_noise_power(N, 30.0, RATE, SIG, 0.0)
    # a tracked trajectory with a long gap: the two runs bounded apart, RMS-combined
    e = np.random.default_rng(3).normal(0.0, 0.3, (N, 3))
    k = np.r_[np.arange(0, 100), np.arange(200, N)]
    a = oracle_fusion_rmse(e[:100], FPS, RATE, SIG, 0.0)
    b = oracle_fusion_rmse(e[100:200], FPS, RATE, SIG, 0.0)
    both = tracked_fusion_bound(k, np.r_[e[:100], e[100:200]], FPS, RATE, SIG, 0.0)
    assert np.isclose(both, np.sqrt((a * a + b * b) / 2), rtol=1e-6)
