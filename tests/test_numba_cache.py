"""numba's on-disk cache of the C2M kernels is written once and then only loaded (issue #14).

Timing-free evidence: the dispatchers' own ``stats`` (signatures loaded from the cache vs compiled
in the process), the cache index files on disk, and ``NUMBA_DEBUG_CACHE=1``'s log of a whole
``mst c2m`` process (``data loaded`` lines, never ``data saved``). The first process may compile
(a fresh checkout: once, 10-30 s); the second must not.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


def _warmup_json() -> dict:
    r = subprocess.run([sys.executable, "-m", "mst.eval.c2m.warmup", "--json", "--no-aot"], capture_output=True, text=True,
                       check=True, timeout=600)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _cached_kernels() -> set[str]:
    """Names of the module-level ``cache=True`` dispatchers of mst.eval.c2m.kernels and
    mst.pipeline.tracking.kernels (prefixed ``tracking.``), mst.meshtools.kernels (``convert.``) and mst.core.klt_kernels (``klt.``) that Python calls (the ``inline="always"``
    helpers are compiled into their callers)."""
    import re

    import numba.core.registry

    from mst.core import klt_kernels
    from mst.eval.c2m import kernels
    from mst.meshtools import kernels as convert_kernels
    from mst.pipeline.tracking import kernels as tracking_kernels

    root = Path(kernels.__file__).resolve().parents[2]
    mods = (kernels, tracking_kernels, convert_kernels, klt_kernels)
    # the Python code outside the kernel modules: a kernel only ever called from other kernels is
    # compiled into them (its dispatcher gets no signature when its caller is loaded from the cache)
    # (the project's own sources: not the tests, not a virtual environment or other hidden folder,
    # whose site-packages made this scan 20 s of the suite)
    mod_files = {Path(m.__file__).resolve() for m in mods}

    def skip(q: str) -> bool:
        return q == "tests" or q.startswith(".") or q in ("build", "dist") or q.endswith(".egg-info")

    files = [p for top in root.iterdir() if not skip(top.name)
             for p in ([top] if top.suffix == ".py" else top.rglob("*.py") if top.is_dir() else [])
             if p.resolve() not in mod_files and not any(skip(q) for q in p.relative_to(root).parts[:-1])]
    others = "\n".join(p.read_text() for p in files)
    out = set()
    for mod, prefix in zip(mods, ("", "tracking.", "convert.", "klt.")):
        for name in dir(mod):
            d = getattr(mod, name)
            if isinstance(d, numba.core.registry.CPUDispatcher) and d.targetoptions.get("inline") != "always":
                assert d._cache.__class__.__name__ == "FunctionCache", f"{name} is not cache=True"
                if re.search(rf"\b{name}\(|import[^\n]*\b{name}\b", others):  # called or imported
                    out.add(prefix + name)
    return out


@pytest.fixture(scope="module")
def cache_written():
    """The first process: this one runs every kernel of the warm-up (compiling and writing the cache
    where it is missing; a subprocess cost ~1.7 s CPU more for the same)."""
    from mst.eval.c2m.warmup import warm_c2m, warm_convert, warm_tracking

    warm_c2m()
    warm_tracking()
    warm_convert()


def test_second_process_loads_every_c2m_and_tracking_kernel_from_the_cache(cache_written):
    second = _warmup_json()["kernels"]
    # the warm-up reaches every kernel mst c2m and the edge tracker call
    assert set(second) == _cached_kernels()
    for name, st in second.items():
        assert st["cache_misses"] == 0, f"{name} recompiled in the second process"
        assert st["cache_hits"] >= 1, name
        stem = "klt_kernels" if name.startswith("klt.") else "kernels"  # the module file's name
        idx = list(Path(st["cache_path"]).glob(f"{stem}.{name.split('.')[-1]}-*.nbi"))
        assert idx, f"no cache index file for {name} in {st['cache_path']}"


def test_mst_c2m_process_only_loads_the_cache(cache_written, tmp_path):
    from mst.meshtools import generate
    from mst.meshtools.formats import save_triangles

    V, F = generate.courtyard()[:2]
    save_triangles(tmp_path / "m.obj", np.asarray(V, float), np.asarray(F))
    P = np.random.default_rng(1).uniform(np.min(V, 0), np.max(V, 0), (500, 3))
    np.savetxt(tmp_path / "c.xyz", P)
    env = dict(os.environ, NUMBA_DEBUG_CACHE="1", MST_AOT="0")  # the JIT path (tests/test_aot.py: the other one)
    r = subprocess.run([sys.executable, "-m", "mst.cli.main", "c2m", str(tmp_path / "c.xyz"), str(tmp_path / "m.obj"),
                        "-q"], capture_output=True, text=True, env=env, timeout=300, check=True)
    log = r.stdout + r.stderr
    assert "[cache] data loaded" in log  # the kernels came from the cache ...
    assert "[cache] data saved" not in log  # ... and nothing was compiled and written
