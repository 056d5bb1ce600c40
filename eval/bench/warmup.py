"""Warm numba's on-disk cache of the C2M kernels (``make setup`` runs it once after the install).

The kernels of :mod:`mst.eval.c2m.kernels` are ``cache=True``: the first process that calls them
compiles them (10-30 s on 2 cores) and writes the machine code next to the module (``__pycache__``,
or numba's user-wide cache directory when that is read-only, or ``$NUMBA_CACHE_DIR``); every later
process loads it (a few ms per kernel). This module calls every kernel on a tiny input with the
argument types ``mst c2m`` uses (dense grid and binned grid, signed and unsigned, ``--max-dist``,
points far outside the grid), so that the first real ``mst c2m`` does not compile.

``python -m mst.eval.bench.warmup --json`` prints, per kernel, the signatures loaded from the cache
(``cache_hits``) and compiled in this process (``cache_misses``): a second run must show no misses.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def warm_c2m() -> None:
    """Run the C2M grid engine (both search structures) on tiny inputs."""
    from mst.eval.c2m.config import C2MConfig
    from mst.eval.c2m.driver import c2m
    from mst.eval.c2m.geometry import prepare_mesh
    from mst.meshtools.generate import courtyard

    V, F = (np.asarray(a) for a in courtyard()[:2])
    rng = np.random.default_rng(0)
    P = rng.uniform(V.min(0) - 1, V.max(0) + 1, (3000, 3))
    P[:10] += 1e5  # far outside the grid: the far-point paths
    for small in (5000, 0):  # dense grid (lazy cells), binned grid (shell search)
        for signed in (False, True):
            for md in (None, 0.5):
                idx = prepare_mesh(V, F, signed=signed, engine="grid", small_mesh_triangles=small)
                c2m(P, idx, C2MConfig(signed=signed, max_dist_m=md))


def kernel_stats() -> dict[str, dict]:
    """Per compiled kernel of :mod:`mst.eval.c2m.kernels`: signatures loaded from the cache and
    compiled in this process, and the cache folder."""
    import numba.core.registry

    from mst.eval.c2m import kernels

    out = {}
    for name in dir(kernels):
        d = getattr(kernels, name)
        if isinstance(d, numba.core.registry.CPUDispatcher) and d.signatures:
            st = d.stats
            out[name] = {"cache_hits": sum(st.cache_hits.values()), "cache_misses": sum(st.cache_misses.values()),
                         "cache_path": st.cache_path}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print the per-kernel cache statistics as JSON")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    warm_c2m()
    stats = kernel_stats()
    dt = time.perf_counter() - t0
    if a.json:
        print(json.dumps({"seconds": dt, "kernels": stats}))
    else:
        compiled = sum(s["cache_misses"] for s in stats.values())
        print(f"mst warm-up: {len(stats)} C2M kernels ready in {dt:.1f} s ({compiled} compiled now, "
              f"the rest loaded from the cache)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
