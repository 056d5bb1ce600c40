"""mst.cpu: the same BLAS kernels on every x86-64 CPU (a process-start setting).

OpenBLAS (numpy's, scipy's and the copy inside pycolmap) picks its kernels by CPU at load time:
Haswell/Zen kernels on an AVX2 machine, SkylakeX/Cooperlake/SapphireRapids ones on an AVX-512 one,
each with its own blocking, vector width and summation order, so a product or a solve differs in its
last bits from one CPU to the next. The tracker itself does not depend on it (its rounding-sensitive
steps are exact, :mod:`mst.pipeline.tracking.exact`), but the SLAM aid does (numpy's products and
solves in the map, PnP, the bundle adjustment): the 320x240 synthetic corridor with the rgbd aid
moved from its 9th frame on under ``OPENBLAS_CORETYPE=Sandybridge`` against ``Haswell`` (session 22).

:func:`pin_blas_kernels` sets ``OPENBLAS_CORETYPE`` before numpy loads, so that every CPU runs the
same kernels: ``Haswell`` (AVX2 + FMA: Intel Core CPUs since Haswell, 2013, AMD ones since
Excavator/Zen), the same instructions giving the same bits on any of them. ``MST_BLAS_CORETYPE``
chooses another core type, or none (an empty value: OpenBLAS's own choice). It overrides an
``OPENBLAS_CORETYPE`` already in the environment: mst's results should not depend on it. A CPU
without AVX2 or FMA, or one whose flags cannot be read (not Linux), is left to OpenBLAS.

Costs nothing measurable: mst's BLAS work is small (3x3 to a few hundred rows), where AVX-512
kernels gain nothing. Imports the standard library only; the ``mst`` command calls it first thing
(:mod:`mst.cli.main`), and so does the test suite's ``conftest.py``. A program that imports numpy
before it calls this keeps the kernels already loaded (the return value says so).
"""

from __future__ import annotations

import os
import sys

#: the pinned core type: AVX2 + FMA kernels, which current x86-64 desktop and server CPUs run
BLAS_CORETYPE = "Haswell"
#: CPU flags (``/proc/cpuinfo``) the pinned kernels need
_NEEDS = ("avx2", "fma")


def _cpu_flags(path: str = "/proc/cpuinfo") -> set[str] | None:
    """The first processor's flags (Linux), or None where they cannot be read."""
    try:
        with open(path, encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.partition(":")[2].split())
    except OSError:
        return None
    return None


def blas_coretype(environ=None, flags: set[str] | None = None) -> str | None:
    """The OpenBLAS core type mst runs with: ``$MST_BLAS_CORETYPE`` when set (empty: None, OpenBLAS's
    own choice), else :data:`BLAS_CORETYPE` where the CPU has its instructions (``flags``: this CPU's,
    read from /proc/cpuinfo when None), else None."""
    environ = os.environ if environ is None else environ
    if "MST_BLAS_CORETYPE" in environ:
        return environ["MST_BLAS_CORETYPE"].strip() or None
    flags = _cpu_flags() if flags is None else flags
    if flags is None or not all(f in flags for f in _NEEDS):
        return None
    return BLAS_CORETYPE


def pin_blas_kernels(environ=None) -> bool:
    """Set ``OPENBLAS_CORETYPE`` to :func:`blas_coretype` in ``environ`` (``os.environ``: this process
    and its children). Returns True when it takes effect in this process (a core type to pin, and
    numpy not loaded yet)."""
    environ = os.environ if environ is None else environ
    core = blas_coretype(environ)
    if core is None:
        return False
    environ["OPENBLAS_CORETYPE"] = core
    return "numpy" not in sys.modules
