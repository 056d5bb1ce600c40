"""Start-up: the whole-process time of each command on a small input (issue #14), best of three.

What a user waits for on a small job is mostly the process start (interpreter, numpy, numba and
its cached kernels, OpenCV, ...), not the work. Each row is one fresh ``mst`` process timed by
:func:`~mst.eval.bench.harness.timed_command` (wall, CPU, peak RSS), with the 1-minute load
average. For ``mst track`` of the 39 teabox frames the row also gives the per-frame median from the
command's ``--json`` and the rest of the wall time (``overhead_s`` = wall - frames x median: start-up,
decoding, initialisation, writing). Rows whose input is absent (the shared teabox data) are skipped.
The ``mst c2m``, ``convert-model`` and ``track`` rows say which kernels ran (ahead of time,
:mod:`mst.core.aot`, or numba's JIT) and, with the extensions built, give the same command on the JIT
(``MST_AOT=0``): ``jit_*`` and ``saved_cpu_s`` / ``saved_wall_s``.

Run alone: ``python -m mst.eval.bench.startup [WORKDIR]``.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"


def _best(cmd: list, repeats: int = 3, env: dict | None = None) -> dict:
    from mst.eval.bench.harness import timed_command

    kw = {} if env is None else {"env": env}
    runs = [timed_command([str(c) for c in cmd], **kw) for _ in range(repeats)]
    best = min(runs, key=lambda r: r["wall_s"])
    best["walls_s"] = [round(r["wall_s"], 3) for r in runs]
    return best


def _row(name: str, r: dict, **extra) -> dict:
    return {"bench": name, "wall_s": round(r["wall_s"], 3), "runs_s": r["walls_s"], "cpu_s": round(r["cpu_s"], 3),
            "peak_rss_mib": round(r["peak_rss_mib"], 1), "load_avg_1min": round(r["load_avg"], 2), **extra}


def run(workdir: Path) -> list[dict]:
    from mst.eval.bench.harness import mst_cmd
    from mst.meshtools import generate
    from mst.meshtools.formats import save_triangles

    w = Path(workdir)
    w.mkdir(parents=True, exist_ok=True)
    rows = [_row("mst --help (start-up only)", _best(mst_cmd("--help")))]
    V, F = (np.asarray(a) for a in generate.courtyard()[:2])
    save_triangles(w / "courtyard.obj", V.astype(float), F)
    np.savetxt(w / "cloud500.xyz", np.random.default_rng(0).uniform(V.min(0), V.max(0), (500, 3)))
    from mst.core.aot import is_current

    c2m = mst_cmd("c2m", w / "cloud500.xyz", w / "courtyard.obj", "-o", w / "c2m_out.ply", "-q")
    conv = mst_cmd("convert-model", ROOT / "samples" / "building_tin.obj", "-o", w / "b.wrl", "-q")
    for label, cmd, mod in ((f"mst c2m, 500 points vs {len(F)} triangles", c2m, "mst.eval.c2m.kernels"),
                            ("mst convert-model samples/building_tin.obj", conv, "mst.meshtools.kernels")):
        aot = is_current(mod)
        r = _row(label, _best(cmd), kernels="ahead-of-time" if aot else "numba JIT")
        if aot:  # the same on numba's JIT kernels (its import and cache load: the start-up AOT removes)
            j = _best(cmd, env=dict(os.environ, MST_AOT="0"))
            r.update(jit_wall_s=round(j["wall_s"], 3), jit_cpu_s=round(j["cpu_s"], 3),
                     saved_cpu_s=round(j["cpu_s"] - r["cpu_s"], 3))
        rows.append(r)
    tb = SHARED / "visp-teabox"
    if not tb.is_dir():
        print(f"[bench startup] shared data absent ({tb}): init/track rows skipped", file=sys.stderr)
        return rows
    model, cam = tb / "teabox.cao", tb / "teabox.xml"
    pose0 = w / "pose0.txt"
    rows.append(_row("mst init (teabox clicks)", _best(mst_cmd(
        "init", "--model", model, "--camera", cam, "--clicks", tb / "teabox.clicks", "--points", tb / "teabox.init",
        "-o", pose0, "-q"))))
    from mst.pipeline.tracking.compiled import MODULES

    track_aot = all(is_current(m) for m in (*MODULES, "mst.core.klt_kernels"))
    for label, extra in (("default mode", ()), ("--slam off (edges)", ("--slam", "off"))):
        cmd = mst_cmd("track", tb / "teabox.mp4", "--model", model, "--camera", cam, "--init", pose0,
                      "-o", w / "traj.txt", "--json", "-q", *extra)
        r = _best(cmd)
        s = json.loads(r["stdout"])
        med = float(s["median_ms"])
        row = _row(f"mst track teabox.mp4 {label}, {s['frames']} frames", r, frames=s["frames"],
                   median_ms=round(med, 2), overhead_s=round(r["wall_s"] - s["frames"] * med / 1e3, 3),
                   kernels="ahead-of-time" if track_aot else "numba JIT")
        if track_aot:  # the same on numba's JIT kernels (session 20 moved the tracker's kernels ahead of time)
            j = _best(cmd, env=dict(os.environ, MST_AOT="0"))
            sj = json.loads(j["stdout"])
            row.update(jit_wall_s=round(j["wall_s"], 3), jit_cpu_s=round(j["cpu_s"], 3), jit_median_ms=round(
                float(sj["median_ms"]), 2), saved_wall_s=round(j["wall_s"] - r["wall_s"], 3))
        rows.append(row)
    return rows


if __name__ == "__main__":
    for row in run(Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/mst-bench-startup")):
        print(json.dumps(row))
