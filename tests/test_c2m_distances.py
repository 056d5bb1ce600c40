"""mst.eval.c2m.distances: exact distances with analytic answers, signs near edges and corners
(pseudo-normals), georeferenced precision, max-dist, for both engines."""

from __future__ import annotations

import numpy as np
import pytest
from c2m_helpers import box_index, box_sdf, dist, winding_number

from mst.eval import c2m


@pytest.mark.parametrize("engine", ["bvh", "grid"])
def test_box_distances_and_signs_near_edges_and_corners(engine):
    idx, V, F = box_index(engine=engine)
    rng = np.random.default_rng(1)
    eps = 1e-3
    # points just inside and just outside every edge and corner, plus face points and random ones
    corners = np.array([[x, y, z] for x in (0, 4) for y in (0, 6) for z in (0, 2)], float)
    ctr = np.array([2.0, 3.0, 1.0])
    dirs = corners - ctr
    near_corners_out = corners + eps * np.sign(dirs)
    near_corners_in = corners - eps * np.sign(dirs)
    # diagonally off an edge (x=4, z=2 edge along y): outside beyond both faces, inside below both
    edge_out = np.array([[4 + eps, y, 2 + eps] for y in np.linspace(0.5, 5.5, 7)])
    edge_in = np.array([[4 - eps, y, 2 - 2 * eps] for y in np.linspace(0.5, 5.5, 7)])
    # outside one face but "behind" the other (where a face-normal sign test fails)
    edge_side = np.array([[4 + eps, y, 2 - 0.5 * eps] for y in np.linspace(0.5, 5.5, 7)])
    rand = rng.uniform(-1, 7, (3000, 3))
    P = np.vstack([near_corners_out, near_corners_in, edge_out, edge_in, edge_side, rand])
    d, s = dist(idx, P)
    sdf = box_sdf(P)
    np.testing.assert_allclose(d, np.abs(sdf), atol=1e-12)
    np.testing.assert_allclose(s, sdf, atol=1e-12)
    n_out = len(near_corners_out)
    assert (s[:n_out] > 0).all() and (s[n_out : 2 * n_out] < 0).all()
    np.testing.assert_allclose(d[:n_out], eps * np.sqrt(3), rtol=1e-9)


def test_points_above_a_plane_and_exactly_on_the_surface():
    # a 10 m x 10 m square (2 triangles) at z = 5; points above its interior are at |z - 5|
    V = np.array([[0, 0, 5], [10, 0, 5], [10, 10, 5], [0, 10, 5]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    idx = c2m.prepare_mesh(V, F, signed=True)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (5000, 2))
    h = rng.uniform(-3, 3, 5000)
    P = np.column_stack([xy, 5 + h])
    d, s = dist(idx, P)
    np.testing.assert_allclose(d, np.abs(h), atol=1e-12)
    np.testing.assert_allclose(s, h, atol=1e-12)  # + above (normal +z), - below
    # exactly on the surface, on the vertices and on the shared diagonal edge: distance 0
    on = np.vstack([np.column_stack([xy, np.full(5000, 5.0)]), V, [[5, 5, 5], [2.5, 2.5, 5]]])
    d0, _ = dist(idx, on)
    assert np.abs(d0).max() < 1e-12
    # beside the square: distance to the nearest edge / vertex
    P2 = np.array([[12, 5, 5], [13, 14, 9], [-3, -4, 5]], float)
    d2, _ = dist(idx, P2)
    np.testing.assert_allclose(d2, [2.0, np.sqrt(9 + 16 + 16), 5.0], atol=1e-12)


def test_vertices_of_a_finely_split_box_and_neighbour_ties():
    idx, V, F = box_index(split=5)
    d, s = dist(idx, V)
    assert np.abs(d).max() < 1e-12
    # points just outside along the vertex normals of the lattice (many exact ties between triangles)
    P = V + 0.01 * np.sign(V - np.array([2.0, 3.0, 1.0]))
    d, s = dist(idx, P)
    np.testing.assert_allclose(s, box_sdf(P), atol=1e-12)


def test_georeferenced_coordinates_keep_precision():
    shift = np.array([512_345.678, 5_432_109.876, 312.5])
    idx, V, F = box_index(shift=shift)
    rng = np.random.default_rng(2)
    P0 = rng.uniform(-1, 7, (2000, 3))
    d, s = dist(idx, P0 + shift)
    # float64 at 5e6 m has ~1e-9 m resolution; float32 would be off by decimetres
    np.testing.assert_allclose(s, box_sdf(P0), atol=2e-9)


def test_max_dist_marks_far_points():
    idx, V, F = box_index()
    P = np.array([[2, 3, 2.5], [2, 3, 2.0 + 4.0], [100, 100, 100], [2, 3, 1.0]])
    d, s = dist(idx, P, max_dist=1.0)
    np.testing.assert_allclose(d[[0, 3]], [0.5, 1.0], atol=1e-12)
    assert np.isnan(d[1]) and np.isnan(d[2])


@pytest.mark.parametrize("engine", ["bvh", "grid"])
@pytest.mark.parametrize("reverse", [False, True])
@pytest.mark.parametrize("shape", ["wedge", "l_shape"])
def test_sign_near_sharp_and_reflex_edges_and_corners(engine, reverse, shape):
    """Near a sharp (17 degree) edge of a wedge prism and the reflex edge of an L-shaped building,
    triangles of both faces tie for the nearest and the point can lie behind the plane of one of
    them; only the pseudo-normal of the shared edge/vertex gives the right sign whichever triangle
    the search returns (the face order is reversed to change how ties are broken)."""
    from mst.meshtools.generate import extrude_model, l_shape, model_to_tin

    rng = np.random.default_rng(7)
    if shape == "wedge":
        V, F = model_to_tin(extrude_model([np.array([[0, 0], [10, 0], [0, 3.0]])], 0.0, 5.0), split=2)
        edge = np.array([10.0, 0.0])
        lo, hi = [-1, -1, -1], [11, 4, 6]
        ztop = 5.0
    else:
        V, F = l_shape(split=2)  # reflex vertical edge at x = y = 4, z in [0, 6]
        edge = np.array([4.0, 4.0])
        lo, hi = [-1, -1, -1], [13, 9, 7]
        ztop = 6.0
    if reverse:
        F = F[::-1].copy()
    idx = c2m.prepare_mesh(V, F, signed=True, engine=engine)
    on_edge = np.column_stack([np.full(400, edge[0]), np.full(400, edge[1]), rng.uniform(0, ztop, 400)])
    ends = np.array([[edge[0], edge[1], 0.0]] * 200 + [[edge[0], edge[1], ztop]] * 200)
    near = np.vstack([on_edge, ends]) + rng.uniform(-0.05, 0.05, (800, 3))
    P = np.vstack([near, rng.uniform(lo, hi, (600, 3))])
    inside = winding_number(P, V, F) > 0.5
    d, s = dist(idx, P)
    assert ((s < 0) == inside).all()
    np.testing.assert_allclose(np.abs(s), d)
