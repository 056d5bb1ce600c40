"""mst.meshtools.polygons: holes bridged into one loop and back, convex-corner starts, triangulation."""

from __future__ import annotations

import numpy as np

from mst.meshtools import generate as gen
from mst.meshtools.model import PolygonModel
from mst.meshtools.polygons import bridge_holes, split_simple, unbridge_faces


def test_bridged_faces_unbridge_to_the_same_holes():
    m = gen.courtyard_model()
    normals = m.face_normals()
    bridged = [bridge_holes(m.vertices, f, hs, n) if hs else np.asarray(f)
               for f, hs, n in zip(m.faces, m.holes, normals)]
    assert any(len(b) > len(f) for b, f in zip(bridged, m.faces))  # the two courtyard faces carry a bridge
    back = unbridge_faces(PolygonModel(m.vertices, bridged))
    assert back.n_holes == m.n_holes
    np.testing.assert_allclose(back.face_areas(), m.face_areas(), rtol=1e-12)
    for f, hs, g, ks in zip(m.faces, m.holes, back.faces, back.holes):
        assert set(np.asarray(f).tolist()) == set(np.asarray(g).tolist())
        assert sorted(sorted(np.asarray(h).tolist()) for h in hs) == sorted(sorted(np.asarray(k).tolist()) for k in ks)


def test_split_simple_cuts_a_figure_eight():
    assert split_simple([0, 1, 2, 3, 4, 2, 5]) == [[2, 3, 4], [0, 1, 2, 5]]
    assert split_simple([0, 1]) == []
