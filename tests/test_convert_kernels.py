"""The numba kernels of convert-model (mst.meshtools.kernels) against the numpy/scipy code they
replace: labels equal, floating-point results and decisions bit for bit (outputs must stay
byte-identical)."""

import numpy as np
import pytest

from mst.meshtools.kernels import components, pair_candidates, plane_ok, region_sums


def test_components_match_scipy_labels():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(0)
    for n, m in ((1, 0), (10, 3), (5000, 4000), (20000, 30000)):
        a, b = rng.integers(0, n, m), rng.integers(0, n, m)
        nc, lab = components(n, a, b)
        ref_n, ref = connected_components(coo_matrix((np.ones(m), (a, b)), shape=(n, n)), directed=False)
        assert nc == ref_n and np.array_equal(lab, ref)
    with pytest.raises(ValueError):
        components(3, np.array([0]), np.array([3]))


def _random_mesh(seed=1, M=50_000, nv=20_000, n_lab=700):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(nv, 3)) * rng.choice([1e-3, 1.0, 1e3], size=(nv, 1))
    F = rng.integers(0, nv, (M, 3))
    N = rng.normal(size=(M, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return rng, X, F, N, rng.random(M), rng.integers(0, n_lab, M), n_lab


def test_region_sums_bitwise():
    _, X, F, N, w, lab, n_lab = _random_mesh()
    nsum, csum, wsum = region_sums(X, F, N, w, lab, n_lab)
    cen = X[F].mean(axis=1)
    assert np.array_equal(nsum, np.stack([np.bincount(lab, weights=N[:, k] * w, minlength=n_lab) for k in range(3)], 1))
    assert np.array_equal(csum, np.stack([np.bincount(lab, weights=cen[:, k] * w, minlength=n_lab) for k in range(3)], 1))
    assert np.array_equal(wsum, np.bincount(lab, weights=w, minlength=n_lab))


def test_pair_and_plane_decisions_bitwise():
    rng, X, F, N, w, lab, n_lab = _random_mesh(seed=2)
    f1, f2 = rng.integers(0, len(F), 40_000), rng.integers(0, len(F), 40_000)
    consistent = rng.random(len(f1)) < 0.9
    cos_pair = np.einsum("ij,ij->i", N[f1], N[f2])
    nsum, csum, wsum = region_sums(X, F, N, w, lab, n_lab)
    nR = nsum / np.linalg.norm(nsum, axis=1, keepdims=True)
    cR = csum / wsum[:, None]
    nRl = nR[lab]
    dots = np.einsum("ij,ij->i", N, nRl)
    d = np.abs(np.einsum("ijk,ik->ij", X[F], nRl) - np.einsum("ij,ij->i", cR[lab], nRl)[:, None]).max(axis=1)
    # thresholds at exact values and one ulp below them: a decision agrees at both only if the
    # kernel's value equals numpy's bit for bit for that element
    for k in rng.integers(0, len(f1), 20):
        for t in (cos_pair[k], np.nextafter(cos_pair[k], 2.0)):
            assert np.array_equal(pair_candidates(N, f1, f2, consistent, t), consistent & (cos_pair >= t))
    for k in rng.integers(0, len(F), 20):
        for half in (dots[k], np.nextafter(dots[k], 2.0)):
            for tol in (d[k], np.nextafter(d[k], -1.0), np.inf):
                assert np.array_equal(plane_ok(X, F, N, lab, nR, cR, half, tol), (dots >= half) & (d <= tol))


def test_edge_order_is_stable_argsort():
    from mst.meshtools.kernels import edge_order

    rng = np.random.default_rng(3)
    for nv, n in ((3, 6), (50, 3000), (20_000, 60_000)):  # small nv: buckets > 32 take the merge-sort branch
        u, v = rng.integers(0, nv, n), rng.integers(0, nv, n)
        key = np.minimum(u, v) * nv + np.maximum(u, v)
        assert np.array_equal(edge_order(u, v, nv), np.argsort(key, kind="stable"))


def test_triangle_cross_bitwise():
    from mst.meshtools.kernels import triangle_cross

    _, X, F, *_ = _random_mesh(seed=4)
    a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    ref = np.cross(b - a, c - a)
    cr, area2 = triangle_cross(X, F)
    assert np.array_equal(cr, ref) and np.array_equal(area2, np.linalg.norm(ref, axis=1))


def test_edge_groups_match_numpy_grouping():
    from mst.meshtools.kernels import edge_groups

    rng = np.random.default_rng(5)
    nv, n = 150, 9000  # ~11,000 keys: single, paired and 3+ edges
    u, v = rng.integers(0, nv, n), rng.integers(0, nv, n)
    order, start, count, edge, pair = edge_groups(u, v, nv)
    key = np.minimum(u, v) * nv + np.maximum(u, v)
    ref_order = np.argsort(key, kind="stable")
    ks = key[ref_order]
    ref_start = np.concatenate([[0], np.flatnonzero(np.diff(ks)) + 1])
    ref_count = np.diff(np.concatenate([ref_start, [n]]))
    ref_edge = np.empty(n, np.int64)
    ref_edge[ref_order] = np.repeat(np.arange(len(ref_start)), ref_count)
    man = ref_start[ref_count == 2]
    assert (count == 2).any() and (count > 2).any()
    for got, ref in ((order, ref_order), (start, ref_start), (count, ref_count), (edge, ref_edge),
                     (pair, np.stack([ref_order[man], ref_order[man + 1]], axis=1))):
        assert np.array_equal(got, ref)
