"""convert-model's kernels (:mod:`mst.meshtools.kernels`): the ahead-of-time extension when it is
built from the current source (:mod:`mst.core.aot`; no numba import, about 0.45 s less per
process), numba's JIT otherwise. ``from mst.meshtools.compiled import edge_groups, ...`` gives the
kernels by name; :func:`components` is the validating wrapper of the union-find kernel."""

from __future__ import annotations

import numpy as np

from mst.core.aot import Kernels

kernels = Kernels("mst.meshtools.kernels")


def components(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """``(n_components, label per node)`` of the undirected graph on nodes ``0..n-1`` with edges
    ``a[k] - b[k]``; components numbered by their smallest node (scipy's numbering)."""
    a = np.ascontiguousarray(a, np.int64)
    b = np.ascontiguousarray(b, np.int64)
    if len(a) != len(b):
        raise ValueError("edge arrays differ in length")
    if len(a) and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n):
        raise ValueError("edge endpoint out of range")
    c, lab = kernels._components(int(n), a, b)
    return int(c), lab


def __getattr__(name: str):
    if name.startswith("__"):
        raise AttributeError(name)
    return getattr(kernels, name)
