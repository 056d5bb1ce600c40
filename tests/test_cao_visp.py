"""ViSP ``.cao`` models as ViSP writes and reads them today (``vpMbTracker::loadCAOModel``).

The files are written by the tests in ViSP's syntax: ``load("part.cao", t=[0.048; 0.0; 0.0],
tu=[0; 0; 90 deg])`` headers (semicolons, units), comments after statements with any leading
characters, quoted names and LOD parameters after faces, V2 points with image coordinates,
faces from lines, free 3D lines, cylinders and circles.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mst import InputError
from mst.meshtools.formats import load_model, load_triangles, save_model
from mst.meshtools.solids import CYLINDER_SEGMENTS

PART = """V1
# a 10 mm square plate in its own frame
4 // number of points
0 0 0        // point 0
0.01 0 0     // point 1
0.01 0.01 0
0 0.01 0     # point 3
0            // no lines
0            // no faces from lines
1            // one face from points
4 0 1 2 3 name="plate top" useLod=true minPolygonAreaThreshold=100 // the face
"""

MAIN = """V1
# two plates, one each side, then the body
load("parts/plate.cao", t=[0.048; 0.0; 0.0], tu=[0; 0; 90 deg])   // right plate
load("./parts/plate.cao", t=[-0.048, 0, 0], tu=[0rad; 0rad; -1.5707963267948966rad])
# 3D Points
5                  # Number of points
0 0 0 // a
1 0 0
1 1 0
0 1 0
0 0 1
# 3D Lines
5  lines
0 1 name=l0 useLod=false
1 2
2 3
3 0
0 4 name=mast minLineLengthThreshold=10 // a free line
# Faces from 3D lines
1
4 0 1 2 3 name=bottom LOD=1
# Faces from 3D points
1
3 0 1 4  name=side   // triangle
# 3D cylinders
1
0 4 0.05 name=pole minLineLengthThreshold=10
# 3D circles
1
0.5 0 1 2 name=ring
"""


@pytest.fixture
def visp_model(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "plate.cao").write_text(PART)
    (tmp_path / "main.cao").write_text(MAIN)
    return tmp_path / "main.cao"


def test_load_with_semicolons_units_and_comments(visp_model):
    m = load_model(visp_model)
    # plate 1: rotated +90 deg about z, then t = (0.048, 0, 0): (x, y) -> (-y, x) + t
    np.testing.assert_allclose(m.vertices[:4], [[0.048, 0, 0], [0.048, 0.01, 0], [0.038, 0.01, 0], [0.038, 0, 0]],
                               atol=1e-15)
    # plate 2: -90 deg (radians with a unit), t = (-0.048, 0, 0): (x, y) -> (y, -x) + t
    np.testing.assert_allclose(m.vertices[4:8], [[-0.048, 0, 0], [-0.048, -0.01, 0], [-0.038, -0.01, 0],
                                                 [-0.038, 0, 0]], atol=1e-15)
    np.testing.assert_array_equal(m.vertices[8:], [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]])
    assert m.names == ["plate top", "plate top", "bottom", "side"]
    np.testing.assert_array_equal(m.faces[2], [8, 9, 10, 11])  # face from lines, chained
    np.testing.assert_array_equal(m.lines, [[8, 12]])  # the line no face uses
    assert m.cylinders == [{"p1": 8, "p2": 12, "radius": 0.05, "name": "pole"}]
    assert m.circles == [{"radius": 0.5, "center": 8, "p1": 9, "p2": 10, "name": "ring"}]
    assert len(load_triangles(visp_model, primitives=False)[1]) == 2 + 2 + 2 + 1
    V, F = load_triangles(visp_model)  # with the cylinder's closed surface (tests/test_cao_cylinders.py)
    assert len(F) == 2 + 2 + 2 + 1 + 4 * CYLINDER_SEGMENTS


def test_units_deg_and_rad_agree(tmp_path):
    (tmp_path / "p.cao").write_text(PART)
    a, b = tmp_path / "a.cao", tmp_path / "b.cao"
    tail = "0\n0\n0\n0\n"
    a.write_text('V1\nload("p.cao", tu=[10 deg; -20deg; 30 deg])\n' + tail)
    b.write_text(f'V1\nload("p.cao", tu=[{math.radians(10)!r}; {math.radians(-20)!r}rad; {math.radians(30)!r}])\n'
                 + tail)
    np.testing.assert_allclose(load_model(a).vertices, load_model(b).vertices, atol=1e-15)


def test_nested_loads_compose_relative_to_each_file(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "b" / "leaf.cao").write_text(PART)
    (tmp_path / "a" / "mid.cao").write_text('V1\nload("b/leaf.cao", t=[1; 0; 0])\n0\n0\n0\n0\n')
    (tmp_path / "top.cao").write_text('V1\nload("a/mid.cao", t=[0; 2; 0], tu=[0; 0; 180 deg])\n0\n0\n0\n0\n')
    m = load_model(tmp_path / "top.cao")
    # leaf point (0.01, 0, 0) -> mid: (1.01, 0, 0) -> top: rotate 180 deg about z, + (0, 2, 0)
    np.testing.assert_allclose(m.vertices[1], [-1.01, 2, 0], atol=1e-12)


def test_v2_points_carry_image_coordinates(tmp_path):
    p = tmp_path / "v2.cao"
    p.write_text("V2\n3\n0 0 0 10 20\n1 0 0 30 40 // ignored image point\n0 1 0 5 6\n0\n0\n1\n3 0 1 2\n")
    m = load_model(p)
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    bad = tmp_path / "v2bad.cao"
    bad.write_text("V2\n3\n0 0 0\n1 0 0 30 40\n0 1 0 5 6\n0\n0\n1\n3 0 1 2\n")
    with pytest.raises(InputError, match="line 3: the point's image row"):
        load_model(bad)


def test_old_style_file_without_cylinder_and_circle_sections(tmp_path):
    p = tmp_path / "old.cao"
    p.write_text("V1\n3\n0 0 0\n1 0 0\n0 1 0\n0\n0\n1\n3 0 1 2\n")
    assert load_model(p).n_faces == 1


def test_text_after_the_circles_is_ignored_like_visp(shared_data):
    """The real cube model carries comments after each statement; ViSP's tutorial data loads."""
    m = load_model(shared_data / "visp-cube-rgbd" / "model" / "cube.cao")
    assert m.n_faces == 6 and len(m.vertices) == 8
    np.testing.assert_allclose(m.face_areas(), 0.042 ** 2, rtol=1e-12)


def test_write_read_keeps_everything(visp_model, tmp_path):
    m = load_model(visp_model)
    out = tmp_path / "copy.cao"
    save_model(out, m)
    back = load_model(out)
    np.testing.assert_array_equal(back.vertices, m.vertices)
    assert back.names == m.names  # a name with blanks is written quoted, as ViSP reads it
    assert back.cylinders == m.cylinders and back.circles == m.circles
    np.testing.assert_array_equal(back.lines, m.lines)


def test_two_point_face_is_a_line_and_version_text(tmp_path):
    """ViSP reads an int after 'V' and skips the line; a 2-point face from points is a line."""
    p = tmp_path / "l.cao"
    p.write_text("V1.0 written by hand\n3\n0 0 0\n1 0 0\n0 1 0\n0\n0\n2\n3 0 1 2\n2 1 2 name=edge\n")
    m = load_model(p)
    assert m.n_faces == 1
    np.testing.assert_array_equal(m.lines, [[1, 2]])


def test_written_loops_start_at_the_widest_convex_corner():
    """ViSP takes a face's normal from its points 0, 1, 2: every written loop starts so that
    point 1 is the convex corner spanning the largest triangle with its neighbours (within the
    1e-6 tie tolerance), whatever the loop's original start."""
    from mst.meshtools.polygons import start_loops_at_convex_corners

    rng = np.random.default_rng(5)
    for _ in range(20):
        k = int(rng.integers(4, 12))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        r = rng.uniform(0.5, 2.0, k)
        V = np.column_stack([r * np.cos(ang), r * np.sin(ang), np.zeros(k)])  # star-shaped, CCW about +z
        loop = np.arange(k)
        n = np.array([[0.0, 0.0, 1.0]])
        outs = [start_loops_at_convex_corners(V, [np.roll(loop, s)], n)[0] for s in range(k)]
        assert all(np.array_equal(o, outs[0]) for o in outs)  # independent of the start
        a, b = V[loop] - V[np.roll(loop, 1)], V[np.roll(loop, -1)] - V[loop]
        turn = np.cross(a, b)[:, 2]
        o = outs[0]
        assert turn[o[1]] >= turn.max() * (1 - 1e-6)
