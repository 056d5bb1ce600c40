"""VRML 2.0 (VRML97): ``IndexedFaceSet`` polygons of every ``Shape``, ``Transform``/``Group`` nesting
(translation, rotation, scale, center, scaleOrientation), ``DEF``/``USE``, ``Switch`` (the chosen
child), ``LOD`` (the first level); Inline is not followed. The writer gives one Shape with one
IndexedFaceSet, holes bridged.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mst import InputError
from mst.meshtools.formats.common import axis_angle_matrix, format_rows
from mst.meshtools.model import PolygonModel
from mst.meshtools.polygons import output_loops

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


def _vrml_transform(T: dict) -> np.ndarray:
    """4x4 of a VRML Transform: T * C * R * SR * S * -SR * -C (VRML 2.0 spec order)."""
    def h(R=None, t=None):
        M = np.eye(4)
        if R is not None:
            M[:3, :3] = R
        if t is not None:
            M[:3, 3] = t
        return M

    SR = axis_angle_matrix(T["scaleOrientation"])
    return (h(t=T["translation"]) @ h(t=T["center"]) @ h(R=axis_angle_matrix(T["rotation"])) @ h(R=SR)
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
    loops = output_loops(model)
    pts = format_rows("", model.vertices).rstrip("\n").replace("\n", ",\n      ")
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
