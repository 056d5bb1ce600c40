"""The C2M pass as restructured for whole-process time (issue #14): searches in blocks of points,
the coordinate check inside the shift kernel, the median without np.median, the flat PLY reader and
the blockwise PLY writer give the answers of the straightforward code."""

from __future__ import annotations

import numpy as np
import pytest
from c2m_helpers import BOX, brute_force_d2, dist

from mst import InputError
from mst.core.ply import PlyVertexWriter, open_vertices
from mst.eval import c2m
from mst.eval.c2m.kernels import QUERY_BLOCK
from mst.eval.c2m.stats import median_in_place
from mst.meshtools.generate import box


@pytest.mark.parametrize("small", [5000, 0])  # the dense grid, the binned grid
def test_searches_in_blocks_equal_the_reference(small):
    """More points than two search blocks (the last one partial), shuffled: the compiled searches give
    the numpy reference path's distances and signs, and a brute-force scan's on a subset (the block
    gather/scatter puts every answer back at its own point: a misplaced one is off by metres)."""
    V, F = box(BOX, split=3)
    rng = np.random.default_rng(5)
    n = 2 * QUERY_BLOCK + 123
    P = rng.uniform(V.min(0) - 1.5, V.max(0) + 1.5, (n, 3))
    idx = c2m.prepare_mesh(V, F, signed=True, engine="grid", small_mesh_triangles=small)
    assert type(idx.search).__name__ == ("DenseGrid" if small else "BinGrid")
    ref = c2m.prepare_mesh(V, F, signed=True, engine="grid", compiled=False)
    d, s = dist(idx, P)
    dr, sr = dist(ref, P)
    # the numpy path computes the edge distances in another order: equal to float64 rounding (1 ulp)
    np.testing.assert_allclose(d, dr, rtol=1e-15, atol=1e-12)
    np.testing.assert_array_equal(np.sign(s), np.sign(sr))
    sub = rng.choice(n, 300, replace=False)
    np.testing.assert_allclose(d[sub] ** 2, brute_force_d2(idx, P[sub] - idx.shift), rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("compiled", [True, False])
def test_coordinates_beyond_the_limit_are_counted_and_refused(compiled):
    """Rows with a finite coordinate beyond MAX_CLOUD_COORD_M are refused with their count (a NaN
    coordinate in the same row does not hide it; NaN rows alone are only excluded)."""
    V, F = box(BOX, split=2)
    idx = c2m.prepare_mesh(V, F, engine="grid", compiled=compiled)
    P = np.random.default_rng(0).uniform(0, 4, (500, 3))
    P[3] = [np.nan, 1.0, 1.0]
    ok = c2m.c2m(P, idx)
    assert ok.points_nonfinite == 1 and ok.points_valid == 499
    P[10, 0] = 2e12
    P[20] = [np.nan, -5e12, 0.0]
    P[30, 2] = np.inf  # not finite: excluded, not refused
    with pytest.raises(InputError, match=r"2 point\(s\) with a coordinate beyond 1e\+12 m"):
        c2m.c2m(P, idx)


def test_median_in_place_is_numpys_median():
    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 4, 7, 10, 1001, 4096):
        for dt in (np.float64, np.float32):
            a = (rng.random(n) * 10).astype(dt)
            want = float(np.median(a.copy()))
            b = a.copy()
            assert median_in_place(b) == want
            assert sorted(b.tolist()) == sorted(a.tolist())  # a permutation of the values


def test_flat_ply_records_read_like_the_structured_path(tmp_path):
    """x y z of one native type are read as one array (float64 without conversion); other layouts
    (big endian, extra properties) keep the record path; the values are the same."""
    rng = np.random.default_rng(4)
    X = rng.normal(size=(1003, 3)) * 1e3
    cases = {"f8": ("<f8", "double"), "f4": ("<f4", "float"), "i2": ("<i2", "short"), "be": (">f8", "double")}
    for name, (code, ply_type) in cases.items():
        arr = X.astype(code)
        fmt = "binary_big_endian" if code[0] == ">" else "binary_little_endian"
        head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(X)}\n" + "".join(f"property {ply_type} {k}\n" for k in "xyz")
                + "end_header\n").encode()
        p = tmp_path / f"{name}.ply"
        p.write_bytes(head + arr.tobytes())
        vs = open_vertices(p)
        assert (vs._flat_type(("x", "y", "z")) is None) == (name == "be")
        parts = list(vs.chunks(400))
        assert [len(c) for c in parts] == [400, 400, 203] and all(c.dtype == np.float64 for c in parts)
        np.testing.assert_array_equal(np.concatenate(parts), arr.astype(np.float64))
        assert open_vertices(p)._flat_type(("x", "y")) is None  # a subset: the record path


def test_vertex_writer_blocks_write_the_same_bytes(tmp_path, monkeypatch):
    """Rows interleaved in blocks (here 7 rows) give the file of one whole-chunk record array, for
    mixed and single property types."""
    rng = np.random.default_rng(6)
    n = 50
    cols = [rng.normal(size=n) * 1e6 for _ in range(3)] + [rng.random(n)]
    for props in ([("x", "f8"), ("y", "f8"), ("z", "f8"), ("scalar_d", "f4")], [(k, "f4") for k in ("x", "y", "z")]):
        data = cols[: len(props)]
        want = np.empty(n, [(k, "<" + t) for k, t in props])
        for (k, _), c in zip(props, data):
            want[k] = c
        monkeypatch.setattr(PlyVertexWriter, "BLOCK_ROWS", 7)
        p = tmp_path / "blocks.ply"
        with PlyVertexWriter(p, n, props) as w:
            w.write(data)
        raw = p.read_bytes()
        assert raw[raw.index(b"end_header\n") + len(b"end_header\n"):] == want.tobytes()


def test_parent_lists_from_the_kernel_chain_give_the_numpy_hierarchys_cell_lists():
    """The dense grid's parents refined level by level in the compiled kernel (distance-ordered) give
    every fine cell the candidate list (same triangles, same order, same lower bound) that parents
    from the numpy coarse-to-fine hierarchy (triangle-id ordered) give."""
    from mst.eval.c2m.grids import DenseGrid
    from mst.meshtools.generate import courtyard

    V, F = courtyard(split=3)
    idx = c2m.prepare_mesh(V, F, engine="grid")
    P = np.random.default_rng(8).uniform(V.min(0) - 2, V.max(0) + 2, (20000, 3)) - idx.shift
    g1, g2 = DenseGrid(idx), DenseGrid(idx)
    if g1.nb is None or g1.levels < 2:
        pytest.skip("no compiled kernels or too few levels for parent lists")
    g2._ancestor_lists = lambda keys, up: g2._tg.candidates(keys, g2.lo, g2.h * (1 << up), g2.levels - up, g2.nb)[:2]
    flat = g1.nb.missing_cells(P, g1.lo.astype(np.float64), 1.0 / g1.h, g1.dims, g1.cell)
    assert len(flat) > 1000
    g1._fill(flat)
    g2._fill(flat)
    np.testing.assert_array_equal(g1.cell, g2.cell)
    np.testing.assert_array_equal(g1.cand, g2.cand)
    np.testing.assert_array_equal(g1.lb, g2.lb)
