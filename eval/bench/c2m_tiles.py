"""Tiled C2M benchmark (``mst c2m-tiles``): a generated cloud in LAZ tiles of 5M points (default 20M
points; ``MST_BENCH_TILES_POINTS=100000000`` for the issue's 100M) against the 640-triangle building,
on a LocalCluster of 1 and of 2 workers (one thread each): wall time of the command, time of the tasks
(planning to reduced statistics, without the cluster's start) and throughput, the largest process's peak RSS, and
whether the two runs' statistics are identical (they must be: the reduction order is fixed).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from mst.eval.bench.c2m import building_mesh, sample_surface
from mst.eval.bench.harness import mst_cmd, timed_command

TILE = 5_000_000


def _tiles(work: Path, n: int) -> list[Path]:
    import laspy

    from mst.meshtools.formats import save_triangles

    V, F = building_mesh()
    save_triangles(work / "building.obj", V, F)
    paths = []
    for i, start in enumerate(range(0, n, TILE)):
        p = work / f"tile{i:03d}.laz"
        paths.append(p)
        if p.exists():
            continue
        P = sample_surface(V, F, min(TILE, n - start), 0.05, 0.02, seed=100 + i)
        h = laspy.LasHeader(point_format=3, version="1.2")
        h.scales, h.offsets = np.array([1e-4] * 3), np.floor(V.min(0))
        las = laspy.LasData(h)
        las.x, las.y, las.z = P[:, 0], P[:, 1], P[:, 2]
        las.write(str(p))
    return paths


def run(workdir: Path) -> list[dict]:
    workdir.mkdir(parents=True, exist_ok=True)
    n = int(os.environ.get("MST_BENCH_TILES_POINTS", 20_000_000))
    _tiles(workdir, n)
    rows, stats = [], {}
    for w in (1, 2):
        r = timed_command(mst_cmd("c2m-tiles", workdir / "building.obj", workdir, "--workers", w, "--json", "-q"))
        s = json.loads(r["stdout"])
        stats[w] = {k: s[k] for k in ("thresholds", "unsigned", "points_valid")}
        rows.append({"bench": f"c2m-tiles: {n / 1e6:g}M points in LAZ tiles vs 640-triangle building, {w} worker(s)",
                     "wall_s": r["wall_s"], "tasks_s": s["elapsed_s"], "mpoints_per_s": n / s["elapsed_s"] / 1e6,
                     "peak_rss_mib": r["peak_rss_mib"], "load_avg": r["load_avg"],
                     "target": "peak RSS per worker <= 1.5 GB", "ok": r["peak_rss_mib"] <= 1536})
    rows[-1]["speedup_vs_1"] = rows[0]["tasks_s"] / rows[1]["tasks_s"]  # the tasks, without the cluster's start
    rows[-1]["stats_identical_to_1_worker"] = stats[1] == stats[2]
    return rows
