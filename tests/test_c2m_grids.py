"""mst.eval.c2m.grids: the compiled and numpy paths of the dense grid agree (and with the BVH engine),
the binned grid equals a brute-force scan on a large surface."""

from __future__ import annotations

import numpy as np
import pytest
from c2m_helpers import brute_force_d2, dist

from mst.eval import c2m


def test_grid_compiled_and_numpy_paths_agree():
    """The numba kernels and the numpy fallback of the grid engine give the same answers, and the
    lazily filled cell cache gives the same answers on a second pass (cells already computed)."""
    from mst.meshtools.generate import courtyard

    V, F = courtyard(split=3)
    rng = np.random.default_rng(11)
    P = rng.uniform(V.min(0) - 3, V.max(0) + 3, (20000, 3))
    P[:50] = rng.uniform(-1e9, 1e9, (50, 3))  # far outliers (outside the grid)
    a = c2m.prepare_mesh(V, F, signed=True, engine="grid")
    b = c2m.prepare_mesh(V, F, signed=True, engine="grid", compiled=False)
    bvh = c2m.prepare_mesh(V, F, signed=True, engine="bvh")
    da, sa = dist(a, P)
    db, sb = dist(b, P)
    dc, sc = dist(bvh, P)
    da2, _ = dist(a, P[::-1])
    np.testing.assert_allclose(da, db, rtol=1e-15, atol=1e-12)
    # the BVH's float32 pick is refined exactly (near ties; far outliers searched again in float64)
    np.testing.assert_allclose(da, dc, rtol=1e-15, atol=1e-12)
    np.testing.assert_array_equal(da2[::-1], da)
    assert (np.sign(sa) == np.sign(sb)).all() and (np.sign(sa) == np.sign(sc)).all()
    # max-dist: cells whose lower bound exceeds it are skipped, the rest exact
    dm, _ = dist(a, P, max_dist=0.5)
    np.testing.assert_array_equal(np.isnan(dm), da > 0.5)
    np.testing.assert_allclose(dm[da <= 0.5], da[da <= 0.5])


@pytest.mark.slow  # suite time; test_grid_compiled_and_numpy_paths_agree keeps the engines' agreement in the default run
def test_binned_grid_engine_matches_brute_force_on_a_large_random_surface():
    """The grid engine on a ~50k-triangle surface (binned cells + shell search, no Open3D) gives the
    exact distances of a brute-force scan (1e-9 m) for points on, near, far above and far outside
    the surface (georeferenced coordinates); max-dist skips exactly the farther points; the sign
    agrees with the BVH engine's."""
    from mst.meshtools.generate import terrain

    V, F, _ = terrain(size=300.0, cells=158, seed=5)
    rng = np.random.default_rng(3)
    V = V.copy()
    V[:, 2] += rng.normal(0, 0.3, len(V))  # rough: many near-ties between neighbouring triangles
    V += np.array([512_000.0, 5_430_000.0, 300.0])  # georeferenced
    assert len(F) > 49_000
    idx = c2m.prepare_mesh(V, F, signed=True, engine="grid")
    assert type(idx.search).__name__ == "BinGrid"
    bvh = c2m.prepare_mesh(V, F, signed=True, engine="bvh")
    lo, hi = V.min(0), V.max(0)
    A = V[F[:, 0]]
    near = A[rng.integers(0, len(F), 150)] + rng.normal(0, 0.05, (150, 3))
    above = rng.uniform(lo - [0, 0, 20], hi + [0, 0, 20], (100, 3))
    outside = rng.uniform(lo - 200, hi + 200, (60, 3))  # beyond the grid margin: the far-point scan
    very_far = rng.uniform(-1e6, 1e6, (10, 3)) + V.mean(0)
    on_vertex = V[rng.integers(0, len(V), 20)]
    P = np.vstack([near, above, outside, very_far, on_vertex])
    d, s = dist(idx, P)
    ref = np.sqrt(brute_force_d2(idx, P - idx.shift))
    np.testing.assert_allclose(d, ref, rtol=0, atol=1e-9)
    assert (d[-20:] < 1e-9).all()
    np.testing.assert_allclose(np.abs(s), d)
    db, sb = dist(bvh, P[:250])
    assert (np.sign(s[:250]) == np.sign(sb)).mean() > 0.99  # BVH float32 picks may differ at exact ties
    # many points (parallel kernel, chunk order independent) agree with the numpy brute force on a sample
    Q = np.vstack([A[rng.integers(0, len(F), 40000)] + rng.normal(0, 0.1, (40000, 3)),
                   rng.uniform(lo - 5, hi + 5, (4000, 3))])
    dq, _ = dist(idx, Q, signed=False)
    k = rng.choice(len(Q), 150, replace=False)
    np.testing.assert_allclose(dq[k], np.sqrt(brute_force_d2(idx, Q[k] - idx.shift)), rtol=0, atol=1e-9)
    dm, _ = dist(idx, Q, signed=False, max_dist=0.2)
    np.testing.assert_array_equal(np.isnan(dm), dq > 0.2)
    np.testing.assert_array_equal(dm[dq <= 0.2], dq[dq <= 0.2])


def test_utm_coordinates_chunked_compiled_equals_numpy_reference():
    """Issue #14's UTM case (the bench's 640-triangle building at easting 500 km, northing 5,400 km,
    noisy points + outliers), streamed in chunks (the first chunk fills its cells before the query,
    later chunks fill lazily): the compiled grid engine equals the numpy reference path to 1e-9 m.
    Budget: both are exact float64 on coordinates shifted to the mesh centre (|p| < 60 m), rounding
    ~1e-14 m; 1e-9 m only allows for a different but equally near triangle at an exact tie."""
    from mst.eval.bench.c2m import building_mesh, sample_surface
    from mst.eval.c2m.config import C2MConfig

    V, F = building_mesh()
    off = np.array([500_000.0, 5_400_000.0, 0.0])
    P = sample_surface(V, F, 30_000, 0.05, 0.02, 7).astype(np.float64) + off
    cfg = C2MConfig(chunk_points=7_000)
    a = c2m.c2m(P, c2m.prepare_mesh(V + off, F, engine="grid"), cfg)
    b = c2m.c2m(P, c2m.prepare_mesh(V + off, F, engine="grid", compiled=False), cfg)
    assert a.points_valid == b.points_valid == len(P)
    np.testing.assert_allclose(a.distances, b.distances, rtol=0, atol=1e-9)
    # the points lie within the sampling noise of the surface (outliers: inside the box grown by 2 m)
    assert np.median(a.distances) < 0.05 * 2


def test_points_outside_the_dense_grid_take_the_compiled_binned_search():
    """Points beyond the dense grid's 10 % margin (here most of them, up to 2 box extents out) are
    searched by a binned grid of the same mesh (issue #14: the numpy coarse-to-fine search took
    2.3 s for 3,000 points around this 3,072-triangle box). Exact: equal to a brute-force scan to
    float64 rounding (1e-12 m on a 10 m box), signs those of the numpy reference path, and with
    ``max_dist`` NaN exactly beyond it."""
    from mst.meshtools.generate import box

    V, F = (np.asarray(a) for a in box(split=16)[:2])
    rng = np.random.default_rng(4)
    ext = V.max(0) - V.min(0)
    P = rng.uniform(V.min(0) - 2 * ext, V.max(0) + 2 * ext, (600, 3))
    a = c2m.prepare_mesh(V, F, signed=True, engine="grid")
    b = c2m.prepare_mesh(V, F, signed=True, engine="grid", compiled=False)
    assert a.n_triangles == 3072
    da, sa = dist(a, P)
    db, sb = dist(b, P)
    ref = np.sqrt(brute_force_d2(a, P - a.shift))
    np.testing.assert_allclose(da, ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(da, db, rtol=0, atol=1e-12)
    assert (np.sign(sa) == np.sign(sb)).all()
    assert a.search._bins is not None  # the binned search did run
    dm, _ = dist(a, P, max_dist=3.0)
    np.testing.assert_array_equal(np.isnan(dm), ref > 3.0)
