"""Tiled C2M on dask (mst.eval.c2m.tiles): LAS tiles in point ranges on a LocalCluster of 2 workers give
the single-process statistics bit for bit (count, mean, std, RMS, min, max, Table 1), the median within
its stated bound, and the same numbers without a cluster."""

from __future__ import annotations

import numpy as np
import pytest
from dask_helpers import fast_local_workers

from mst.eval.c2m.config import C2MConfig

BOXV = np.array([[-1, -0.75, 0], [1, -0.75, 0], [1, 0.75, 0], [-1, 0.75, 0],
                 [-1, -0.75, 1.2], [1, -0.75, 1.2], [1, 0.75, 1.2], [-1, 0.75, 1.2]], float)
BOXF = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                 [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def _las(path, xyz):
    import laspy

    h = laspy.LasHeader(point_format=3, version="1.2")
    h.scales = np.array([1e-4, 1e-4, 1e-4])
    h.offsets = np.array([0.0, 0.0, 0.0])
    las = laspy.LasData(h)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(str(path))


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    from mst.meshtools.formats import save_triangles

    d = tmp_path_factory.mktemp("tiles")
    save_triangles(d / "box.obj", BOXV, BOXF)
    rng = np.random.default_rng(3)
    P = rng.uniform([-2, -2, -0.5], [2, 2, 2], (25_000, 3))
    sizes = [12_000, 5_000, 8_000]  # multiples of chunk_points: the concatenation has the same chunks
    paths, k = [], 0
    for i, n in enumerate(sizes):
        paths.append(d / f"tile{i}.laz")
        _las(paths[-1], P[k:k + n])
        k += n
    _las(d / "all.las", P)
    return d, paths


def test_tiles_on_two_workers_equal_the_single_process_run(tiles):
    from dask.distributed import Client, LocalCluster

    from mst.eval.c2m.runner import run_c2m
    from mst.eval.c2m.tiles import c2m_tiles

    d, paths = tiles
    cfg = C2MConfig(chunk_points=1000, thresholds_m=(0.05, 0.2, 0.5))
    single = run_c2m(d / "all.las", d / "box.obj", cfg).to_json()
    local = c2m_tiles(paths, d / "box.obj", cfg, chunks_per_task=3).to_json()
    with fast_local_workers(), LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                            dashboard_address=None) as lc, Client(lc) as client:
        dist = c2m_tiles(paths, d / "box.obj", cfg, client=client, chunks_per_task=3).to_json()
    assert dist["tasks"] == 4 + 2 + 3
    for r in (local, dist):
        assert r["thresholds"] == single["thresholds"]
        for k in ("count", "mean", "std", "rms", "min", "max"):
            assert r["unsigned"][k] == single["unsigned"][k], k
        assert (r["points_total"], r["points_valid"]) == (single["points_total"], single["points_valid"])
        assert abs(r["unsigned"]["median"] - single["unsigned"]["median"]) <= r["median_bound_m"] + 1e-12
    assert dist["unsigned"] == local["unsigned"]
    exact = c2m_tiles(paths, d / "box.obj", cfg, chunks_per_task=3, exact_median=True).to_json()
    assert exact["unsigned"] == single["unsigned"] and exact["median"] == "exact (second pass)"


def test_c2m_tiles_command(tiles):
    import json

    from conftest import run_mst

    d, paths = tiles
    with fast_local_workers():
        r = run_mst("c2m-tiles", d / "box.obj", d / "tile*.laz", "--chunk", "1000", "--thresholds", "0.05,0.2,0.5",
                    "--workers", "1", "--json", "-q")
    res = json.loads(r.stdout)
    assert res["files"] == [str(p) for p in paths] and res["points_valid"] == 25_000
    assert res["config"]["thresholds_m"] == [0.05, 0.2, 0.5] and res["median"] == "histogram"
    bad = run_mst("c2m-tiles", d / "box.obj", d / "nope.laz", check=False)
    assert bad.returncode == 1 and "nope.laz: cloud file does not exist" in bad.stderr


def test_distance_tiles_written_with_every_dimension_and_the_distance(tiles, tmp_path):
    import laspy

    from mst.eval.c2m.distances import point_distances
    from mst.eval.c2m.runner import load_mesh_index, run_c2m
    from mst.eval.c2m.tiles import c2m_tiles

    d, paths = tiles
    cfg = C2MConfig(chunk_points=1000, thresholds_m=(0.05, 0.2, 0.5))
    res = c2m_tiles(paths, d / "box.obj", cfg, out_dir=tmp_path).to_json()
    assert res["unsigned"]["mean"] == run_c2m(d / "all.las", d / "box.obj", cfg).unsigned.mean
    for p in paths:
        out = laspy.read(tmp_path / f"{p.stem}_c2m.laz")
        src = laspy.read(p)
        assert np.array_equal(out.X, src.X) and np.array_equal(out.Z, src.Z)
        idx = load_mesh_index(d / "box.obj", cfg)
        xyz = np.stack([np.asarray(src.x), np.asarray(src.y), np.asarray(src.z)], axis=1)
        ref, _ = point_distances(idx, xyz - idx.shift)  # every point, in file order
        assert np.array_equal(np.asarray(out["C2M_absolute_distances"]), ref)
