"""``mst batch`` and ``mst report`` benchmarks: six synthetic sequences (two models x two scenarios
and two option variants, 320x240, 20 frames, with depth, reference mesh and ground truth) through the
whole chain on a LocalCluster of 1 and of 2 workers, the rerun of the finished batch (every stage
fresh: no cluster), and the HTML report of the batch folder. Whole commands, timed as subprocesses.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from mst.eval.bench.harness import mst_cmd, timed_command

SIZE = ["--frames", "20", "--width", "320", "--height", "240", "--aa", "0", "--texture-size", "512", "-q"]


def _campaign(work: Path) -> Path:
    import yaml

    from mst.meshtools.formats import save_model
    from mst.meshtools.generate import l_shape_model

    house = Path(__file__).resolve().parents[2] / "samples" / "building_tin.obj"
    lshape = work / "lshape.obj"
    save_model(lshape, l_shape_model())
    seqs = []
    for model, mname in ((house, "house"), (lshape, "lshape")):
        for scen, extra in (("orbit", []), ("fast", ["--drop", "3"])):
            d = work / f"{mname}-{scen}"
            if not (d / "scene.json").exists():
                subprocess.run(mst_cmd("synth", scen, *extra, "--model", model, "-o", d, *SIZE), check=True)
            seqs.append({"name": d.name, "frames": f"{d.name}/rgb", "model": str(model), "camera": f"{d.name}/camera.json",
                         "clicks": f"{d.name}/clicks.txt", "depth": f"{d.name}/depth", "reference": f"{d.name}/scene.ply",
                         "gt": f"{d.name}/gt.txt"})
    seqs.append({**seqs[0], "name": "house-orbit-edges", "options": {"track": {"slam": "off"}}})
    seqs.append({**seqs[2], "name": "lshape-orbit-voxel5", "options": {"fuse": {"voxel": 0.05}}})
    m = work / "batch.yaml"
    m.write_text(yaml.safe_dump({"defaults": {"fps": 30, "options": {"eval": {"align": "none"}}}, "sequences": seqs},
                                sort_keys=False))
    return m


def run(workdir: Path) -> list[dict]:
    workdir.mkdir(parents=True, exist_ok=True)
    manifest = _campaign(workdir)
    rows = []
    walls = {}
    for n in (1, 2):
        out = workdir / f"out{n}"
        r = timed_command(mst_cmd("batch", manifest, "-o", out, "--workers", n, "-q"))
        walls[n] = r["wall_s"]
        rows.append({"bench": f"batch: 6 sequences 320x240x20, whole chain, {n} local worker(s)", "wall_s": r["wall_s"],
                     "cpu_s": r["cpu_s"], "load_avg": r["load_avg"]})
    rows[-1]["speedup_vs_1"] = walls[1] / walls[2]
    r = timed_command(mst_cmd("batch", manifest, "-o", workdir / "out2", "-q"))
    rows.append({"bench": "batch: rerun of the finished batch (every stage fresh, no cluster)", "wall_s": r["wall_s"],
                 "target": "< 2 s", "ok": r["wall_s"] < 2.0})
    html = workdir / "report.html"
    r = timed_command(mst_cmd("report", workdir / "out2", "-o", html, "-q"))
    rows.append({"bench": "report: the batch folder (6 sequences, overview + sections)", "wall_s": r["wall_s"],
                 "peak_rss_mib": r["peak_rss_mib"], "html_mib": html.stat().st_size / 2**20})
    return rows
