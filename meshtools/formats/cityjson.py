"""CityJSON 1.0-2.0: every surface of every city object (one LoD per object), vertex transform
applied, holes kept, geometry templates resolved; read only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mst import InputError
from mst.meshtools.model import PolygonModel


def read_cityjson(p: Path, lod: str | None = None) -> PolygonModel:
    """CityJSON 1.0-2.0: every surface of every city object, holes kept, transform applied.

    Per city object only the geometries of one LoD are read (``lod``, default the highest the
    object has), so that LoD1 and LoD2 shells are not stacked. Face names are the city object ids
    (a face of a BuildingPart is named after the part). GeometryInstance (templates) are resolved
    with their transformation matrix. Vertices: ``vertex * scale + translate`` (metres in the file's CRS).
    """
    with open(p, encoding="utf-8") as fh:
        try:
            d = json.load(fh)
        except json.JSONDecodeError as e:
            raise InputError(p, f"not valid JSON: {e}") from None
    if not isinstance(d, dict) or d.get("type") != "CityJSON":
        raise InputError(p, "not a CityJSON file (type != 'CityJSON')")
    V = _vertices(p, d)
    extra_V: list[np.ndarray] = []
    nV = len(V)
    tmpl = d.get("geometry-templates") or {}
    tV = np.asarray(tmpl.get("vertices-templates", []), np.float64).reshape(-1, 3)
    faces: list[np.ndarray] = []
    holes: list[list[np.ndarray]] = []
    names: list[str | None] = []
    cos = d.get("CityObjects", {})
    if not isinstance(cos, dict):
        raise InputError(p, "CityJSON 'CityObjects' is not a JSON object")
    for oid, obj in cos.items():
        if not isinstance(obj, dict):
            raise InputError(p, f"city object {oid!r} is not a JSON object")
        geoms = obj.get("geometry", []) or []
        if not isinstance(geoms, list):
            raise InputError(p, f"city object {oid!r}: 'geometry' is not a list")
        if not geoms:
            continue
        if not all(isinstance(g, dict) for g in geoms):
            raise InputError(p, f"city object {oid!r}: a geometry is not a JSON object")
        lods = [str(g.get("lod", "")) for g in geoms]
        want = lod if lod is not None else max(lods, key=lambda s: (_lod_key(s)))
        for g, gl in zip(geoms, lods):
            if g.get("type") == "GeometryInstance":
                tg = tmpl.get("templates", [])[g["template"]]
                if lod is not None and str(tg.get("lod", "")) != lod:
                    continue
                M = np.asarray(g["transformationMatrix"], float).reshape(4, 4)
                ref = V[g["boundaries"][0]]
                used = sorted({i for s in _surfaces(p, oid, tg) for ring in s for i in ring})
                remap = {u: nV + j for j, u in enumerate(used)}
                X = tV[used] @ M[:3, :3].T + M[:3, 3] + ref
                extra_V.append(X)
                nV += len(X)
                for s in _surfaces(p, oid, tg):
                    rings = [np.array([remap[i] for i in ring], np.int64) for ring in s]
                    faces.append(rings[0])
                    holes.append(rings[1:])
                    names.append(oid)
                continue
            if gl != want:
                continue
            for s in _surfaces(p, oid, g):
                rings = [np.asarray(ring, np.int64) for ring in s]
                if not rings or len(rings[0]) < 3:
                    continue
                faces.append(rings[0])
                holes.append([r for r in rings[1:] if len(r) >= 3])
                names.append(oid)
    if extra_V:
        V = np.concatenate([V, *extra_V])
    return PolygonModel(V, faces, holes=holes, names=names)


def _vertices(p: Path, d: dict) -> np.ndarray:
    """The file's vertices (N, 3) in metres: ``vertex * scale + translate``."""
    try:
        V = np.asarray(d.get("vertices", []), dtype=np.float64)
    except (ValueError, TypeError):
        raise InputError(p, "CityJSON 'vertices' is not a list of [x, y, z] numbers") from None
    if V.size and (V.ndim != 2 or V.shape[1] != 3):
        raise InputError(p, "CityJSON 'vertices' is not a list of [x, y, z] numbers")
    V = V.reshape(-1, 3)
    tr = d.get("transform")
    version = str(d.get("version", ""))
    if tr is None and version not in ("", "1.0") and len(V):
        raise InputError(p, f"CityJSON {version} without 'transform' (required since 1.1: vertices are integers to scale)")
    if tr is not None:
        try:
            sc = np.asarray(tr["scale"], float).reshape(3)
            tl = np.asarray(tr["translate"], float).reshape(3)
        except (KeyError, TypeError, ValueError):
            raise InputError(p, "CityJSON 'transform' needs 'scale' and 'translate' of 3 numbers each") from None
        if not (np.isfinite(sc).all() and np.isfinite(tl).all()) or (sc == 0).any():
            raise InputError(p, "CityJSON 'transform' scale/translate must be finite, scale non-zero")
        V = V * sc + tl
    return V


def _ring_ok(ring) -> bool:
    return isinstance(ring, list) and all(type(i) is int for i in ring)


def _surfaces(p: Path, oid: str, geom: dict):
    """Surfaces (lists of rings of int vertex indices) of a geometry of city object ``oid``; wrong
    nesting or a non-integer index (1.5, "3", null) raises InputError naming the object."""
    if not isinstance(geom, dict):
        raise InputError(p, f"city object {oid!r}: a geometry is not a JSON object")
    t = geom.get("type")
    b = geom.get("boundaries", [])
    depth = {"MultiSurface": 0, "CompositeSurface": 0, "Solid": 1, "MultiSolid": 2, "CompositeSolid": 2}.get(t)
    if depth is None:
        return  # points, lines: no surfaces
    level = [b]
    for _ in range(depth + 1):
        if not all(isinstance(x, list) for x in level):
            raise InputError(p, f"city object {oid!r}: {t} boundaries are not nested {depth + 3} deep")
        level = [y for x in level for y in x]
    for surf in level:
        if not isinstance(surf, list) or not all(_ring_ok(r) for r in surf):
            raise InputError(p, f"city object {oid!r}: {t} boundary holds a ring that is not a list of "
                                "integer vertex indices (wrong nesting, or an index like 1.5)")
        yield surf


def _lod_key(s: str) -> tuple:
    try:
        return (float(s),)
    except ValueError:
        return (-1.0,)
