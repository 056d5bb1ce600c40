"""The polygon model shared by every stage.

Frames and units: vertices are in the *model frame*, metres (or the model file's unit).
Each face is an outer loop of vertex indices ordered counter-clockwise when seen from outside the
object, so the right-hand (Newell) normal points out; holes are loops ordered the other way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PolygonModel:
    """A polygon model: shared vertices, faces as index loops, optional holes and names.

    Attributes
    ----------
    vertices : (N, 3) float64, model frame, metres.
    faces : list of (k,) int64 arrays, the outer loop of each face (k >= 3).
    holes : list (one entry per face) of lists of (m,) int64 loops; empty list = no hole.
    names : list (one per face) of str or None.
    lines : (L, 2) int64 extra 3D segments that belong to no face (ViSP ``.cao`` lines).
    cylinders, circles : ViSP primitives kept verbatim as dicts (read, written, not tracked).
    """

    vertices: np.ndarray
    faces: list[np.ndarray]
    holes: list[list[np.ndarray]] = field(default_factory=list)
    names: list[str | None] = field(default_factory=list)
    lines: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    cylinders: list[dict] = field(default_factory=list)
    circles: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = [np.asarray(f, dtype=np.int64).ravel() for f in self.faces]
        if not self.holes:
            self.holes = [[] for _ in self.faces]
        self.holes = [[np.asarray(h, dtype=np.int64).ravel() for h in hs] for hs in self.holes]
        if not self.names:
            self.names = [None] * len(self.faces)
        self.lines = np.asarray(self.lines, dtype=np.int64).reshape(-1, 2)
        if len(self.holes) != len(self.faces) or len(self.names) != len(self.faces):
            raise ValueError("holes and names need one entry per face")

    # ------------------------------------------------------------------ basic queries
    @property
    def n_faces(self) -> int:
        return len(self.faces)

    @property
    def n_holes(self) -> int:
        return sum(len(h) for h in self.holes)

    def loops(self) -> list[np.ndarray]:
        """Every loop (outer loops and holes), in face order."""
        out: list[np.ndarray] = []
        for f, hs in zip(self.faces, self.holes):
            out.append(f)
            out.extend(hs)
        return out

    def edges(self) -> np.ndarray:
        """(E, 2) unique undirected edges of all loops plus the extra lines, sorted per row."""
        segs = [np.stack([lp, np.roll(lp, -1)], axis=1) for lp in self.loops() if len(lp) >= 2]
        if len(self.lines):
            segs.append(self.lines)
        if not segs:
            return np.zeros((0, 2), np.int64)
        e = np.sort(np.concatenate(segs), axis=1)
        e = e[e[:, 0] != e[:, 1]]
        return np.unique(e, axis=0)

    def _flat_loops(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All loops concatenated: (idx, next_idx, face_of_entry, loop_start_of_entry), vectorised helpers."""
        loops, face_of = [], []
        for i, (f, hs) in enumerate(zip(self.faces, self.holes)):
            loops.append(f)
            face_of.append(i)
            for h in hs:
                loops.append(h)
                face_of.append(i)
        if not loops:
            z = np.zeros(0, np.int64)
            return z, z, z, z
        lens = np.array([len(lp) for lp in loops], np.int64)
        idx = np.concatenate(loops).astype(np.int64)
        starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
        ls = np.repeat(starts, lens)
        ll = np.repeat(lens, lens)
        pos = np.arange(len(idx))
        nxt = idx[ls + (pos - ls + 1) % np.maximum(ll, 1)]
        return idx, nxt, np.repeat(np.array(face_of, np.int64), lens), ls

    def _vector_areas(self) -> np.ndarray:
        """(F, 3) Newell vector area of each face (outer loop + holes), vertices taken relative to
        the face's first vertex for precision."""
        idx, nxt, face, _ = self._flat_loops()
        out = np.zeros((self.n_faces, 3))
        if len(idx) == 0:
            return out
        ref = self.vertices[np.array([int(f[0]) if len(f) else 0 for f in self.faces], np.int64)]
        p = self.vertices[idx] - ref[face]
        q = self.vertices[nxt] - ref[face]
        c = np.cross(p, q) * 0.5
        for k in range(3):
            out[:, k] = np.bincount(face, weights=c[:, k], minlength=self.n_faces)
        return out

    def face_normals(self) -> np.ndarray:
        """(F, 3) unit Newell normals of the faces (outer loop and holes; zero rows for degenerate faces)."""
        n = self._vector_areas()
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def face_areas(self) -> np.ndarray:
        """(F,) area of each face (outer loop minus holes), square model units."""
        return np.linalg.norm(self._vector_areas(), axis=1)

    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner of the vertices used by faces or lines."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def check_finite(self, path: str | None = None) -> None:
        """Raise :class:`mst.InputError` if any vertex coordinate is NaN or infinite."""
        from mst import InputError

        bad = ~np.isfinite(self.vertices).all(axis=1)
        if bad.any():
            raise InputError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates (first: #{int(np.argmax(bad))})")

    # ------------------------------------------------------------------ conversions
    def triangulate(self, return_index: bool = False):
        """Triangulate every face (holes included) with earcut in the face's plane.

        Returns ``(V, F)``: V (N, 3) float64 = ``self.vertices`` (model frame, metres), F (M, 3) int64
        triangles wound like their polygon (right-hand normal out). With ``return_index=True`` also
        the (M,) source face index of each triangle. See :func:`mst.meshtools.polygons.triangulate_model`.
        """
        from mst.meshtools.polygons import triangulate_model

        return triangulate_model(self, return_index=return_index)


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
