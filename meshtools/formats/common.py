"""Helpers shared by the text format writers and readers of :mod:`mst.meshtools.formats`: shortest
round-trip number text, axis-angle rotation matrices.

Imports numpy and the standard library only.
"""

from __future__ import annotations

import math

import numpy as np


def format_number(x: float) -> str:
    """Shortest text that reads back to the same float64 (``repr``), integers without ``.0``."""
    x = float(x)
    if x == 0.0:
        return "0"
    if x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


def format_rows(tag: str, A: np.ndarray) -> str:
    """Rows of numbers as ``tag a b c`` lines; floats as :func:`format_number` (shortest round-trip
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


def axis_angle_matrix(r: np.ndarray) -> np.ndarray:
    axis = np.asarray(r[:3], float)
    n = np.linalg.norm(axis)
    if n == 0 or r[3] == 0:
        return np.eye(3)
    k = axis / n
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = float(r[3])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * (K @ K)
