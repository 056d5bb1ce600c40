"""``python -m mst.eval.bench --out bench-results.json`` (``make bench``): every stage's benchmark.

OpenBLAS's kernels are pinned first, as the ``mst`` command pins them (:mod:`mst.cpu`), so that the
in-process rows run what the command runs."""

import sys

from mst.cpu import pin_blas_kernels

pin_blas_kernels()

from mst.eval.bench.harness import main  # noqa: E402  (after the pin: it loads numpy)

sys.exit(main())
