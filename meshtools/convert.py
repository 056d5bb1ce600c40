"""TIN -> polygon model: the ``mst convert-model`` stage.

Algorithm (all vectorised with numpy/scipy except the fallback queue and pinch vertices):

1. **Weld** vertices closer than ``weld_tol_m`` metres (KD-tree pairs + connected components; each
   cluster keeps its lowest-index vertex, coordinates unchanged). **Drop** triangles that become
   degenerate: repeated vertex or zero area (area <= ``1e-12 * scale^2``); they are counted.
2. **Edges**: half-edges grouped by undirected key. An edge with 2 triangles is manifold; 1 = border;
   3+ = non-manifold (counted; no region grows and no orientation propagates across it).
3. **Orientation**: triangles across manifold edges are made consistent (BFS tree over the face
   graph, parities resolved by pointer jumping). Then per connected component: a *closed* component
   (every edge manifold) is flipped if its signed volume is negative, so normals point out; an *open*
   component (a terrain, a facade) keeps the orientation of the majority (by area) of its input
   triangles.
4. **Regions**: a triangle joins a region only if its unit normal is within ``angle_tol/2`` of the
   region normal and its 3 vertices are within ``dist_tol_m`` of the region plane; regions grow over
   manifold edges whose dihedral angle is <= ``angle_tol``. So any two triangles of a region differ
   by at most ``angle_tol`` and every crease edge (dihedral > ``angle_tol``) lies on a region
   boundary. Fast path: connected components of the candidate edges whose triangles all pass the
   test against the component's area-weighted plane are accepted as they are. Components that fail
   (slowly curving surfaces that would chain) are regrown with an explicit queue (no recursion):
   seeds by decreasing area, region plane = seed plane.
5. **Outlines**: half-edges whose opposite triangle is in another region (or missing) form the region
   boundary, already oriented (region on the left). They are chained into loops (vectorised list
   ranking); at a pinch vertex (several outgoing edges) the region's wedges are closed locally and a
   loop that still visits a vertex twice is split there, so every loop is simple (holes may touch
   the outline or each other at single vertices). Loop signed area in the region plane tells the
   outer loop (> 0) from holes (< 0); zero-area loops (slits) are dropped and counted. Half-edges
   left unbalanced by non-orientable tangles are dropped and counted (never a crash).
6. **Simplify**: a vertex is removed when it is a straight pass-through (within ``collinear_tol_m``)
   in *every* loop that uses it; a vertex where any loop turns (corners, T-junctions of three
   regions) is kept in all loops, so neighbouring polygons share the same vertices and no crack opens.
7. **Write** ``.wrl``, ``.cao`` or ``.obj`` (holes bridged: see :mod:`mst.meshtools.formats`), atomically.

Modules: :mod:`mst.meshtools.regions` (steps 1-4: weld, edges, orientation, region growing),
:mod:`mst.meshtools.outlines` (steps 5-6); this module holds the configuration, the core
:func:`tin_to_polygons` (arrays in, :class:`~mst.meshtools.model.PolygonModel` and a typed
:class:`ConvertResult` out) and the runner :func:`convert_model` (files in and out).

Units: metres (or the file's unit) for lengths, degrees for ``angle_tol_deg``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mst import InputError, atomic_output, check_outputs
from mst.core.config import Config, param
from mst.meshtools.compiled import triangle_cross
from mst.meshtools.model import PolygonModel
from mst.meshtools.outlines import outlines
from mst.meshtools.regions import (
    PLANARITY_ROUNDS,
    edges,
    grow_regions,
    nonplanar_regions,
    orient,
    regrow,
    renumber,
    weld,
)

log = logging.getLogger(__name__)


@dataclass
class ConvertConfig(Config):
    """Tolerances of :func:`tin_to_polygons` (``mst convert-model``)."""

    angle_tol_deg: float = param(1.0, min=0, help="max angle (degrees) between any two triangle normals of one "
                                                  "polygon (each within half of it from the polygon's normal)")
    dist_tol_m: float | None = param(None, min=0, help="max distance (m) of a polygon's vertices from its plane; "
                                                       "null: 1e-4 of the bounding-box diagonal")
    weld_tol_m: float = param(1e-6, min=0, help="vertices closer than this (m) are merged first; 0: exact "
                                                "duplicates only")
    collinear_tol_m: float | None = param(None, min=0, help="max distance (m) of a removed vertex from the line "
                                                            "through its neighbours; null: max(weld_tol_m, 1e-6 "
                                                            "diagonal), at most the plane tolerance (float32 files "
                                                            "carry ~1e-7 relative noise)")


@dataclass
class ConvertResult:
    """What :func:`tin_to_polygons` found and did (counts), the plane tolerance it used
    (``dist_tol_used_m``: the config's ``dist_tol_m``, or derived when that is null), the configuration, and for
    :func:`convert_model` the files and the time taken."""

    config: ConvertConfig
    triangles_in: int = 0
    vertices_in: int = 0
    welded_vertices: int = 0
    degenerate_dropped: int = 0
    nonmanifold_edges: int = 0
    border_edges: int = 0
    components: int = 0
    closed_components: int = 0
    flipped_triangles: int = 0
    regions: int = 0
    regrown_triangles: int = 0
    loops: int = 0
    slit_loops_dropped: int = 0
    pinch_vertices: int = 0
    loops_split_at_pinches: int = 0
    vertices_removed: int = 0
    regions_without_outer_loop: int = 0
    open_boundary_edges_dropped: int = 0
    replanarised_triangles: int = 0
    polygons_out: int = 0
    vertices_out: int = 0
    holes: int = 0
    dist_tol_used_m: float = 0.0
    input: str | None = None
    output: str | None = None
    elapsed_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        """The summary as JSON-ready values; ``config`` is the full effective configuration (give it
        back with ``--config`` to repeat the run)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["config"] = self.config.to_dict()
        return d


# ====================================================================== stage runner
def convert_model(input_path: str | Path, output_path: str | Path, config: ConvertConfig | None = None,
                  progress: Callable[[str], None] | None = None) -> ConvertResult:
    """Read a TIN, group it into planar polygons, write the polygon model atomically.

    ``progress(step_name)`` is called after each of the steps (read, weld, orient, regions,
    outlines, write). Raises :class:`mst.InputError` for unreadable or degenerate input; nothing is
    written then.
    """
    from mst.meshtools.formats import WRITE_SUFFIXES, load_triangles, model_suffix, save_model

    cfg = config or ConvertConfig()
    out = Path(output_path)
    check_outputs([out], [input_path])  # not over the input; the folder exists and is writable
    if model_suffix(out) not in WRITE_SUFFIXES:
        raise InputError(out, f"unknown output format {out.suffix!r} (use .wrl, .cao or .obj)")
    t0 = time.perf_counter()
    step = progress or (lambda name: None)
    V, F = load_triangles(input_path, primitives=False)  # a .cao's cylinders and circles are not polygons
    if model_suffix(Path(input_path)) == ".cao":
        _warn_primitives(input_path)
    step("read")
    model, result = tin_to_polygons(V, F, cfg, path=str(input_path), progress=step)
    with atomic_output(out) as tmp:
        save_model(tmp, model)
    step("write")
    return dataclasses.replace(result, input=str(input_path), output=str(out),
                               elapsed_s=round(time.perf_counter() - t0, 4))


def _warn_primitives(path) -> None:
    """Log a warning when a ``.cao`` input has cylinders or circles: the conversion keeps its polygon faces only."""
    from mst.meshtools.formats import load_model

    m = load_model(path)
    what = ", ".join(f"{n} {k}" for n, k in ((len(m.cylinders), "cylinder(s)"), (len(m.circles), "circle(s)")) if n)
    if what:
        log.warning(f"{Path(path).name}: {what} not converted: the output holds the polygon faces only")


# ====================================================================== stage core
def _checked_arrays(V, F, path: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``V``, ``F`` as float64/int64 arrays, checked; with the used vertices and their bounding box."""
    V = np.asarray(V, np.float64).reshape(-1, 3)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if len(F) == 0:
        raise InputError(path, "no triangles in the mesh")
    if not np.isfinite(V).all():
        bad = ~np.isfinite(V).all(axis=1)
        raise InputError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates (first: #{int(np.argmax(bad))})")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(path, "triangle vertex index out of range")
    used_mask = np.zeros(len(V), bool)
    used_mask[F] = True
    used_v = np.flatnonzero(used_mask)
    lo, hi = V[used_v].min(0), V[used_v].max(0)
    return V, F, used_v, lo, hi


def tin_to_polygons(V: np.ndarray, F: np.ndarray, config: ConvertConfig | None = None, path: str | None = None,
                    progress: Callable[[str], None] | None = None) -> tuple[PolygonModel, ConvertResult]:
    """Core of :func:`convert_model` on arrays: ``V`` (N, 3) metres, ``F`` (M, 3) int.

    Returns the :class:`PolygonModel` (faces = outer loops CCW seen from outside, holes CW, only the
    vertices used, in input order) and a :class:`ConvertResult`.
    """
    cfg = config or ConvertConfig()
    step = progress or (lambda name: None)
    V, F, used_v, lo, hi = _checked_arrays(V, F, path)
    diag = float(np.linalg.norm(hi - lo))
    if diag == 0:
        raise InputError(path, "all vertices coincide (degenerate mesh)")
    dist_tol = float(cfg.dist_tol_m) if cfg.dist_tol_m is not None else 1e-4 * diag
    col_tol = (float(cfg.collinear_tol_m) if cfg.collinear_tol_m is not None
               else min(max(cfg.weld_tol_m, 1e-6 * diag), dist_tol))
    # work in coordinates centred on the bounding box (precision for large map coordinates)
    center = (lo + hi) / 2
    X = V - center
    stats: dict = {"triangles_in": int(len(F)), "vertices_in": int(len(used_v))}

    # ---- 1. weld + drop degenerate
    F, n_welded = weld(X, F, cfg.weld_tol_m)
    cr, area2 = triangle_cross(X, F)  # (b - a) x (c - a) and its norm (= twice the area)
    degenerate = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2]) | (area2 <= 2e-12 * diag**2)
    stats.update(welded_vertices=int(n_welded), degenerate_dropped=int(degenerate.sum()))
    if degenerate.any():
        F, cr, area2 = F[~degenerate], cr[~degenerate], area2[~degenerate]
    if len(F) == 0:
        raise InputError(path, "every triangle is degenerate (zero area)")
    step("weld")

    # ---- 2. edges
    E = edges(F, len(X))
    stats.update(nonmanifold_edges=int((E.count >= 3).sum()), border_edges=int((E.count == 1).sum()))

    # ---- 3. orientation
    F, flipped, comp, n_comp, closed = orient(X, F, E, area2, cr)
    stats.update(components=int(n_comp), closed_components=int(closed.sum()), flipped_triangles=int(flipped))
    if flipped:
        cr = triangle_cross(X, F)[0]
        E = edges(F, len(X))
    N = cr / area2[:, None]
    step("orient")

    # ---- 4. regions
    region, n_fallback = grow_regions(X, F, N, area2, E, np.deg2rad(cfg.angle_tol_deg), dist_tol)
    stats.update(regions=int(region.max()) + 1, regrown_triangles=int(n_fallback))
    step("regions")

    # ---- 5./6. outlines, then the planarity promise checked on the OUTPUT polygons
    faces, holes = _planar_outlines(X, F, N, area2, cr, E, region, cfg, dist_tol, col_tol, diag, stats)
    # keep only used vertices, input order
    loops = faces + [h for hs in holes for h in hs]
    used = np.zeros(len(X), bool)
    for lp in loops:
        used[lp] = True
    remap = np.cumsum(used) - 1
    if not faces:
        raise InputError(path, "no polygon could be formed (degenerate mesh)")
    model = PolygonModel(V[used], [remap[f] for f in faces], holes=[[remap[h] for h in hs] for hs in holes])
    stats.update(polygons_out=model.n_faces, vertices_out=int(used.sum()), holes=model.n_holes,
                 dist_tol_used_m=dist_tol)
    step("outlines")
    return model, ConvertResult(cfg, **stats)


def _planar_outlines(X, F, N, area2, cr, E, region, cfg: ConvertConfig, dist_tol: float, col_tol: float,
                     diag: float, stats: dict) -> tuple[list, list]:
    """Outlines of the regions (steps 5-6); regions with an output polygon off its plane by more than
    ``dist_tol`` are regrown in a thinner slab (:data:`~mst.meshtools.regions.PLANARITY_ROUNDS`
    times), then split into triangles. Adds the outline counts to ``stats``."""
    n_regions = int(region.max()) + 1
    faces, holes, ostats, face_region = outlines(X, F, region, n_regions, cr, E, col_tol, diag)
    n_replanarised = 0
    for it in range(PLANARITY_ROUNDS + 3):  # the last rounds split what still fails into triangles
        bad_reg = nonplanar_regions(X, faces, holes, face_region, dist_tol, diag)
        if len(bad_reg) == 0:
            break
        bad_tri = np.isin(region, bad_reg)
        n_replanarised += int(bad_tri.sum())
        if it < PLANARITY_ROUNDS:  # regrow those regions in a thinner slab
            region = regrow(X, F, N, area2, E, region, bad_tri, np.deg2rad(cfg.angle_tol_deg),
                            dist_tol * 0.5 ** (it + 1))
        else:  # last resort: one region per triangle (a triangle is exactly planar)
            region = renumber(np.where(bad_tri, region.max() + 1 + np.arange(len(F)), region))
        n_regions = int(region.max()) + 1
        faces, holes, ostats, face_region = outlines(X, F, region, n_regions, cr, E, col_tol, diag)
    stats.update(ostats, regions=n_regions, replanarised_triangles=n_replanarised)
    return faces, holes


def summary_lines(s: ConvertResult) -> list[str]:
    """Human summary (stderr) of a :func:`convert_model` result."""
    return [
        f"triangles in {s.triangles_in:,} ({s.vertices_in:,} vertices): welded {s.welded_vertices:,}, "
        f"degenerate dropped {s.degenerate_dropped:,}, non-manifold edges {s.nonmanifold_edges:,}, "
        f"components {s.components:,} ({s.closed_components:,} closed), flipped {s.flipped_triangles:,}",
        f"regions {s.regions:,} -> polygons out {s.polygons_out:,}, vertices out {s.vertices_out:,}, "
        f"holes {s.holes:,} (tolerances: angle {s.config.angle_tol_deg:g} deg, dist {s.dist_tol_used_m:.3g} m)",
        f"wrote {s.output} in {s.elapsed_s:.2f} s",
    ]


__all__ = ["ConvertConfig", "ConvertResult", "convert_model", "tin_to_polygons", "summary_lines"]
