"""mst.meshtools.formats: reading and writing polygon models and triangle meshes, one module per format,
dispatched here by suffix (:func:`load_model`, :func:`load_triangles`, :func:`save_model`, :func:`save_triangles`).
Imports numpy, :mod:`mst`, :mod:`mst.core` (PLY) and :mod:`mst.meshtools.model` / :mod:`~mst.meshtools.polygons`.

Formats (chosen by suffix, case-insensitive):

========================  ======  ======  ===========================================================
suffix                    read    write   notes
========================  ======  ======  ===========================================================
``.obj``                  yes     yes     polygon faces kept (``f`` with any vertex count), ``l`` lines,
                                          ``o``/``g`` names; negative indices and ``v/vt/vn`` accepted
``.wrl`` ``.vrml``        yes     yes     VRML 2.0 ``IndexedFaceSet`` polygons, several ``Shape``\\ s,
                                          ``Transform``/``Group`` nesting (translation, rotation, scale,
                                          center, scaleOrientation), ``DEF``/``USE``; ``Switch``: the
                                          chosen child, ``LOD``: the first level; Inline not followed
``.cao``                  yes     yes     ViSP model V1/V2: points, lines, faces from lines, faces from
                                          points, cylinders, circles, ``load("sub.cao", t=[..], tu=[..])``
                                          as loadCAOModel reads them (see read_cao)
``.off``                  yes     no      polygon faces kept
``.ply``                  yes     no      :mod:`mst.core.ply` (triangles; polygons fanned)
``.stl``                  yes     no      binary or ASCII (triangles)
``.json`` ``.city.json``  yes     no      CityJSON 1.0-2.0: every surface of every city object (highest
                                          LoD per object), vertex transform applied, holes kept
========================  ======  ======  ===========================================================

Holes on write: VRML ``IndexedFaceSet`` and ViSP ``.cao`` polygons cannot carry holes, and ViSP's
reader accepts only one index loop per face. A face with holes is therefore written as ONE
weakly-simple polygon: each hole is cut open by a *bridge* (a pair of coincident, opposite edges
from a vertex of the outer loop, or of an already bridged hole, to the nearest visible vertex of the
hole). The polygon encloses exactly the face's area, its outline draws every edge of the outer loop
and holes, and it triangulates correctly with ear clipping. OBJ keeps the same convention so that
all three writers agree. The bridge edges are not image edges: they are the only edges a polygon
uses twice (once each way). :func:`load_model` undoes the bridges of such faces
(:func:`~mst.meshtools.polygons.unbridge_faces`), so a model read back from our own file has its holes again and
``PolygonModel.edges()`` contains no bridge; readers that take the file as is (ViSP) still get a
correct, weakly-simple polygon.

Every loop is written starting at a strictly convex corner, so the first three points of a polygon
give its outward normal (ViSP computes visibility from them).

Units and frames: vertices are in the model frame, in the file's unit (metres for mst models).
Bad files raise :class:`mst.InputError` naming the file and the problem.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mst import InputError, require_file
from mst.meshtools.formats.cao import cao_text, read_cao
from mst.meshtools.formats.cityjson import read_cityjson
from mst.meshtools.formats.obj import obj_text, read_obj, read_obj_triangles, write_obj_triangles
from mst.meshtools.formats.off import read_off
from mst.meshtools.formats.ply import read_ply_mesh, write_ply_triangles
from mst.meshtools.formats.stl import read_stl
from mst.meshtools.formats.vrml import read_vrml, vrml_text
from mst.meshtools.model import PolygonModel
from mst.meshtools.polygons import unbridge_faces

MODEL_SUFFIXES = (".obj", ".wrl", ".vrml", ".cao", ".off", ".ply", ".stl", ".json")
WRITE_SUFFIXES = (".obj", ".wrl", ".vrml", ".cao")


def _triangle_model(read: Callable[[Path], tuple[np.ndarray, np.ndarray]]) -> Callable[[Path], PolygonModel]:
    """A polygon model reader from a triangle reader (each triangle one face)."""

    def load(p: Path) -> PolygonModel:
        V, F = read(p)
        return PolygonModel(V, list(F))

    return load


#: suffix -> polygon model reader (``.city.json`` is ``.json``)
READERS: dict[str, Callable[[Path], PolygonModel]] = {
    ".obj": read_obj, ".wrl": read_vrml, ".vrml": read_vrml, ".cao": read_cao, ".off": read_off,
    ".ply": _triangle_model(read_ply_mesh), ".stl": _triangle_model(read_stl), ".json": read_cityjson}
#: suffix -> polygon model text writer
WRITERS: dict[str, Callable[[PolygonModel], str]] = {".obj": obj_text, ".wrl": vrml_text, ".vrml": vrml_text,
                                                     ".cao": cao_text}


def model_suffix(path: Path) -> str:
    """The lower-case suffix that picks a format (``.city.json`` counts as ``.json``)."""
    name = path.name.lower()
    if name.endswith(".city.json"):
        return ".json"
    return path.suffix.lower()


def load_model(path: str | os.PathLike) -> PolygonModel:
    """Read a polygon model (see the module docstring for formats).

    Raises :class:`mst.InputError` for a missing, unreadable, corrupt or empty file, for indices out
    of range, and for NaN or infinite coordinates.
    """
    p = require_file(path, "model file")
    suf = model_suffix(p)
    with np.errstate(all="ignore"):  # overflow to inf etc. is reported as an InputError below
        return _load_model(p, suf)


def _load_model(p: Path, suf: str) -> PolygonModel:
    try:
        reader = READERS.get(suf)
        if reader is None:
            raise InputError(p, f"unknown model format {p.suffix!r} (expected one of {', '.join(MODEL_SUFFIXES)})")
        m = reader(p)
    except InputError:
        raise
    except UnicodeDecodeError:
        raise InputError(p, f"not a text {suf} file (binary or wrong encoding)") from None
    except RecursionError:
        raise InputError(p, f"{suf} file nested too deeply") from None
    except (ValueError, IndexError, KeyError, TypeError, AttributeError, OverflowError) as e:
        raise InputError(p, f"corrupt {suf} file: {type(e).__name__}: {e}") from None
    _validate(m, p)
    if suf in (".obj", ".wrl", ".vrml", ".cao", ".off"):
        m = unbridge_faces(m)
    return m


def load_tracking_model(path: str | os.PathLike) -> PolygonModel:
    """Read a polygon model with :func:`load_model` and check that it can be tracked.

    Raises :class:`mst.InputError` naming the file for a missing file, a model without faces or
    lines, non-finite vertices, or degenerate geometry (all vertices at one point or on one line:
    no edge of it constrains a pose). The model loader of ``mst track``, ``init`` and auto-init."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "model file does not exist")
    model = load_model(p)
    if not len(model.faces) and not len(getattr(model, "lines", [])) and not model.cylinders:
        extra = (f" (its {len(model.circles)} circle(s) alone are not tracked: a circle is tracked as the end rim of a "
                 "cylinder)") if model.circles else ""
        raise InputError(p, "model has no faces" + extra)
    model.check_finite(str(p))
    V = np.asarray(model.vertices, float).reshape(-1, 3)
    used = np.unique(np.concatenate([np.asarray(f, np.int64).ravel() for f in model.faces]
                                    + [np.asarray(getattr(model, "lines", []), np.int64).ravel()]))
    X = V[used[(used >= 0) & (used < len(V))]]
    if model.cylinders:  # a cylinder spans its surface, not only its axis
        from mst.meshtools.solids import cylinder_surface

        X = np.concatenate([X] + [cylinder_surface(V[int(c["p1"])], V[int(c["p2"])], float(c["radius"]), 8)[0]
                                  for c in model.cylinders])
    ext = float(np.ptp(X, axis=0).max()) if len(X) else 0.0
    # rank of the centred vertices: 0 = one point, 1 = one line (relative to the model's size)
    sv = np.linalg.svd(X - X.mean(0), compute_uv=False) if len(X) >= 2 else np.zeros(1)
    if ext <= 0.0 or sv.size < 2 or sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise InputError(p, "model is degenerate: its vertices lie at one point or on one line")
    return model


def load_triangles(path: str | os.PathLike, primitives: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read any supported model as a triangle mesh.

    Returns ``V`` (N, 3) float64 (model frame, file units, normally metres) and ``F`` (M, 3) int64.
    Polygons (with holes) are triangulated with earcut, and a ``.cao``'s cylinders added as closed surfaces
    (:func:`mst.meshtools.solids.model_triangles`); triangle files (OBJ/PLY/STL/OFF with only
    triangles) keep their vertices and faces exactly as stored (no welding, no reordering).
    ``primitives=False``: the polygon faces only (a ``.cao``'s cylinders left out).
    """
    p = require_file(path, "mesh file")
    with np.errstate(all="ignore"):  # overflow to inf etc. is reported as an InputError
        return _load_triangles(p, model_suffix(p), primitives)


def _load_triangles(p: Path, suf: str, primitives: bool = True) -> tuple[np.ndarray, np.ndarray]:
    if suf in (".ply", ".stl"):
        try:
            V, F = read_ply_mesh(p) if suf == ".ply" else read_stl(p)
        except (ValueError, IndexError, KeyError, TypeError, AttributeError, OverflowError) as e:
            raise InputError(p, f"corrupt {suf} file: {type(e).__name__}: {e}") from None
        _check_arrays(V, F, p)
        return V, F
    if suf == ".obj":
        try:
            fast = read_obj_triangles(p)
        except ValueError:  # anything odd: the general reader says what and where
            fast = None
        if fast is not None:
            V, F = fast
            _check_arrays(V, F, p)
            return V, F
    from mst.meshtools.solids import model_triangles

    m = load_model(p)
    V, F = model_triangles(m) if primitives else m.triangulate()  # with a .cao's cylinders' surfaces, or not
    _check_arrays(V, F, p)
    return V, F


def save_model(path: str | os.PathLike, model: PolygonModel) -> None:
    """Write ``model`` to ``path`` (.wrl, .cao or .obj by suffix). Holes are bridged (module doc).

    The file is written as given: wrap the call in :func:`mst.atomic_output` for all-or-nothing
    output in a stage.
    """
    p = Path(path)
    suf = model_suffix(p)
    writer = WRITERS.get(suf)
    if writer is None:
        raise InputError(p, f"cannot write {p.suffix!r} (expected one of {', '.join(WRITE_SUFFIXES)})")
    text = writer(model)
    with open(p, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(text)


def save_triangles(path: str | os.PathLike, V: np.ndarray, F: np.ndarray) -> None:
    """Write a triangle mesh: ``.obj`` (text), ``.ply`` (binary, float64 vertices) or what trimesh
    exports (.stl float32, .off)."""
    p = Path(path)
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if model_suffix(p) == ".obj":
        write_obj_triangles(p, V, F)
        return
    if model_suffix(p) == ".ply":  # binary PLY with float64 vertices (trimesh would write float32)
        write_ply_triangles(p, V, F)
        return
    import trimesh

    trimesh.Trimesh(V, F, process=False).export(p)


def _check_arrays(V: np.ndarray, F: np.ndarray, path) -> None:
    if len(F) == 0:
        raise InputError(path, "no faces in the mesh")
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates (first: #{int(np.argmax(bad))})")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(path, f"face index out of range (vertices: {len(V)}, index {int(F.max() if F.max() >= len(V) else F.min())})")


def _validate(m: PolygonModel, path) -> None:
    if m.n_faces == 0 and len(m.lines) == 0 and not m.cylinders and not m.circles:
        raise InputError(path, "no faces in the model")
    m.check_finite(str(path))
    n = len(m.vertices)
    loops = m.loops()
    if loops:
        allidx = np.concatenate(loops)
        if len(allidx) and (allidx.min() < 0 or allidx.max() >= n):
            raise InputError(path, f"a face has a vertex index out of range (vertices: {n})")
    short = [i for i, f in enumerate(m.faces) if len(f) < 3]
    if short:
        raise InputError(path, f"face {short[0]} has {len(m.faces[short[0]])} vertices (need at least 3)")
    if len(m.lines) and (m.lines.min() < 0 or m.lines.max() >= n):
        raise InputError(path, f"line vertex index out of range (vertices: {n})")
    for i, c in enumerate(m.cylinders):  # indices were checked by the reader
        if not np.linalg.norm(m.vertices[int(c["p2"])] - m.vertices[int(c["p1"])]) > 0.0:
            raise InputError(path, f"cylinder {i}: its two axis points {int(c['p1'])} and {int(c['p2'])} coincide "
                                   "(a zero-length axis)")


__all__ = ["MODEL_SUFFIXES", "WRITE_SUFFIXES", "load_model", "load_tracking_model", "load_triangles", "model_suffix",
           "save_model", "save_triangles", "read_cao", "read_cityjson", "read_obj", "read_off", "read_vrml"]
