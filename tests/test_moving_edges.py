"""The moving-edge search (:func:`mst.pipeline.tracking.moving_edges.search_edges`) on synthetic step edges:
position within the quantisation budget, polarity (ViSP's contrast test), search range, threshold."""

from __future__ import annotations

import numpy as np

from mst.pipeline.tracking.moving_edges import canonical_normals, reference_contrast, search_edges

ME = dict(threshold=20, mu1=0.5, mu2=0.5, size=5, n_masks=180)


def _step(d0: float, lo: int = 60, hi: int = 180, W: int = 101) -> np.ndarray:
    """A vertical step edge at x = 50 + d0 (dark left, bright right), 16x horizontally supersampled."""
    xx = np.arange(W)[None, :] + (np.arange(16)[:, None] + 0.5) / 16 - 0.5
    cover = (xx > 50 + d0).mean(0)
    return np.tile(np.round(lo + (hi - lo) * cover).astype(np.uint8), (W, 1))


def _samples():
    return canonical_normals(np.tile([1.0, 0.0], (9, 1)), 180)  # normal along +x


def _search(img, d_ref=None, search_range=4, ref_img=None):
    uv = np.stack([np.full(9, 50.0), np.linspace(30, 70, 9)], 1)
    n, midx = _samples()
    ref = None if ref_img is None else reference_contrast(ref_img, uv, n, midx, 5, 180)
    return search_edges(img, uv, n, ref, search_range=search_range, n_candidates=1, mask_idx=midx, **ME)


def test_subpixel_offset_found_within_the_quantisation_budget():
    """Offsets -3..3 px in 1/8 steps; budget 0.2 px (gray-level quantisation of the coverage,
    the parabola's model error on the 5 px mask's response; see test_moving_edges_subpixel)."""
    for d0 in np.arange(-3.0, 3.01, 0.125):
        m = _search(_step(d0))
        err = np.abs(m.offset[:, 0] - d0)
        assert np.isfinite(err).all() and err.max() < 0.2, (d0, err)


def test_polarity_with_a_reference_contrast():
    """With the previous image's contrast as reference, an edge of the same polarity is found and the
    inverted edge (bright left, dark right) at the same place is refused (contrast ratio < 0)."""
    ref_img = _step(0.0)
    assert np.isfinite(_search(_step(1.5), ref_img=ref_img).offset).all()
    assert np.isnan(_search(_step(1.5, lo=180, hi=60), ref_img=ref_img).offset).all()
    # without a reference both polarities are edges
    assert np.isfinite(_search(_step(1.5, lo=180, hi=60)).offset).all()


def test_search_range_bounds_the_offset():
    """An edge 8 px away: beyond a 4 px range plus the 5 px mask's half width nothing is found; a
    10 px range finds it."""
    img = _step(8.0)
    assert np.isnan(_search(img, search_range=4).offset).all()
    m = _search(img, search_range=10)
    assert np.abs(m.offset[:, 0] - 8.0).max() < 0.2


def test_contrast_below_the_threshold_is_no_edge():
    assert np.isnan(_search(_step(0.0, lo=100, hi=115)).offset).all()  # a 15-level step, threshold 20
    assert np.isfinite(_search(_step(0.0, lo=100, hi=130)).offset).all()
