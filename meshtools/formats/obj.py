"""Wavefront OBJ: polygon faces kept (``f`` with any vertex count), ``l`` lines, ``o``/``g`` names,
negative indices and ``v/vt/vn``; a vectorised reader for pure triangle files; writers for polygon
models (holes bridged) and triangle meshes.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mst import InputError
from mst.meshtools.formats.common import format_rows
from mst.meshtools.model import PolygonModel
from mst.meshtools.polygons import output_loops


def read_obj_triangles(p: Path) -> tuple[np.ndarray, np.ndarray] | None:
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
    out = [f"# mst polygon model: {len(model.vertices)} vertices, {model.n_faces} faces\n", format_rows("v", model.vertices)]
    cur = None
    for f, name in zip(output_loops(model), model.names):
        if name != cur:
            out.append(f"g {_token(name)}\n" if name else "g\n")  # bare g: no name (reads back as None)
            cur = name
        out.append("f " + " ".join(str(int(i) + 1) for i in f) + "\n")
    if len(model.lines):
        out.append(format_rows("l", model.lines + 1))
    return "".join(out)


def _token(name: str) -> str:
    return re.sub(r"\s+", "_", str(name).strip()) or "_"


def write_obj_triangles(p: Path, V: np.ndarray, F: np.ndarray) -> None:
    """A triangle mesh as OBJ text: ``v`` lines (shortest round-trip numbers), 1-based ``f`` lines."""
    with open(p, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(f"# {len(V)} vertices, {len(F)} triangles\n")
        fh.write(format_rows("v", V))
        fh.write(format_rows("f", F + 1))
