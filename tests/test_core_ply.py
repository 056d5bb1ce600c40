"""mst.core.ply: the one PLY reader/writer (header, streamed vertices, meshes with face properties)."""

from __future__ import annotations

import numpy as np
import pytest

from mst import InputError
from mst.core.ply import PlyVertexWriter, open_vertices, read_header, read_mesh, write_ply


def test_write_ply_mesh_with_face_property_reads_back(tmp_path):
    rng = np.random.default_rng(0)
    V = rng.normal(size=(50, 3)) * 1e6  # georeferenced magnitudes keep their float64 bits
    F = rng.integers(0, 50, (80, 3))
    lab = rng.integers(0, 4, 80).astype(np.uint8)
    p = tmp_path / "m.ply"
    write_ply(p, {"x": V[:, 0], "y": V[:, 1], "z": V[:, 2]}, F, face_properties={"label": lab}, comments=["c1"])
    head = p.read_bytes()[:300].split(b"end_header\n")[0].decode()
    assert head.splitlines() == ["ply", "format binary_little_endian 1.0", "comment c1", "element vertex 50",
                                 "property double x", "property double y", "property double z", "element face 80",
                                 "property list uchar int vertex_indices", "property uchar label"]
    h = read_header(p)
    assert h.comments == ("c1",) and [e.name for e in h.elements] == ["vertex", "face"]
    m = read_mesh(h)
    np.testing.assert_array_equal(m.vertices, V)
    np.testing.assert_array_equal(m.faces, F)
    np.testing.assert_array_equal(m.face_properties["label"], lab)
    trimesh = pytest.importorskip("trimesh")
    t = trimesh.load(p, process=False, force="mesh")
    np.testing.assert_array_equal(t.vertices, V)
    np.testing.assert_array_equal(t.faces, F)


def test_vertex_stream_chunks_named_properties_both_byte_orders_and_ascii(tmp_path):
    n = 1003
    rng = np.random.default_rng(1)
    X = rng.normal(size=(n, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    for fmt, bo in (("binary_little_endian", "<"), ("binary_big_endian", ">"), ("ascii", None)):
        p = tmp_path / f"{fmt}.ply"
        head = (f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
                "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
        if bo is None:
            body = "".join(f"{a!r} {b!r} {c!r} {r} {g} {bl}\n" for (a, b, c), (r, g, bl)
                           in zip(X.astype(float).tolist(), rgb.tolist())).encode()
        else:
            rec = np.empty(n, [(k, bo + "f4") for k in "xyz"] + [(k, "u1") for k in ("red", "green", "blue")])
            for j, k in enumerate("xyz"):
                rec[k] = X[:, j]
            for j, k in enumerate(("red", "green", "blue")):
                rec[k] = rgb[:, j]
            body = rec.tobytes()
        p.write_bytes(head + body)
        vs = open_vertices(p)
        assert vs.count == n and vs.types["x"] == "f4" and vs.has("red", "green", "blue")
        sizes = [len(c) for c in vs.chunks(100)]
        assert sizes == [100] * 10 + [3]
        np.testing.assert_array_equal(vs.read(), X.astype(np.float64))
        np.testing.assert_array_equal(vs.read(("blue", "red")), rgb[:, [2, 0]].astype(np.float64))


def test_vertex_writer_streams_and_checks_the_count(tmp_path):
    p = tmp_path / "c.ply"
    with PlyVertexWriter(p, 5, [("x", "f8"), ("y", "f8"), ("z", "f8"), ("scalar_d", "f4")]) as w:
        w.write([np.arange(3.0), np.ones(3), np.zeros(3), np.full(3, 0.5)])
        w.write([np.arange(2.0), np.ones(2), np.zeros(2), np.full(2, 0.25)])
    vs = open_vertices(p)
    np.testing.assert_array_equal(vs.read(("x", "scalar_d"))[:, 1], [0.5, 0.5, 0.5, 0.25, 0.25])
    with pytest.raises(RuntimeError, match="2 vertices written, header says 3"):
        with PlyVertexWriter(tmp_path / "d.ply", 3, [("x", "f4"), ("y", "f4"), ("z", "f4")]) as w:
            w.write([np.zeros(2)] * 3)


def test_strict_header_names_the_file(tmp_path):
    p = tmp_path / "t.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n" + b"\0" * 12)
    with pytest.raises(InputError, match="truncated") as e:
        read_header(p)
    assert str(p) in str(e.value)


def test_ascii_mesh_polygons_and_face_properties(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text("ply\nformat ascii 1.0\ncomment hand made\nelement vertex 5\nproperty float x\nproperty float y\n"
                 "property float z\nelement face 2\nproperty list uchar int vertex_indices\nproperty uchar label\n"
                 "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 2 0\n4 0 1 2 3 7\n3 1 4 2 9\n")
    m = read_mesh(read_header(p))
    assert [f.tolist() for f in m.faces] == [[0, 1, 2, 3], [1, 4, 2]]
    assert m.face_properties["label"].tolist() == [7, 9] and m.face_properties["label"].dtype == np.uint8
