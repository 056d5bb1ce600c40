"""mst c2m: exact distances with analytic answers, signs near edges/corners, statistics, CLI outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst import InputError
from mst.eval import c2m
from mst.eval.cloud_io import write_cloud
from mst.meshtools.generate import box
from mst.meshtools.io import save_triangles

BOX = (4.0, 6.0, 2.0)  # box from (0,0,0) to (4,6,2), outward winding


def _box_index(signed=True, engine="bvh", split=2, shift=(0.0, 0.0, 0.0)):
    V, F = box(BOX, split=split)
    return c2m.prepare_mesh(V + np.asarray(shift), F, signed=signed, engine=engine), V, F


def _box_sdf(P):
    """Analytic signed distance to the axis-aligned box [0,4]x[0,6]x[0,2] (negative inside)."""
    lo, hi = np.zeros(3), np.array(BOX)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(P - c) - h
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(1), 0)
    return outside + inside


def _dist(idx, P, signed=True, max_dist=None):
    d, s = c2m.point_distances(idx, np.asarray(P, float) - idx.shift, signed, max_dist)
    return d, s


@pytest.mark.parametrize("engine", ["bvh", "grid"])
def test_box_distances_and_signs_near_edges_and_corners(engine):
    idx, V, F = _box_index(engine=engine)
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
    d, s = _dist(idx, P)
    sdf = _box_sdf(P)
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
    d, s = _dist(idx, P)
    np.testing.assert_allclose(d, np.abs(h), atol=1e-12)
    np.testing.assert_allclose(s, h, atol=1e-12)  # + above (normal +z), - below
    # exactly on the surface, on the vertices and on the shared diagonal edge: distance 0
    on = np.vstack([np.column_stack([xy, np.full(5000, 5.0)]), V, [[5, 5, 5], [2.5, 2.5, 5]]])
    d0, _ = _dist(idx, on)
    assert np.abs(d0).max() < 1e-12
    # beside the square: distance to the nearest edge / vertex
    P2 = np.array([[12, 5, 5], [13, 14, 9], [-3, -4, 5]], float)
    d2, _ = _dist(idx, P2)
    np.testing.assert_allclose(d2, [2.0, np.sqrt(9 + 16 + 16), 5.0], atol=1e-12)


def test_vertices_of_a_finely_split_box_and_neighbour_ties():
    idx, V, F = _box_index(split=5)
    d, s = _dist(idx, V)
    assert np.abs(d).max() < 1e-12
    # points just outside along the vertex normals of the lattice (many exact ties between triangles)
    P = V + 0.01 * np.sign(V - np.array([2.0, 3.0, 1.0]))
    d, s = _dist(idx, P)
    np.testing.assert_allclose(s, _box_sdf(P), atol=1e-12)


def test_georeferenced_coordinates_keep_precision():
    shift = np.array([512_345.678, 5_432_109.876, 312.5])
    idx, V, F = _box_index(shift=shift)
    rng = np.random.default_rng(2)
    P0 = rng.uniform(-1, 7, (2000, 3))
    d, s = _dist(idx, P0 + shift)
    # float64 at 5e6 m has ~1e-9 m resolution; float32 would be off by decimetres
    np.testing.assert_allclose(s, _box_sdf(P0), atol=2e-9)


def test_max_dist_marks_far_points():
    idx, V, F = _box_index()
    P = np.array([[2, 3, 2.5], [2, 3, 2.0 + 4.0], [100, 100, 100], [2, 3, 1.0]])
    d, s = _dist(idx, P, max_dist=1.0)
    np.testing.assert_allclose(d[[0, 3]], [0.5, 1.0], atol=1e-12)
    assert np.isnan(d[1]) and np.isnan(d[2])


def test_closest_point_reference_matches_fast_routine():
    idx, V, F = _box_index(split=3)
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


# ------------------------------------------------------------------------------- run_c2m / CLI
def _building_case(tmp_path, n=20000, sigma=0.1, seed=0, nonfinite=3):
    """Noisy points on a box building (distances known from the analytic SDF of the noise-free box)."""
    V, F = box(BOX, split=3)
    mesh = tmp_path / "building.obj"
    save_triangles(mesh, V, F)
    rng = np.random.default_rng(seed)
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    ar = np.linalg.norm(np.cross(B - A, C - A), axis=1)
    t = rng.choice(len(F), n, p=ar / ar.sum())
    u = rng.random((n, 2))
    m = u.sum(1) > 1
    u[m] = 1 - u[m]
    P = A[t] + u[:, :1] * (B - A)[t] + u[:, 1:] * (C - A)[t] + rng.normal(0, sigma, (n, 3))
    P[:nonfinite] = [np.nan, np.inf, -np.inf][:nonfinite] if nonfinite else P[:0]
    return mesh, P


def test_run_c2m_statistics_match_analytic(tmp_path):
    mesh, P = _building_case(tmp_path)
    cloud = tmp_path / "cloud.ply"
    write_cloud(cloud, P)
    cfg = c2m.C2MConfig(signed=True, chunk_points=7000)
    s = c2m.run_c2m(cloud, mesh, cfg, out_cloud=tmp_path / "out.ply").to_json()
    fin = np.isfinite(P).all(1)
    sdf = _box_sdf(P[fin])
    d = np.abs(sdf)
    assert s["points_total"] == len(P) and s["points_nonfinite"] == 3 and s["points_valid"] == len(P) - 3
    for row in s["thresholds"]:
        under = d[d < row["max_dist"]]
        assert row["count"] == len(under)
        assert row["percent"] == pytest.approx(100 * len(under) / len(d), abs=1e-12)
        assert row["mean"] == pytest.approx(under.mean(), abs=1e-12)
        assert row["std"] == pytest.approx(under.std(), abs=1e-12)
    u = s["unsigned"]
    assert u["mean"] == pytest.approx(d.mean(), abs=1e-12)
    assert u["median"] == pytest.approx(np.median(d), abs=1e-12)
    assert u["std"] == pytest.approx(d.std(), abs=1e-12)
    assert u["rms"] == pytest.approx(np.sqrt((d**2).mean()), abs=1e-12)
    assert u["max"] == pytest.approx(d.max(), abs=1e-12)
    assert s["signed"]["mean"] == pytest.approx(sdf.mean(), abs=1e-12)
    # the output cloud: same points, scalar fields in CloudCompare's naming, NaN for invalid points
    hdr = (tmp_path / "out.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "property float scalar_C2M_absolute_distances" in hdr and "scalar_C2M_signed_distances" in hdr
    from mst.eval.cloud_io import _open_ply

    src = _open_ply(tmp_path / "out.ply")
    assert src.count == len(P)
    raw = np.fromfile(tmp_path / "out.ply", dtype=np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                                                            ("a", "<f4"), ("s", "<f4")]),
                      offset=len(hdr.split("end_header\n")[0]) + len("end_header\n"))
    assert np.isnan(raw["a"][:3]).all()
    np.testing.assert_allclose(raw["a"][3:], d, atol=1e-6)
    np.testing.assert_allclose(raw["s"][3:], sdf, atol=1e-6)
    np.testing.assert_array_equal(np.column_stack([raw["x"], raw["y"], raw["z"]])[3:], P[3:])


def test_cli_json_csv_markdown_plot(tmp_path, mst):
    mesh, P = _building_case(tmp_path, n=5000, nonfinite=0)
    cloud = tmp_path / "cloud.xyz"
    write_cloud(cloud, P)
    r = mst("c2m", cloud, mesh, "--json", "--thresholds", "0.05,0.1,0.2", "--markdown", tmp_path / "t.md",
            "--plot", tmp_path / "h.png", "-o", tmp_path / "o.ply")
    s = json.loads(r.stdout)
    d = np.abs(_box_sdf(P))
    assert [t["max_dist"] for t in s["thresholds"]] == [0.05, 0.1, 0.2]
    assert s["thresholds"][1]["percent"] == pytest.approx(100 * (d < 0.1).mean(), abs=1e-9)
    assert "Max. C2M distance [m]" in r.stderr  # the rich table on stderr
    md = (tmp_path / "t.md").read_text()
    assert "| % of points less than max. distance |" in md
    assert (tmp_path / "h.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r2 = mst("c2m", cloud, mesh, "--csv", "-q")
    lines = r2.stdout.strip().splitlines()
    assert lines[0] == "Max. C2M distance [m],0.1,0.2,0.5,1.0"
    assert float(lines[1].split(",")[2]) == pytest.approx(100 * (d < 0.2).mean(), abs=1e-9)
    assert r2.stderr == ""


def test_cli_max_dist(tmp_path, mst):
    mesh, P = _building_case(tmp_path, n=2000, nonfinite=0)
    P = np.vstack([P, [[50, 50, 50], [2, 3, 5.5]]])  # 48+ m away, and 3.5 m above the roof
    cloud = tmp_path / "c.ply"
    write_cloud(cloud, P)
    s = json.loads(mst("c2m", cloud, mesh, "--json", "--max-dist", "1", "-q").stdout)
    d = np.abs(_box_sdf(P))
    assert s["points_beyond_max_dist"] == int((d > 1).sum()) >= 2
    assert s["unsigned"]["count"] == int((d <= 1).sum())
    assert s["unsigned"]["max"] == pytest.approx(d[d <= 1].max(), abs=1e-12)
    assert s["thresholds"][-1]["percent"] == pytest.approx(100 * (d < 1).mean(), abs=1e-9)


def test_cli_errors(tmp_path, mst):
    mesh, P = _building_case(tmp_path, n=100, nonfinite=0)
    empty = tmp_path / "empty.xyz"
    empty.write_text("# nothing\n")
    r = mst("c2m", empty, mesh, check=False)
    assert r.returncode == 1 and r.stderr.strip() == f"mst c2m: error: {empty}: cloud has no points"
    allnan = tmp_path / "nan.xyz"
    allnan.write_text("nan 1 2\n1 inf 2\n")
    r = mst("c2m", allnan, mesh, check=False)
    assert r.returncode == 1 and "no finite points" in r.stderr
    cloud = tmp_path / "c.xyz"
    write_cloud(cloud, P)
    r = mst("c2m", cloud, tmp_path / "missing.obj", check=False)
    assert r.returncode == 1 and "does not exist" in r.stderr
    nomesh = tmp_path / "pts.obj"
    nomesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    r = mst("c2m", cloud, nomesh, "-o", tmp_path / "never.ply", check=False)
    assert r.returncode == 1 and "error" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "never.ply").exists()
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
                    b"property float y\nproperty float z\nend_header\n" + b"\0" * 50)
    r = mst("c2m", bad, mesh, check=False)
    assert r.returncode == 1 and "truncated" in r.stderr


def _winding_number(P, V, F):
    """Generalised winding number of points w.r.t. a closed mesh (Van Oosterom-Strackee solid angles)."""
    A = V[F[:, 0]][None] - P[:, None]
    B = V[F[:, 1]][None] - P[:, None]
    C = V[F[:, 2]][None] - P[:, None]
    a, b, c = (np.linalg.norm(X, axis=2) for X in (A, B, C))
    num = np.einsum("ijk,ijk->ij", A, np.cross(B, C))
    den = a * b * c + np.einsum("ijk,ijk->ij", A, B) * c + np.einsum("ijk,ijk->ij", B, C) * a \
        + np.einsum("ijk,ijk->ij", C, A) * b
    return (2 * np.arctan2(num, den)).sum(1) / (4 * np.pi)


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
    inside = _winding_number(P, V, F) > 0.5
    d, s = _dist(idx, P)
    assert ((s < 0) == inside).all()
    np.testing.assert_allclose(np.abs(s), d)


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
    da, sa = _dist(a, P)
    db, sb = _dist(b, P)
    dc, sc = _dist(bvh, P)
    da2, _ = _dist(a, P[::-1])
    np.testing.assert_allclose(da, db, rtol=1e-15, atol=1e-12)
    # the BVH's float32 pick is refined exactly (near ties; far outliers searched again in float64)
    np.testing.assert_allclose(da, dc, rtol=1e-15, atol=1e-12)
    np.testing.assert_array_equal(da2[::-1], da)
    assert (np.sign(sa) == np.sign(sb)).all() and (np.sign(sa) == np.sign(sc)).all()
    # max-dist: cells whose lower bound exceeds it are skipped, the rest exact
    dm, _ = _dist(a, P, max_dist=0.5)
    np.testing.assert_array_equal(np.isnan(dm), da > 0.5)
    np.testing.assert_allclose(dm[da <= 0.5], da[da <= 0.5])


def test_polygon_models_cao_and_wrl_give_the_same_distances(tmp_path, mst, shared_data):
    """The real teabox model as ViSP .cao and as VRML: triangulated on load, identical C2M results."""
    from mst.meshtools.io import load_triangles

    cao, wrl = shared_data / "visp-teabox" / "teabox.cao", shared_data / "visp-teabox" / "teabox.wrl"
    V, F = load_triangles(cao)
    lo, hi = V.min(0), V.max(0)
    rng = np.random.default_rng(4)
    P = rng.uniform(lo - 0.02, hi + 0.02, (3000, 3))
    cloud = tmp_path / "c.xyz"
    write_cloud(cloud, P)
    a = json.loads(mst("c2m", cloud, cao, "--json", "-q", "--signed").stdout)
    b = json.loads(mst("c2m", cloud, wrl, "--json", "-q", "--signed").stdout)
    assert a["mesh_triangles"] == b["mesh_triangles"] == 12
    for k in ("mean", "median", "std", "max"):
        assert a["unsigned"][k] == pytest.approx(b["unsigned"][k], abs=1e-12)
        assert a["signed"][k] == pytest.approx(b["signed"][k], abs=1e-12)
    # signs agree with the winding number of the closed model
    idx = c2m.prepare_mesh(V, F, signed=True)
    _, s = _dist(idx, P)
    inside = _winding_number(P, V, F) > 0.5
    assert inside.sum() > 100 and ((s < 0) == inside).all()


def _brute_force_d2(idx, P):
    """Exact squared distances of shifted points to every triangle (numpy, blockwise): the reference."""
    m = idx.n_triangles
    out = np.empty(len(P))
    for i, p in enumerate(P):
        d2, _, _ = c2m.triangle_distances(idx, np.broadcast_to(p, (m, 3)), np.arange(m))
        out[i] = d2.min()
    return out


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
    d, s = _dist(idx, P)
    ref = np.sqrt(_brute_force_d2(idx, P - idx.shift))
    np.testing.assert_allclose(d, ref, rtol=0, atol=1e-9)
    assert (d[-20:] < 1e-9).all()
    np.testing.assert_allclose(np.abs(s), d)
    db, sb = _dist(bvh, P[:250])
    assert (np.sign(s[:250]) == np.sign(sb)).mean() > 0.99  # BVH float32 picks may differ at exact ties
    # many points (parallel kernel, chunk order independent) agree with the numpy brute force on a sample
    Q = np.vstack([A[rng.integers(0, len(F), 40000)] + rng.normal(0, 0.1, (40000, 3)),
                   rng.uniform(lo - 5, hi + 5, (4000, 3))])
    dq, _ = _dist(idx, Q, signed=False)
    k = rng.choice(len(Q), 150, replace=False)
    np.testing.assert_allclose(dq[k], np.sqrt(_brute_force_d2(idx, Q[k] - idx.shift)), rtol=0, atol=1e-9)
    dm, _ = _dist(idx, Q, signed=False, max_dist=0.2)
    np.testing.assert_array_equal(np.isnan(dm), dq > 0.2)
    np.testing.assert_array_equal(dm[dq <= 0.2], dq[dq <= 0.2])


def test_table1_decimals_follow_the_thresholds():
    """The paper's 2 decimals at metre thresholds; one more per decade below 0.1 m."""
    from mst.eval.c2m import table1_rows

    def rows(ths):
        return table1_rows({"thresholds": [{"max_dist": t, "percent": 57.54, "mean": 0.0623456, "std": 0.00456} for t in ths]})

    paper = rows([0.1, 0.2, 0.5, 1.0])
    assert paper[0] == ["Max. C2M distance [m]", "0.1", "0.2", "0.5", "1"]
    assert paper[1][1:] == ["57.5"] * 4 and paper[2][1:] == ["0.06"] * 4 and paper[3][1:] == ["0.00"] * 4
    assert rows([0.01, 0.02])[2][1:] == ["0.062", "0.062"]
    assert rows([0.005])[3][1:] == ["0.0046"]
