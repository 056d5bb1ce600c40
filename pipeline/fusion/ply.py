"""The fusion's PLY files through :mod:`mst.core.ply` (the project's one PLY module): the layout of
the fused cloud it writes, and the point clouds it reads (landmarks).
"""

from __future__ import annotations

import os

import numpy as np

from mst import InputError, require_file
from mst.core.ply import open_vertices
from mst.core.ply import write_ply as write_ply_columns


def write_ply(path: str | os.PathLike, X: np.ndarray, rgb: np.ndarray | None = None, count: np.ndarray | None = None,
              comments: list[str] | None = None) -> None:
    """Binary little-endian PLY: ``x y z`` as double (metres, full georeferenced precision),
    optional ``red green blue`` uchar and ``count`` uint (depth samples merged into the point)."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    cols = {"x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}
    if rgb is not None:
        cols.update(red=rgb[:, 0].astype(np.uint8), green=rgb[:, 1].astype(np.uint8), blue=rgb[:, 2].astype(np.uint8))
    if count is not None:
        cols["count"] = np.minimum(count, np.iinfo(np.uint32).max).astype(np.uint32)
    write_ply_columns(path, cols, comments=comments or [])


def read_ply_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a PLY point cloud: ``(X (N, 3) float64, rgb (N, 3) uint8 or None)``.

    ASCII or binary; the strict header checks of :func:`mst.core.ply.read_header`. Non-finite
    coordinates are refused.
    """
    p = require_file(path, "point cloud")
    vs = open_vertices(p)
    X = vs.read(("x", "y", "z"))
    if not np.isfinite(X).all():
        raise InputError(p, "point cloud holds NaN or infinite coordinates")
    rgb = None
    if vs.has("red", "green", "blue"):
        rgb = vs.read(("red", "green", "blue")).clip(0, 255).astype(np.uint8)
    return X, rgb
