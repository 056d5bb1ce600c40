"""mst.eval.c2m.geometry: the exact closest point on a triangle (reference vs fast routine) and the
mesh checks of prepare_mesh."""

from __future__ import annotations

import numpy as np
import pytest
from c2m_helpers import box_index

from mst import InputError
from mst.eval import c2m


def test_closest_point_reference_matches_fast_routine():
    idx, V, F = box_index(split=3)
    rng = np.random.default_rng(5)
    P = rng.uniform(-2, 8, (4000, 3)) - idx.shift
    ti = rng.integers(0, idx.n_triangles, 4000)
    C, f_ref = c2m.closest_point_on_triangles(P, idx.A[ti], idx.AB[ti], idx.AC[ti])
    d2, f, C2 = c2m.triangle_distances(idx, P, ti, need_closest=True)
    np.testing.assert_allclose(d2, ((P - C) ** 2).sum(1), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(C2, C, atol=1e-9)
    assert (f == f_ref).mean() > 0.999  # codes differ only on exact region boundaries


def test_mesh_errors():
    with pytest.raises(InputError, match="no triangles"):
        c2m.prepare_mesh(np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(InputError, match="degenerate"):
        c2m.prepare_mesh(np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]), np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="NaN"):
        c2m.prepare_mesh(np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]))
