"""The C2M stage core: distances of a stream of point chunks to a prepared mesh, merged into the
typed :class:`C2MResult` (Table 1, overall statistics, counts). No file is read or written here:
:func:`c2m` takes an array, :func:`stream_distances` any iterator of chunks (the runner's file
reader); an ``on_chunk`` callback receives every chunk's distances in order (the runner writes the
output cloud from it).

Chunks run in a thread pool (numpy and Open3D release the GIL): ``workers`` of them concurrently for
the BVH engine, one at a time for the compiled grid engine (its kernels use every core themselves).
Statistics merge chunk by chunk in input order, so a result does not depend on the thread timing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from mst import InputError
from mst.eval.c2m.config import C2MConfig
from mst.eval.c2m.distances import point_distances
from mst.eval.c2m.geometry import MeshIndex, prepare_mesh
from mst.eval.c2m.stats import DistanceStats, Moments, ThresholdRow

#: largest accepted |coordinate| of a cloud point, metres. Nothing measured lies 1e12 m away (Earth-
#: centred coordinates are ~6.4e6 m); such values are corrupt and, near 1e154, overflow the squared
#: distances into inf/NaN. Clouds holding them are refused (NaN/inf points are counted and excluded).
MAX_CLOUD_COORD_M = 1e12

#: ``on_chunk(xyz, finite, unsigned, signed)``: the chunk's points (n, 3), the finite-row mask (n,),
#: the distances of the finite rows (NaN beyond max_dist_m) and the signed ones (or None)
ChunkCallback = Callable[[np.ndarray, np.ndarray, np.ndarray, "np.ndarray | None"], None]


@dataclass(frozen=True)
class C2MTiming:
    """Wall times, seconds: ``distance_s`` the streamed pass (read + distances + write, chunks
    overlapping), ``worker_s`` the summed per-chunk distance time of the workers."""

    mesh_s: float
    distance_s: float
    worker_s: float
    total_s: float
    points_per_s: float | None

    def to_json(self) -> dict:
        return {"mesh_s": self.mesh_s, "distance_s": self.distance_s, "worker_s": self.worker_s,
                "total_s": self.total_s, "points_per_s": self.points_per_s}


@dataclass(frozen=True)
class C2MResult:
    """Result of the C2M stage; :meth:`to_json` is the ``mst c2m --json`` summary.

    ``distances`` holds the finite unsigned distances (float64, float32 beyond 20M points) for plots;
    it is not part of the JSON.
    """

    cloud: str | None
    mesh: str | None
    output: str | None
    points_total: int
    points_valid: int
    points_nonfinite: int
    points_beyond_max_dist: int
    max_dist: float | None
    mesh_triangles: int
    mesh_degenerate_dropped: int
    engine: str
    global_shift: list[float]
    thresholds: list[ThresholdRow]
    unsigned: DistanceStats
    signed: DistanceStats | None
    timing: C2MTiming
    config: C2MConfig
    distances: np.ndarray = field(repr=False)

    def to_json(self) -> dict:
        return {
            "cloud": self.cloud, "mesh": self.mesh, "output": self.output,
            "points_total": self.points_total, "points_valid": self.points_valid,
            "points_nonfinite": self.points_nonfinite, "points_beyond_max_dist": self.points_beyond_max_dist,
            "max_dist": self.max_dist, "mesh_triangles": self.mesh_triangles,
            "mesh_degenerate_dropped": self.mesh_degenerate_dropped, "engine": self.engine,
            "global_shift": self.global_shift,
            "thresholds": [r.to_json() for r in self.thresholds],
            "unsigned": self.unsigned.to_json(),
            "signed": self.signed.to_json() if self.signed is not None else None,
            "timing": self.timing.to_json(),
            "config": self.config.to_dict(),
        }


def c2m(points: np.ndarray, mesh: MeshIndex | tuple[np.ndarray, np.ndarray], cfg: C2MConfig | None = None
        ) -> C2MResult:
    """Cloud-to-mesh distances of ``points (n, 3)`` (metres; NaN/inf rows counted and excluded) to
    ``mesh``: a :class:`MeshIndex` (prepared with ``signed=True`` for signed distances) or the
    triangles ``(V (k, 3), F (m, 3))``. Processes the points in chunks of ``cfg.chunk_points``."""
    cfg = cfg or C2MConfig()
    t0 = time.perf_counter()
    if not isinstance(mesh, MeshIndex):
        mesh = prepare_mesh(*mesh, signed=cfg.signed, engine=cfg.engine, small_mesh_triangles=cfg.small_mesh_triangles)
    if cfg.signed and mesh.vert_n is None:
        raise ValueError("signed distances need a mesh prepared with signed=True")
    P = np.asarray(points).reshape(-1, 3)
    if len(P) == 0:
        raise InputError(None, "cloud has no points")
    step = cfg.chunk_points
    return stream_distances(mesh, (P[i : i + step] for i in range(0, len(P), step)), len(P), cfg,
                            started=t0, mesh_s=time.perf_counter() - t0)


def stream_distances(idx: MeshIndex, chunks: Iterable[np.ndarray], n_total: int, cfg: C2MConfig, *,
                     on_chunk: ChunkCallback | None = None, cloud: str | None = None, mesh: str | None = None,
                     output: str | None = None, started: float | None = None, mesh_s: float = 0.0) -> C2MResult:
    """The streaming core: distances of the ``n_total`` points delivered by ``chunks`` to ``idx``.

    ``cloud``/``mesh``/``output`` name the files in the result (and ``cloud`` in errors); ``started``
    (``time.perf_counter()``) and ``mesh_s`` are the caller's start time and mesh preparation time.
    Raises :class:`mst.InputError` naming ``cloud`` for a point beyond :data:`MAX_CLOUD_COORD_M`, a
    count that differs from ``n_total`` and a cloud without finite points.
    """
    t0 = time.perf_counter() if started is None else started
    acc = _Accumulator(idx, cfg, n_total)
    work = _chunk_work(idx, cfg, cloud)
    t_loop = time.perf_counter()
    workers = 1 if idx.kernels is not None else cfg.workers
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for xyz, fin, du, ds, dt in _in_order(pool, work, iter(chunks), workers + 1):
            acc.add(xyz, fin, du, ds, dt)
            if on_chunk is not None:
                on_chunk(xyz, fin, du, ds)
    t_loop = time.perf_counter() - t_loop
    if acc.n_seen != n_total:
        raise InputError(cloud, f"read {acc.n_seen} points, header says {n_total}")
    if n_total - acc.n_nonfinite == 0:
        raise InputError(cloud, "cloud has no finite points")
    return acc.result(cfg, cloud=cloud, mesh=mesh, output=output, t0=t0, mesh_s=mesh_s, t_loop=t_loop)


def _chunk_work(idx: MeshIndex, cfg: C2MConfig, cloud: str | None):
    """The per-chunk job run in the pool: ``xyz -> (xyz, finite mask, unsigned, signed, seconds)``."""
    shift = idx.shift
    nb = idx.kernels  # compiled helpers when the grid engine has them

    def work(xyz: np.ndarray):
        ts = time.perf_counter()
        if nb is not None:  # shift, finite rows and the coordinate check in one compiled pass
            P, fin, n_far = nb.shift_points(np.ascontiguousarray(xyz, np.float64), shift, MAX_CLOUD_COORD_M)
        else:
            with np.errstate(invalid="ignore"):
                n_far = int(((np.abs(xyz) > MAX_CLOUD_COORD_M) & np.isfinite(xyz)).any(axis=1).sum())
        if n_far:
            raise InputError(cloud, f"{n_far} point(s) with a coordinate beyond {MAX_CLOUD_COORD_M:g} m "
                                    "(corrupt values?); NaN/inf points are excluded, these are refused")
        if nb is not None:
            if not fin.all():
                P = P[fin]
        else:
            fin = np.isfinite(xyz).all(1)
            P = xyz - shift if fin.all() else xyz[fin] - shift
        du, ds = point_distances(idx, P, cfg.signed, cfg.max_dist_m)
        return xyz, fin, du, ds, time.perf_counter() - ts

    return work


def _in_order(pool: ThreadPoolExecutor, work, chunks: Iterator[np.ndarray], depth: int) -> Iterator[tuple]:
    """``work(chunk)`` of every chunk, results in input order, up to ``depth`` chunks in flight."""
    pending = []
    exhausted = False
    while pending or not exhausted:
        while not exhausted and len(pending) < depth:
            try:
                pending.append(pool.submit(work, next(chunks)))
            except StopIteration:
                exhausted = True
        if not pending:
            break
        yield pending.pop(0).result()


class _Accumulator:
    """Counts, streamed moments (overall and per threshold) and the stored distances of a pass."""

    def __init__(self, idx: MeshIndex, cfg: C2MConfig, n_total: int):
        self.idx = idx
        self.thr = np.asarray(sorted(float(t) for t in cfg.thresholds_m), np.float64)
        keep_f64 = n_total <= 20_000_000
        self.store = np.empty(n_total, np.float64 if keep_f64 else np.float32)
        self.store_s = np.empty(n_total, np.float64 if keep_f64 else np.float32) if cfg.signed else None
        self.n_store = 0
        self.mo_u, self.mo_s = Moments(), Moments()
        self.th_mo = [Moments() for _ in self.thr]
        self.n_nonfinite = self.n_beyond = self.n_seen = 0
        self.t_dist = 0.0
        self.n_total = n_total

    def add(self, xyz: np.ndarray, fin: np.ndarray, du: np.ndarray, ds: np.ndarray | None, dt: float) -> None:
        nb = self.idx.kernels
        self.t_dist += dt
        self.n_seen += len(xyz)
        self.n_nonfinite += int((~fin).sum())
        valid = ~np.isnan(du)
        nv = int(valid.sum())
        self.n_beyond += len(du) - nv
        dv = du if nv == len(du) else du[valid]
        if nb is not None:
            cnt, s1, s2, lo, hi = nb.threshold_sums(dv, self.thr)
            self.mo_u.add_sums(int(cnt[-1]), float(s1[-1]), float(s2[-1]), float(lo), float(hi))
            for j, mo in enumerate(self.th_mo):
                mo.add_sums(int(cnt[j]), float(s1[j]), float(s2[j]))
        else:
            self.mo_u.add(dv)
            for t, mo in zip(self.thr, self.th_mo):
                mo.add(dv[dv < t], extremes=False)
        self.store[self.n_store : self.n_store + len(dv)] = dv
        if self.store_s is not None:
            sv = ds if nv == len(ds) else ds[valid]
            self.mo_s.add(sv)
            self.store_s[self.n_store : self.n_store + len(sv)] = sv
        self.n_store += len(dv)

    def result(self, cfg: C2MConfig, *, cloud, mesh, output, t0: float, mesh_s: float, t_loop: float) -> C2MResult:
        n_valid = self.n_total - self.n_nonfinite
        dist = self.store[: self.n_store]
        table = [ThresholdRow.from_moments(t, mo, n_valid) for t, mo in zip(self.thr, self.th_mo)]
        unsigned = DistanceStats.from_moments(self.mo_u, dist)
        signed = DistanceStats.from_moments(self.mo_s, self.store_s[: self.n_store]) if cfg.signed else None
        total_s = time.perf_counter() - t0
        timing = C2MTiming(mesh_s=mesh_s, distance_s=t_loop, worker_s=self.t_dist, total_s=total_s,
                           points_per_s=n_valid / t_loop if t_loop > 0 else None)
        idx = self.idx
        return C2MResult(cloud=cloud, mesh=mesh, output=output, points_total=self.n_total, points_valid=n_valid,
                         points_nonfinite=self.n_nonfinite, points_beyond_max_dist=self.n_beyond,
                         max_dist=cfg.max_dist_m, mesh_triangles=idx.n_triangles,
                         mesh_degenerate_dropped=idx.n_dropped, engine=idx.engine,
                         global_shift=idx.shift.tolist(), thresholds=table, unsigned=unsigned, signed=signed,
                         timing=timing, config=cfg, distances=dist)
