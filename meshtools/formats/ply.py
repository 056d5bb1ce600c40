"""PLY meshes through :mod:`mst.core.ply` (the project's one PLY module): triangles and polygons
(fanned), ascii and binary; binary layouts that module does not vectorise (polygon lists) are read
by trimesh after the strict header check. Writing: binary, float64 vertices.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.ply import read_header, read_mesh, write_ply


def _trimesh_load(p: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        mesh = trimesh.load(p, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001
        raise InputError(p, f"cannot read mesh: {e}") from None
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
    if len(F) == 0:
        raise InputError(p, "no faces in the mesh")
    return V, F


def _fan(faces: list[np.ndarray]) -> np.ndarray:
    """Triangle fans of polygon index loops: (M, 3) int64 (triangles pass through unchanged)."""
    out = [np.stack([np.full(len(f) - 2, f[0]), f[1:-1], f[2:]], 1) for f in faces if len(f) >= 3]
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 3), np.int64)


def read_ply_mesh(p: Path) -> tuple[np.ndarray, np.ndarray]:
    """A PLY mesh as ``V`` (N, 3) float64, ``F`` (M, 3) int64 (polygons fanned into triangles).

    Binary triangle meshes (any scalar face properties): vectorised (:func:`mst.core.ply.read_mesh`);
    other binary layouts: trimesh after the header check; ASCII: one element instance per line,
    every line checked. Bad headers, short bodies and missing faces raise :class:`mst.InputError`.
    """
    h = read_header(p)
    if h.element("face") is None:
        raise InputError(p, "PLY has no 'face' element (a point cloud, not a mesh)")
    mesh = read_mesh(h)
    if mesh is not None:
        F = mesh.faces if isinstance(mesh.faces, np.ndarray) else _fan(mesh.faces)
        return mesh.vertices, F
    V, F = _trimesh_load(p)
    nv = h.element("vertex").count
    if len(V) != nv:
        raise InputError(p, f"PLY announces {nv} vertices, {len(V)} were read")
    return V, F


def write_ply_triangles(p: Path, V: np.ndarray, F: np.ndarray) -> None:
    """Binary PLY with float64 vertices (trimesh would write float32) and int triangles."""
    V = np.asarray(V, np.float64)
    write_ply(p, {"x": V[:, 0], "y": V[:, 1], "z": V[:, 2]}, np.asarray(F, np.int64), comments=["mst triangle mesh"])
