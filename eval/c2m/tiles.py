"""C2M at scale: one large cloud or many cloud tiles (LAS/LAZ and binary PLY read by point ranges; any
other cloud file whole) as dask tasks, the mesh index built once per worker, the statistics reduced on
the client without ever gathering the points. ``mst c2m --workers N | --scheduler ADDRESS`` (and its
alias ``mst c2m-tiles``) run this engine.

Exact where the single-process run is: every task streams its range in the chunks that
:func:`mst.eval.c2m.run_c2m` would use (``chunk_points`` from the start of each file; a range
starts on a chunk boundary) and returns per chunk the count, sum, sum of squares, min and max of the
distances, overall and under each Table-1 threshold (the compiled ``threshold_sums``, as the single
run computes them); the client merges them in file and chunk order with the same
:class:`~mst.eval.c2m.stats.Moments`, so count, mean, std, RMS, min, max and Table 1 are bit-identical
to a single-process run over the same files. The median is read from a merged fixed-width histogram
(``HIST_BINS`` bins over ``[0, HIST_RANGE_X * max(thresholds))``): within half a bin width of the
exact median (``median_bound_m`` in the result), None when the median lies beyond the histogram; or
exact (``exact_median``): a second pass returns only the distances in the middle ranks' bins.
Unsigned distances only, grid engine only (the compiled kernels); ``max_dist_m`` applies as usual.
With an output folder each tile is one task that also writes its distance cloud: a LAS/LAZ tile with
the distance as an extra dimension (``<stem>_c2m.laz``, every original dimension kept), any other
cloud as binary PLY with the scalar field (``<stem>_c2m.ply``, as ``mst c2m -o`` writes it).

On a dask worker of one thread, LAZ is decompressed by the single-threaded ``lazrs`` backend (laspy's
default, ``lazrs`` parallel, starts a thread pool over every core in every worker: with N workers on N
cores that oversubscribes the machine and a 1-worker run is not the one-core baseline it claims to
be). The result records every worker's CPU seconds and peak RSS over the run (``workers``).
"""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mst import InputError
from mst.errors import ConfigError
from mst.eval.c2m.config import C2MConfig
from mst.eval.c2m.stats import Moments, ThresholdRow

HIST_BINS = 1 << 16
HIST_RANGE_X = 8.0
LAS_SUFFIXES = (".las", ".laz")
#: default chunks per task: tasks of 2M points (the default chunk) keep two workers evenly loaded (20M
#: points in 4-chunk tasks were 5 tasks, split 3:2; the per-task cost, a file open and a seek, is ~ms)
TASK_CHUNKS = 2


@dataclass(frozen=True)
class PointRange:
    """Points ``start .. start + count`` of one cloud file (a task)."""

    path: str
    start: int
    count: int
    whole: bool  #: the whole file (formats without random access)


def _binary_ply(path: str | os.PathLike):
    """The vertex stream of a binary PLY (random access by point index), else None."""
    if Path(path).suffix.lower() != ".ply":
        return None
    from mst.core.ply import open_vertices

    vs = open_vertices(path)
    return None if vs.header.format == "ascii" else vs


def plan_ranges(paths: list[str | os.PathLike], cfg: C2MConfig, chunks_per_task: int = TASK_CHUNKS,
                whole_files: bool = False) -> list[PointRange]:
    """The tasks over ``paths``: LAS/LAZ and binary PLY in ranges of ``chunks_per_task`` chunks, other
    files (and every file with ``whole_files``) whole."""
    from mst.eval.cloud_io import open_cloud

    out = []
    step = cfg.chunk_points * chunks_per_task
    for p in paths:
        n = open_cloud(p).count
        ranged = Path(p).suffix.lower() in LAS_SUFFIXES or _binary_ply(p) is not None
        if ranged and not whole_files:
            out += [PointRange(str(p), s, min(step, n - s), False) for s in range(0, n, step)]
        else:
            out.append(PointRange(str(p), 0, n, True))
    return out


def _read(r: PointRange, size: int):
    """Float64 (k, 3) blocks of ``size`` points of the range, in file order."""
    if r.whole:
        from mst.eval.cloud_io import open_cloud

        yield from open_cloud(r.path).chunks(size)
        return
    if Path(r.path).suffix.lower() == ".ply":
        yield from _read_ply(r, size)
        return
    import laspy

    try:
        with laspy.open(r.path, laz_backend=_laz_backend()) as f:
            f.seek(r.start)
            left = r.count
            while left > 0:
                pts = f.read_points(min(size, left))
                left -= len(pts)
                if len(pts) == 0:
                    raise InputError(r.path, f"ended {left} points early")
                yield np.stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                np.asarray(pts.z, np.float64)], axis=1)
    except InputError:
        raise
    except Exception as e:  # laspy raises several types for corrupt files
        raise InputError(r.path, f"cannot read LAS/LAZ points ({e})") from None


def _read_ply(r: PointRange, size: int):
    """A binary PLY's range: the records ``start ..`` read from their byte offset and converted as
    :class:`mst.core.ply.VertexStream` converts them (so the chunks equal a whole-file read's)."""
    vs = _binary_ply(r.path)
    with open(r.path, "rb") as f:
        f.seek(vs.offset + r.start * vs.dtype.itemsize)
        left = r.count
        while left > 0:
            blk = np.fromfile(f, dtype=vs.dtype, count=min(size, left))
            if len(blk) == 0:
                raise InputError(r.path, f"ended {left} points early")
            left -= len(blk)
            out = np.empty((len(blk), 3), np.float64)
            with np.errstate(invalid="ignore"):  # signalling NaNs pass through as NaN
                for j, k in enumerate("xyz"):
                    out[:, j] = blk[k]
            yield out


def _worker_nthreads() -> int | None:
    """The threads of the dask worker this runs on (None: not on a worker)."""
    try:
        from distributed import get_worker

        return int(get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None


def _laz_backend():
    """Single-threaded LAZ decompression on a worker of one thread; laspy's default elsewhere."""
    if _worker_nthreads() != 1:
        return None
    import laspy

    return laspy.LazBackend.Lazrs


#: per worker process: (mesh path, mtime, settings) -> its MeshIndex (built once per worker)
_INDEXES: dict[tuple, Any] = {}


def _index(mesh: str, cfg: C2MConfig):
    from mst.eval.c2m.runner import load_mesh_index

    key = (mesh, os.stat(mesh).st_mtime_ns, cfg.engine, cfg.small_mesh_triangles)
    idx = _INDEXES.get(key)
    if idx is None:
        _INDEXES.clear()
        idx = _INDEXES[key] = load_mesh_index(mesh, cfg)
    return idx


def _chunk_sums(idx, dv: np.ndarray, thr: np.ndarray) -> tuple[list, list, list, float, float]:
    """(counts, sums, sums of squares) under each threshold and overall (last), min, max of one chunk's
    distances, computed as the single-process accumulator does (compiled, else numpy)."""
    if idx.kernels is not None:
        cnt, s1, s2, lo, hi = idx.kernels.threshold_sums(dv, thr)
        return np.asarray(cnt).tolist(), np.asarray(s1).tolist(), np.asarray(s2).tolist(), float(lo), float(hi)
    cnt, s1, s2 = [], [], []
    for x in [*(dv[dv < t] for t in thr), dv]:
        x = np.asarray(x, np.float64)
        cnt.append(len(x))
        s1.append(float(x.sum()))
        s2.append(float(np.dot(x, x)))
    lo, hi = (float(dv.min()), float(dv.max())) if len(dv) else (np.inf, -np.inf)
    return cnt, s1, s2, lo, hi


def _worker_threads() -> None:
    """On a dask worker, the compiled kernels use as many threads as the worker has (its ``nthreads``):
    workers of one thread each share a machine's cores instead of oversubscribing them."""
    n = _worker_nthreads()
    if n is None:
        return  # not in a worker: the process's own setting
    import numba

    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


def output_name(path: str | os.PathLike, out_dir: str | os.PathLike) -> Path:
    """The distance cloud of a tile: ``<out_dir>/<stem>_c2m.<las|laz>`` (a LAS/LAZ tile keeps its format),
    ``<out_dir>/<stem>_c2m.ply`` for every other cloud format."""
    p = Path(path)
    suf = p.suffix.lower()
    return Path(out_dir) / f"{p.stem}_c2m{suf if suf in LAS_SUFFIXES else '.ply'}"


class _LasDistanceWriter:
    """Reads a LAS/LAZ tile's point records chunk by chunk and writes them, every dimension kept, with the
    extra dimension ``C2M_absolute_distances`` (float64, NaN for invalid or beyond-max-dist points) to
    ``tmp`` (readable by CloudCompare and PDAL)."""

    def __init__(self, src: str, tmp: Path):
        import collections

        import laspy

        self.src, self.tmp = src, tmp
        self.queue: collections.deque = collections.deque()
        self._reader = laspy.open(src, laz_backend=_laz_backend())
        header = self._reader.header
        self.header = laspy.LasHeader(point_format=header.point_format.id, version=header.version)
        self.header.scales, self.header.offsets = header.scales, header.offsets
        for d in header.point_format.extra_dimensions:
            self.header.add_extra_dim(laspy.ExtraBytesParams(d.name, d.dtype))
        self.header.add_extra_dim(laspy.ExtraBytesParams("C2M_absolute_distances", np.float64))
        self._writer = laspy.open(tmp, mode="w", header=self.header, do_compress=tmp.suffix.lower() == ".laz",
                                  laz_backend=_laz_backend())

    def chunks(self, size: int):
        for pts in self._reader.chunk_iterator(size):
            self.queue.append(pts)
            yield np.stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                            np.asarray(pts.z, np.float64)], axis=1)

    def write(self, fin: np.ndarray, du: np.ndarray) -> None:
        import laspy

        pts = self.queue.popleft()
        out = laspy.ScaleAwarePointRecord.zeros(len(pts), header=self.header)
        for name in pts.array.dtype.names:
            out.array[name] = pts.array[name]
        d = np.full(len(pts), np.nan)
        d[fin] = du
        out["C2M_absolute_distances"] = d
        self._writer.write_points(out)

    def close(self) -> None:
        self._writer.close()
        self._reader.close()


def range_partials(r: PointRange, mesh: str, cfg_dict: dict, out_dir: str | None = None,
                   select: tuple[int, int] | None = None) -> dict[str, Any]:
    """The dask task: per chunk of the range ``(n seen, n non-finite, n beyond, cnt, s1, s2, lo, hi)``
    (arrays over the thresholds + overall last) and the range's distance histogram; with ``out_dir`` (a
    whole LAS/LAZ tile) also its distance cloud :func:`output_name`, written atomically; with ``select``
    (first, last histogram bin) only the distances in those bins (``selected``), for the exact median."""
    from mst import atomic_output
    from mst.eval.c2m.driver import stream_distances

    cfg = C2MConfig.from_dict(cfg_dict)
    _worker_threads()
    idx = _index(mesh, cfg)
    thr = np.asarray(sorted(float(t) for t in cfg.thresholds_m), np.float64)
    edges_hi = HIST_RANGE_X * float(thr[-1])
    hist = np.zeros(HIST_BINS + 1, np.int64)  # the last bin: at or beyond the histogram
    chunks: list[tuple] = []
    picked: list[np.ndarray] = []

    def on_chunk(xyz, fin, du, ds):
        valid = ~np.isnan(du)
        dv = du if valid.all() else du[valid]
        chunks.append((len(xyz), int((~fin).sum()), len(du) - len(dv), *_chunk_sums(idx, dv, thr)))
        b = np.minimum((dv * (HIST_BINS / edges_hi)).astype(np.int64), HIST_BINS)
        hist[:] += np.bincount(b, minlength=HIST_BINS + 1)
        if select is not None:
            picked.append(dv[(b >= select[0]) & (b <= select[1])])

    if out_dir is None:
        stream_distances(idx, _read(r, cfg.chunk_points), r.count, cfg, on_chunk=on_chunk, cloud=r.path, mesh=mesh)
    elif Path(r.path).suffix.lower() in LAS_SUFFIXES:
        with atomic_output(output_name(r.path, out_dir)) as tmp:
            w = _LasDistanceWriter(r.path, Path(tmp))
            try:
                def both(xyz, fin, du, ds):
                    on_chunk(xyz, fin, du, ds)
                    w.write(fin, du)

                stream_distances(idx, w.chunks(cfg.chunk_points), r.count, cfg, on_chunk=both, cloud=r.path,
                                 mesh=mesh)
            finally:
                w.close()
    else:  # binary PLY with the scalar field, as `mst c2m -o` writes it
        from mst.eval.c2m.runner import _distance_cloud_writer
        from mst.eval.cloud_io import open_cloud

        src = open_cloud(r.path)
        xyz_dtype = src.xyz_dtype if src.xyz_dtype.itemsize == 8 or np.abs(idx.shift).max() < 1e5 else np.float64
        with atomic_output(output_name(r.path, out_dir)) as tmp, \
                _distance_cloud_writer(tmp, r.count, False, xyz_dtype) as write:
            def both(xyz, fin, du, ds):
                on_chunk(xyz, fin, du, ds)
                write(xyz, fin, du, None)

            stream_distances(idx, _read(r, cfg.chunk_points), r.count, cfg, on_chunk=both, cloud=r.path, mesh=mesh)
    return {"range": (r.path, r.start), "chunks": chunks, "hist": hist, "triangles": idx.n_triangles,
            "shift": idx.shift.tolist(), "selected": np.concatenate(picked) if picked else np.zeros(0)}


@dataclass
class TiledC2M:
    """The statistics of a tiled run: :meth:`to_json` has the fields of ``mst c2m --json`` it computes."""

    files: list[str]
    mesh: str
    points_total: int
    points_valid: int
    points_nonfinite: int
    points_beyond_max_dist: int
    thresholds: list[ThresholdRow]
    unsigned: dict[str, Any]
    median_bound_m: float
    tasks: int
    elapsed_s: float
    config: C2MConfig
    hist: np.ndarray = field(repr=False, default=None)
    median_method: str = "histogram"
    mesh_triangles: int = 0
    global_shift: list[float] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)     #: the distance clouds written (one per tile)
    workers: list[dict[str, Any]] = field(default_factory=list)  #: per process: worker, cpu_s, peak_rss_mib
    client_cpu_s: float = 0.0                            #: CPU seconds of this (the client) process

    def to_json(self) -> dict[str, Any]:
        n = len(self.files)
        return {"cloud": self.files[0] if n == 1 else os.path.commonpath([os.path.abspath(f) for f in self.files]), "files": self.files,
                "mesh": self.mesh, "outputs": self.outputs, "points_total": self.points_total,
                "points_valid": self.points_valid, "points_nonfinite": self.points_nonfinite,
                "points_beyond_max_dist": self.points_beyond_max_dist, "max_dist": self.config.max_dist_m,
                "mesh_triangles": self.mesh_triangles, "engine": "grid", "global_shift": self.global_shift,
                "thresholds": [t.to_json() for t in self.thresholds], "unsigned": self.unsigned, "signed": None,
                "median": self.median_method, "median_bound_m": self.median_bound_m, "tasks": self.tasks,
                "elapsed_s": self.elapsed_s,
                "points_per_s": self.points_valid / self.elapsed_s if self.elapsed_s > 0 else None,
                "workers": self.workers, "client_cpu_s": self.client_cpu_s, "config": self.config.to_dict()}


def _median(hist: np.ndarray, n: int, width: float) -> float | None:
    """The histogram's median: the centre of the bin of the middle rank (the mean of the two middle ranks'
    bin centres for an even count, as the median averages them), so within ``width / 2`` of the exact
    one; None when it lies beyond the histogram."""
    if n == 0:
        return None
    ranks = [(n + 1) // 2] if n % 2 else [n // 2, n // 2 + 1]
    bins = np.searchsorted(np.cumsum(hist), ranks)
    if bins.max() >= len(hist) - 1:
        return None
    return float(np.mean((bins + 0.5) * width))


def reduce_partials(parts: list[dict[str, Any]], files: list[str], mesh: str, cfg: C2MConfig, t0: float) -> TiledC2M:
    """Merge the tasks' chunks in file and chunk order (the single run's order) and their histograms."""
    order = {f: i for i, f in enumerate(files)}
    parts = sorted(parts, key=lambda p: (order[p["range"][0]], p["range"][1]))
    thr = sorted(float(t) for t in cfg.thresholds_m)
    mo_u, th_mo = Moments(), [Moments() for _ in thr]
    n_seen = n_nonfinite = n_beyond = 0
    hist = np.zeros(HIST_BINS + 1, np.int64)
    for p in parts:
        hist += p["hist"]
        for seen, nonfin, beyond, cnt, s1, s2, lo, hi in p["chunks"]:
            n_seen, n_nonfinite, n_beyond = n_seen + seen, n_nonfinite + nonfin, n_beyond + beyond
            mo_u.add_sums(int(cnt[-1]), float(s1[-1]), float(s2[-1]), float(lo), float(hi))
            for j, mo in enumerate(th_mo):
                mo.add_sums(int(cnt[j]), float(s1[j]), float(s2[j]))
    n_valid = n_seen - n_nonfinite
    if n_valid == 0:
        raise InputError(files[0] if len(files) == 1 else None, "the clouds have no finite points")
    width = HIST_RANGE_X * thr[-1] / HIST_BINS
    unsigned = {"count": mo_u.n, "mean": mo_u.mean if mo_u.n else None, "median": _median(hist, mo_u.n, width),
                "std": mo_u.std() if mo_u.n else None, "rms": float(np.sqrt(mo_u.sumsq / mo_u.n)) if mo_u.n else None,
                "min": mo_u.min if mo_u.n else None, "max": mo_u.max if mo_u.n else None}
    return TiledC2M(files, mesh, n_seen, n_valid, n_nonfinite, n_beyond,
                    [ThresholdRow.from_moments(t, mo, n_valid) for t, mo in zip(thr, th_mo)], unsigned, width / 2,
                    len(parts), round(time.perf_counter() - t0, 3), cfg, hist,
                    mesh_triangles=int(parts[0]["triangles"]), global_shift=list(parts[0]["shift"]))


def c2m_tiles(paths: list[str | os.PathLike], mesh: str | os.PathLike, cfg: C2MConfig | None = None,
              client=None, chunks_per_task: int = TASK_CHUNKS, out_dir: str | os.PathLike | None = None,
              exact_median: bool = False) -> TiledC2M:
    """C2M statistics of the cloud tiles ``paths`` against ``mesh``: on ``client`` (a dask Client) as one
    task per point range, or in this process (``client=None``) with the same reduction. With ``out_dir``
    every tile (LAS/LAZ only) is one task that also writes its distance cloud there. With ``exact_median``
    a second pass over the points gives the exact median (the histogram's bins of the middle ranks)."""
    cfg = cfg or C2MConfig()
    if chunks_per_task < 1:
        raise ConfigError("chunks_per_task", "must be >= 1")
    if cfg.signed:
        raise ConfigError("signed", "tiled C2M computes unsigned distances only")
    if cfg.engine == "bvh":
        raise ConfigError("engine", "tiled C2M needs the grid engine (its compiled per-chunk sums)")
    t0, c0 = time.perf_counter(), time.process_time()
    files = [str(p) for p in paths]
    if not files:
        raise InputError(None, "no cloud files given")
    out_dir = None if out_dir is None else str(out_dir)
    ranges = plan_ranges(files, cfg, chunks_per_task, whole_files=out_dir is not None)
    mesh = str(mesh)
    before = _usage(client)

    def run(out: str | None, select: tuple[int, int] | None) -> list[dict[str, Any]]:
        if client is None:
            return [range_partials(r, mesh, cfg.to_dict(), out, select) for r in ranges]
        futures = [client.submit(range_partials, r, mesh, cfg.to_dict(), out, select, pure=False) for r in ranges]
        return client.gather(futures)

    res = reduce_partials(run(out_dir, None), files, mesh, cfg, t0)
    if exact_median and res.unsigned["count"]:
        res = _exact_median(res, run)
    if out_dir is not None:
        res.outputs = [str(output_name(f, out_dir)) for f in files]
    res.elapsed_s = round(time.perf_counter() - t0, 3)
    res.client_cpu_s = round(time.process_time() - c0, 3)
    after = _usage(client)
    res.workers = [{"worker": w, "cpu_s": round(after[w][0] - before[w][0], 3), "peak_rss_mib": round(after[w][1], 1)}
                   for w in sorted(after) if w in before]
    return res


def _usage(client) -> dict[str, tuple[float, float]]:
    """Per process that runs the tasks (every worker, or this one): (CPU seconds user + system so far, peak
    RSS MiB). Asked with builtins only, so that the question itself imports nothing on the workers."""
    def one(u) -> tuple[float, float]:
        return u.ru_utime + u.ru_stime, u.ru_maxrss / 1024

    if client is None:
        return {"local": one(resource.getrusage(resource.RUSAGE_SELF))}
    return {w: one(resource.struct_rusage(u)) for w, u in
            client.run(resource.getrusage, resource.RUSAGE_SELF).items()}


def _exact_median(res: TiledC2M, run) -> TiledC2M:
    """The exact median by a second pass: the tasks return only the distances in the bins of the middle
    ranks; the client sorts those few (the same value ``np.median`` gives a single-process run)."""
    n = res.unsigned["count"]
    ranks = [(n + 1) // 2] if n % 2 else [n // 2, n // 2 + 1]
    cum = np.cumsum(res.hist)
    bins = np.searchsorted(cum, ranks)
    lo, hi = int(bins.min()), int(bins.max())
    below = int(cum[lo - 1]) if lo > 0 else 0
    vals = np.sort(np.concatenate([p["selected"] for p in run(None, (lo, hi))]))
    mid = [vals[r - below - 1] for r in ranks]
    res.unsigned["median"] = float(np.mean(mid))
    res.median_bound_m = 0.0
    res.median_method = "exact (second pass)"
    return res
