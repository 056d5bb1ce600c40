"""The fusion's PLY files: the binary cloud it writes and the point clouds it reads (landmarks).

One small function each (to be replaced by the shared PLY module of :mod:`mst.core`).
"""

from __future__ import annotations

import os

import numpy as np

from mst import InputError, require_file


def write_ply(path: str | os.PathLike, X: np.ndarray, rgb: np.ndarray | None = None, count: np.ndarray | None = None,
              comments: list[str] | None = None) -> None:
    """Binary little-endian PLY: ``x y z`` as double (metres, full georeferenced precision),
    optional ``red green blue`` uchar and ``count`` uint (depth samples merged into the point)."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    props = ["property double x", "property double y", "property double z"]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    if count is not None:
        fields += [("count", "<u4")]
        props += ["property uint count"]
    a = np.empty(len(X), dtype=fields)
    a["x"], a["y"], a["z"] = X[:, 0], X[:, 1], X[:, 2]
    if rgb is not None:
        a["red"], a["green"], a["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if count is not None:
        a["count"] = np.minimum(count, np.iinfo(np.uint32).max)
    head = ["ply", "format binary_little_endian 1.0"] + [f"comment {c}" for c in (comments or [])]
    head += [f"element vertex {len(X)}", *props, "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode("ascii"))
        f.write(a.tobytes())


def read_ply_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a PLY point cloud: ``(X (N, 3) float64, rgb (N, 3) uint8 or None)``.

    Handles ASCII and binary PLY whose first element is ``vertex`` with scalar properties.
    """
    from mst.meshtools.io import PLY_TYPES

    p = require_file(path, "point cloud")
    raw = p.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(p, "not a PLY file (no 'ply' magic or no end_header)")
    nl = raw.find(b"\n", end)
    header = raw[:end].decode("ascii", "replace").splitlines()
    body = raw[nl + 1:]
    fmt, n, props, elements = None, None, [], []
    for line in header:
        w = line.split()
        if not w:
            continue
        if w[0] == "format" and len(w) > 1:
            fmt = w[1]
        elif w[0] == "element" and len(w) > 2:
            elements.append(w[1])
            if len(elements) == 1:
                try:
                    n = int(w[2])
                except ValueError:
                    raise InputError(p, f"bad element line {line!r}") from None
        elif w[0] == "property" and len(elements) == 1 and len(w) > 2:
            if w[1] == "list":
                raise InputError(p, "list properties in the vertex element are not supported")
            if w[1] not in PLY_TYPES:
                raise InputError(p, f"unknown PLY property type {w[1]!r}")
            props.append((w[2], PLY_TYPES[w[1]]))
    first = elements[0] if elements else None
    if first != "vertex" or n is None:
        raise InputError(p, "the first PLY element must be 'vertex'")
    names = [nm for nm, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise InputError(p, "PLY vertices have no x, y, z")
    if fmt == "ascii":
        try:
            rows = np.loadtxt(body.decode("ascii").splitlines()[:n], ndmin=2) if n else np.empty((0, len(props)))
        except ValueError as e:
            raise InputError(p, f"bad ASCII PLY data ({e})") from None
        if rows.shape != (n, len(props)):
            raise InputError(p, f"ASCII PLY: expected {n} vertices of {len(props)} values")
        cols = {nm: rows[:, i] for i, nm in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        e = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(nm, e + t) for nm, t in props])
        if len(body) < n * dt.itemsize:
            raise InputError(p, f"PLY is truncated: {n} vertices need {n * dt.itemsize} bytes, found {len(body)}")
        a = np.frombuffer(body, dtype=dt, count=n)
        cols = {nm: a[nm] for nm in names}
    else:
        raise InputError(p, f"unknown PLY format {fmt!r}")
    X = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    if not np.isfinite(X).all():
        raise InputError(p, "point cloud holds NaN or infinite coordinates")
    rgb = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).clip(0, 255).astype(np.uint8)
    return X, rgb
