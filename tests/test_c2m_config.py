"""mst c2m's configuration (C2MConfig on mst.core.config) and the pure core ``c2m(points, mesh, cfg)``:
a setting from a config file takes effect, explicit options override it, unknown keys fail naming
the key, the --json "config" block repeats the run, and the array core equals the file runner."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst import ConfigError
from mst.eval import c2m
from mst.eval.cloud_io import write_cloud
from mst.meshtools.formats import save_triangles
from mst.meshtools.generate import box


@pytest.fixture()
def case(tmp_path):
    V, F = box((4.0, 6.0, 2.0), split=2)
    mesh = tmp_path / "box.obj"
    save_triangles(mesh, V, F)
    rng = np.random.default_rng(0)
    P = rng.uniform(-1, 7, (3000, 3))
    cloud = tmp_path / "c.ply"  # binary float64: the file holds exactly P
    write_cloud(cloud, P)
    return cloud, mesh, P, V, F


def test_config_file_sets_thresholds_and_options_override(case, tmp_path, mst):
    cloud, mesh, _, _, _ = case
    cfg = tmp_path / "c2m.yaml"
    cfg.write_text("thresholds_m: [0.05, 0.3]\nsigned: true\n")
    s = json.loads(mst("c2m", cloud, mesh, "--config", cfg, "--json", "-q").stdout)
    assert [t["max_dist"] for t in s["thresholds"]] == [0.05, 0.3]
    assert s["signed"] is not None and s["config"]["signed"] is True
    assert s["config"]["thresholds_m"] == [0.05, 0.3]
    s2 = json.loads(mst("c2m", cloud, mesh, "--config", cfg, "--thresholds", "0.2", "--json", "-q").stdout)
    assert [t["max_dist"] for t in s2["thresholds"]] == [0.2]
    s3 = json.loads(mst("c2m", cloud, mesh, "--config", cfg, "--set", "max_dist_m=0.5", "--json", "-q").stdout)
    assert s3["max_dist"] == 0.5 and s3["points_beyond_max_dist"] > 0


def test_json_config_block_repeats_the_run(case, tmp_path, mst):
    cloud, mesh, _, _, _ = case
    s = json.loads(mst("c2m", cloud, mesh, "--thresholds", "0.1,0.4", "--max-dist", "2", "--json", "-q").stdout)
    (tmp_path / "again.json").write_text(json.dumps(s["config"]))
    s2 = json.loads(mst("c2m", cloud, mesh, "--config", tmp_path / "again.json", "--json", "-q").stdout)
    assert s2["config"] == s["config"]
    assert s2["thresholds"] == s["thresholds"] and s2["unsigned"] == s["unsigned"]


def test_unknown_key_and_bad_values_name_the_key(case, tmp_path, mst):
    cloud, mesh, _, _, _ = case
    bad = tmp_path / "bad.yaml"
    bad.write_text("thresholdz: [0.1]\n")
    r = mst("c2m", cloud, mesh, "--config", bad, check=False)
    assert r.returncode == 1 and "thresholdz" in r.stderr and str(bad) in r.stderr
    r = mst("c2m", cloud, mesh, "--set", "engine=octree", check=False)
    assert r.returncode == 1 and "engine" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    with pytest.raises(ConfigError, match="thresholds_m"):
        c2m.C2MConfig(thresholds_m=())
    with pytest.raises(ConfigError, match="max_dist_m"):
        c2m.C2MConfig(max_dist_m=-1.0)


def test_show_config_lists_the_settings(mst):
    r = mst("c2m", "--show-config")
    assert r.returncode == 0 and "thresholds_m" in r.stdout and "max_dist_m" in r.stdout
    r = mst("eval", "traj", "--show-config")
    assert r.returncode == 0 and "t_max_diff_s" in r.stdout and "csv_columns" in r.stdout


def test_array_core_equals_the_file_runner(case):
    cloud, mesh, P, V, F = case
    cfg = c2m.C2MConfig(signed=True, chunk_points=1000)
    a = c2m.c2m(P, (V, F), cfg)
    b = c2m.run_c2m(cloud, mesh, cfg)
    ja, jb = a.to_json(), b.to_json()
    for k in ("thresholds", "unsigned", "signed", "points_valid", "mesh_triangles", "config"):
        assert ja[k] == jb[k], k
    assert ja["cloud"] is None and jb["cloud"] == str(cloud)
    np.testing.assert_array_equal(a.distances, b.distances)
