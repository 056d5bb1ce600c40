"""Moving edges locate a straight step edge to a fraction of a pixel at every orientation."""

from __future__ import annotations

import numpy as np
import pytest

from mst.pipeline.tracking.moving_edges import canonical_normals, search_edges


@pytest.mark.parametrize("ang_deg", np.arange(0.0, 180.0, 7.5))
def test_step_edge_subpixel_at_every_angle(ang_deg):
    """An anti-aliased step edge (8x8 supersampled coverage, 120 gray levels) at a random sub-pixel
    offset from the samples. Error budget: coverage quantisation 1/120 px, the parabola's model
    error on the 5 px mask's response (< 0.1 px measured over 0-180 deg): 0.2 px. Pixels read
    along a slanted normal are 0-1.41 px apart; a unit-spacing parabola was off by up to 1.13 px."""
    H = W = 101
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    n = np.array([np.cos(np.radians(ang_deg)), np.sin(np.radians(ang_deg))])
    d0 = np.random.default_rng(int(ang_deg * 10)).uniform(-0.5, 0.5)
    c = np.array([50.0, 50.0])
    ss = (np.arange(8) + 0.5) / 8 - 0.5
    cover = sum(((xx + sx - c[0]) * n[0] + (yy + sy - c[1]) * n[1] > d0).astype(float) for sx in ss for sy in ss) / 64
    img = (60 + 120 * cover).round().astype(np.uint8)
    uv = c + np.outer(np.linspace(-20, 20, 11), [-n[1], n[0]])  # samples on the line through c
    nn, midx = canonical_normals(np.tile(n, (len(uv), 1)), 180)
    m = search_edges(img, uv, nn, None, search_range=4, threshold=20, mu1=0.5, mu2=0.5, size=5, n_masks=180,
                     n_candidates=1, mask_idx=midx)
    err = np.abs(m.offset[:, 0] * np.sign(nn[0] @ n) - d0)
    assert np.isfinite(err).all() and err.max() < 0.2, err
