"""The edge tracker's numba kernels through :class:`mst.core.aot.Kernels`: the ahead-of-time extension
when it was built from the current source (``make setup``: :mod:`mst.eval.c2m.warmup`), numba's JIT
otherwise (and for argument types not compiled ahead of time). With the extensions ``mst track`` runs
without importing numba: ~0.8 s less start-up per process (its import, the first cached load with
LLVM's initialisation and ``scipy.linalg``, ~25 further kernel loads; README, benchmarks).

``from mst.pipeline.tracking.compiled import kernels`` and ``kernels.me_convolve(...)``: the kernel
modules themselves (:mod:`mst.pipeline.tracking.kernels`, ``covariance_kernels``, ``exact_kernels``,
:mod:`mst.pipeline.zbuffer_kernels`) are imported only on the JIT path."""

from __future__ import annotations

from mst.core.aot import Kernels

kernels = Kernels("mst.pipeline.tracking.kernels")
covariance = Kernels("mst.pipeline.tracking.covariance_kernels")
exact = Kernels("mst.pipeline.tracking.exact_kernels")
zbuffer = Kernels("mst.pipeline.zbuffer_kernels")

#: the kernel modules above, compiled ahead of time by the warm-up
MODULES = ("mst.pipeline.tracking.kernels", "mst.pipeline.tracking.covariance_kernels",
           "mst.pipeline.tracking.exact_kernels", "mst.pipeline.zbuffer_kernels")
