"""The surfaces of ViSP's curved primitives: a model's cylinders as closed triangle meshes.

A ViSP ``.cao`` cylinder is the surface of revolution of radius ``r`` about the segment from point
``p1`` to point ``p2``; ViSP tracks it by its two limbs (the lines where the view rays graze it), which
are the silhouette of that surface. mst renders it: :func:`model_triangles` adds each cylinder, closed
by its two end discs, to the model's triangulated polygon faces, so every stage that reads a model
as triangles (``mst synth``, ``c2m``, ``refine``, render-based edges) sees the cylinder, and its
silhouette and its end rims (creases at 90 deg) come out of the render. A ``.cao`` circle is a 3D
curve, not a surface: where it is the rim of a cylinder's end (:func:`circle_on_cylinder_end`) the
render has it as that crease.

Frames and units: model frame, metres (the model's unit).
"""

from __future__ import annotations

import numpy as np

#: sides of a tessellated cylinder: the chords lie within ``r (1 - cos(pi / n))`` = 7.5e-5 r of the
#: surface (0.004 mm for a 5 cm radius, 0.01 px at 1 m with f = 600 px)
CYLINDER_SEGMENTS = 256


def cylinder_surface(p1: np.ndarray, p2: np.ndarray, radius: float,
                     segments: int = CYLINDER_SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """Closed triangle mesh of the cylinder of ``radius`` about the segment ``p1`` -> ``p2`` (3,):
    ``segments`` sides and the two end discs (``trimesh.creation.cylinder``, watertight).

    Returns ``V`` (K, 3) float64 and ``F`` (4 segments, 3) int64, wound so that the right-hand normals point
    out. Raises ``ValueError`` for a zero-length axis or a radius that is not positive.
    """
    import trimesh

    p1 = np.asarray(p1, np.float64).reshape(3)
    p2 = np.asarray(p2, np.float64).reshape(3)
    length = float(np.linalg.norm(p2 - p1))
    if not length > 0.0 or not radius > 0.0:
        raise ValueError(f"cylinder with an axis of length {length:g} and a radius of {radius:g}")
    m = trimesh.creation.cylinder(radius=float(radius), segment=np.stack([p1, p2]), sections=int(segments))
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def model_triangles(model) -> tuple[np.ndarray, np.ndarray]:
    """``(V (N, 3), F (M, 3) int64)``: the model's polygon faces triangulated (:meth:`PolygonModel.triangulate`,
    their vertices first, as there) and each of its cylinders as a closed surface (:func:`cylinder_surface`)."""
    V, F = model.triangulate()
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    cyl = getattr(model, "cylinders", None) or []
    if not cyl:
        return V, F
    Vs, Fs, off = [V], [F], len(V)
    for c in cyl:
        Vc, Fc = cylinder_surface(model.vertices[int(c["p1"])], model.vertices[int(c["p2"])], float(c["radius"]))
        Vs.append(Vc)
        Fs.append(Fc + off)
        off += len(Vc)
    return np.concatenate(Vs), np.concatenate(Fs)


def circle_on_cylinder_end(model, circle: dict, rel_tol: float = 1e-3) -> bool:
    """Whether a ``.cao`` circle is the rim of one of the model's cylinder ends: the same radius, its
    centre on that end's centre and its plane normal to the axis (within ``rel_tol`` x the radius)."""
    V = model.vertices
    c = V[int(circle["center"])]
    r = float(circle["radius"])
    n = np.cross(V[int(circle["p1"])] - c, V[int(circle["p2"])] - c)
    nn = float(np.linalg.norm(n))
    if not nn > 0.0:
        return False
    n /= nn
    tol = rel_tol * r
    for cy in getattr(model, "cylinders", None) or []:
        p1, p2 = V[int(cy["p1"])], V[int(cy["p2"])]
        a = (p2 - p1) / max(float(np.linalg.norm(p2 - p1)), 1e-300)
        if abs(float(cy["radius"]) - r) > tol or np.linalg.norm(np.cross(a, n)) * r > tol:
            continue
        if min(np.linalg.norm(c - p1), np.linalg.norm(c - p2)) <= tol:
            return True
    return False
