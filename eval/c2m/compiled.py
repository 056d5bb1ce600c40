"""The C2M grid engine's kernels (:mod:`mst.eval.c2m.kernels`): the ahead-of-time extension when it
is built from the current source (:mod:`mst.core.aot`; no numba import, about 0.45 s less per
process), numba's JIT otherwise. Use as ``from mst.eval.c2m.compiled import kernels as nb``."""

from __future__ import annotations

from mst.core.aot import Kernels

kernels = Kernels("mst.eval.c2m.kernels")
