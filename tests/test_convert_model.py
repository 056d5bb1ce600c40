"""``mst convert-model`` / mst.meshtools.convert on generated TINs and real CityJSON buildings."""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest

from mst import InputError
from mst.meshtools import generate as gen
from mst.meshtools.convert import ConvertConfig, tin_to_polygons
from mst.meshtools.formats import load_model, read_cao, read_obj, read_vrml, save_model, save_triangles
from mst.meshtools.model import PolygonModel


# ====================================================================== property checks
def tri_area(V, F):
    return float(np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum() / 2)


def xy_area(V, F, signed=True):
    a, b, c = V[F[:, 0], :2], V[F[:, 1], :2], V[F[:, 2], :2]
    s = ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])) / 2
    return float(s.sum() if signed else np.abs(s).sum())


def signed_volume(V, F):
    c = V[F].reshape(-1, 3).mean(0)
    a, b, d = V[F[:, 0]] - c, V[F[:, 1]] - c, V[F[:, 2]] - c
    return float(np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6)


def crease_edges(V, F, angle_tol_deg):
    """(K, 2) vertex pairs of manifold TIN edges whose dihedral angle exceeds the tolerance."""
    u, v = F.ravel(), F[:, [1, 2, 0]].ravel()
    key = np.minimum(u, v) * len(V) + np.maximum(u, v)
    o = np.argsort(key, kind="stable")
    ks = key[o]
    same = np.flatnonzero(ks[1:] == ks[:-1])
    h1, h2 = o[same], o[same + 1]
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    cosd = np.einsum("ij,ij->i", N[h1 // 3], N[h2 // 3])
    sel = cosd < np.cos(np.deg2rad(angle_tol_deg))
    return np.stack([u[h1[sel]], v[h1[sel]]], 1)


def point_segment_distance(P, A, B):
    """(K,) distance of each point to the nearest of the segments A-B."""
    out = np.full(len(P), np.inf)
    d = B - A
    dd = np.maximum((d * d).sum(1), 1e-300)
    for s in range(0, len(P), 512):
        p = P[s:s + 512, None, :]
        t = np.clip(((p - A) * d).sum(-1) / dd, 0, 1)
        out[s:s + 512] = np.linalg.norm(p - (A + t[..., None] * d), axis=-1).min(1)
    return out


def check_conversion(V, F, model: PolygonModel, stats,  angle_tol_deg: float, rel_area_tol: float = 1e-9,
                     max_polygons: int | None = None, closed: bool | None = None) -> None:
    """The issue's acceptance checks for one converted TIN."""
    dist_tol = stats.dist_tol_used_m
    diag = float(np.linalg.norm(np.ptp(V[np.unique(F)], axis=0)))
    # 1. area preserved
    Vo, Fo = model.triangulate()
    a_in, a_out = tri_area(V, F), tri_area(Vo, Fo)
    assert abs(a_out - a_in) <= rel_area_tol * a_in, (a_in, a_out)
    # 2. every polygon planar within dist_tol (half-width along the least-squares normal)
    for f, hs in zip(model.faces, model.holes):
        P = model.vertices[np.concatenate([f, *hs])]
        c = P.mean(0)
        n = np.linalg.svd(P - c)[2][2]
        d = (P - c) @ n
        assert (d.max() - d.min()) / 2 <= dist_tol * (1 + 1e-9) + 1e-12 * diag
    # 3. polygon count
    if max_polygons is not None:
        assert model.n_faces <= max_polygons
    # 4. crease edges lie on polygon boundaries (both ends and the midpoint)
    C = crease_edges(V, F, angle_tol_deg)
    if len(C):
        segs = np.concatenate([np.stack([lp, np.roll(lp, -1)], 1) for lp in model.loops()])
        A, B = model.vertices[segs[:, 0]], model.vertices[segs[:, 1]]
        pts = np.concatenate([V[C[:, 0]], V[C[:, 1]], (V[C[:, 0]] + V[C[:, 1]]) / 2])
        assert point_segment_distance(pts, A, B).max() <= 1e-6 * diag
    # 5. closed solids: outward normals, watertight (no cracks: every directed edge has its reverse)
    if closed:
        assert signed_volume(Vo, Fo) > 0
        assert signed_volume(Vo, Fo) == pytest.approx(signed_volume(V, F), rel=max(rel_area_tol, 1e-9))
        e = np.concatenate([np.stack([lp, np.roll(lp, -1)], 1) for lp in model.loops()])
        fwd = {tuple(x) for x in e.tolist()}
        assert all((b, a) in fwd for a, b in fwd), "crack: an outline edge has no opposite edge"


def convert(V, F, **kw):
    return tin_to_polygons(V, F, ConvertConfig(**kw))


# ====================================================================== generated shapes
@pytest.mark.parametrize("name,n_faces,n_holes,n_vertices", [
    ("box", 6, 0, 8), ("l_shape", 8, 0, 12), ("courtyard", 10, 2, 16), ("gabled_house", 7, 0, 10),
])
@pytest.mark.parametrize("split", [1, 5])
def test_generated_buildings_exact(name, n_faces, n_holes, n_vertices, split):
    V, F = getattr(gen, name)(split=split)
    model, stats = convert(V, F)
    truth = getattr(gen, f"{name}_model")()
    assert (model.n_faces, model.n_holes, len(model.vertices)) == (n_faces, n_holes, n_vertices)
    check_conversion(V, F, model, stats, 1.0, max_polygons=truth.n_faces, closed=True)
    # same set of (normal, area) as the ground truth polygons
    got = sorted(zip(np.round(model.face_normals(), 9).tolist(), np.round(model.face_areas(), 6)))
    want = sorted(zip(np.round(truth.face_normals(), 9).tolist(), np.round(truth.face_areas(), 6)))
    assert got == want


@pytest.mark.parametrize("mode", ["inverted", "mixed"])
def test_winding_fixed_outward(mode):
    V, F = gen.courtyard(split=3)
    F = F[:, [0, 2, 1]].copy() if mode == "inverted" else F.copy()
    if mode == "mixed":
        F[::3] = F[::3][:, [0, 2, 1]]
    model, stats = convert(V, F)
    Vg, Fg = gen.courtyard(split=3)
    assert stats.flipped_triangles == (len(F) if mode == "inverted" else len(F[::3]))
    check_conversion(Vg, Fg, model, stats, 1.0, closed=True)


def test_open_tin_keeps_majority_orientation():
    V, F, _ = gen.terrain(50.0, 20, n_creases=0, slope=0.0)
    F2 = F.copy()
    F2[:10] = F2[:10, [0, 2, 1]]  # a few triangles wound the wrong way
    model, stats = convert(V, F2)
    assert model.n_faces == 1 and stats.flipped_triangles == 10
    assert model.face_normals()[0] == pytest.approx([0, 0, 1])
    model_dn, _ = convert(V, F[:, [0, 2, 1]])
    assert model_dn.face_normals()[0] == pytest.approx([0, 0, -1])


def test_cylinder_does_not_merge_at_small_tolerance():
    V, F = gen.cylinder(split=2, sections=64)  # walls 5.625 deg apart
    model, stats = convert(V, F, angle_tol_deg=1.0)
    assert model.n_faces == 66
    check_conversion(V, F, model, stats, 1.0, closed=True)
    merged, _ = convert(V, F, angle_tol_deg=12.0, dist_tol_m=10.0)
    assert merged.n_faces < 66 // 2 + 2  # large tolerance: neighbouring walls merge


def test_fine_cylinder_no_chaining():
    """Walls 0.35 deg apart: every neighbour pair is below the 1 deg tolerance (a neighbour-only test
    chains the whole side into one "plane"), but each polygon must span <= 1 deg of normals."""
    V, F = gen.cylinder(split=1, sections=1024, radius=30.0, height=5.0)
    model, stats = convert(V, F, angle_tol_deg=1.0, dist_tol_m=1.0)
    n = model.face_normals()
    side = np.abs(n[:, 2]) < 0.5
    assert side.sum() >= 360  # each side polygon covers at most 1 deg of the circle
    assert stats.regrown_triangles > 0
    # merged walls are not exactly coplanar: area and volume hold to the tolerance only
    check_conversion(V, F, model, stats, 1.0, rel_area_tol=1e-4, closed=True)


def test_t_junction_vertex_kept_no_crack():
    """Front = vertical wall for x in [0,1], tilted wall for x in [1,2]: the floor edge y=0 is
    straight through (1,0,0) but the walls have a corner there: the floor keeps the vertex."""
    P = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0],  # 0-4 floor
                  [0, 0, 1], [1, 0, 1], [1, 0.3, 1], [2, 0.3, 1], [2, 1, 1], [0, 1, 1]], float)  # 5-10 top
    faces = [[0, 4, 3, 2, 1],  # floor (down)
             [0, 1, 6, 5],  # vertical front
             [1, 2, 8, 7],  # tilted front
             [1, 7, 6],  # step triangle (x=1, facing +x)
             [2, 3, 9, 8],  # side x=2
             [3, 4, 10, 9],  # back y=1
             [4, 0, 5, 10],  # side x=0
             [5, 6, 7, 8, 9, 10]]  # roof (L-shaped)
    truth = PolygonModel(P, faces)
    V, F = gen.model_to_tin(truth, split=4)
    model, stats = convert(V, F)
    assert model.n_faces == 8
    check_conversion(V, F, model, stats, 1.0, max_polygons=8, closed=True)
    floor = [f for f, n in zip(model.faces, model.face_normals()) if n[2] < -0.99][0]
    assert len(floor) == 5  # the T-junction vertex stays
    assert any(np.allclose(model.vertices[i], [1, 0, 0]) for i in floor)


def test_weld_and_degenerate_and_nonmanifold():
    V, F = gen.box(split=2)
    # unweld: every triangle gets its own copies of its vertices, shifted by < weld_tol
    rng = np.random.default_rng(1)
    V2 = V[F.ravel()] + rng.uniform(-1e-8, 1e-8, (3 * len(F), 3))
    F2 = np.arange(3 * len(F)).reshape(-1, 3)
    # a zero-area triangle and a fin (non-manifold edge)
    F2 = np.vstack([F2, [F2[0, 0], F2[0, 0], F2[0, 1]]])
    model, stats = convert(V2, F2, weld_tol_m=1e-6)
    assert stats.welded_vertices == 3 * len(F) - len(V)
    assert stats.degenerate_dropped == 1
    assert model.n_faces == 6
    fin = np.array([[0, 0, 4], [10, 0, 4], [5, -3, 7]], float)  # on the top edge y=0, z=4
    V3 = np.vstack([V, fin])
    idx = {tuple(p): i for i, p in enumerate(V.tolist())}
    a, b = idx[(0.0, 0.0, 4.0)], idx[(10.0, 0.0, 4.0)]
    F3 = np.vstack([gen.box(split=1)[1], [[a, b, len(V) + 2]]])
    V3 = np.vstack([gen.box(split=1)[0], [[5, -3, 7]]])
    a, b = [int(np.flatnonzero((V3 == q).all(1))[0]) for q in ([0, 0, 4], [10, 0, 4])]
    F3[-1] = [a, b, len(V3) - 1]
    model3, stats3 = convert(V3, F3)
    assert stats3.nonmanifold_edges == 1
    assert model3.n_faces == 7


def test_terrain_with_creases_and_hole_regions():
    V, F, _ = gen.terrain(200.0, 120, n_creases=4, slope=0.3, seed=3)  # 28,800 triangles, 25 planar patches
    model, stats = convert(V, F, angle_tol_deg=0.5)
    assert model.n_faces <= 25
    check_conversion(V, F, model, stats, 0.5)


def test_curved_terrain_iterative():
    """A smooth bump: regions are grown with a queue over ~50k triangles (no recursion limit)."""
    n = 160
    x = np.linspace(-50, 50, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    Z = 20 * np.exp(-(X**2 + Y**2) / 800)
    V = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    model, stats = convert(V, F, angle_tol_deg=2.0, dist_tol_m=0.05)
    assert stats.regrown_triangles > 10_000
    assert 50 < model.n_faces < len(F)
    # merged triangles are coplanar only within the tolerances, so the 3D area holds to ~1e-3;
    # the footprint (xy-projected area) must be exact: no overlaps, no gaps
    check_conversion(V, F, model, stats, 2.0, rel_area_tol=2e-3)
    Vo, Fo = model.triangulate()
    assert xy_area(Vo, Fo) == pytest.approx(100.0 * 100.0, rel=1e-12)
    assert np.abs(xy_area(Vo, Fo, signed=False)) == pytest.approx(100.0 * 100.0, rel=1e-12)


# ====================================================================== real CityJSON buildings
def _buildings(path):
    m = load_model(path)
    by = defaultdict(list)
    for i, name in enumerate(m.names):
        by[name].append(i)
    out = {}
    for name, idx in by.items():
        sub = PolygonModel(m.vertices, [m.faces[i] for i in idx], holes=[m.holes[i] for i in idx])
        V, F = sub.triangulate()
        used = np.zeros(len(V), bool)
        used[F] = True
        remap = np.cumsum(used) - 1
        out[name] = (V[used], remap[F], len(idx))
    return out


@pytest.mark.parametrize("fname", ["delft_1b.json", "DH_01_subs.city.json", "rotterdam_subset.json"])
def test_cityjson_buildings(shared_data, fname):
    """Per building: triangulate its surfaces, convert, check the issue's properties. The files'
    surfaces are planar only to ~1 cm (DH_01: a roof quad is 1.02 cm off its best plane), so the
    distance tolerance is 2 cm; at a tighter one such a quad rightly stays two polygons."""
    p = shared_data / "cityjson" / fname
    scale = float(json.loads(p.read_text())["transform"]["scale"][0])
    n_checked = 0
    for V, F, n_surfaces in _buildings(p).values():
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        _, cnt = np.unique(e, axis=0, return_counts=True)
        closed = bool((cnt == 2).all())
        model, stats = convert(V, F, angle_tol_deg=1.0, dist_tol_m=0.02)
        check_conversion(V, F, model, stats, 1.0, rel_area_tol=1e-9 + scale, max_polygons=n_surfaces, closed=closed)
        n_checked += 1
    assert n_checked >= 1


# ====================================================================== CLI
def test_cli_wrl_cao_obj_and_json(tmp_path, mst):
    V, F = gen.courtyard(split=3)
    src = tmp_path / "tin.obj"
    save_triangles(src, V, F)
    before = src.read_bytes()
    for suf in (".wrl", ".cao", ".obj"):
        out = tmp_path / f"poly{suf}"
        r = mst("convert-model", src, "-o", out, "--json", "--angle-tol", "1", "--dist-tol", "0.001")
        s = json.loads(r.stdout)
        assert s["triangles_in"] == len(F) and s["polygons_out"] == 10 and s["holes"] == 2
        assert "polygons out 10" in r.stderr
        m = load_model(out)
        assert m.n_faces == 10 and m.n_holes == 2  # bridged in the file, restored on reading
        Vo, Fo = m.triangulate()
        assert tri_area(Vo, Fo) == pytest.approx(tri_area(V, F), rel=1e-12)
        assert signed_volume(Vo, Fo) == pytest.approx(signed_volume(V, F), rel=1e-12)
        # exact round trip of the written file
        save_model(tmp_path / f"again{suf}", m)
        assert (tmp_path / f"again{suf}").read_bytes() == out.read_bytes()
    assert src.read_bytes() == before  # input untouched


def test_cli_cityjson_input(shared_data, tmp_path, mst):
    out = tmp_path / "delft.cao"
    r = mst("convert-model", shared_data / "cityjson" / "delft_1b.json", "-o", out, "--json", "-q")
    s = json.loads(r.stdout)
    assert s["polygons_out"] < s["triangles_in"] and out.exists() and r.stderr == ""


@pytest.mark.parametrize("case", ["missing", "nan", "empty", "garbage", "degenerate", "bad_suffix", "no_folder"])
def test_cli_bad_input(tmp_path, mst, case):
    src = tmp_path / "in.obj"
    out = tmp_path / "out.wrl"
    if case == "nan":
        src.write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n")
    elif case == "empty":
        src.write_text("")
    elif case == "garbage":
        src = tmp_path / "in.ply"
        src.write_bytes(b"\x00\x01garbage" * 100)
    elif case == "degenerate":
        src.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    elif case == "bad_suffix":
        src.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
        out = tmp_path / "out.stl"
    elif case == "no_folder":
        src.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
        out = tmp_path / "nope" / "out.wrl"
    r = mst("convert-model", src, "-o", out, check=False)
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mst convert-model: error: "), r.stderr
    assert not out.exists()
    assert not list(tmp_path.glob(".out*"))  # no temporary left behind


def test_refuses_to_overwrite_input(tmp_path, mst):
    src = tmp_path / "m.obj"
    save_triangles(src, *gen.box())
    before = src.read_bytes()
    r = mst("convert-model", src, "-o", src, check=False)
    assert r.returncode == 1 and "overwrite the input" in r.stderr
    assert src.read_bytes() == before


def test_stage_rejects_nan_arrays():
    V, F = gen.box()
    V[3, 1] = np.inf
    with pytest.raises(InputError, match="NaN or infinite"):
        tin_to_polygons(V, F)


# ====================================================================== topology corner cases
def _grid_plate(n=6, size=6.0):
    """Flat open n x n grid in z=0, normals up: (V, F, cell index per triangle)."""
    x = np.linspace(0, size, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    cell = np.concatenate([np.arange(n * n)] * 2)
    return V, F, cell


def test_holes_touching_outer_boundary_and_each_other(tmp_path):
    """Cells removed from a plate so that holes touch the border and each other at single
    vertices (pinch vertices): loops stay simple, area and holes are right."""
    n = 6
    V, F, cell = _grid_plate(n)
    ci, cj = cell // n, cell % n
    cells = [(1, 1), (2, 2), (0, 4), (1, 3), (4, 3)]  # (1,3) touches the border notch (0,4) at a vertex
    removed = np.zeros(len(F), bool)
    for i, j in cells:
        removed |= (ci == i) & (cj == j)
    F = F[~removed]
    model, stats = convert(V, F)
    assert model.n_faces >= 1 and stats.pinch_vertices >= 2
    check_conversion(V, F, model, stats, 1.0)
    for lp in model.loops():
        assert len(np.unique(lp)) == len(lp)  # simple loops
    Vo, Fo = model.triangulate()
    assert tri_area(Vo, Fo) == pytest.approx(36 - 5, rel=1e-12)
    assert xy_area(Vo, Fo) == pytest.approx(36 - 5, rel=1e-12)
    # written with holes spliced/bridged: no zero-length edge, same area, all triangles up
    save_model(tmp_path / "p.cao", model)
    raw = read_cao(tmp_path / "p.cao")
    for f in raw.faces:
        assert (f != np.roll(f, -1)).all()
    Vo, Fo = raw.triangulate()
    assert xy_area(Vo, Fo) == pytest.approx(36 - 5, rel=1e-12)
    assert xy_area(Vo, Fo, signed=False) == pytest.approx(36 - 5, rel=1e-12)
    back = load_model(tmp_path / "p.cao")
    assert (back.n_faces, back.n_holes) == (model.n_faces, model.n_holes)
    np.testing.assert_allclose(back.face_areas(), model.face_areas(), rtol=1e-12)


def test_many_holes_bridged_for_writers(tmp_path):
    """A plate with 5 holes: each writer gets one weakly-simple loop per face whose earcut
    triangulation covers exactly the plate minus the holes."""
    n = 9
    V, F, cell = _grid_plate(n, 9.0)
    ci, cj = cell // n, cell % n
    holes = [(1, 1), (1, 5), (4, 3), (6, 7), (7, 1)]
    removed = np.zeros(len(F), bool)
    for i, j in holes:
        removed |= (ci == i) & (cj == j)
    F = F[~removed]
    model, stats = convert(V, F)
    assert model.n_faces == 1 and model.n_holes == 5
    for suf in (".wrl", ".cao", ".obj"):
        save_model(tmp_path / f"p{suf}", model)
        raw = {".cao": read_cao, ".wrl": read_vrml, ".obj": read_obj}[suf](tmp_path / f"p{suf}")
        assert raw.n_faces == 1 and len(raw.faces[0]) == 4 + 5 * 4 + 2 * 5  # one bridged loop
        Vr, Fr = raw.triangulate()
        assert xy_area(Vr, Fr, signed=False) == pytest.approx(81 - 5, rel=1e-12)
        m = load_model(tmp_path / f"p{suf}")
        assert m.n_faces == 1 and m.n_holes == 5 and len(m.faces[0]) == 4
        Vo, Fo = m.triangulate()
        assert tri_area(Vo, Fo) == pytest.approx(81 - 5, rel=1e-12)
        assert xy_area(Vo, Fo) == pytest.approx(81 - 5, rel=1e-12)  # all triangles face up


def test_vrml_output_read_by_meshlab(tmp_path):
    """An independent VRML 2.0 reader (MeshLab) accepts the bridged polygons: same area/volume."""
    pymeshlab = pytest.importorskip("pymeshlab")
    V, F = gen.courtyard(split=2)
    model, _ = convert(V, F)
    save_model(tmp_path / "c.wrl", model)
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(tmp_path / "c.wrl"))
    except pymeshlab.PyMeshLabException as e:  # VRML plugin missing (no libOpenGL on this machine)
        pytest.skip(f"pymeshlab cannot read VRML here: {e}")
    g = ms.get_geometric_measures()
    assert g["surface_area"] == pytest.approx(tri_area(V, F), rel=1e-6)
    assert g["mesh_volume"] == pytest.approx(signed_volume(V, F), rel=1e-6)


def test_mobius_strip_does_not_crash():
    """A non-orientable strip: orientation cannot be made consistent; conversion still succeeds."""
    k = 48
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    pts = []
    for s_ in (-1.0, 1.0):
        r = 5 + s_ * np.cos(t / 2)
        pts.append(np.column_stack([r * np.cos(t), r * np.sin(t), s_ * np.sin(t / 2)]))
    V = np.concatenate(pts)
    F = []
    for i in range(k):
        j = (i + 1) % k
        a, b = i, k + i
        c, d = (j, k + j) if j else (k + j, j)  # the half twist swaps the two rails
        F += [[a, c, b], [b, c, d]]
    model, stats = convert(V, np.array(F), angle_tol_deg=1.0, dist_tol_m=0.01)
    assert model.n_faces > 10 and stats.components == 1


@pytest.mark.slow
def test_city_block_1m():
    """The benchmark's ~1,000,000-triangle city block (terrain of planar patches + 64 buildings):
    every property checked (the timing is in eval/bench/convert.py)."""
    V, F = gen.city_block(n_triangles=1_000_000, buildings=64, seed=0)
    model, stats = convert(V, F)
    # 16 each of box (6), L (8), courtyard (10, 2 holes), gabled (7) + at most 7 x 7 terrain patches
    assert stats.components == 65 and stats.closed_components == 64
    assert 496 < model.n_faces <= 496 + 49 and model.n_holes == 32
    check_conversion(V, F, model, stats, 1.0, rel_area_tol=1e-9)


def test_cli_config_file_sets_a_tolerance_and_json_echoes_it(tmp_path, mst):
    """One convert setting through --config YAML changes the result; the --json 'config' block
    repeats the run exactly; an explicit option overrides the file."""
    V, F = gen.courtyard(split=2)
    rng = np.random.default_rng(3)
    soup = V[F].reshape(-1, 3) + rng.uniform(-1e-5, 1e-5, (3 * len(F), 3))  # unwelded, 10 um apart
    src = tmp_path / "soup.obj"
    save_triangles(src, soup, np.arange(len(soup)).reshape(-1, 3))
    base = json.loads(mst("convert-model", src, "-o", tmp_path / "a.obj", "--json", "-q").stdout)
    (tmp_path / "c.yaml").write_text("convert-model:\n  weld_tol_m: 0.001\n")
    loose = json.loads(mst("convert-model", src, "-o", tmp_path / "b.obj", "--json", "-q",
                           "--config", tmp_path / "c.yaml").stdout)
    assert loose["config"]["weld_tol_m"] == 0.001 and base["config"]["weld_tol_m"] == 1e-6
    assert base["welded_vertices"] == 0 and loose["welded_vertices"] > len(F)  # the soup is welded
    assert loose["polygons_out"] < base["polygons_out"]
    (tmp_path / "again.json").write_text(json.dumps(loose["config"]))
    again = json.loads(mst("convert-model", src, "-o", tmp_path / "c.obj", "--json", "-q",
                           "--config", tmp_path / "again.json").stdout)
    assert (tmp_path / "c.obj").read_bytes() == (tmp_path / "b.obj").read_bytes()
    assert again["config"] == loose["config"]
    over = json.loads(mst("convert-model", src, "-o", tmp_path / "d.obj", "--json", "-q",
                          "--config", tmp_path / "c.yaml", "--weld-tol", "1e-6").stdout)
    assert over["polygons_out"] == base["polygons_out"]


def test_cli_config_unknown_key_and_bad_value_are_named(tmp_path, mst):
    src = tmp_path / "in.obj"
    src.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "bad.yaml").write_text("angle_tol: 2\n")
    r = mst("convert-model", src, "-o", tmp_path / "o.wrl", "--config", tmp_path / "bad.yaml", check=False)
    assert r.returncode == 1 and "angle_tol" in r.stderr and "unknown key" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "o.wrl").exists()
    r = mst("convert-model", src, "-o", tmp_path / "o.wrl", "--set", "weld_tol_m=-1", check=False)
    assert r.returncode == 1 and "weld_tol_m" in r.stderr and "--" not in r.stderr.split("error:")[1]
    assert not (tmp_path / "o.wrl").exists()


def test_config_bounds_checked_once_in_the_config():
    from mst.errors import ConfigError

    with pytest.raises(ConfigError, match="dist_tol_m"):
        ConvertConfig(dist_tol_m=-1.0)
    assert ConvertConfig.from_dict({"collinear_tol_m": "null"}).collinear_tol_m is None


def test_cli_show_config_lists_every_setting(mst):
    out = mst("convert-model", "--show-config").stdout
    assert all(k in out for k in ("angle_tol_deg", "dist_tol_m", "weld_tol_m", "collinear_tol_m"))
