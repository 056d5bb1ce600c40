"""Benchmark of ``mst synth``: 640x480 colour + depth rendering speed and memory.

Rows:

Wall times on a shared machine vary with its load (each row reports the 1-minute ``load_avg``);
``cpu_ms_per_frame`` (process CPU time) of the one-thread row is the steadier single-core figure.
The numba kernels are compiled (or loaded from their on-disk cache) by a warm-up render first.

* ``render_640x480_1thread``: in-process :class:`~mst.pipeline.render.ShadedRenderer` on the orbit
  scene of the bundled sample house, one ray-casting thread: ms per colour+depth frame (edge
  anti-aliasing on, 16 rays per edge pixel, the CLI default), with ``cast_ms`` the time Embree takes
  to cast one ray per pixel (for scale); target <= 50 ms per frame on one core.
* ``render_640x480_1thread_aa8``: the same with 8 sub-pixel rays per edge pixel (``--aa 8``), and
  ``edge_mad_vs_aa16``: mean absolute difference (8-bit levels) of its edge pixels from the 16-ray ones.
* ``render_640x480_all_threads``: the same (16 rays) with all cores.
* ``synth_orbit_60``: the whole command ``mst synth orbit --frames 60 --depth`` on the sample
  (PNG/NPY writing, texture generation included): frames per second and peak RSS.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from mst.eval.bench.harness import mst_cmd, timed_command

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "samples" / "building_tin.obj"


def _render_rows() -> list[dict]:
    import cv2

    from mst.core.poses import inv_T
    from mst.pipeline.synth import SynthConfig, build_scene, load_model_triangles

    V, F = load_model_triangles(SAMPLE)
    rows = []
    n_cv = cv2.getNumThreads()
    for nthreads, aa, name in ((1, 16, "render_640x480_1thread"), (1, 8, "render_640x480_1thread_aa8"),
                               (0, 16, "render_640x480_all_threads")):
        cv2.setNumThreads(1 if nthreads == 1 else n_cv)  # OpenCV's remap is multi-threaded too
        cfg = SynthConfig(nthreads=nthreads)
        cam, R_cm, scene, renderer, _ = build_scene("orbit", cfg, V, F)
        poses = [inv_T(scene.pose(k / 30.0)) for k in range(20)]
        renderer.render(cam, poses[0])  # warm-up (BVH, caches)
        t_tot, t_cpu, t_cast, edge_px, mad = [], [], [], [], []
        for T in poses:
            t0, c0 = time.perf_counter(), time.process_time()
            out = renderer.render(cam, T, aa_samples=aa)
            t_tot.append(time.perf_counter() - t0)
            t_cpu.append(time.process_time() - c0)
            edge_px.append(out["n_edge_px"])
            if aa != 16:
                ref = renderer.render(cam, T, aa_samples=16)["rgb"]
                e = out["edges"]
                mad.append(255.0 * float(np.abs(out["rgb"][e] - ref[e]).mean()) if e.any() else 0.0)
            x, y, _ = renderer.camera_dirs(cam)
            o, d = renderer.rays_for(T, x, y)
            t1 = time.perf_counter()
            renderer.cast(o, d)
            t_cast.append(time.perf_counter() - t1)
        ms = 1000 * float(np.median(t_tot))
        row = {"bench": name, "ms_per_frame": ms, "fps": 1000.0 / ms, "cpu_ms_per_frame": 1000 * float(np.median(t_cpu)),
               "cast_ms": 1000 * float(np.median(t_cast)), "edge_px": int(np.median(edge_px)),
               "load_avg": round(os.getloadavg()[0], 2)}
        if mad:
            row["edge_mad_vs_aa16"] = float(np.mean(mad))
        if nthreads == 1 and aa == 16:
            row.update(target="<= 50 ms per 640x480 colour+depth frame on one core", ok=ms <= 50.0)
        rows.append(row)
    cv2.setNumThreads(n_cv)
    return rows


def run(workdir: Path) -> list[dict]:
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    rows = _render_rows()
    out = workdir / "orbit60"
    r = timed_command(mst_cmd("synth", "orbit", "--model", SAMPLE, "-o", out, "--frames", "60", "--depth",
                              "--overwrite", "-q"))
    rows.append({"bench": "synth_orbit_60_640x480", "wall_s": r["wall_s"], "fps": 60 / r["wall_s"],
                 "ms_per_frame": 1000 * r["wall_s"] / 60, "peak_rss_mib": r["peak_rss_mib"],
                 "load_avg": round(os.getloadavg()[0], 2)})
    return rows


if __name__ == "__main__":
    import json
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for row in run(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tmp)):
            print(json.dumps(row))
