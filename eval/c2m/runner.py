"""``run_c2m``: the file runner of the C2M stage (read the cloud and the mesh, call the core
:func:`~mst.eval.c2m.driver.stream_distances`, write the output cloud atomically)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from contextlib import contextmanager, nullcontext

import numpy as np

from mst import InputError, atomic_outputs, require_file
from mst.eval.c2m.config import C2MConfig
from mst.eval.c2m.driver import C2MResult, stream_distances
from mst.eval.c2m.geometry import MeshIndex, prepare_mesh


def run_c2m(cloud_path: str | os.PathLike, mesh_path: str | os.PathLike, config: C2MConfig | None = None,
            out_cloud: str | os.PathLike | None = None, progress: Callable[[int], None] | None = None) -> C2MResult:
    """Cloud-to-mesh distances of every point of ``cloud_path`` to the mesh ``mesh_path``.

    Streams the cloud in chunks of ``config.chunk_points``. Writes ``out_cloud`` (binary PLY with the
    scalar fields ``C2M_absolute_distances`` and, when signed, ``C2M_signed_distances``; NaN for
    invalid or beyond-max-dist points) atomically. ``progress(n)`` is called with the points done per
    chunk.
    """
    from mst.eval.cloud_io import open_cloud

    cfg = config or C2MConfig()
    t0 = time.perf_counter()
    src = open_cloud(cloud_path)
    if src.count == 0:
        raise InputError(cloud_path, "cloud has no points")
    idx = load_mesh_index(mesh_path, cfg)
    t_mesh = time.perf_counter() - t0
    xyz_dtype = src.xyz_dtype if src.xyz_dtype.itemsize == 8 or np.abs(idx.shift).max() < 1e5 else np.float64
    with atomic_outputs(out_cloud) as (tmp_out,):
        writer = nullcontext() if tmp_out is None else _distance_cloud_writer(tmp_out, src.count, cfg.signed, xyz_dtype)
        with writer as write:
            def on_chunk(xyz, fin, du, ds):
                if write is not None:
                    write(xyz, fin, du, ds)
                if progress is not None:
                    progress(len(xyz))

            return stream_distances(idx, src.chunks(cfg.chunk_points), src.count, cfg, on_chunk=on_chunk,
                                    cloud=str(cloud_path), mesh=str(mesh_path),
                                    output=None if out_cloud is None else str(out_cloud), started=t0, mesh_s=t_mesh)


def load_mesh_triangles(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of a mesh or polygon model file (OBJ PLY STL OFF WRL CAO CityJSON, polygons
    triangulated): ``(V (n, 3) float64 metres, F (m, 3) int64)``."""
    from mst.meshtools.formats import load_triangles

    return load_triangles(require_file(path, "mesh file"))


def load_mesh_index(mesh_path: str | os.PathLike, cfg: C2MConfig) -> MeshIndex:
    """The mesh file read and prepared for ``cfg`` (the BVH engine's Open3D import overlaps the read)."""
    pre = _prefetch_open3d() if cfg.engine == "bvh" else None
    try:
        V, F = load_mesh_triangles(mesh_path)
        return prepare_mesh(V, F, mesh_path, signed=cfg.signed, engine=cfg.engine,
                            small_mesh_triangles=cfg.small_mesh_triangles)
    finally:
        if pre is not None:  # never leave an import running in a thread at interpreter exit
            pre.join()


@contextmanager
def _distance_cloud_writer(path, count: int, signed: bool, xyz_dtype):
    """The output cloud (binary PLY, float32 scalar fields in CloudCompare's naming); yields
    ``write(xyz, finite, unsigned, signed)`` for each chunk, NaN at the non-finite rows."""
    from mst.eval.cloud_io import PlyChunkWriter

    fields = ["C2M_absolute_distances"] + (["C2M_signed_distances"] if signed else [])
    with PlyChunkWriter(path, count, fields, xyz_dtype) as w:
        def write(xyz, fin, du, ds):
            sc = {"C2M_absolute_distances": _expand(du, fin, len(xyz))}
            if signed:
                sc["C2M_signed_distances"] = _expand(ds, fin, len(xyz))
            w.write(xyz, **sc)

        yield write


def _expand(v: np.ndarray, fin: np.ndarray, n: int) -> np.ndarray:
    """Values of the finite rows back at their rows of the chunk (NaN for non-finite rows)."""
    if len(v) == n:
        return v
    o = np.full(n, np.nan, np.float32)
    o[fin] = v
    return o


def _prefetch_open3d():
    """Start importing Open3D in a thread; returns the thread (None when already imported)."""
    import importlib
    import sys
    import threading

    if "open3d" in sys.modules:
        return None
    th = threading.Thread(target=importlib.import_module, args=("open3d",), daemon=True)
    th.start()
    return th
