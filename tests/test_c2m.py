"""mst c2m: the runner's statistics against the analytic distances, the output cloud, the CLI outputs
and errors, polygon models, the Table-1 report (geometry, distances, grids: test_c2m_*.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from c2m_helpers import box_sdf, building_case, dist, winding_number

from mst.eval import c2m
from mst.eval.cloud_io import write_cloud


def test_run_c2m_statistics_match_analytic(tmp_path):
    mesh, P = building_case(tmp_path)
    cloud = tmp_path / "cloud.ply"
    write_cloud(cloud, P)
    cfg = c2m.C2MConfig(signed=True, chunk_points=7000)
    s = c2m.run_c2m(cloud, mesh, cfg, out_cloud=tmp_path / "out.ply").to_json()
    fin = np.isfinite(P).all(1)
    sdf = box_sdf(P[fin])
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
    mesh, P = building_case(tmp_path, n=5000, nonfinite=0)
    cloud = tmp_path / "cloud.xyz"
    write_cloud(cloud, P)
    r = mst("c2m", cloud, mesh, "--json", "--thresholds", "0.05,0.1,0.2", "--markdown", tmp_path / "t.md",
            "--plot", tmp_path / "h.png", "-o", tmp_path / "o.ply")
    s = json.loads(r.stdout)
    d = np.abs(box_sdf(P))
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
    mesh, P = building_case(tmp_path, n=2000, nonfinite=0)
    P = np.vstack([P, [[50, 50, 50], [2, 3, 5.5]]])  # 48+ m away, and 3.5 m above the roof
    cloud = tmp_path / "c.ply"
    write_cloud(cloud, P)
    s = json.loads(mst("c2m", cloud, mesh, "--json", "--max-dist", "1", "-q").stdout)
    d = np.abs(box_sdf(P))
    assert s["points_beyond_max_dist"] == int((d > 1).sum()) >= 2
    assert s["unsigned"]["count"] == int((d <= 1).sum())
    assert s["unsigned"]["max"] == pytest.approx(d[d <= 1].max(), abs=1e-12)
    assert s["thresholds"][-1]["percent"] == pytest.approx(100 * (d < 1).mean(), abs=1e-9)


def test_cli_errors(tmp_path, mst):
    mesh, P = building_case(tmp_path, n=100, nonfinite=0)
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


def test_polygon_models_cao_and_wrl_give_the_same_distances(tmp_path, mst, shared_data):
    """The real teabox model as ViSP .cao and as VRML: triangulated on load, identical C2M results."""
    from mst.meshtools.formats import load_triangles

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
    _, s = dist(idx, P)
    inside = winding_number(P, V, F) > 0.5
    assert inside.sum() > 100 and ((s < 0) == inside).all()


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
