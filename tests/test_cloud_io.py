"""Cloud readers/writers: every format returns the exact coordinates written."""

from __future__ import annotations

import numpy as np
import pytest

from mst import InputError
from mst.eval.cloud_io import open_cloud, read_cloud, write_cloud

RNG = np.random.default_rng(0)
P = np.column_stack([RNG.uniform(512000, 513000, 257), RNG.uniform(5.4e6, 5.401e6, 257), RNG.uniform(0, 50, 257)])
P = np.round(P, 3)


def _ply(path, fmt, P, dtype="double", extra_elements=False):
    hdr = ["ply", f"format {fmt} 1.0"]
    if extra_elements:
        hdr += ["element camera 1", "property float k"]
    hdr += [f"element vertex {len(P)}", f"property {dtype} x", f"property {dtype} y", f"property {dtype} z",
            "property uchar red", "element face 0", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(hdr) + "\n").encode())
        if fmt == "ascii":
            f.write("".join(f"{float(x)!r} {float(y)!r} {float(z)!r} 7\n" for x, y, z in P).encode())
        else:
            end = "<" if fmt == "binary_little_endian" else ">"
            t = end + ("f8" if dtype == "double" else "f4")
            if extra_elements:
                np.array([1.5], end + "f4").tofile(f)
            rec = np.empty(len(P), [("x", t), ("y", t), ("z", t), ("r", "u1")])
            rec["x"], rec["y"], rec["z"], rec["r"] = P[:, 0], P[:, 1], P[:, 2], 7
            rec.tofile(f)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_formats(tmp_path, fmt):
    p = tmp_path / "c.ply"
    _ply(p, fmt, P, extra_elements=fmt != "ascii")
    src = open_cloud(p)
    assert src.count == len(P)
    np.testing.assert_array_equal(np.concatenate(list(src.chunks(100))), P)


def test_ply_float32_and_writer_roundtrip(tmp_path):
    p = tmp_path / "f.ply"
    _ply(p, "binary_little_endian", P - P.mean(0), dtype="float")
    np.testing.assert_array_equal(read_cloud(p), (P - P.mean(0)).astype(np.float32).astype(np.float64))
    q = tmp_path / "w.ply"
    write_cloud(q, P, {"C2M_absolute_distances": np.arange(len(P), dtype=np.float32)})
    np.testing.assert_array_equal(read_cloud(q), P)  # float64 coordinates kept exactly
    assert b"property float scalar_C2M_absolute_distances" in q.read_bytes()[:500]


def test_pcd_ascii_and_binary(tmp_path):
    hdr = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 8 8 8 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
           f"WIDTH {len(P)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(P)}\n")
    a = tmp_path / "a.pcd"
    a.write_text(hdr + "DATA ascii\n" + "".join(f"{float(x)!r} {float(y)!r} {float(z)!r} 1\n" for x, y, z in P))
    np.testing.assert_array_equal(read_cloud(a), P)
    b = tmp_path / "b.pcd"
    rec = np.empty(len(P), [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("i", "<f4")])
    rec["x"], rec["y"], rec["z"], rec["i"] = P[:, 0], P[:, 1], P[:, 2], 1
    b.write_bytes((hdr + "DATA binary\n").encode() + rec.tobytes())
    np.testing.assert_array_equal(read_cloud(b), P)


@pytest.mark.parametrize("suffix,sep,header", [(".xyz", " ", ""), (".txt", "\t", "# comment\n"),
                                               (".csv", ",", "X,Y,Z,Intensity\n")])
def test_text_clouds(tmp_path, suffix, sep, header):
    p = tmp_path / f"c{suffix}"
    p.write_text(header + "".join(sep.join([repr(float(x)), repr(float(y)), repr(float(z)), "3"]) + "\n" for x, y, z in P))
    np.testing.assert_array_equal(read_cloud(p), P)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_laz_roundtrip(tmp_path, suffix):
    p = tmp_path / f"c{suffix}"
    write_cloud(p, P)
    np.testing.assert_allclose(read_cloud(p), P, atol=1e-4)  # LAS stores scaled integers (0.1 mm)


def test_bad_clouds(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_cloud(tmp_path / "none.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"plx\n")
    with pytest.raises(InputError, match="bad magic"):
        open_cloud(bad)
    noxyz = tmp_path / "n.ply"
    noxyz.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n")
    with pytest.raises(InputError, match="x, y, z"):
        open_cloud(noxyz)
    txt = tmp_path / "t.xyz"
    txt.write_text("1 2 3\n4 five 6\n")
    with pytest.raises(InputError, match="not a number"):
        open_cloud(txt)
    with pytest.raises(InputError, match="unknown cloud format"):
        p = tmp_path / "c.abc"
        p.write_text("1 2 3\n")
        open_cloud(p)
