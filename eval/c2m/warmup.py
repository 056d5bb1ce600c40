"""Warm numba's on-disk cache of the C2M and tracking kernels (``make setup`` runs it once after the install).

The kernels of :mod:`mst.eval.c2m.kernels` are ``cache=True``: the first process that calls them
compiles them (10-30 s on 2 cores) and writes the machine code next to the module (``__pycache__``,
or numba's user-wide cache directory when that is read-only, or ``$NUMBA_CACHE_DIR``); every later
process loads it (a few ms per kernel). This module calls every kernel on a tiny input with the
argument types ``mst c2m`` uses (dense grid and binned grid, signed and unsigned, ``--max-dist``,
points far outside the grid), so that the first real ``mst c2m`` does not compile; and the edge
tracker's kernels (:mod:`mst.pipeline.tracking.kernels`: moving edges on 8-bit and float32 images,
with and without a contrast reference, VVS with and without KLT points), so that ``mst track``
does not compile either; and ``convert-model``'s kernels (:mod:`mst.meshtools.kernels`).

``python -m mst.eval.c2m.warmup --json`` prints, per kernel, the signatures loaded from the cache
(``cache_hits``) and compiled in this process (``cache_misses``): a second run must show no misses.

Then the C2M, convert-model, edge-tracker, navigation-filter and initialisation-search kernels
(:data:`AOT_MODULES`) are compiled ahead of time (:mod:`mst.core.aot`, with the signatures the warm-up
gave them) into extension modules that ``mst c2m``, ``mst convert-model``, ``mst track``, ``mst init`` and
``mst nav fuse`` load without importing numba (about 0.45 s less per c2m process, ~0.8 s per track
process); skipped when the extensions of the
current sources exist (``--force-aot`` rebuilds, ``--no-aot`` skips), and left to the JIT path when
no C compiler is available. The warm-up itself always runs the JIT kernels (``MST_AOT=0``).
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
    # a dense grid of few levels: its cells' lists by the coarse-to-fine hierarchy (pairs_d2), not
    # from parent lists (a mesh whose grid has under 8 cells along every axis)
    from mst.eval.c2m.grids import DenseGrid

    DenseGrid(prepare_mesh(V, F, engine="grid"), max_cells=64).nearest(P[10:] - (V.min(0) + V.max(0)) / 2, None)


def warm_tracking() -> None:
    """Run the edge tracker's kernels (moving edges, VVS) with the argument types tracking uses."""
    from mst.core.poses import se3_exp
    from mst.pipeline.tracking.health import sobel_at
    from mst.pipeline.tracking.moving_edges import canonical_normals, reference_contrast, search_edges
    from mst.pipeline.tracking.vvs import solve_pose

    img = np.zeros((60, 80), np.uint8)
    img[:, 40:] = 200
    k = np.arange(12, dtype=np.float64)
    uv = np.column_stack([40.0 + 0.3 * np.sin(k), 8.0 + 4.0 * k])
    normal, midx = canonical_normals(np.tile([1.0, 0.0], (len(k), 1)), 180)
    edge = (k // 4).astype(np.int64)
    sobel_at(img, uv)
    for im in (img, img.astype(np.float32)):  # full resolution (uint8), pyramid levels (float32 after pyrDown)
        ref = reference_contrast(im, uv, normal, midx, 5, 180)
        for r in (None, ref):
            search_edges(im, uv, normal, r, search_range=4, threshold=10.0, mu1=0.5, mu2=0.5, size=5, n_masks=180,
                         n_candidates=2, mask_idx=midx, edge=edge)
    # VVS: a cube's edges seen from 5 m, candidates on the true projection, a perturbed start
    K = np.array([[500.0, 0, 40], [0, 500.0, 30], [0, 0, 1]])
    A = np.array([[-.5, -.5, 0], [.5, -.5, 0], [.5, .5, 0], [-.5, .5, 0]])
    B = np.roll(A, -1, axis=0)
    t = np.linspace(0.1, 0.9, 8)
    X = np.concatenate([A[i] + t[:, None] * (B[i] - A[i]) for i in range(4)])
    e = np.repeat(np.arange(4), len(t))
    T = np.eye(4)
    T[2, 3] = 5.0
    Xc = X @ T[:3, :3].T + T[:3, 3]
    uvX = Xc[:, :2] / Xc[:, 2:3] * 500.0 + [40, 30]
    cand = np.stack([uvX, uvX + 3.0], 1)
    T0 = se3_exp(np.array([0.01, 0, 0, 0, 0.01, 0])) @ T
    for klt in (False, True):
        kw = {"klt_X_model": X[::4], "klt_uv": uvX[::4]} if klt else {}
        solve_pose(T0, K, X, e, A, B, cand, **kw).cov  # noqa: B018 (the cluster-robust covariance's kernels)
    # edge sampling (visibility.visible_samples -> kernels.edge_samples), with and without the LOD rule
    from mst.meshtools.generate import l_shape_model
    from mst.pipeline.tracking.visibility import ModelGeometry, visible_samples

    geom = ModelGeometry.from_model(l_shape_model())
    Tl = np.eye(4)
    Tl[:3, 3] = -geom.vertices.mean(0) + [0.0, 0.0, 4.0 * geom.scale_m]
    for lod in (0.0, 12.0):  # also the face angles, the face areas and the depth buffer's set-up (non-convex)
        S = visible_samples(geom, Tl, K, 80, 60, 4.0, 0.01, None, 80.0, 85.0, lod_min_line_px=lod,
                            lod_min_face_px2=4.0 * lod)
    # the point transform (depth_buffer._mat3: a pose's strided R made contiguous) and the covariance's PSD
    # floor (vvs.VVSResult.cov with enough clusters), so that both are compiled ahead of time too
    from mst.pipeline.tracking.covariance import psd_max
    from mst.pipeline.tracking.depth_buffer import _mat3

    _mat3(geom.vertices, Tl[:3, :3], Tl[:3, 3])
    _mat3(geom.vertices, Tl[:3, :3])
    psd_max(np.eye(6), 2.0 * np.eye(6))
    # the CPU-independent eigen-decomposition (the error budget's covariance tests, mst.pipeline.tracking.exact)
    from mst.pipeline.tracking.exact import eigh

    eigh(np.diag([1.0, 2.0, 3.0]) + 0.1)
    # the health tests and the evidence gradients (EdgeTracker._absolute_health, evidence)
    from mst.pipeline.tracking.kernels import pose_gradients, pose_health

    args = (img, S.X_model, S.A_model, S.B_model, S.edge, Tl, 500.0, 500.0, 40.0, 30.0)
    pose_health(*args, 0.005, 40.0)
    pose_gradients(*args, 40.0, 0.87)
    from mst.pipeline.tracking.kernels import (
        surface_values,  # the evidence's surface values (hidden and convex)
    )

    fv = np.ones(len(geom.faces), np.bool_)
    for use_buf in (True, False):
        surface_values(img, S.X_model, S.edge % len(geom.faces), fv, Tl, 500.0, 500.0, 40.0, 30.0, 0.005,
                       np.zeros((30, 40), np.float32), 0.5, use_buf)
    # render-based edges' contour tests (render_edges.crossing_offsets, contour_side_test) on 8-bit frames
    from mst.pipeline.tracking.render_edges import contour_side_test, crossing_offsets

    n2 = np.array([[1.0, 0.0], [0.0, 1.0]])
    uv2, off2 = np.array([[30.0, 20.0], [40.0, 30.0]]), np.array([[0.5, np.nan], [-1.0, 0.0]])
    crossing_offsets(img, uv2, n2, off2, n2)
    from mst.pipeline.tracking.edgelets import smoothed_gradient  # the inverse-depth gradient of a render

    smoothed_gradient(img[:20, :30].astype(np.float64))
    contour_side_test(img, np.array([[500.0, 0, 40.0], [0, 500.0, 30.0], [0, 0, 1]]), uv2, n2,
                      np.array([[-0.02, -0.02, 1.0], [0.0, 0.0, 1.0]]), off2, n2, img, np.eye(4))
    # the KLT front end (mst.core.klt_kernels: the tracker's and the SLAM's forward-backward LK)
    from mst.core.klt import KltConfig, track_forward_backward

    pts = np.array([[40.0, 20.0], [41.0, 40.0]])
    for win in (5, 11, 7):  # the two compiled window sizes and the generic kernel
        track_forward_backward(img, img, pts, KltConfig(window_px=win, pyramid_levels=1), guess_px=pts)


def warm_convert() -> None:
    """Run ``convert-model``'s kernels (:mod:`mst.meshtools.kernels`): a small building, once wound
    consistently and once with flipped triangles and duplicated vertices (weld, orientation, regions,
    the regrowth queue, outlines)."""
    from mst.meshtools.convert import tin_to_polygons
    from mst.meshtools.generate import gabled_house, uneven_arc

    V, F = (np.asarray(a) for a in gabled_house(split=2)[:2])
    tin_to_polygons(V, F)
    F2 = np.asarray(F, np.int64).copy()
    F2[::3] = F2[::3, ::-1]
    tin_to_polygons(np.concatenate([V, V]), np.where(np.arange(len(F2))[:, None] % 2 == 1, F2 + len(V), F2))
    V, F = (np.asarray(a) for a in uneven_arc()[:2])
    tin_to_polygons(V, F)


def warm_nav_and_autoinit() -> None:
    """Run ``mst nav fuse``'s filter/smoother kernels (:mod:`mst.pipeline.nav.kernels`, both modes, a
    vision gap) and ``mst init --from-nav``'s search kernels (:mod:`mst.pipeline.autoinit_kernels`)
    once, so that their first command (or test) loads them from the cache instead of compiling."""
    from mst.core.camera import Camera
    from mst.core.poses import inv_T, look_at
    from mst.meshtools.generate import l_shape_model
    from mst.pipeline.autoinit import auto_init
    from mst.pipeline.nav.fusion import FusionConfig, fuse_navigation
    from mst.pipeline.nav.log import NavSimConfig, simulate_nav

    t = np.arange(0.0, 20.0, 0.5)
    T = np.stack([look_at(np.array([30.0 * np.cos(0.1 * a), 30.0 * np.sin(0.1 * a), 20.0]), np.zeros(3)) for a in t])
    keep = (t < 8.0) | (t >= 12.0)
    C = np.tile(np.diag([0.05**2] * 3 + [np.radians(0.2) ** 2] * 3), (int(keep.sum()), 1, 1))
    nav = simulate_nav(t, T, NavSimConfig(seed=0)).nav
    for mode in ("smoother", "filter"):
        fuse_navigation(t[keep], T[keep], C, nav, FusionConfig(mode=mode))
    cam = Camera(150.0, 150.0, 79.5, 59.5, 160, 120)
    gray = np.zeros((120, 160), np.uint8)
    gray[30:90, 50:110] = 200
    m = l_shape_model()
    T_mc = look_at(np.array([0.0, -12.0, 6.0]), np.asarray(m.vertices, float).mean(0))
    auto_init(gray, m, cam, inv_T(T_mc))  # a refusal in this blank image is a result too


def kernel_stats() -> dict[str, dict]:
    """Per compiled kernel of :mod:`mst.eval.c2m.kernels`, :mod:`mst.pipeline.tracking.kernels`,
    :mod:`mst.meshtools.kernels` and :mod:`mst.core.klt_kernels`:
    signatures loaded from the cache and compiled in this process, and the cache folder."""
    import numba.core.registry

    from mst.core import klt_kernels
    from mst.eval.c2m import kernels
    from mst.meshtools import kernels as convert_kernels
    from mst.pipeline.tracking import kernels as tracking_kernels

    out = {}
    for mod, prefix in ((kernels, ""), (tracking_kernels, "tracking."), (convert_kernels, "convert."), (klt_kernels, "klt.")):
        for name in dir(mod):
            d = getattr(mod, name)
            if isinstance(d, numba.core.registry.CPUDispatcher) and d.signatures:
                st = d.stats
                out[prefix + name] = {"cache_hits": sum(st.cache_hits.values()),
                                      "cache_misses": sum(st.cache_misses.values()), "cache_path": st.cache_path}
    return out


#: the numba modules compiled ahead of time (their callers go through mst.core.aot.Kernels)
AOT_MODULES = ("mst.eval.c2m.kernels", "mst.meshtools.kernels", "mst.pipeline.tracking.kernels",
               "mst.pipeline.tracking.covariance_kernels", "mst.pipeline.tracking.exact_kernels",
               "mst.pipeline.zbuffer_kernels", "mst.core.klt_kernels", "mst.pipeline.nav.kernels",
               "mst.pipeline.autoinit_kernels")


def build_aot(force: bool = False) -> dict[str, str]:
    """Compile :data:`AOT_MODULES` ahead of time (after the warm-up, in this process); per module
    "built", "current" (already built from this source) or the error that left it to the JIT."""
    import importlib

    from mst.core import aot

    out = {}
    for m in AOT_MODULES:
        if not force and aot.is_current(m) and aot.covers(m):
            out[m] = "current"
            continue
        importlib.import_module(m)
        try:
            aot.build(m)
            out[m] = "built"
        except Exception as e:  # no C compiler, read-only folder, ...: the JIT path stays
            out[m] = f"not built ({type(e).__name__}: {e})"
    return out


def main(argv: list[str] | None = None) -> int:
    import os

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print the per-kernel cache statistics as JSON")
    ap.add_argument("--no-aot", action="store_true", help="do not build the ahead-of-time extensions")
    ap.add_argument("--force-aot", action="store_true", help="rebuild the ahead-of-time extensions")
    a = ap.parse_args(argv)
    os.environ["MST_AOT"] = "0"  # the warm-up runs (and gives signatures to) the JIT kernels
    t0 = time.perf_counter()
    warm_c2m()
    warm_tracking()
    warm_convert()
    warm_nav_and_autoinit()
    stats = kernel_stats()
    dt = time.perf_counter() - t0
    built = {} if a.no_aot else build_aot(a.force_aot)
    if a.json:
        print(json.dumps({"seconds": dt, "kernels": stats, "aot": built}))
    else:
        compiled = sum(s["cache_misses"] for s in stats.values())
        print(f"mst warm-up: {len(stats)} C2M, tracking and convert kernels ready in {dt:.1f} s ({compiled} compiled now, "
              f"the rest loaded from the cache)", file=sys.stderr)
        for m, st in built.items():
            print(f"mst warm-up: {m} ahead of time: {st}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
