"""Side-by-side rows: mst against a reference tool measured in the same bench run, on the same
machine and the same inputs (issue #14): CloudCompare 2.11's C2M (``CloudCompare -SILENT``, the
Debian package ``cloudcompare``) for ``mst c2m``.

Both tools are timed as whole processes (start-up, reading, distances, writing the output cloud),
best of ``repeats`` runs each, interleaved (mst, reference, mst, ...) so that a change of the
machine's load hits both alike. Rows give both times, their ratio, points per second of each whole
process, and the 1-minute load average before the first run. Where the ahead-of-time kernels are
built (:mod:`mst.core.aot`), the same mst command also runs on numba's JIT kernels (``MST_AOT=0``,
the engine before them) in the same interleaving: ``mst_jit_*`` and ``ratio_jit_vs_cloudcompare``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from statistics import median


def cloudcompare() -> str | None:
    """Path of the CloudCompare executable (None: not installed; the rows then quote targets)."""
    return shutil.which(os.environ.get("CLOUDCOMPARE", "CloudCompare"))


def cloudcompare_c2m_cmd(exe: str, cloud: Path, mesh: Path, out: Path) -> list[str]:
    """CloudCompare's command-line C2M of ``cloud`` against ``mesh``, the cloud with its distance
    field saved to ``out`` (binary PLY; mst writes its output cloud too)."""
    return [exe, "-SILENT", "-AUTO_SAVE", "OFF", "-C_EXPORT_FMT", "PLY", "-O", str(cloud), "-O", str(mesh),
            "-C2M_DIST", "-SAVE_CLOUDS", "FILE", str(out)]


def best_of(cmds: dict[str, list[str]], repeats: int = 3, env: dict[str, dict] | None = None) -> dict[str, dict]:
    """Run every command of ``cmds`` ``repeats`` times, interleaved; per name the run with the
    smallest wall time (``timed_command``'s dict) plus ``walls_s`` and ``cpus_s`` (all runs) and
    ``load_avg_first``."""
    from mst.eval.bench.harness import timed_command

    best: dict[str, dict] = {}
    walls: dict[str, list[float]] = {k: [] for k in cmds}
    cpus: dict[str, list[float]] = {k: [] for k in cmds}
    load0 = os.getloadavg()[0]
    for _ in range(repeats):
        for name, cmd in cmds.items():
            kw = {"env": env[name]} if env and name in env else {}
            r = timed_command(cmd, **kw)
            walls[name].append(round(r["wall_s"], 3))
            cpus[name].append(round(r["cpu_s"], 3))
            if name not in best or r["wall_s"] < best[name]["wall_s"]:
                best[name] = r
    for name, r in best.items():
        r["walls_s"] = walls[name]
        r["cpus_s"] = cpus[name]
        r["load_avg_first"] = load0
    return best


def c2m_side_by_side(mst_cmd: list[str], cloud: Path, mesh: Path, out_dir: Path, points: int, repeats: int = 5,
                     target_ratio: float = 0.5, mst_env: dict | None = None) -> dict | None:
    """Whole-process times of ``mst_cmd`` (an ``mst c2m`` command, run with ``mst_env``) and
    CloudCompare's C2M on the same files, best of ``repeats``; None when CloudCompare is absent.
    ``ok``: mst <= ``target_ratio`` x CC."""
    exe = cloudcompare()
    if exe is None:
        return None
    cc_out = Path(out_dir) / f"{Path(cloud).stem}_cc_out.ply"
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")  # no display needed
    cmds = {"mst": mst_cmd, "cc": cloudcompare_c2m_cmd(exe, cloud, mesh, cc_out)}
    envs = {"cc": env, "mst": dict(mst_env or os.environ)}
    from mst.core.aot import is_current

    if is_current("mst.eval.c2m.kernels"):  # the same command on numba's JIT kernels (before issue #14's AOT)
        jit_out = Path(out_dir) / f"{Path(cloud).stem}_jit_out.ply"
        cmds["mst_jit"] = [str(jit_out) if str(a).endswith("_out.ply") else a for a in mst_cmd]
        envs["mst_jit"] = dict(mst_env or os.environ, MST_AOT="0")
    runs = best_of(cmds, repeats, env=envs)
    cc_out.unlink(missing_ok=True)
    m, c = runs["mst"], runs["cc"]
    ratio = m["wall_s"] / c["wall_s"]
    jit = {}
    if "mst_jit" in runs:
        j = runs["mst_jit"]
        jit_out.unlink(missing_ok=True)
        jit = {"mst_jit_best_s": round(j["wall_s"], 3), "mst_jit_runs_s": j["walls_s"], "mst_jit_cpu_s": round(j["cpu_s"], 3),
               "ratio_jit_vs_cloudcompare": round(j["wall_s"] / c["wall_s"], 3)}
    return {"mst_best_s": round(m["wall_s"], 3), "mst_runs_s": m["walls_s"], "mst_cpu_s": round(m["cpu_s"], 3),
            "kernels": "ahead-of-time" if jit else "numba JIT", **jit,
            "ratio_cpu_vs_cloudcompare": round(m["cpu_s"] / c["cpu_s"], 3),
            "mst_cpu_runs_s": m["cpus_s"], "cloudcompare_cpu_runs_s": c["cpus_s"],
            # CPU seconds depend less on the other processes than wall times: the medians' ratio
            "ratio_cpu_median_vs_cloudcompare": round(median(m["cpus_s"]) / median(c["cpus_s"]), 3),
            "mst_peak_rss_mib": round(m["peak_rss_mib"], 1),
            "cloudcompare_best_s": round(c["wall_s"], 3), "cloudcompare_runs_s": c["walls_s"],
            "cloudcompare_cpu_s": round(c["cpu_s"], 3), "cloudcompare_peak_rss_mib": round(c["peak_rss_mib"], 1),
            "ratio_vs_cloudcompare": round(ratio, 3),
            "mst_points_per_s_whole": round(points / m["wall_s"]), "cloudcompare_points_per_s_whole": round(points / c["wall_s"]),
            "load_avg_1min": round(m["load_avg_first"], 2), "stdout": m["stdout"],
            "target": f"whole process <= {target_ratio:g} x CloudCompare 2.11 (same run, best of {repeats})",
            "ok": bool(ratio <= target_ratio)}
