"""``mst nav fuse``'s kernels (:mod:`mst.pipeline.nav.kernels`) through :class:`mst.core.aot.Kernels`: the
ahead-of-time extension when it was built from the current source for this CPU (``make setup``), numba's JIT
otherwise; with it the command does not import numba (~0.8 s of start-up)."""

from __future__ import annotations

from mst.core.aot import Kernels

kernels = Kernels("mst.pipeline.nav.kernels")
