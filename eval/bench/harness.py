"""``make bench``: run every stage benchmark, print a table, write a JSON report.

Each benchmark module ``mst.eval.bench.<stage>`` exposes ``run(workdir: Path) -> list[dict]``;
every dict has ``bench`` (a name), and metric keys (``*_s`` seconds, ``*_ms``, ``*_mib``, ``fps``,
``target`` text and ``ok`` bool where a target exists). Whole commands are timed as subprocesses
(``peak_rss_mib`` from ``resource.getrusage(RUSAGE_CHILDREN)`` of a fresh child).
"""

from __future__ import annotations

import argparse
import importlib
import json
import resource
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

STAGES = ["startup", "convert", "c2m", "synth", "track", "slam", "fuse", "nav", "refine", "batch", "c2m_tiles", "uav"]


def timed_command(cmd: list[str], **kw) -> dict:
    """Run ``cmd`` in a fresh Python child; return wall seconds, the child's CPU seconds (user +
    system), its peak RSS (MiB) and the 1-minute load average before the run.

    The child is wrapped so that its own ``ru_maxrss`` is reported (not the max over earlier children).
    On a shared machine the wall time of a run depends on the other processes, its CPU time much less.
    """
    import os

    wrapper = (
        "import resource,subprocess,sys,time,json;t=time.perf_counter();"
        "r=subprocess.run(sys.argv[1:]);w=time.perf_counter()-t;u=resource.getrusage(resource.RUSAGE_CHILDREN);"
        "print(json.dumps({'rc':r.returncode,'wall_s':w,'cpu_s':u.ru_utime+u.ru_stime,"
        "'peak_rss_mib':u.ru_maxrss/1024}),file=sys.stderr)"
    )
    load = os.getloadavg()[0]
    r = subprocess.run([sys.executable, "-c", wrapper, *cmd], capture_output=True, text=True, **kw)
    last = r.stderr.strip().splitlines()[-1]
    out = json.loads(last)
    if out["rc"] != 0:
        raise RuntimeError(f"command failed: {' '.join(cmd)}\n{r.stderr[-3000:]}")
    out["stdout"] = r.stdout
    out["load_avg"] = load
    return out


def mst_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "mst.cli.main", *map(str, args)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench-results.json", help="JSON report path")
    ap.add_argument("--only", nargs="*", default=None, help=f"stages to run (default all: {' '.join(STAGES)})")
    ap.add_argument("--workdir", default=None, help="keep generated inputs here (default: a temp folder)")
    a = ap.parse_args(argv)
    results: list[dict] = []
    failed = []
    with tempfile.TemporaryDirectory(prefix="mst-bench-") as tmp:
        work = Path(a.workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for stage in a.only or STAGES:
            try:
                mod = importlib.import_module(f"mst.eval.bench.{stage}")
            except ModuleNotFoundError:
                print(f"[bench] {stage}: no benchmark module", file=sys.stderr)
                continue
            t0 = time.perf_counter()
            print(f"[bench] {stage} ...", file=sys.stderr, flush=True)
            try:
                rows = mod.run(work / stage)
            except Exception:
                traceback.print_exc()
                failed.append(stage)
                continue
            for r in rows:
                r.setdefault("stage", stage)
                results.append(r)
                print("  " + json.dumps(r), file=sys.stderr, flush=True)
            print(f"[bench] {stage} done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    Path(a.out).write_text(json.dumps({"results": results, "failed": failed,
                                       "maxrss_self_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}, indent=2))
    _print_table(results)
    return 1 if failed else 0


def _print_table(results: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title="mst benchmarks")
    for c in ("stage", "bench", "metrics", "target", "ok"):
        t.add_column(c)
    for r in results:
        metrics = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()
                            if k not in ("stage", "bench", "target", "ok"))
        t.add_row(r["stage"], r.get("bench", ""), metrics, str(r.get("target", "")), str(r.get("ok", "")))
    Console(stderr=False).print(t)


if __name__ == "__main__":
    sys.exit(main())
