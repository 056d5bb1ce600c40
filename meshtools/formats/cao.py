"""ViSP ``.cao`` models V1/V2 as ``vpMbTracker::loadCAOModel`` reads them: points, lines, faces from
lines, faces from points, cylinders, circles, ``load("sub.cao", t=[..], tu=[..])`` (see
:func:`read_cao`); the writer gives V1 with faces from points (holes bridged).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from mst import InputError
from mst.meshtools.formats.common import axis_angle_matrix, format_number, format_rows
from mst.meshtools.model import PolygonModel, merge_models
from mst.meshtools.polygons import output_loops


def _theta_u_matrix(tu: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(tu))
    if th == 0:
        return np.eye(3)
    return axis_angle_matrix(np.array([*(np.asarray(tu) / th), th]))


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
    version = _cao_version(c, p)
    parts = _cao_loads(c, p, (*_stack, me))
    V = _cao_points(c, version)
    L = _cao_lines(c, p, len(V))
    faces, names, used_lines, extra_lines = _cao_faces(c, p, L, len(V))
    cyl, circ = _cao_cylinders_circles(c, p, len(V))
    # anything after the circles is ignored, as ViSP does (cube.cao carries its .init there)
    free_lines = np.concatenate([L[~used_lines], np.array(extra_lines, np.int64).reshape(-1, 2)])
    own = PolygonModel(V, faces, names=names, lines=free_lines, cylinders=cyl, circles=circ)
    if not np.isfinite(V).all():
        own.check_finite(str(p))
    if not parts:
        return own
    return merge_models([*parts, own])


def _cao_version(c: _CaoCursor, p: Path) -> int:
    """The ``V1``/``V2`` header (1 when absent)."""
    version = 1
    if c.peek_char() in ("V", "v"):
        lno = c.ln + 1
        mv = re.match(r"[Vv]\s*(\d+)", c.rest().strip())  # ViSP reads an int after 'V', then skips the line
        if not mv:
            raise InputError(p, f"line {lno}: bad version header (expected V1 or V2)")
        version = int(mv.group(1))
        if version not in (0, 1, 2):
            raise InputError(p, f"unsupported .cao version V{version} (V1 or V2)")
    return version


def _cao_loads(c: _CaoCursor, p: Path, stack: tuple[Path, ...]) -> list[PolygonModel]:
    """The ``load("sub.cao", t=[..], tu=[..])`` lines: the sub-models, mapped into this file's frame."""
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
        sm = read_cao(sub, stack)
        R = _theta_u_matrix(vec.get("tu", np.zeros(3)))
        sm.vertices = sm.vertices @ R.T + vec.get("t", np.zeros(3))
        parts.append(sm)
    return parts


def _cao_points(c: _CaoCursor, version: int) -> np.ndarray:
    """The points section: (n, 3) (V2: each point's two image coordinates are read and ignored)."""
    n = c.count("points")
    V = np.empty((n, 3))
    for i in range(n):
        V[i] = [c.float("a point coordinate"), c.float("a point coordinate", True), c.float("a point coordinate", True)]
        if version == 2:
            c.int("the point's image row (V2)", True)
            c.int("the point's image column (V2)", True)
        c.rest()
    return V


def _cao_lines(c: _CaoCursor, p: Path, n: int) -> np.ndarray:
    """The lines section: (n_l, 2) point indices."""
    n_l = c.count("lines")
    L = np.empty((n_l, 2), np.int64)
    for i in range(n_l):
        L[i] = [c.int("line point index"), c.int("line point index", True)]
        if L[i].min() < 0 or L[i].max() >= n:
            raise InputError(p, f"line {c.ln + 1}: line {i} point index out of range (0..{n - 1})")
        c.params()
    return L


def _cao_faces(c: _CaoCursor, p: Path, L: np.ndarray, n: int):
    """Faces from lines, then faces from points: ``(faces, names, lines used by a face, 2-point faces)``."""
    n_l = len(L)
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
    return faces, names, used_lines, extra_lines


def _cao_cylinders_circles(c: _CaoCursor, p: Path, n: int) -> tuple[list[dict], list[dict]]:
    """The optional cylinders and circles sections (absent in old files)."""
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
    return cyl, circ


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


def _cao_name(name: str) -> str:
    """A ``name=`` value as ViSP parses it: one token, or quoted when it holds blanks."""
    name = str(name).replace('"', "'").replace("\n", " ").strip()
    if not name:
        return "_"
    return f'"{name}"' if re.search(r"\s", name) or "=" in name else name


def cao_text(model: PolygonModel) -> str:
    """ViSP ``.cao`` V1 text: points, lines, no faces from lines, faces from points (holes bridged,
    ``name=`` when named), cylinders, circles."""
    loops = output_loops(model)
    out = ["V1\n", "# 3D Points\n", f"{len(model.vertices)}\n", format_rows("", model.vertices)]
    out += ["# 3D Lines\n", f"{len(model.lines)}\n", format_rows("", model.lines)]
    out += ["# Faces from 3D lines\n", "0\n"]
    out += ["# Faces from 3D points\n", f"{len(loops)}\n"]
    for f, name in zip(loops, model.names):
        s = f"{len(f)} " + " ".join(str(int(i)) for i in f)
        if name:
            s += f" name={_cao_name(name)}"
        out.append(s + "\n")
    out += ["# 3D cylinders\n", f"{len(model.cylinders)}\n"]
    for c in model.cylinders:
        s = f"{int(c['p1'])} {int(c['p2'])} {format_number(c['radius'])}"
        out.append(s + (f" name={_cao_name(c['name'])}" if c.get("name") else "") + "\n")
    out += ["# 3D circles\n", f"{len(model.circles)}\n"]
    for c in model.circles:
        s = f"{format_number(c['radius'])} {int(c['center'])} {int(c['p1'])} {int(c['p2'])}"
        out.append(s + (f" name={_cao_name(c['name'])}" if c.get("name") else "") + "\n")
    return "".join(out)
