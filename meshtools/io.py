"""Read and write polygon models and triangle meshes.

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
``.ply`` ``.stl``         yes     no      through trimesh (triangles)
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
(:func:`unbridge_faces`), so a model read back from our own file has its holes again and
``PolygonModel.edges()`` contains no bridge; readers that take the file as is (ViSP) still get a
correct, weakly-simple polygon.

Every loop is written starting at a strictly convex corner, so the first three points of a polygon
give its outward normal (ViSP computes visibility from them).

Units and frames: vertices are in the model frame, in the file's unit (metres for mst models).
Bad files raise :class:`mst.InputError` naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np

from mst import InputError, require_file
from mst.meshtools.model import PolygonModel

MODEL_SUFFIXES = (".obj", ".wrl", ".vrml", ".cao", ".off", ".ply", ".stl", ".json")
WRITE_SUFFIXES = (".obj", ".wrl", ".vrml", ".cao")


def _suffix(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".city.json"):
        return ".json"
    return path.suffix.lower()


# ====================================================================== public API
def load_model(path: str | os.PathLike) -> PolygonModel:
    """Read a polygon model (see the module docstring for formats).

    Raises :class:`mst.InputError` for a missing, unreadable, corrupt or empty file, for indices out
    of range, and for NaN or infinite coordinates.
    """
    p = require_file(path, "model file")
    suf = _suffix(p)
    with np.errstate(all="ignore"):  # overflow to inf etc. is reported as an InputError below
        return _load_model(p, suf)


def _load_model(p: Path, suf: str) -> PolygonModel:
    try:
        if suf == ".obj":
            m = read_obj(p)
        elif suf in (".wrl", ".vrml"):
            m = read_vrml(p)
        elif suf == ".cao":
            m = read_cao(p)
        elif suf == ".off":
            m = read_off(p)
        elif suf == ".ply":
            V, F = _read_ply_mesh(p)
            m = PolygonModel(V, list(F))
        elif suf == ".stl":
            V, F = _read_stl(p)
            m = PolygonModel(V, list(F))
        elif suf == ".json":
            m = read_cityjson(p)
        else:
            raise InputError(p, f"unknown model format {p.suffix!r} (expected one of {', '.join(MODEL_SUFFIXES)})")
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


def load_triangles(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read any supported model as a triangle mesh.

    Returns ``V`` (N, 3) float64 (model frame, file units, normally metres) and ``F`` (M, 3) int64.
    Polygons (with holes) are triangulated with earcut; triangle files (OBJ/PLY/STL/OFF with only
    triangles) keep their vertices and faces exactly as stored (no welding, no reordering).
    """
    p = require_file(path, "mesh file")
    with np.errstate(all="ignore"):  # overflow to inf etc. is reported as an InputError
        return _load_triangles(p, _suffix(p))


def _load_triangles(p: Path, suf: str) -> tuple[np.ndarray, np.ndarray]:
    if suf in (".ply", ".stl"):
        try:
            V, F = _read_ply_mesh(p) if suf == ".ply" else _read_stl(p)
        except (ValueError, IndexError, KeyError, TypeError, AttributeError, OverflowError) as e:
            raise InputError(p, f"corrupt {suf} file: {type(e).__name__}: {e}") from None
        _check_arrays(V, F, p)
        return V, F
    if suf == ".obj":
        try:
            fast = _read_obj_triangles_fast(p)
        except ValueError:  # anything odd: the general reader says what and where
            fast = None
        if fast is not None:
            V, F = fast
            _check_arrays(V, F, p)
            return V, F
    m = load_model(p)
    V, F = m.triangulate()
    _check_arrays(V, F, p)
    return V, F


def save_model(path: str | os.PathLike, model: PolygonModel) -> None:
    """Write ``model`` to ``path`` (.wrl, .cao or .obj by suffix). Holes are bridged (module doc).

    The file is written as given: wrap the call in :func:`mst.atomic_output` for all-or-nothing
    output in a stage.
    """
    p = Path(path)
    suf = _suffix(p)
    if suf in (".wrl", ".vrml"):
        text = vrml_text(model)
    elif suf == ".cao":
        text = cao_text(model)
    elif suf == ".obj":
        text = obj_text(model)
    else:
        raise InputError(p, f"cannot write {p.suffix!r} (expected one of {', '.join(WRITE_SUFFIXES)})")
    with open(p, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(text)


def save_triangles(path: str | os.PathLike, V: np.ndarray, F: np.ndarray) -> None:
    """Write a triangle mesh: ``.obj`` (text), ``.ply`` (binary, float64 vertices) or what trimesh
    exports (.stl float32, .off)."""
    p = Path(path)
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if _suffix(p) == ".obj":
        with open(p, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(f"# {len(V)} vertices, {len(F)} triangles\n")
            fh.write(_fmt_rows("v", V))
            fh.write(_fmt_rows("f", F + 1))
        return
    if _suffix(p) == ".ply":  # binary PLY with float64 vertices (trimesh would write float32)
        head = (f"ply\nformat binary_little_endian 1.0\ncomment mst triangle mesh\nelement vertex {len(V)}\n"
                "property double x\nproperty double y\nproperty double z\n"
                f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
        rec = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        rec["n"] = 3
        rec["i"] = F
        with open(p, "wb") as fh:
            fh.write(head.encode("ascii"))
            fh.write(V.astype("<f8").tobytes())
            fh.write(rec.tobytes())
        return
    import trimesh

    trimesh.Trimesh(V, F, process=False).export(p)


# ====================================================================== checks
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


def ply_header(p: Path) -> tuple[str, list[tuple[str, int, list[list[str]]]], int]:
    """Strictly parsed PLY header: ``(format, [(element, count, [property tokens])], data offset)``.

    Raises :class:`mst.InputError` for a missing ``end_header``, an unknown format or type, a
    negative or non-integer element count, a ``property list`` on a vertex coordinate, no vertex
    x/y/z, and a binary body too short for what the header announces (each face needs at least 3
    indices).
    """
    with open(p, "rb") as fh:
        head = fh.read(1 << 20)
    if not head.startswith(b"ply"):
        raise InputError(p, "not a PLY file (bad magic: it does not start with 'ply')")
    m = re.search(rb"end_header[ \t]*\r?\n", head)
    if not m:
        raise InputError(p, "PLY header has no 'end_header' line (truncated or corrupt)")
    lines = head[:m.start()].decode("ascii", "replace").splitlines()
    fmt = None
    elems: list[tuple[str, int, list[list[str]]]] = []
    for ln in lines[1:]:
        t = ln.split()
        if not t or t[0] in ("comment", "obj_info"):
            continue
        if t[0] == "format":
            fmt = t[1] if len(t) > 1 else None
            if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise InputError(p, f"unknown PLY format {fmt!r}")
        elif t[0] == "element":
            if len(t) != 3 or not re.fullmatch(r"\d+", t[2]):
                raise InputError(p, f"PLY header: bad element line {ln.strip()[:60]!r} (count must be an integer >= 0)")
            elems.append((t[1], int(t[2]), []))
        elif t[0] == "property":
            if not elems:
                raise InputError(p, "PLY header: property before any element")
            if len(t) >= 2 and t[1] == "list":
                if len(t) != 5 or t[2] not in PLY_TYPES or t[3] not in PLY_TYPES:
                    raise InputError(p, f"PLY header: bad list property {ln.strip()[:60]!r}")
                if elems[-1][0] == "vertex" and t[4] in ("x", "y", "z"):
                    raise InputError(p, f"PLY header: vertex coordinate {t[4]!r} declared as a list")
            elif len(t) != 3 or t[1] not in PLY_TYPES:
                raise InputError(p, f"PLY header: bad property {ln.strip()[:60]!r}")
            elems[-1][2].append(t[1:])
        else:
            raise InputError(p, f"PLY header: unexpected line {ln.strip()[:60]!r}")
    if fmt is None:
        raise InputError(p, "PLY header has no 'format' line")
    names = [e[0] for e in elems]
    if "vertex" not in names:
        raise InputError(p, "PLY has no 'vertex' element")
    vprops = [pr[-1] for pr in elems[names.index("vertex")][2]]
    if not {"x", "y", "z"} <= set(vprops):
        raise InputError(p, "PLY vertex element lacks x, y, z properties")
    if fmt != "ascii":
        need = 0
        for name, count, props in elems:
            per = 0
            for pr in props:
                if pr[0] == "list":  # at least the count and, for faces, 3 indices
                    per += np.dtype(PLY_TYPES[pr[1]]).itemsize + (3 * np.dtype(PLY_TYPES[pr[2]]).itemsize if name == "face" else 0)
                else:
                    per += np.dtype(PLY_TYPES[pr[0]]).itemsize
            need += per * count
        have = p.stat().st_size - m.end()
        if have < need:
            counts = ", ".join(f"{c} {n}" for n, c, _ in elems)
            raise InputError(p, f"PLY is truncated: the header announces {counts} (at least {need} bytes), the body has {have}")
    return fmt, elems, m.end()


def _fan(faces: list[np.ndarray]) -> np.ndarray:
    """Triangle fans of polygon index loops: (M, 3) int64 (triangles pass through unchanged)."""
    out = [np.stack([np.full(len(f) - 2, f[0]), f[1:-1], f[2:]], 1) for f in faces if len(f) >= 3]
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 3), np.int64)


def _read_ply_mesh(p: Path) -> tuple[np.ndarray, np.ndarray]:
    """A PLY mesh as ``V`` (N, 3) float64, ``F`` (M, 3) int64 (polygons fanned into triangles).

    Binary triangle meshes: vectorised (:func:`_read_ply_triangles_fast`); other binary layouts:
    trimesh after the header check; ASCII: one element instance per line, every line checked.
    Bad headers, short bodies and missing faces raise :class:`mst.InputError`.
    """
    fmt, elems, start = ply_header(p)
    names = [e[0] for e in elems]
    if "face" not in names:
        raise InputError(p, "PLY has no 'face' element (a point cloud, not a mesh)")
    if fmt == "ascii":
        return _read_ply_ascii(p, elems, start)
    fast = _read_ply_triangles_fast(p)
    if fast is not None:
        return fast
    V, F = _trimesh_load(p)
    nv = elems[names.index("vertex")][1]
    if len(V) != nv:
        raise InputError(p, f"PLY announces {nv} vertices, {len(V)} were read")
    return V, F


def _read_ply_ascii(p: Path, elems, start: int) -> tuple[np.ndarray, np.ndarray]:
    with open(p, "rb") as fh:
        fh.seek(start)
        body = fh.read()
    try:
        rows = body.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError(p, "ascii PLY body has non-ASCII bytes") from None
    rows = [r for r in rows if r.strip()]
    k = 0
    V = F = None
    for name, count, props in elems:
        if k + count > len(rows):
            raise InputError(p, f"ascii PLY is truncated: {count} {name} elements announced, {len(rows) - k} lines left")
        chunk = rows[k:k + count]
        k += count
        if name == "vertex":
            if any(pr[0] == "list" for pr in props):
                raise InputError(p, "ascii PLY vertex with list properties is not supported")
            cols = [[pr[-1] for pr in props].index(c) for c in "xyz"]
            try:
                A = np.array(" ".join(chunk).split(), dtype=np.float64)
            except ValueError:
                raise InputError(p, "ascii PLY: a vertex value is not a number") from None
            if A.size != count * len(props):
                raise InputError(p, f"ascii PLY: vertex lines hold {A.size} numbers, {count} x {len(props)} expected")
            V = A.reshape(count, len(props))[:, cols]
        elif name == "face":
            lists = [i for i, pr in enumerate(props) if pr[0] == "list"]
            named = [i for i in lists if props[i][-1] in ("vertex_indices", "vertex_index")]
            if not lists:
                raise InputError(p, "ascii PLY face element without an index list")
            which = (named or lists)[0]
            faces = []
            for j, r in enumerate(chunk):
                t = r.split()
                pos, idx = 0, None
                try:
                    for i, pr in enumerate(props):  # one instance per line, properties in header order
                        if pr[0] == "list":
                            n = int(t[pos])
                            vals = t[pos + 1:pos + 1 + n]
                            if i == which:
                                idx = [int(x) for x in vals]
                                if n < 3 or len(idx) != n:
                                    raise IndexError
                            pos += 1 + n
                        else:
                            float(t[pos])
                            pos += 1
                except (ValueError, IndexError):
                    raise InputError(p, f"ascii PLY: face {j} is not a list of >= 3 integer indices with its "
                                        f"properties ({r.strip()[:40]!r})") from None
                if pos != len(t):
                    raise InputError(p, f"ascii PLY: face {j} has {len(t)} values, its properties need {pos} "
                                        f"({r.strip()[:40]!r})")
                faces.append(np.array(idx, np.int64))
            F = _fan(faces)
    if V is None or F is None:
        raise InputError(p, "ascii PLY without vertex or face data")
    return V, F


def _read_stl(p: Path) -> tuple[np.ndarray, np.ndarray]:
    """STL (binary or ASCII) as unwelded triangles: ``V`` (3M, 3) float64, ``F`` (M, 3)."""
    data = p.read_bytes()
    if len(data) >= 84:
        n = int(np.frombuffer(data, "<u4", 1, 80)[0])
        if len(data) == 84 + 50 * n:
            rec = np.frombuffer(data, dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")], count=n, offset=84)
            V = rec["v"].reshape(-1, 3).astype(np.float64)
            return V, np.arange(len(V), dtype=np.int64).reshape(-1, 3)
    if data.lstrip()[:5].lower() != b"solid":
        size = f"{len(data)} bytes" + (f", a binary STL of {n} triangles needs {84 + 50 * n}" if len(data) >= 84 else "")
        raise InputError(p, f"not an STL file or truncated ({size})")
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        raise InputError(p, "ascii STL with non-ASCII bytes (or a binary STL whose size does not match its count)") from None
    toks = re.findall(r"(?im)^\s*vertex\s+(\S+)\s+(\S+)\s+(\S+)\s*$", text)
    n_vert_lines = len(re.findall(r"(?im)^\s*vertex\b", text))
    if n_vert_lines != len(toks):
        raise InputError(p, "ascii STL is truncated or corrupt: a 'vertex' line does not hold exactly 3 values")
    try:
        V = np.array(toks, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise InputError(p, "ascii STL: a vertex coordinate is not a number") from None
    if len(V) % 3 or len(re.findall(r"(?im)^\s*endfacet\b", text)) * 3 != len(V):
        raise InputError(p, f"ascii STL is truncated or corrupt ({len(V)} vertices, not 3 per facet)")
    return V, np.arange(len(V), dtype=np.int64).reshape(-1, 3)


#: PLY scalar type names -> numpy dtype codes (the one table of the project)
PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply_triangles_fast(p: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Vectorised reader for binary PLY triangle meshes (``vertex`` x y z + ``face`` lists of 3).

    Returns None for anything else (ASCII, polygons, unusual layouts): trimesh reads those.
    Avoids importing trimesh (about 1 s) on the common path.
    """
    with open(p, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        return None
    lines = head[:end].decode("ascii", "replace").splitlines()
    fmt = None
    elems: list[tuple[str, int, list]] = []
    for ln in lines[1:]:
        t = ln.split()
        if not t or t[0] in ("comment", "obj_info"):
            continue
        if t[0] == "format":
            fmt = t[1]
        elif t[0] == "element":
            elems.append((t[1], int(t[2]), []))
        elif t[0] == "property" and elems:
            elems[-1][2].append(t[1:])
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        return None
    bo = "<" if fmt == "binary_little_endian" else ">"
    data = np.memmap(p, dtype=np.uint8, mode="r", offset=end + len(b"end_header\n"))
    pos = 0
    V = F = None
    for name, count, props in elems:
        if name == "vertex":
            try:
                dt = np.dtype([(pr[1], bo + PLY_TYPES[pr[0]]) for pr in props])
            except (KeyError, IndexError):
                return None
            if not {"x", "y", "z"} <= set(dt.names):
                return None
            n = count * dt.itemsize
            rec = np.frombuffer(data[pos:pos + n], dtype=dt, count=count)
            V = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
            pos += n
        elif name == "face":
            if len(props) != 1 or props[0][0] != "list" or props[0][3] not in ("vertex_indices", "vertex_index"):
                return None
            try:
                ct, it = PLY_TYPES[props[0][1]], PLY_TYPES[props[0][2]]
            except KeyError:
                return None
            dt = np.dtype([("n", bo + ct), ("i", bo + it, (3,))])
            n = count * dt.itemsize
            if pos + n > len(data):
                return None
            rec = np.frombuffer(data[pos:pos + n], dtype=dt, count=count)
            if count and not (rec["n"] == 3).all():
                return None
            F = rec["i"].astype(np.int64)
            pos += n
        else:
            if any(pr[0] == "list" for pr in props):
                if V is not None and F is not None:
                    break
                return None
            try:
                pos += count * sum(np.dtype(PLY_TYPES[pr[0]]).itemsize for pr in props)
            except KeyError:
                return None
    if V is None or F is None or pos > len(data):
        return None
    return V, F


# ====================================================================== number formatting
def _fmt_num(x: float) -> str:
    """Shortest text that reads back to the same float64 (``repr``), integers without ``.0``."""
    x = float(x)
    if x == 0.0:
        return "0"
    if x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


def _fmt_rows(tag: str, A: np.ndarray) -> str:
    """Rows of numbers as ``tag a b c`` lines; floats as :func:`_fmt_num` (shortest round-trip
    text, integral values without ``.0``). Vectorised enough for millions of rows."""
    A = np.asarray(A)
    if A.size == 0:
        return ""
    A = A.reshape(len(A), -1)
    k = A.shape[1]
    flat = A.ravel()
    vals = flat.tolist()
    if A.dtype.kind in "iu":
        strs = list(map(str, vals))
    else:
        strs = list(map(repr, vals))
        integral = np.flatnonzero((flat == np.trunc(flat)) & (np.abs(flat) < 1e15))
        for i in integral.tolist():
            strs[i] = str(int(vals[i]))
    lines = map(" ".join, zip(*[strs[j::k] for j in range(k)]))
    pre = f"{tag} " if tag else ""
    return pre + ("\n" + pre).join(lines) + "\n"


# ====================================================================== OBJ
def _read_obj_triangles_fast(p: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Vectorised OBJ reader for pure triangle files (``v`` and ``f a b c`` without slashes).

    Returns None when the file has anything else (the general reader handles it).
    """
    data = p.read_bytes()
    if b"/" in data or b"\\\n" in data:
        return None
    while data[:1] == b"#":  # leading comment lines (cheap)
        data = data[data.find(b"\n") + 1:] if b"\n" in data else b""
    if b"#" in data:
        data = re.sub(rb"(?m)^[ \t]*#[^\n]*\n?", b"", data)
    data = data.replace(b"\r\n", b"\n")
    if not data.endswith(b"\n"):
        data += b"\n"
    # common layout: all "v" lines, then all "f" lines -> parse two blocks in C
    j = data.find(b"\nf ")
    nv_lines = data.count(b"v ", 0, j + 1)
    nf_lines = data.count(b"f ", j + 1)
    if (data.startswith(b"v ") and j > 0 and data.count(b"\n", 0, j + 1) == nv_lines
            and data.count(b"\n", j + 1) == nf_lines and data.count(b"v", 0, j + 1) == nv_lines):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            V = np.fromstring(data[: j + 1].replace(b"v ", b"").decode("ascii", "replace"), sep=" ")
            F = np.fromstring(data[j + 1:].replace(b"f ", b"").decode("ascii", "replace"), dtype=np.int64, sep=" ")
        vl = range(nv_lines)
        fl = range(nf_lines)
    else:
        lines = data.split(b"\n")
        vl = [ln[2:] for ln in lines if ln[:2] == b"v "]
        fl = [ln[2:] for ln in lines if ln[:2] == b"f "]
        other = [ln for ln in lines if ln[:2] not in (b"v ", b"f ") and ln.strip()]
        if other or not fl:
            return None
        try:
            V = np.array(b" ".join(vl).split(), dtype=np.float64)
            F = np.array(b" ".join(fl).split(), dtype=np.int64)
        except ValueError:
            return None
    if len(V) != 3 * len(vl) or len(F) != 3 * len(fl):
        return None
    V = V.reshape(-1, 3)
    F = F.reshape(-1, 3)
    F = np.where(F < 0, F + len(V), F - 1)
    return V, F


def read_obj(p: Path) -> PolygonModel:
    """Wavefront OBJ with polygon faces kept; ``o``/``g`` names become face names; ``l`` lines kept."""
    V: list[list[float]] = []
    faces: list[list[int]] = []
    names: list[str | None] = []
    lines: list[tuple[int, int]] = []
    name: str | None = None
    with open(p, encoding="utf-8", errors="strict") as fh:
        text = fh.read().replace("\\\n", " ")
    for lineno, raw in enumerate(text.splitlines(), 1):
        s = raw.split("#", 1)[0].split()
        if not s:
            continue
        tag = s[0]
        if tag == "v":
            if len(s) not in (4, 5, 7):  # x y z [w] or x y z r g b
                raise InputError(p, f"line {lineno}: vertex needs 3 coordinates (got {len(s) - 1} values)")
            try:
                V.append([float(s[1]), float(s[2]), float(s[3])])
            except ValueError:
                raise InputError(p, f"line {lineno}: vertex coordinate is not a number ({raw.strip()[:40]!r})") from None
        elif tag in ("f", "l"):
            idx = []
            for tok in s[1:]:
                head = tok.split("/", 1)[0]
                if not re.fullmatch(r"[+-]?\d+", head):
                    raise InputError(p, f"line {lineno}: {tag!r} index {tok[:20]!r} is not an integer")
                i = int(head)
                if i == 0 or -i > len(V):  # positive ones are checked once every vertex is read
                    raise InputError(p, f"line {lineno}: {tag!r} index {i} out of range (vertices so far: {len(V)})")
                idx.append(i - 1 if i > 0 else len(V) + i)
            if tag == "f" and len(idx) < 3:
                raise InputError(p, f"line {lineno}: face has {len(idx)} vertices (need at least 3)")
            if tag == "f":
                faces.append(idx)
                names.append(name)
            else:
                lines.extend(zip(idx[:-1], idx[1:]))
        elif tag in ("o", "g"):
            name = " ".join(s[1:]) or None
    return PolygonModel(np.array(V, np.float64).reshape(-1, 3), faces, names=names,
                        lines=np.array(lines, np.int64).reshape(-1, 2))


def obj_text(model: PolygonModel) -> str:
    """OBJ text: ``v`` lines, then ``f`` lines (1-based, holes bridged), ``g name`` when the name changes."""
    out = [f"# mst polygon model: {len(model.vertices)} vertices, {model.n_faces} faces\n", _fmt_rows("v", model.vertices)]
    cur = None
    for f, name in zip(_output_loops(model), model.names):
        if name != cur:
            out.append(f"g {_token(name)}\n" if name else "g\n")  # bare g: no name (reads back as None)
            cur = name
        out.append("f " + " ".join(str(int(i) + 1) for i in f) + "\n")
    if len(model.lines):
        out.append(_fmt_rows("l", model.lines + 1))
    return "".join(out)


def _token(name: str) -> str:
    return re.sub(r"\s+", "_", str(name).strip()) or "_"


# ====================================================================== OFF
def read_off(p: Path) -> PolygonModel:
    """OFF (``OFF`` header, counts, vertices, ``n i0 .. in-1`` faces; polygons kept, colours ignored)."""
    toks_lines = []
    with open(p, encoding="utf-8") as fh:
        for raw in fh:
            s = raw.split("#", 1)[0].split()
            if s:
                toks_lines.append(s)
    if not toks_lines or not toks_lines[0][0].upper().endswith("OFF"):
        raise InputError(p, "not an OFF file (no OFF header)")
    if len(toks_lines) < 2 and not toks_lines[0][1:]:
        raise InputError(p, "OFF file ends after its header (no counts)")
    head = toks_lines[0][1:] or toks_lines[1]
    start = 1 if toks_lines[0][1:] else 2
    if len(head) < 2 or not all(re.fullmatch(r"\d+", x) for x in head[:3]):
        raise InputError(p, f"OFF counts must be integers >= 0 (got {' '.join(head)[:40]!r})")
    nv, nf = int(head[0]), int(head[1])
    rows = toks_lines[start:]
    if len(rows) < nv + nf:
        raise InputError(p, f"truncated: {nv} vertices and {nf} faces announced, {len(rows)} rows found")
    if any(len(r) < 3 for r in rows[:nv]):
        raise InputError(p, "an OFF vertex row has fewer than 3 coordinates")
    try:
        V = np.array([[float(x) for x in r[:3]] for r in rows[:nv]], np.float64).reshape(-1, 3)
    except ValueError:
        raise InputError(p, "an OFF vertex coordinate is not a number") from None
    faces = []
    for j, r in enumerate(rows[nv:nv + nf]):
        if not all(re.fullmatch(r"[+-]?\d+", x) for x in r[:1 + (int(r[0]) if r[0].isdigit() else 0)]):
            raise InputError(p, f"OFF face {j}: indices must be integers ({' '.join(r)[:40]!r})")
        k = int(r[0])
        if k < 3 or len(r) < 1 + k:
            raise InputError(p, f"OFF face {j}: {k} vertices announced, {len(r) - 1} values given (need >= 3)")
        faces.append([int(x) for x in r[1:1 + k]])
    return PolygonModel(V, faces)


# ====================================================================== VRML 2.0
_VRML_TOKEN = re.compile(r'\s*(?:(#[^\n]*)|("(?:[^"\\]|\\.)*")|([{}\[\]])|([^\s,{}\[\]"#]+))|\s*,', re.S)


class _VrmlParser:
    """A small recursive-descent VRML 2.0 parser for geometry (nesting depth = scene depth only)."""

    GROUPS = {"Transform", "Group", "Anchor", "Billboard", "Collision", "LOD", "Switch", "Inline"}

    def __init__(self, text: str, path: Path):
        self.t = text
        self.i = 0
        self.path = path
        self.defs: dict[str, tuple] = {}
        self.V: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.names: list[str | None] = []
        self.nv = 0

    # -- scanning
    def peek(self) -> str | None:
        j = self.i
        while True:
            m = _VRML_TOKEN.match(self.t, j)
            if not m or m.end() == j:
                return None
            if m.group(1) is not None or (m.group(2) is None and m.group(3) is None and m.group(4) is None):
                j = m.end()
                continue
            return m.group(2) or m.group(3) or m.group(4)

    def next(self) -> str:
        while True:
            m = _VRML_TOKEN.match(self.t, self.i)
            if not m or m.end() == self.i:
                if self.t[self.i:].strip():
                    raise InputError(self.path, f"VRML syntax error near offset {self.i}")
                raise InputError(self.path, "unexpected end of VRML file")
            self.i = m.end()
            if m.group(1) is not None or (m.group(2) is None and m.group(3) is None and m.group(4) is None):
                continue
            return m.group(2) or m.group(3) or m.group(4)

    def expect(self, tok: str) -> None:
        got = self.next()
        if got != tok:
            raise InputError(self.path, f"VRML syntax error near offset {self.i}: expected {tok!r}, got {got!r}")

    def numbers(self, k: int) -> list[float]:
        return [float(self.next()) for _ in range(k)]

    def mf_numbers(self) -> np.ndarray:
        """An MF numeric field: ``[ n, n, ... ]`` parsed in one numpy call, or a single value."""
        if self.peek() != "[":
            return np.array([float(self.next())])
        self.expect("[")
        j = self.t.find("]", self.i)
        if j < 0:
            raise InputError(self.path, "unterminated '[' in VRML file")
        chunk = self.t[self.i:j]
        if "#" in chunk:
            chunk = re.sub(r"#[^\n]*", " ", chunk)
        chunk = chunk.replace(",", " ")
        vals = chunk.split()
        try:
            arr = np.array(vals, dtype=np.float64)
        except ValueError:
            raise InputError(self.path, f"non-numeric value in a VRML array near offset {self.i}") from None
        self.i = j + 1
        return arr

    def skip_value(self) -> None:
        tok = self.peek()
        if tok is None:
            raise InputError(self.path, "unexpected end of VRML file")
        if tok == "[":
            self.skip_balanced("[", "]")
        elif tok in ("DEF", "USE") or (tok[0].isalpha() and self._next_is_brace()):
            self.node()
        else:
            # SF values: numbers, TRUE/FALSE, a string, NULL
            self.next()
            while True:
                nt = self.peek()
                if nt is None or not _is_number(nt):
                    break
                self.next()

    def _next_is_brace(self) -> bool:
        save = self.i
        self.next()
        ok = self.peek() == "{"
        self.i = save
        return ok

    def skip_balanced(self, op: str, cl: str) -> None:
        self.expect(op)
        depth = 1
        while depth:
            tok = self.next()
            if tok == op:
                depth += 1
            elif tok == cl:
                depth -= 1

    # -- nodes: a node returns a "scene" = list of (V (n,3), faces, names) after its own transform
    def scene(self) -> None:
        while self.peek() is not None:
            tok = self.peek()
            if tok == "ROUTE":
                for _ in range(4):
                    self.next()
                continue
            if tok in ("PROTO", "EXTERNPROTO"):
                self.next()
                self.next()
                self.skip_balanced("[", "]")
                if tok == "PROTO":
                    self.skip_balanced("{", "}")
                else:
                    self.skip_value()
                continue
            for V, faces, name in self.node():
                self._emit(V, faces, name)

    def _emit(self, V: np.ndarray, faces: list[np.ndarray], name: str | None) -> None:
        self.V.append(V)
        for f in faces:
            self.faces.append(f + self.nv)
            self.names.append(name)
        self.nv += len(V)

    def node(self) -> list[tuple]:
        tok = self.next()
        if tok == "USE":
            name = self.next()
            if name not in self.defs:
                raise InputError(self.path, f"USE of undefined node {name!r}")
            return self.defs[name]
        defname = None
        if tok == "DEF":
            defname = self.next()
            tok = self.next()
        ntype = tok
        self.expect("{")
        out: list[tuple] = []
        if ntype in self.GROUPS:
            out = self._group(ntype, defname)
        elif ntype == "Shape":
            out = self._shape(defname)
        elif ntype == "IndexedFaceSet":
            out = [("ifs", *self._ifs())]
        elif ntype == "Coordinate":
            out = [("coord", self._coordinate())]
        else:
            self._skip_fields()
        if defname is not None:
            self.defs[defname] = out
        return out

    def _skip_fields(self) -> None:
        while self.peek() != "}":
            self.next()
            self.skip_value()
        self.expect("}")

    def _group(self, ntype: str, defname: str | None) -> list[tuple]:
        T = {"translation": np.zeros(3), "rotation": np.array([0, 0, 1, 0.0]), "scale": np.ones(3),
             "center": np.zeros(3), "scaleOrientation": np.array([0, 0, 1, 0.0])}
        per_child: list[list[tuple]] = []
        which = 0
        while self.peek() != "}":
            f = self.next()
            if f in ("children", "level", "choice"):
                if self.peek() == "[":
                    self.expect("[")
                    while self.peek() != "]":
                        per_child.append(self.node())
                    self.expect("]")
                else:
                    per_child.append(self.node())
            elif f == "whichChoice" and ntype == "Switch":
                which = int(float(self.next()))
            elif f in ("translation", "scale", "center") and ntype == "Transform":
                T[f] = np.array(self.numbers(3))
            elif f in ("rotation", "scaleOrientation") and ntype == "Transform":
                T[f] = np.array(self.numbers(4))
            else:
                self.skip_value()
        self.expect("}")
        if ntype == "Switch":  # the chosen child (whichChoice; -1 = none shown -> the first one)
            per_child = per_child[which:which + 1] if 0 <= which < len(per_child) else per_child[:1]
        elif ntype == "LOD":  # the most detailed level
            per_child = per_child[:1]
        kids = [k for c in per_child for k in c]
        if ntype != "Transform":
            return kids
        M = _vrml_transform(T)
        return [(V @ M[:3, :3].T + M[:3, 3], faces, name) for V, faces, name in kids]

    def _shape(self, defname: str | None) -> list[tuple]:
        geo = []
        while self.peek() != "}":
            f = self.next()
            if f == "geometry":
                if self.peek() == "NULL":
                    self.next()
                    continue
                save_name = self.peek()
                got = self.node()
                geo = [g for g in got if g and g[0] == "ifs"]
                if save_name == "DEF" and defname is None:
                    pass
            else:
                self.skip_value()
        self.expect("}")
        out = []
        for _, V, faces, gname in geo:
            out.append((V, faces, gname or defname))
        return out

    def _coordinate(self) -> np.ndarray:
        P = np.zeros((0, 3))
        while self.peek() != "}":
            f = self.next()
            if f == "point":
                a = self.mf_numbers()
                if len(a) % 3:
                    raise InputError(self.path, f"Coordinate point has {len(a)} numbers (not a multiple of 3)")
                P = a.reshape(-1, 3)
            else:
                self.skip_value()
        self.expect("}")
        return P

    def _ifs(self) -> tuple[np.ndarray, list[np.ndarray], str | None]:
        P = None
        idx = np.zeros(0)
        while self.peek() != "}":
            f = self.next()
            if f == "coord":
                if self.peek() == "NULL":
                    self.next()
                    continue
                got = self.node()
                cs = [g for g in got if g and g[0] == "coord"]
                if cs:
                    P = cs[0][1]
            elif f == "coordIndex":
                idx = self.mf_numbers()
            else:
                self.skip_value()
        self.expect("}")
        if P is None:
            raise InputError(self.path, "IndexedFaceSet without Coordinate points")
        if not (np.isfinite(idx).all() and (idx == np.round(idx)).all()):
            raise InputError(self.path, "coordIndex holds a value that is not an integer")
        idx = idx.astype(np.int64)
        bad = (idx < -1) | (idx >= len(P))
        if bad.any():
            raise InputError(self.path, f"coordIndex {int(idx[bad][0])} out of range ({len(P)} points)")
        return P, _split_minus_one(idx), None


def _split_minus_one(idx: np.ndarray) -> list[np.ndarray]:
    if len(idx) == 0:
        return []
    if idx[-1] != -1:
        idx = np.append(idx, -1)
    ends = np.flatnonzero(idx == -1)
    starts = np.concatenate([[0], ends[:-1] + 1])
    return [idx[s:e] for s, e in zip(starts, ends) if e > s]


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return tok in ("TRUE", "FALSE")


def _axis_angle(r: np.ndarray) -> np.ndarray:
    axis = np.asarray(r[:3], float)
    n = np.linalg.norm(axis)
    if n == 0 or r[3] == 0:
        return np.eye(3)
    k = axis / n
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = float(r[3])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * (K @ K)


def _vrml_transform(T: dict) -> np.ndarray:
    """4x4 of a VRML Transform: T * C * R * SR * S * -SR * -C (VRML 2.0 spec order)."""
    def h(R=None, t=None):
        M = np.eye(4)
        if R is not None:
            M[:3, :3] = R
        if t is not None:
            M[:3, 3] = t
        return M

    SR = _axis_angle(T["scaleOrientation"])
    return (h(t=T["translation"]) @ h(t=T["center"]) @ h(R=_axis_angle(T["rotation"])) @ h(R=SR)
            @ h(R=np.diag(T["scale"])) @ h(R=SR.T) @ h(t=-T["center"]))


def read_vrml(p: Path) -> PolygonModel:
    """VRML 2.0: all ``IndexedFaceSet`` faces of all Shapes, transforms applied, in file order.

    Each Shape's points are kept as they are (not welded across shapes). Face names: the ``DEF``
    name of the Shape or of its IndexedFaceSet, if any.
    """
    text = p.read_text(encoding="utf-8")
    head = text.lstrip()[:16]
    if not head.startswith("#VRML V2.0"):
        if head.startswith("#VRML V1.0"):
            raise InputError(p, "VRML 1.0 is not supported (need VRML 2.0 / VRML97)")
        raise InputError(p, "not a VRML 2.0 file (missing '#VRML V2.0' header)")
    ps = _VrmlParser(text, p)
    ps.scene()
    V = np.concatenate(ps.V) if ps.V else np.zeros((0, 3))
    return PolygonModel(V, ps.faces, names=ps.names)


def vrml_text(model: PolygonModel) -> str:
    """VRML 2.0 text: one Shape with one IndexedFaceSet; holes bridged (module docstring).

    Polygons are listed in model order, each ending with -1. ``solid FALSE`` and ``convex FALSE``
    tell viewers that faces may be non-convex; ``creaseAngle 0`` keeps flat shading.
    """
    loops = _output_loops(model)
    pts = _fmt_rows("", model.vertices).rstrip("\n").replace("\n", ",\n      ")
    idx = ",\n      ".join(",".join(str(int(i)) for i in f) + ",-1" for f in loops)
    return (
        "#VRML V2.0 utf8\n"
        f"# mst polygon model: {len(model.vertices)} vertices, {len(loops)} faces\n"
        "Shape {\n"
        "  appearance Appearance { material Material { diffuseColor 0.8 0.8 0.8 } }\n"
        "  geometry IndexedFaceSet {\n"
        "    solid FALSE\n"
        "    convex FALSE\n"
        "    creaseAngle 0\n"
        "    coord Coordinate {\n"
        "      point [\n"
        f"      {pts}\n"
        "      ]\n"
        "    }\n"
        "    coordIndex [\n"
        f"      {idx}\n"
        "    ]\n"
        "  }\n"
        "}\n"
    )


# ====================================================================== ViSP .cao
def _theta_u_matrix(tu: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(tu))
    if th == 0:
        return np.eye(3)
    return _axis_angle(np.array([*(np.asarray(tu) / th), th]))


_CAO_INT = re.compile(r"[+-]?\d+")
_CAO_FLOAT = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:inf|nan)(?![A-Za-z])", re.I)
_CAO_PARAM = re.compile(r'([A-Za-z_]\w*)\s*=\s*(?:"([^"]*)"|([^\s"]*))')
_CAO_VEC = re.compile(r"\b(t|tu)\s*=\s*\[([^\]]*)\]")
_CAO_MAX_COUNT = 10_000_000


class _CaoCursor:
    """ViSP-style stream over a ``.cao`` text, with line numbers for messages.

    ViSP's ``loadCAOModel`` reads numbers with ``>>`` (whitespace, newlines included, skipped), then
    drops the rest of the line (counts, points) or parses it as ``key=value`` parameters (lines,
    faces, cylinders, circles). Text after the expected numbers is therefore a comment whatever it
    starts with (``#``, ``//``, words); lines whose first non-blank character is ``#`` and blank
    lines are skipped between statements.
    """

    def __init__(self, text: str, path: Path):
        self.lines = text.splitlines()
        self.path = path
        self.ln = 0  # current line index
        self.col = 0  # position in the current line

    def _skip(self) -> None:
        while self.ln < len(self.lines):
            rest = self.lines[self.ln][self.col:]
            st = rest.lstrip()
            if not st or (st.startswith("#") and not self.lines[self.ln][:self.col].strip()):
                self.ln, self.col = self.ln + 1, 0
                continue
            self.col += len(rest) - len(st)
            return

    def at_end(self) -> bool:
        self._skip()
        return self.ln >= len(self.lines)

    def peek_char(self) -> str:
        self._skip()
        return self.lines[self.ln][self.col] if self.ln < len(self.lines) else ""

    def _token(self, rx: re.Pattern, what: str, same_line: bool = False) -> str:
        if same_line:  # the statement goes on: its numbers must be on the line
            if self.ln >= len(self.lines) or not self.lines[self.ln][self.col:].strip():
                raise InputError(self.path, f"line {self.ln + 1}: {what} missing (fewer numbers than the statement needs)")
        self._skip()
        if self.ln >= len(self.lines):
            raise InputError(self.path, f"file ends where {what} was expected")
        m = rx.match(self.lines[self.ln], self.col)
        if not m:
            got = self.lines[self.ln][self.col:].split()[0][:20]
            raise InputError(self.path, f"line {self.ln + 1}: expected {what}, got {got!r}")
        self.col = m.end()
        return m.group(0)

    def int(self, what: str, same_line: bool = False) -> int:
        tok = self._token(_CAO_INT, what, same_line)
        nxt = self.lines[self.ln][self.col:self.col + 1]
        if nxt in (".", "e", "E"):
            raise InputError(self.path, f"line {self.ln + 1}: expected {what} (an integer), got {tok + nxt!r}...")
        return int(tok)

    def count(self, what: str) -> int:
        n = self.int(f"the number of {what}")
        if n < 0 or n > _CAO_MAX_COUNT:
            raise InputError(self.path, f"line {self.ln + 1}: {n} {what} announced (must be 0..{_CAO_MAX_COUNT})")
        self.rest()
        if n > len(self.lines) - self.ln:  # one line each at least
            raise InputError(self.path, f"{n} {what} announced, the file has {len(self.lines) - self.ln} lines left (truncated)")
        return n

    def index(self, what: str, n: int) -> int:
        i = self.int(what, same_line=True)
        if not 0 <= i < n:
            raise InputError(self.path, f"line {self.ln + 1}: {what} {i} out of range (0..{n - 1})")
        return i

    def float(self, what: str, same_line: bool = False) -> float:
        return float(self._token(_CAO_FLOAT, what, same_line))

    def rest(self) -> str:
        """The rest of the current line (then move to the next line)."""
        if self.ln >= len(self.lines):
            return ""
        r = self.lines[self.ln][self.col:]
        self.ln, self.col = self.ln + 1, 0
        return r

    def params(self) -> dict[str, str]:
        """``key=value`` / ``key="value"`` pairs at the start of the rest of the line (ViSP's
        parseParameters: ``name``, ``useLod``, ``minLineLengthThreshold``, ``minPolygonAreaThreshold``,
        and any other key); parsing stops at the first other text (a comment)."""
        r, out, j = self.rest(), {}, 0
        while True:
            while j < len(r) and r[j] in " \t":
                j += 1
            m = _CAO_PARAM.match(r, j)
            if not m:
                return out
            out[m.group(1)] = m.group(2) if m.group(2) is not None else m.group(3)
            j = m.end()


def _cao_vector(p: Path, name: str, text: str) -> np.ndarray:
    """``t=[..]`` (metres) or ``tu=[..]`` (theta-u; each value radians, or with a ``deg``/``rad``
    unit) of a ``load()``: 3 values separated by ``;`` (ViSP) or ``,``."""
    vals = [v.strip() for v in re.split(r"[;,]", text)]
    if len(vals) == 1:  # space-separated
        vals = text.split()
    if len(vals) != 3:
        raise InputError(p, f"load(): {name}=[{text}] needs 3 values separated by ';'")
    out = []
    for v in vals:
        m = re.fullmatch(r"([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(deg|rad)?", v)
        if not m or (m.group(2) and name != "tu"):
            raise InputError(p, f"load(): bad value {v!r} in {name}=[{text}]")
        x = float(m.group(1))
        out.append(math.radians(x) if m.group(2) == "deg" else x)
    return np.array(out)


def read_cao(p: Path, _stack: tuple[Path, ...] = ()) -> PolygonModel:
    """ViSP ``.cao`` as ``vpMbTracker::loadCAOModel`` reads it (V1, V2).

    Sections in order: ``V1``/``V2`` header; ``load("sub.cao", t=[tx; ty; tz], tu=[rx; ry; rz])``
    lines; points (V2: each followed by two image coordinates, ignored); lines ``i j``; faces from
    lines ``n l1 .. ln``; faces from points ``n p1 .. pn``; cylinders ``p1 p2 radius``; circles
    ``radius center p1 p2`` (the last two sections optional, as in old files). Text after a
    statement's numbers is a comment; faces, lines, cylinders and circles may carry ``key=value``
    parameters (``name=...`` or ``name="a b"`` becomes the face name; ``useLod``, thresholds and
    others are accepted and ignored).

    ``load()``: the sub-model's path is relative to this file's folder (or absolute); its points are
    mapped by ``X = R(tu) X_sub + t`` (tu theta-u, radians unless ``deg``; t metres; ``;`` or ``,``
    between values), nested loads compose. A cycle raises :class:`mst.InputError` (ViSP warns and
    skips it); a file loaded twice from different places is loaded twice (ViSP keeps only the first).

    Faces from lines become point loops. Lines used by no face-from-lines, and faces from points
    with only 2 points, are kept in ``model.lines`` (ViSP tracks both as 2-point polygons). Cylinders ``{p1, p2, radius, name}`` and
    circles ``{radius, center, p1, p2, name}`` cannot be polygon faces: they are kept as dicts
    (point indices into ``model.vertices``) and written back by :func:`cao_text`; mst's tracker
    does not use them.
    """
    p = Path(p)
    me = p.resolve()
    if me in _stack:
        chain = " -> ".join(q.name for q in (*_stack, me))
        raise InputError(p, f"load() cycle: {chain}")
    if len(_stack) > 32:
        raise InputError(p, "load() nesting deeper than 32")
    text = p.read_text(encoding="utf-8-sig")
    if "\x00" in text:
        raise InputError(p, "not a text .cao file (NUL bytes)")
    c = _CaoCursor(text, p)
    version = 1
    if c.peek_char() in ("V", "v"):
        lno = c.ln + 1
        mv = re.match(r"[Vv]\s*(\d+)", c.rest().strip())  # ViSP reads an int after 'V', then skips the line
        if not mv:
            raise InputError(p, f"line {lno}: bad version header (expected V1 or V2)")
        version = int(mv.group(1))
        if version not in (0, 1, 2):
            raise InputError(p, f"unsupported .cao version V{version} (V1 or V2)")
    parts: list[PolygonModel] = []
    while c.peek_char() in ("l", "L"):
        lno = c.ln + 1
        line = c.rest().strip()
        m = re.match(r'load\s*\(\s*"([^"]+)"\s*([^)]*)\)', line)
        if not m:
            raise InputError(p, f"line {lno}: cannot parse {line[:60]!r} (expected load(\"file.cao\", t=[..], tu=[..]))")
        args = m.group(2).strip()
        vec = {name: _cao_vector(p, name, val) for name, val in _CAO_VEC.findall(args)}
        leftover = _CAO_VEC.sub("", args).replace(",", " ").strip()
        if leftover:
            raise InputError(p, f"line {lno}: load(): unexpected {leftover[:40]!r} (only t=[..] and tu=[..])")
        sub = Path(m.group(1))
        sub = sub if sub.is_absolute() else p.parent / sub
        if not sub.is_file():
            raise InputError(p, f"line {lno}: load(): {m.group(1)} not found (looked at {sub})")
        sm = read_cao(sub, (*_stack, me))
        R = _theta_u_matrix(vec.get("tu", np.zeros(3)))
        sm.vertices = sm.vertices @ R.T + vec.get("t", np.zeros(3))
        parts.append(sm)

    n = c.count("points")
    V = np.empty((n, 3))
    for i in range(n):
        V[i] = [c.float("a point coordinate"), c.float("a point coordinate", True), c.float("a point coordinate", True)]
        if version == 2:
            c.int("the point's image row (V2)", True)
            c.int("the point's image column (V2)", True)
        c.rest()
    n_l = c.count("lines")
    L = np.empty((n_l, 2), np.int64)
    for i in range(n_l):
        L[i] = [c.int("line point index"), c.int("line point index", True)]
        if L[i].min() < 0 or L[i].max() >= n:
            raise InputError(p, f"line {c.ln + 1}: line {i} point index out of range (0..{n - 1})")
        c.params()
    faces: list[np.ndarray] = []
    names: list[str | None] = []
    used_lines = np.zeros(n_l, bool)
    for i in range(c.count("faces from lines")):
        k = c.int("the number of lines of a face")
        if k < 3 or k > n_l:
            raise InputError(p, f"line {c.ln + 1}: face from lines {i} has {k} lines (need 3..{n_l})")
        li = [c.index("line index", n_l) for _ in range(k)]
        par = c.params()
        used_lines[li] = True
        faces.append(_chain_lines(L[li], p, i))
        names.append(par.get("name") or None)
    extra_lines: list[list[int]] = []
    for i in range(c.count("faces from points")):
        k = c.int("the number of points of a face")
        if k < 2 or k > _CAO_MAX_COUNT:
            raise InputError(p, f"line {c.ln + 1}: face from points {i} has {k} points (need at least 3, or 2 for a line)")
        idx = [c.index("point index", n) for _ in range(k)]
        par = c.params()
        if k == 2:  # ViSP tracks a 2-point "face" as a line
            extra_lines.append(idx)
            continue
        faces.append(np.array(idx, np.int64))
        names.append(par.get("name") or None)
    cyl: list[dict] = []
    circ: list[dict] = []
    if not c.at_end():
        for _ in range(c.count("cylinders")):
            p1 = c.int("cylinder point index")
            p2 = c.index("cylinder point index", n)
            if not 0 <= p1 < n:
                raise InputError(p, f"line {c.ln + 1}: cylinder point index {p1} out of range (0..{n - 1})")
            r = c.float("the cylinder radius", True)
            if not (r > 0 and math.isfinite(r)):
                raise InputError(p, f"line {c.ln + 1}: cylinder radius {r} (must be > 0)")
            cyl.append({"p1": p1, "p2": p2, "radius": r, "name": c.params().get("name") or None})
    if not c.at_end():
        for _ in range(c.count("circles")):
            r = c.float("the circle radius")
            if not (r > 0 and math.isfinite(r)):
                raise InputError(p, f"line {c.ln + 1}: circle radius {r} (must be > 0)")
            ids = [c.index("circle point index", n) for _ in range(3)]
            circ.append({"radius": r, "center": ids[0], "p1": ids[1], "p2": ids[2],
                         "name": c.params().get("name") or None})
    # anything after the circles is ignored, as ViSP does (cube.cao carries its .init there)
    free_lines = np.concatenate([L[~used_lines], np.array(extra_lines, np.int64).reshape(-1, 2)])
    own = PolygonModel(V, faces, names=names, lines=free_lines, cylinders=cyl, circles=circ)
    if not np.isfinite(V).all():
        own.check_finite(str(p))
    if not parts:
        return own
    return merge_models([*parts, own])


def _chain_lines(L: np.ndarray, p: Path, i: int) -> np.ndarray:
    """Order the segments of a ViSP face-from-lines into one loop of point indices."""
    if len(L) < 3:
        raise InputError(p, f"face from lines {i}: needs at least 3 lines")
    rest = [tuple(e) for e in L.tolist()]
    a, b = rest.pop(0)
    loop = [a, b]
    while rest:
        cur = loop[-1]
        for j, (u, v) in enumerate(rest):
            if u == cur or v == cur:
                rest.pop(j)
                loop.append(v if u == cur else u)
                break
        else:
            raise InputError(p, f"face from lines {i}: lines do not form a closed loop")
    if loop[-1] != loop[0]:
        raise InputError(p, f"face from lines {i}: lines do not form a closed loop")
    return np.array(loop[:-1], np.int64)


def merge_models(models: list[PolygonModel]) -> PolygonModel:
    """Concatenate models (vertex indices offset; no welding)."""
    V, faces, holes, names, lines, cyl, circ = [], [], [], [], [], [], []
    off = 0
    for m in models:
        V.append(m.vertices)
        faces += [f + off for f in m.faces]
        holes += [[h + off for h in hs] for hs in m.holes]
        names += list(m.names)
        lines.append(m.lines + off)
        cyl += [{**c, "p1": c["p1"] + off, "p2": c["p2"] + off} for c in m.cylinders]
        circ += [{**c, "center": c["center"] + off, "p1": c["p1"] + off, "p2": c["p2"] + off} for c in m.circles]
        off += len(m.vertices)
    return PolygonModel(np.concatenate(V) if V else np.zeros((0, 3)), faces, holes=holes, names=names,
                        lines=np.concatenate(lines) if lines else np.zeros((0, 2), np.int64), cylinders=cyl, circles=circ)


def _cao_name(name: str) -> str:
    """A ``name=`` value as ViSP parses it: one token, or quoted when it holds blanks."""
    name = str(name).replace('"', "'").replace("\n", " ").strip()
    if not name:
        return "_"
    return f'"{name}"' if re.search(r"\s", name) or "=" in name else name


def cao_text(model: PolygonModel) -> str:
    """ViSP ``.cao`` V1 text: points, lines, no faces from lines, faces from points (holes bridged,
    ``name=`` when named), cylinders, circles."""
    loops = _output_loops(model)
    out = ["V1\n", "# 3D Points\n", f"{len(model.vertices)}\n", _fmt_rows("", model.vertices)]
    out += ["# 3D Lines\n", f"{len(model.lines)}\n", _fmt_rows("", model.lines)]
    out += ["# Faces from 3D lines\n", "0\n"]
    out += ["# Faces from 3D points\n", f"{len(loops)}\n"]
    for f, name in zip(loops, model.names):
        s = f"{len(f)} " + " ".join(str(int(i)) for i in f)
        if name:
            s += f" name={_cao_name(name)}"
        out.append(s + "\n")
    out += ["# 3D cylinders\n", f"{len(model.cylinders)}\n"]
    for c in model.cylinders:
        s = f"{int(c['p1'])} {int(c['p2'])} {_fmt_num(c['radius'])}"
        out.append(s + (f" name={_cao_name(c['name'])}" if c.get("name") else "") + "\n")
    out += ["# 3D circles\n", f"{len(model.circles)}\n"]
    for c in model.circles:
        s = f"{_fmt_num(c['radius'])} {int(c['center'])} {int(c['p1'])} {int(c['p2'])}"
        out.append(s + (f" name={_cao_name(c['name'])}" if c.get("name") else "") + "\n")
    return "".join(out)


# ====================================================================== CityJSON
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
    extra_V: list[np.ndarray] = []
    nV = len(V)
    tmpl = d.get("geometry-templates") or {}
    tV = np.asarray(tmpl.get("vertices-templates", []), np.float64).reshape(-1, 3)
    faces: list[np.ndarray] = []
    holes: list[list[np.ndarray]] = []
    names: list[str | None] = []

    def ring_ok(ring) -> bool:
        return isinstance(ring, list) and all(type(i) is int for i in ring)

    def surfaces(geom: dict):
        """Surfaces (lists of rings of int vertex indices) of a geometry; wrong nesting or a
        non-integer index (1.5, "3", null) raises InputError naming the object."""
        if not isinstance(geom, dict):
            raise InputError(p, f"city object {cur_oid!r}: a geometry is not a JSON object")
        t = geom.get("type")
        b = geom.get("boundaries", [])
        depth = {"MultiSurface": 0, "CompositeSurface": 0, "Solid": 1, "MultiSolid": 2, "CompositeSolid": 2}.get(t)
        if depth is None:
            return  # points, lines: no surfaces
        level = [b]
        for _ in range(depth + 1):
            if not all(isinstance(x, list) for x in level):
                raise InputError(p, f"city object {cur_oid!r}: {t} boundaries are not nested {depth + 3} deep")
            level = [y for x in level for y in x]
        for surf in level:
            if not isinstance(surf, list) or not all(ring_ok(r) for r in surf):
                raise InputError(p, f"city object {cur_oid!r}: {t} boundary holds a ring that is not a list of "
                                    "integer vertex indices (wrong nesting, or an index like 1.5)")
            yield surf

    cos = d.get("CityObjects", {})
    if not isinstance(cos, dict):
        raise InputError(p, "CityJSON 'CityObjects' is not a JSON object")
    cur_oid = None
    for oid, obj in cos.items():
        cur_oid = oid
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
                used = sorted({i for s in surfaces(tg) for ring in s for i in ring})
                remap = {u: nV + j for j, u in enumerate(used)}
                X = tV[used] @ M[:3, :3].T + M[:3, 3] + ref
                extra_V.append(X)
                nV += len(X)
                for s in surfaces(tg):
                    rings = [np.array([remap[i] for i in ring], np.int64) for ring in s]
                    faces.append(rings[0])
                    holes.append(rings[1:])
                    names.append(oid)
                continue
            if gl != want:
                continue
            for s in surfaces(g):
                rings = [np.asarray(ring, np.int64) for ring in s]
                if not rings or len(rings[0]) < 3:
                    continue
                faces.append(rings[0])
                holes.append([r for r in rings[1:] if len(r) >= 3])
                names.append(oid)
    if extra_V:
        V = np.concatenate([V, *extra_V])
    return PolygonModel(V, faces, holes=holes, names=names)


def _lod_key(s: str) -> tuple:
    try:
        return (float(s),)
    except ValueError:
        return (-1.0,)


# ====================================================================== holes -> bridged loops
def _output_loops(model: PolygonModel) -> list[np.ndarray]:
    """One index loop per face: holes bridged, loop started at a strictly convex corner."""
    normals = model.face_normals()
    loops = [bridge_holes(model.vertices, f, hs, n) if hs else np.asarray(f, np.int64)
             for f, hs, n in zip(model.faces, model.holes, normals)]
    return start_loops_at_convex_corners(model.vertices, loops, normals)


def start_loops_at_convex_corners(V: np.ndarray, loops: list[np.ndarray], normals: np.ndarray) -> list[np.ndarray]:
    """Rotate each loop so that its vertex 1 is a strictly convex corner: points 0, 1, 2 then give
    the face's outward normal (ViSP computes face visibility from them). Vectorised over all loops.

    Among the corners whose turn about the face normal is clearly positive (sine > 1e-9), the one
    spanning the largest triangle with its two neighbours (``(b - a) x (c - b) . n``) is chosen, ties
    by the smallest (vertex index, next vertex index): the plane of points 0, 1, 2 is then as well
    conditioned as the loop allows (a short or nearly straight corner would tilt ViSP's normal; on the
    real Rotterdam set the first-corner choice put vertices 71 mm off that plane at ``--dist-tol
    0.01``). The choice does not depend on where the loop starts, so writing a model read back from
    our own file gives the same bytes. Loops without such a corner (degenerate) are left as they are.
    """
    if not loops:
        return []
    lens = np.array([len(lp) for lp in loops], np.int64)
    idx = np.concatenate([np.asarray(lp, np.int64) for lp in loops])
    L = len(loops)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    lid = np.repeat(np.arange(L), lens)
    ls = starts[lid]
    ll = np.maximum(lens[lid], 1)
    loc = np.arange(len(idx)) - ls
    prv = idx[ls + (loc - 1) % ll]
    nxt = idx[ls + (loc + 1) % ll]
    a = V[idx] - V[prv]
    b = V[nxt] - V[idx]
    turn = np.einsum("ij,ij->i", np.cross(a, b), np.asarray(normals, float)[lid])
    scale = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    convex = (turn > 1e-9 * scale) & (scale > 0) & (lens[lid] >= 3)
    big = np.iinfo(np.int64).max
    # near-ties (within 1e-6 of the loop's best turn: rounding depends on where the loop starts)
    # are broken by vertex index, so the choice is the same for every rotation of the loop
    best = np.full(L, -np.inf)
    np.maximum.at(best, lid, np.where(convex, turn, -np.inf))
    good = convex & (turn >= best[lid] * (1 - 1e-6))
    k1 = np.where(good, idx, big)
    k2 = np.where(good, nxt, big)
    order = np.lexsort((k2, k1, lid))
    first = order[np.concatenate([[0], np.flatnonzero(np.diff(lid[order])) + 1])]
    shift = np.where(good[first], (loc[first] - 1) % np.maximum(lens, 1), 0)
    rotated = idx[ls + (loc + shift[lid]) % ll]
    return np.split(rotated, starts[1:])


def start_at_convex_corner(V: np.ndarray, loop: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Single-loop form of :func:`start_loops_at_convex_corners`."""
    return start_loops_at_convex_corners(V, [np.asarray(loop, np.int64)], np.asarray(n, float)[None])[0]


def _plane_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal in-plane axes (u, v) with u x v = n (so CCW about n stays CCW in 2D)."""
    nx, ny, nz = (float(x) for x in n)
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn == 0:
        return np.eye(3)[:, :2]
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    k = min(range(3), key=lambda i: abs((nx, ny, nz)[i]))
    ax, ay, az = (1.0 if k == 0 else 0.0), (1.0 if k == 1 else 0.0), (1.0 if k == 2 else 0.0)
    ux, uy, uz = ay * nz - az * ny, az * nx - ax * nz, ax * ny - ay * nx  # a x n
    un = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / un, uy / un, uz / un
    vx, vy, vz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux  # n x u
    return np.array([[ux, vx], [uy, vy], [uz, vz]])


def unbridge_faces(model: PolygonModel) -> PolygonModel:
    """Turn weakly-simple faces written by :func:`bridge_holes` back into outer loop + holes.

    For a face loop that visits a vertex twice: edges used in both directions by the loop (bridges)
    are removed, the remaining edges are chained in loop order and split at repeated vertices. The
    result is accepted only if it is one loop turning like the face (positive signed area about the
    face normal) plus loops turning the other way (holes) with the same total vector area;
    otherwise the face is kept as read. Faces without repeated vertices are untouched.
    """
    if not model.faces:
        return model
    lens = np.array([len(f) for f in model.faces], np.int64)
    fid = np.repeat(np.arange(len(lens)), lens)
    key = np.sort(fid * (len(model.vertices) + 1) + np.concatenate(model.faces))
    dup_faces = np.unique(key[1:][key[1:] == key[:-1]] // (len(model.vertices) + 1))
    cand = [int(i) for i in dup_faces if not model.holes[i]]
    if not cand:
        return model
    faces = list(model.faces)
    holes = [list(h) for h in model.holes]
    normals = model.face_normals()
    areas = model.face_areas()
    V = model.vertices
    for i in cand:
        seq = faces[i].tolist()
        k = len(seq)
        edges = [(seq[j], seq[(j + 1) % k]) for j in range(k)]
        count: dict[tuple[int, int], int] = {}
        for e in edges:
            count[e] = count.get(e, 0) + 1
        keep = [True] * k
        used_rev: dict[tuple[int, int], int] = {}
        for j, (a, b) in enumerate(edges):
            if a == b:
                keep[j] = False
                continue
            r = (b, a)
            avail = min(count.get((a, b), 0), count.get(r, 0))
            if avail and used_rev.get((a, b), 0) < avail:
                used_rev[(a, b)] = used_rev.get((a, b), 0) + 1
                keep[j] = False
        if all(keep):
            loops = _split_simple(seq)
        else:
            rem = [edges[j] for j in range(k) if keep[j]]
            loops = _chain_in_order(rem)
            if loops is None:
                continue
            loops = [sub for lp in loops for sub in _split_simple(lp)]
        if len(loops) < 2:
            continue
        n = normals[i]
        sa = []
        for lp in loops:
            P = V[lp] - V[lp[0]]
            sa.append(0.5 * float(np.cross(P, np.roll(P, -1, axis=0)).sum(0) @ n))
        pos = [j for j, a in enumerate(sa) if a > 0]
        if len(pos) != 1 or any(a >= 0 for j, a in enumerate(sa) if j != pos[0]):
            continue
        if abs(sum(sa) - areas[i]) > 1e-9 * max(abs(areas[i]), 1e-300) + 1e-12:
            continue
        faces[i] = np.asarray(loops[pos[0]], np.int64)
        holes[i] = [np.asarray(lp, np.int64) for j, lp in enumerate(loops) if j != pos[0]]
    return PolygonModel(model.vertices, faces, holes=holes, names=list(model.names), lines=model.lines,
                        cylinders=model.cylinders, circles=model.circles)


def _split_simple(seq: list[int]) -> list[list[int]]:
    """Split a closed vertex sequence at repeated vertices into simple closed loops (>= 3 vertices)."""
    out: list[list[int]] = []
    path: list[int] = []
    pos: dict[int, int] = {}
    for x in seq:
        if x in pos:
            p = pos[x]
            out.append(path[p:])
            for y in path[p + 1:]:
                del pos[y]
            path = path[: p + 1]
        else:
            pos[x] = len(path)
            path.append(x)
    out.append(path)
    return [lp for lp in out if len(lp) >= 3]


def _chain_in_order(edges: list[tuple[int, int]]) -> list[list[int]] | None:
    """Chain directed edges into closed vertex loops, taking at each vertex the first unused edge
    that follows in the given (cyclic) order. None if they do not close."""
    m = len(edges)
    out_at: dict[int, list[int]] = {}
    for j, (a, _) in enumerate(edges):
        out_at.setdefault(a, []).append(j)
    used = [False] * m
    loops = []
    for s in range(m):
        if used[s]:
            continue
        start = edges[s][0]
        lp: list[int] = []
        j = s
        while True:
            used[j] = True
            a, b = edges[j]
            lp.append(a)
            if b == start:
                break
            cands = [c for c in out_at.get(b, []) if not used[c]]
            if not cands:
                return None
            after = [c for c in cands if c > j]
            j = after[0] if after else cands[0]
        loops.append(lp)
    return loops


def bridge_holes(V: np.ndarray, outer: np.ndarray, holes: list[np.ndarray], n: np.ndarray) -> np.ndarray:
    """Cut every hole open into the outer loop with a bridge edge: one weakly-simple loop.

    Holes are processed by decreasing maximum u coordinate (plane basis from ``n``); each hole is
    joined from its rightmost vertex H to the closest vertex P of the current loop such that the
    segment H-P crosses no edge of the outer loop or of any hole (standard hole elimination, as in
    earcut). The result visits ``P ... H (hole loop) H P ...``: P and H appear twice. A hole that
    shares a vertex with the loop (touching holes) is spliced in at that vertex without a bridge.
    Outer loop CCW about ``n``, holes CW (as stored in :class:`PolygonModel`).
    """
    B = _plane_basis(n)
    outer = np.asarray(outer, np.int64)
    P2 = lambda idx: (V[idx] - V[outer[0]]) @ B  # noqa: E731
    holes = [np.asarray(h, np.int64) for h in holes if len(h) >= 3]
    loop = list(outer.tolist())
    # all segments of outer + holes, for visibility tests
    segs_idx = [np.stack([lp, np.roll(lp, -1)], 1) for lp in [outer, *holes]]
    S = np.concatenate(segs_idx)
    SA, SB = P2(S[:, 0]), P2(S[:, 1])
    hole_pts = [P2(h) for h in holes]
    order = np.argsort([-hp[:, 0].max() for hp in hole_pts], kind="stable")
    for hi in order:
        h = holes[hi]
        hp = hole_pts[hi]
        shared = np.intersect1d(h, np.asarray(loop, np.int64))
        if len(shared):  # the hole touches the loop at a vertex: splice it in there, no bridge
            v = int(shared[0])
            c = loop.index(v)
            j = int(np.flatnonzero(h == v)[0])
            hrot = np.roll(h, -j).tolist()
            loop = loop[:c] + hrot + loop[c:]
            continue
        j = int(np.argmax(hp[:, 0]))
        H = hp[j]
        L = np.array(loop, np.int64)
        LP = P2(L)
        d2 = ((LP - H) ** 2).sum(1)
        cand = np.argsort(d2, kind="stable")
        chosen = None
        for c in cand:
            if _segment_clear(H, LP[c], SA, SB, S, int(h[j]), int(L[c])):
                chosen = int(c)
                break
        if chosen is None:
            chosen = int(cand[0])
        hrot = np.roll(h, -j).tolist()
        loop = loop[: chosen + 1] + hrot + [hrot[0]] + loop[chosen:]
        # the bridge itself becomes an obstacle for the next holes
        S = np.vstack([S, [[int(L[chosen]), int(h[j])]]])
        SA = np.vstack([SA, LP[chosen][None]])
        SB = np.vstack([SB, H[None]])
    return np.array(loop, np.int64)


def _segment_clear(a, b, SA, SB, S, ia, ib) -> bool:
    """True if segment a-b properly crosses none of the segments SA-SB (those sharing an endpoint
    index with a-b are ignored)."""
    share = (S[:, 0] == ia) | (S[:, 1] == ia) | (S[:, 0] == ib) | (S[:, 1] == ib)

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    d1 = orient(a, b, SA)
    d2 = orient(a, b, SB)
    d3 = orient(SA, SB, a)
    d4 = orient(SA, SB, b)
    cross = (d1 * d2 < 0) & (d3 * d4 < 0)
    return not np.any(cross & ~share)


# ====================================================================== triangulation
def triangulate_model(model: PolygonModel, return_index: bool = False):
    """Triangulate every face (holes included) with earcut in the face's plane.

    Returns ``V`` (N, 3) float64 (= ``model.vertices``, unchanged) and ``F`` (M, 3) int64, each
    triangle wound like its polygon (right-hand normal = the polygon's Newell normal). With
    ``return_index`` also ``face_index`` (M,) int64: the source face of each triangle.
    Degenerate faces (zero area) give no triangles.
    """
    import mapbox_earcut

    V = model.vertices
    tris: list[np.ndarray] = []
    src: list[np.ndarray] = []
    # fast path: plain triangles
    simple_tri = [i for i, (f, hs) in enumerate(zip(model.faces, model.holes)) if len(f) == 3 and not hs]
    if simple_tri:
        tris.append(np.stack([model.faces[i] for i in simple_tri]))
        src.append(np.array(simple_tri, np.int64))
    simple = set(simple_tri)
    normals = None
    for i, (f, hs) in enumerate(zip(model.faces, model.holes)):
        if i in simple:
            continue
        if normals is None:
            normals = model.face_normals()
        n = normals[i]
        if not np.any(n):
            continue
        rings = [f, *[h for h in hs if len(h) >= 3]]
        idx = np.concatenate(rings)
        P = (V[idx] - V[f[0]]) @ _plane_basis(n)
        ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
        t = np.asarray(mapbox_earcut.triangulate_float64(P, ends), np.int64).reshape(-1, 3)
        if len(t) == 0:
            continue
        a, b, c = P[t[:, 0]], P[t[:, 1]], P[t[:, 2]]
        s = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        t = np.where((s < 0)[:, None], t[:, [0, 2, 1]], t)
        tris.append(idx[t])
        src.append(np.full(len(t), i, np.int64))
    F = np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)
    fi = np.concatenate(src) if src else np.zeros(0, np.int64)
    if len(simple_tri) and len(tris) > 1:
        order = np.argsort(fi, kind="stable")
        F, fi = F[order], fi[order]
    if return_index:
        return V, F, fi
    return V, F
