"""STL, binary or ASCII, as unwelded triangles; read only (writing goes through trimesh)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mst import InputError


def read_stl(p: Path) -> tuple[np.ndarray, np.ndarray]:
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
