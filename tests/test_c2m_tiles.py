"""Tiled C2M on dask (mst.eval.c2m.tiles): LAS tiles in point ranges on a LocalCluster of 2 workers give
the single-process statistics bit for bit (count, mean, std, RMS, min, max, Table 1), the median within
its stated bound, and the same numbers without a cluster; ``mst c2m --workers/--scheduler`` runs the same
engine on one large binary PLY or many tiles, writes a distance cloud per file, and refuses bad input
with one line and nothing written."""

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
    from mst.eval.cloud_io import write_cloud

    write_cloud(d / "all.ply", laspy_xyz(d / "all.las"))  # the LAS points (quantised), binary PLY
    return d, paths


def laspy_xyz(path):
    import laspy

    las = laspy.read(path)
    return np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)


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


EXACT = ("count", "mean", "std", "rms", "min", "max")


def test_c2m_workers_equal_the_single_process_command(tiles, tmp_path):
    """`mst c2m --workers 2` on one binary PLY (cut into point ranges) and on the LAZ tiles: the exact fields
    bit-identical to `mst c2m` of the same points, the median within the stated bound (half a histogram
    bin) and exact with --exact-median; the PLY written per file equals `mst c2m -o` byte for byte."""
    import json

    from conftest import run_mst

    d, paths = tiles
    common = ["--chunk", "1000", "--thresholds", "0.05,0.2,0.5", "--json", "-q"]
    single = json.loads(run_mst("c2m", d / "all.ply", d / "box.obj", *common, "-o", tmp_path / "one.ply").stdout)
    out = tmp_path / "tiles"
    out.mkdir()
    with fast_local_workers():
        ply = json.loads(run_mst("c2m", d / "all.ply", d / "box.obj", *common, "--workers", "2",
                                 "--chunks-per-task", "3").stdout)
        laz = json.loads(run_mst("c2m", *paths, d / "box.obj", *common, "--workers", "2", "--exact-median",
                                 "--output-dir", out).stdout)
    from mst.eval.c2m.tiles import c2m_tiles  # the same engine in this process (no cluster to start)

    cfg = C2MConfig(chunk_points=1000, thresholds_m=(0.05, 0.2, 0.5))
    whole = c2m_tiles([d / "all.ply"], d / "box.obj", cfg, out_dir=out).to_json()
    assert ply["tasks"] == 9 and ply["config"] == single["config"] and ply["dask"]["workers"] == 2
    for r in (ply, laz, whole):
        assert r["thresholds"] == single["thresholds"]
        assert all(r["unsigned"][k] == single["unsigned"][k] for k in EXACT)
        assert (r["points_total"], r["points_valid"], r["mesh_triangles"]) == \
               (single["points_total"], single["points_valid"], single["mesh_triangles"])
    assert abs(ply["unsigned"]["median"] - single["unsigned"]["median"]) <= ply["median_bound_m"]
    assert laz["unsigned"]["median"] == single["unsigned"]["median"] and laz["median_bound_m"] == 0
    assert len(ply["workers"]) == 2 and all(w["cpu_s"] > 0 and w["peak_rss_mib"] > 0 for w in ply["workers"])
    assert sorted(p.name for p in out.iterdir()) == ["all_c2m.ply", "tile0_c2m.laz", "tile1_c2m.laz", "tile2_c2m.laz"]
    assert (out / "all_c2m.ply").read_bytes() == (tmp_path / "one.ply").read_bytes()


def test_c2m_distributed_bad_input_one_line_nothing_written(tiles, tmp_path):
    import socket

    from conftest import run_mst

    d, _ = tiles
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    md = tmp_path / "t.md"
    cases = [(["--scheduler", f"tcp://127.0.0.1:{port}", "--markdown", md], "cannot reach the dask scheduler"),
             (["--workers", "0", "--markdown", md], "'--workers': 0 is not in the range"),
             (["--workers", "1", "-o", tmp_path / "x.ply"], "-o needs the distances in one process"),
             (["--workers", "1", "--signed", "--markdown", md], "unsigned distances only"),
             (["--output-dir", tmp_path, "--markdown", md], "--output-dir is an option of a distributed run"),
             (["--workers", "1", "--output-dir", tmp_path / "nope"], "output folder does not exist")]
    for extra, msg in cases:
        r = run_mst("c2m", d / "all.ply", d / "box.obj", *extra, check=False)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 1 and len(lines) == 1 and msg in lines[0], (extra, r.stderr)
    assert list(tmp_path.iterdir()) == []
    r = run_mst("c2m", d, d / "box.obj", check=False)  # a folder without --workers: as before, a usage error
    assert r.returncode == 1 and "CLOUD" in r.stderr


@pytest.mark.slow
def test_c2m_on_a_real_scheduler_and_workers_as_processes(tiles):
    """`dask scheduler` and `dask worker --nworkers 2` as separate processes: `mst c2m --scheduler` gives the
    single-process statistics (exact fields bit-identical, the median within its bound)."""
    import json
    import os
    import socket
    import subprocess
    import sys

    from conftest import run_mst

    d, paths = tiles
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    addr = f"tcp://127.0.0.1:{port}"
    common = ["--chunk", "1000", "--thresholds", "0.05,0.2,0.5", "--json", "-q"]
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port",
                               str(port), "--dashboard-address", ":0"], env=dict(os.environ),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "1",
                                       "--nworkers", "2", "--no-dashboard"], env=dict(os.environ),
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=d))
        from dask.distributed import Client

        with Client(addr, timeout=60) as c:
            c.wait_for_workers(2, timeout=60)
        res = json.loads(run_mst("c2m", *paths, d / "box.obj", *common, "--scheduler", addr).stdout)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)
    single = json.loads(run_mst("c2m", d / "all.las", d / "box.obj", *common).stdout)
    assert res["scheduler"] == addr and len(res["workers"]) == 2 and res["thresholds"] == single["thresholds"]
    assert all(res["unsigned"][k] == single["unsigned"][k] for k in EXACT)
    assert abs(res["unsigned"]["median"] - single["unsigned"]["median"]) <= res["median_bound_m"]
