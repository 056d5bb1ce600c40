"""Model readers/writers, triangulation and procedural TINs (mst.meshtools.formats / polygons / generate)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst import InputError
from mst.meshtools import generate as gen
from mst.meshtools.formats import (
    load_model,
    load_triangles,
    read_cao,
    read_obj,
    read_vrml,
    save_model,
    save_triangles,
)
from mst.meshtools.model import PolygonModel


def signed_volume(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6)


def tri_area(V, F):
    return float(np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum() / 2)


# ---------------------------------------------------------------- generated shapes
@pytest.mark.parametrize("name,volume,area", [
    ("box", 240.0, 248.0),
    ("l_shape", 384.0, 368.0),
    ("courtyard", 20 * 16 * 7 - 8 * 6 * 7, 2 * (20 * 16 - 8 * 6) + 7 * 2 * (20 + 16 + 8 + 6)),
    ("gabled_house", 12 * 8 * 5 + 12 * 8 * 3 / 2, 2 * 12 * 8 / 2 + 0 + 12 * 8 + 2 * 12 * 5 + 2 * (8 * 5 + 8 * 3 / 2)
     + 2 * 12 * np.hypot(4, 3) - 12 * 8),
])
@pytest.mark.parametrize("split", [1, 4])
def test_generated_tins_closed_outward(name, volume, area, split):
    V, F = getattr(gen, name)(split=split)
    assert len(F) == len(getattr(gen, name)(split=1)[1]) * split * split
    assert signed_volume(V, F) == pytest.approx(volume, rel=1e-12)
    assert tri_area(V, F) == pytest.approx(area, rel=1e-12)
    # closed 2-manifold: every directed edge appears once and its reverse once
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    assert len(np.unique(e, axis=0)) == len(e)
    fwd = {tuple(x) for x in e.tolist()}
    assert all((b, a) in fwd for a, b in fwd)


def test_courtyard_model_has_holes():
    m = gen.courtyard_model()
    assert m.n_holes == 2 and m.n_faces == 2 + 8
    assert m.face_areas()[:2] == pytest.approx([20 * 16 - 8 * 6] * 2)


def test_city_block_size():
    V, F = gen.city_block(n_triangles=20_000, buildings=9)
    assert 15_000 < len(F) < 30_000
    assert F.max() < len(V) and np.isfinite(V).all()


# ---------------------------------------------------------------- triangulate
def test_triangulate_with_hole_preserves_area_and_normal():
    m = gen.courtyard_model()
    V, F, fi = m.triangulate(return_index=True)
    for i in range(m.n_faces):
        Fi = F[fi == i]
        assert tri_area(V, Fi) == pytest.approx(m.face_areas()[i], rel=1e-12)
        n = np.cross(V[Fi[:, 1]] - V[Fi[:, 0]], V[Fi[:, 2]] - V[Fi[:, 0]])
        assert (n @ m.face_normals()[i] > 0).all()


# ---------------------------------------------------------------- readers on real files
def test_read_teabox_cao_and_wrl_agree(shared_data):
    a = load_model(shared_data / "visp-teabox" / "teabox.cao")
    b = load_model(shared_data / "visp-teabox" / "teabox.wrl")
    assert a.n_faces == b.n_faces == 6
    np.testing.assert_array_equal(a.vertices, b.vertices)
    for fa, fb in zip(a.faces, b.faces):
        np.testing.assert_array_equal(fa, fb)
    V, F = a.triangulate()
    assert signed_volume(V, F) == pytest.approx(0.165 * 0.068 * 0.08, rel=1e-12)


def test_read_cube_cao(shared_data):
    m = load_model(shared_data / "visp-cube-rgbd" / "model" / "cube.cao")
    V, F = m.triangulate()
    assert m.n_faces == 6 and len(F) == 12
    assert abs(signed_volume(V, F)) == pytest.approx(0.042**3, rel=1e-9)


@pytest.mark.parametrize("fname,objects", [("delft_1b.json", 1), ("DH_01_subs.city.json", 9),
                                           ("rotterdam_subset.json", 16)])
def test_read_cityjson(shared_data, fname, objects):
    p = shared_data / "cityjson" / fname
    m = load_model(p)
    d = json.loads(p.read_text())
    assert len({n for n in m.names}) == objects
    # transform applied: vertices lie inside the translated bounding box
    t = np.array(d["transform"]["translate"])
    assert (m.vertices >= t - 1).all() and (m.vertices[:, :2] < t[:2] + 2000).all()
    V, F = load_triangles(p)
    # the files' surfaces are planar only to their 1 mm vertex grid: triangle area vs Newell area
    assert tri_area(V, F) == pytest.approx(m.face_areas().sum(), rel=1e-6)


# ---------------------------------------------------------------- writers and exact round trips
def _cao_with_everything(tmp_path):
    sub = tmp_path / "parts"
    sub.mkdir()
    (sub / "part.cao").write_text(
        "V1\n# a unit square plate\n4\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0\n0\n1\n4 0 1 2 3 name=plate\n0\n0\n")
    main = tmp_path / "main.cao"
    main.write_text(
        'V1\nload("parts/part.cao", t=[10, 0, 0], tu=[0, 0, 1.5707963267948966])\n'
        "# points\n6 # six\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 2\n0.5 0.5 0\n"
        "# lines\n5\n0 1\n1 2\n2 3\n3 0\n0 4 name=mast\n"
        "# faces from lines\n1\n4 0 1 2 3\n"
        "# faces from points\n1\n3 0 1 4 name=side\n"
        "# cylinders\n1\n0 4 0.05 name=pole\n"
        "# circles\n1\n0.25 5 0 1\n")
    return main


def test_cao_load_lines_faces_cylinders_circles(tmp_path):
    m = load_model(_cao_with_everything(tmp_path))
    # sub-model points rotated 90 deg about z then shifted by t
    np.testing.assert_allclose(m.vertices[:4], [[10, 0, 0], [10, 1, 0], [9, 1, 0], [9, 0, 0]], atol=1e-12)
    assert m.n_faces == 3
    assert m.names == ["plate", None, "side"]
    # face from lines chained into a point loop (sub-model has 4 points, so offset 4)
    np.testing.assert_array_equal(m.faces[1], [4, 5, 6, 7])
    np.testing.assert_array_equal(m.lines, [[4, 8]])  # the only line no face uses
    assert m.cylinders == [{"p1": 4, "p2": 8, "radius": 0.05, "name": "pole"}]
    assert m.circles == [{"radius": 0.25, "center": 9, "p1": 4, "p2": 5, "name": None}]


@pytest.mark.parametrize("suffix", [".cao", ".wrl", ".obj"])
def test_round_trip_exact(tmp_path, suffix):
    src = gen.courtyard_model()
    src.vertices = src.vertices * 0.1 + [1e5 / 3, 0.1, -2.7]  # non-trivial floats
    a, b, c = (tmp_path / f"{k}{suffix}" for k in "abc")
    save_model(a, src)
    m1 = load_model(a)
    save_model(b, m1)
    assert b.read_bytes() == a.read_bytes()
    m2 = load_model(b)
    save_model(c, m2)
    assert c.read_bytes() == b.read_bytes()
    np.testing.assert_array_equal(m1.vertices, src.vertices)  # shortest repr reads back exactly
    # in the file every face is one loop (holes bridged); reading restores outer loop + holes
    raw = {".cao": read_cao, ".wrl": read_vrml, ".obj": read_obj}[suffix](a)
    assert raw.n_faces == src.n_faces and raw.n_holes == 0
    assert sorted(len(f) for f in raw.faces)[-2:] == [10, 10]  # 4 + 4 + 2 bridge ends
    np.testing.assert_allclose(raw.face_areas(), src.face_areas(), rtol=1e-12)
    assert m1.n_holes == src.n_holes == 2 and m1.n_faces == src.n_faces
    np.testing.assert_allclose(m1.face_areas(), src.face_areas(), rtol=1e-12)
    np.testing.assert_allclose(m1.face_normals(), src.face_normals(), atol=1e-12)
    V1, F1 = m1.triangulate()
    assert tri_area(V1, F1) == pytest.approx(src.face_areas().sum(), rel=1e-12)
    assert signed_volume(V1, F1) > 0


def test_round_trip_cao_with_primitives(tmp_path):
    m = load_model(_cao_with_everything(tmp_path))
    save_model(tmp_path / "x.cao", m)
    save_model(tmp_path / "y.cao", load_model(tmp_path / "x.cao"))
    assert (tmp_path / "x.cao").read_bytes() == (tmp_path / "y.cao").read_bytes()
    m2 = load_model(tmp_path / "y.cao")
    assert m2.cylinders == m.cylinders and m2.circles == m.circles
    np.testing.assert_array_equal(m2.lines, m.lines)


def test_round_trip_teabox_wrl(shared_data, tmp_path):
    m = load_model(shared_data / "visp-teabox" / "teabox.wrl")
    save_model(tmp_path / "a.wrl", m)
    save_model(tmp_path / "b.wrl", load_model(tmp_path / "a.wrl"))
    assert (tmp_path / "a.wrl").read_text() == (tmp_path / "b.wrl").read_text()


def test_vrml_transforms_and_multiple_shapes(tmp_path):
    p = tmp_path / "t.wrl"
    p.write_text("""#VRML V2.0 utf8
# two shapes, one nested in a transform
Group { children [
  DEF A Shape { geometry IndexedFaceSet { coord DEF C Coordinate { point [ 0 0 0, 1 0 0, 0 1 0 ] }
                                     coordIndex [ 0 1 2 -1 ] } }
  Transform { translation 10 0 0 rotation 0 0 1 1.5707963267948966 scale 2 2 2
    children Shape { appearance Appearance { material Material { diffuseColor 1 0 0 } }
                     geometry IndexedFaceSet { coord USE C coordIndex [ 0, 1, 2, -1 ] } } }
] }
""")
    m = load_model(p)
    assert m.n_faces == 2 and m.names[0] == "A"
    np.testing.assert_allclose(m.vertices[3:], [[10, 0, 0], [10, 2, 0], [8, 0, 0]], atol=1e-12)


def test_obj_polygons_names_lines(tmp_path):
    p = tmp_path / "m.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\no plate\nf 1/1/1 2/2/2 3/3/3 4/4/4\n"
                 "g tri\nf -5 -4 -1\nl 1 5\n")
    m = load_model(p)
    assert [len(f) for f in m.faces] == [4, 3] and m.names == ["plate", "tri"]
    np.testing.assert_array_equal(m.faces[1], [0, 1, 4])
    np.testing.assert_array_equal(m.lines, [[0, 4]])


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".off"])
def test_load_triangles_formats(tmp_path, suffix):
    V, F = gen.l_shape(split=2)
    p = tmp_path / f"l{suffix}"
    save_triangles(p, V, F)
    V2, F2 = load_triangles(p)
    assert tri_area(V2, F2) == pytest.approx(tri_area(V, F), rel=1e-6)
    assert signed_volume(V2, F2) == pytest.approx(signed_volume(V, F), rel=1e-6)
    if suffix in (".obj", ".ply"):
        np.testing.assert_array_equal(F2, F)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("suffix,text,match", [
    (".obj", "v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "NaN"),
    (".obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "out of range"),
    (".obj", "# nothing\n", "no faces"),
    (".wrl", "#VRML V2.0 utf8\nShape { geometry IndexedFaceSet { coord Coordinate { point [ 0 0 0, 1 0 0 ",
     "unterminated|end of VRML"),
    (".wrl", "hello", "not a VRML 2.0"),
    (".cao", "V1\n3\n0 0 0\n1 0 0\n", "truncated|point"),
    (".json", "{\"type\": \"Feature\"}", "not a CityJSON"),
    (".off", "garbage\n", "OFF"),
])
def test_bad_files_raise_input_error(tmp_path, suffix, text, match):
    p = tmp_path / f"bad{suffix}"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        load_model(p)


def test_missing_file_and_binary_garbage(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_model(tmp_path / "nope.obj")
    p = tmp_path / "g.wrl"
    p.write_bytes(bytes(range(256)) * 10)
    with pytest.raises(InputError):
        load_model(p)


def test_polygon_model_write_unknown_suffix(tmp_path):
    with pytest.raises(InputError, match="cannot write"):
        save_model(tmp_path / "x.ply", PolygonModel(np.eye(3), [[0, 1, 2]]))


def test_ply_reader_agrees_with_trimesh(tmp_path):
    import trimesh

    from mst.core.ply import read_header, read_mesh

    V, F = gen.gabled_house(split=3)
    a = tmp_path / "ours.ply"
    save_triangles(a, V, F)  # float64, written by us
    t = trimesh.load(a, process=False)
    np.testing.assert_array_equal(t.vertices, V)
    np.testing.assert_array_equal(t.faces, F)
    b = tmp_path / "trimesh.ply"
    trimesh.Trimesh(V, F, process=False).export(b)  # float32, written by trimesh
    mb = read_mesh(read_header(b))
    Vb, Fb = mb.vertices, mb.faces
    tb = trimesh.load(b, process=False)
    np.testing.assert_array_equal(Vb, tb.vertices)
    np.testing.assert_array_equal(Fb, tb.faces)
    c = tmp_path / "ascii.ply"
    trimesh.Trimesh(V, F, process=False).export(c, encoding="ascii")
    assert isinstance(read_mesh(read_header(c)).faces, list)  # ASCII: line by line, faces as loops
    Vc, Fc = load_triangles(c)
    np.testing.assert_allclose(Vc, V, atol=1e-5)
    np.testing.assert_array_equal(Fc, F)


def test_generate_command_line(tmp_path):
    assert gen.main(["l_shape", "-o", str(tmp_path / "l.obj"), "--split", "2"]) == 0
    V, F = load_triangles(tmp_path / "l.obj")
    assert len(F) == 20 * 4 and signed_volume(V, F) == pytest.approx(384.0)
    assert gen.main(["courtyard", "--polygons", "-o", str(tmp_path / "c.cao")]) == 0
    m = load_model(tmp_path / "c.cao")
    assert (m.n_faces, m.n_holes) == (10, 2)


def test_cityjson_holes_lods_templates(tmp_path):
    """Synthetic CityJSON 2.0: a wall with a window hole (MultiSurface), a LoD1 and a LoD2 solid of
    one building (only LoD2 read), a template instance; integer vertices with a transform."""
    cube = [[[[0, 1, 2, 3]], [[4, 7, 6, 5]], [[0, 4, 5, 1]], [[1, 5, 6, 2]], [[2, 6, 7, 3]], [[3, 7, 4, 0]]]]
    verts = [[0, 0, 0], [0, 1000, 0], [1000, 1000, 0], [1000, 0, 0],
             [0, 0, 1000], [0, 1000, 1000], [1000, 1000, 1000], [1000, 0, 1000]]
    base = len(verts)
    verts += [[5000, 0, 0], [9000, 0, 0], [9000, 0, 4000], [5000, 0, 4000],  # wall, y=0
              [6000, 0, 1000], [6000, 0, 2000], [7000, 0, 2000], [7000, 0, 1000]]  # window (reversed)
    wall = [[[base, base + 1, base + 2, base + 3], [base + 4, base + 5, base + 6, base + 7]]]
    d = {
        "type": "CityJSON", "version": "2.0",
        "transform": {"scale": [0.001, 0.001, 0.001], "translate": [100000.0, 400000.0, 5.0]},
        "vertices": verts,
        "CityObjects": {
            "bldg": {"type": "Building", "geometry": [
                {"type": "Solid", "lod": "1", "boundaries": cube},
                {"type": "Solid", "lod": "2.2", "boundaries": cube}]},
            "wall": {"type": "GenericCityObject", "geometry": [{"type": "MultiSurface", "lod": "2", "boundaries": wall}]},
            "tree": {"type": "SolitaryVegetationObject", "geometry": [{
                "type": "GeometryInstance", "template": 0, "boundaries": [0],
                "transformationMatrix": [2, 0, 0, 10, 0, 2, 0, 20, 0, 0, 2, 0, 0, 0, 0, 1]}]},
        },
        "geometry-templates": {"templates": [{"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2]]]}],
                               "vertices-templates": [[0, 0, 0], [1, 0, 0], [0, 1, 0]]},
    }
    p = tmp_path / "t.city.json"
    p.write_text(json.dumps(d))
    m = load_model(p)
    assert m.names.count("bldg") == 6 and m.names.count("wall") == 1 and m.names.count("tree") == 1
    wi = m.names.index("wall")
    assert len(m.holes[wi]) == 1
    assert m.face_areas()[wi] == pytest.approx(4 * 4 - 1 * 1)
    np.testing.assert_allclose(m.vertices[m.faces[wi][0]], [100005.0, 400000.0, 5.0])
    ti = m.names.index("tree")
    np.testing.assert_allclose(m.vertices[m.faces[ti]], [[100010, 400020, 5], [100012, 400020, 5], [100010, 400022, 5]])
    V, F = m.triangulate()
    assert tri_area(V, F) == pytest.approx(6 * 1 + 15 + 2, rel=1e-9)


def test_vrml_switch_and_lod(tmp_path):
    p = tmp_path / "s.wrl"
    tri = "Shape {{ geometry IndexedFaceSet {{ coord Coordinate {{ point [ {0} 0 0, {0} 1 0, {0} 0 1 ] }} coordIndex [ 0 1 2 -1 ] }} }}"
    p.write_text("#VRML V2.0 utf8\n"
                 f"Switch {{ whichChoice 1 choice [ {tri.format(1)} {tri.format(2)} {tri.format(3)} ] }}\n"
                 f"LOD {{ range [ 10 ] level [ {tri.format(4)} {tri.format(5)} ] }}\n")
    m = load_model(p)
    assert m.n_faces == 2
    assert sorted(m.vertices[:, 0].tolist()) == [2, 2, 2, 4, 4, 4]


def test_load_tracking_model_refuses_degenerate_geometry(tmp_path):
    from mst.meshtools.formats import load_tracking_model

    p = tmp_path / "line.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    assert load_model(p).n_faces == 1  # a valid file ...
    with pytest.raises(InputError, match="degenerate") as e:  # ... but nothing to track
        load_tracking_model(p)
    assert str(p) in str(e.value)
    save_model(tmp_path / "box.obj", gen.box_model())
    assert load_tracking_model(tmp_path / "box.obj").n_faces == 6
