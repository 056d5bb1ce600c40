"""OFF (Object File Format): polygon faces kept, colours ignored; read only."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mst import InputError
from mst.meshtools.model import PolygonModel


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
