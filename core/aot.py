"""Ahead-of-time compiled numba kernels: the same machine code without numba's start-up (issue #14).

Every process that calls a ``cache=True`` numba kernel pays about 0.45 s before the first call
(measured, CPU, on the 2-core machine: ``import numba`` 0.21-0.23 s, ``numba.np.arraymath`` 0.06 s,
the first cache load 0.11-0.13 s for LLVM's initialisation, a few ms per further kernel). For a
command whose work is 0.2-1 s (``mst c2m`` of 1M points, ``convert-model`` of a 1M-triangle TIN)
that is most of the difference to a C++ tool.

:func:`build` compiles the kernels of a numba module (their Python functions, the single signature
each was compiled for in the warm-up) with ``numba.pycc`` into a CPython extension module beside
numba's cache (``__pycache__`` of the source package, or ``$MST_AOT_DIR``), with a JSON spec of the
argument types and the SHA-256 of the source file. :class:`Kernels` gives the kernels of a module
by attribute: the extension's function when it was built from the current source and the call's
arguments have exactly the compiled types, otherwise the JIT dispatcher of the source module (numba
imported then, on first need). The extension does not import numba; its functions release the GIL
(callers may split work over threads, see :func:`threads`). Results are those of the JIT kernels:
same source, same LLVM, no fastmath (prange loops run serially; no kernel reduces across them).

``MST_AOT=0`` disables the extensions (JIT only). ``make setup`` builds them
(``python -m mst.eval.c2m.warmup``); a checkout without a C compiler simply keeps the JIT path.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import sys
import sysconfig
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

SPEC_VERSION = 1
_SCALARS = {"float64": (float, np.float64), "int64": (int, np.int64), "bool": (bool, np.bool_)}


def _source_file(module: str) -> Path:
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError(module)
    return Path(spec.origin)


def aot_dir(module: str) -> Path:
    """Folder of the extension of ``module``: ``$MST_AOT_DIR`` or the source package's ``__pycache__``."""
    env = os.environ.get("MST_AOT_DIR")
    return Path(env) if env else _source_file(module).parent / "__pycache__"


def ext_name(module: str) -> str:
    """Extension module name of ``module`` (``mst.eval.c2m.kernels`` -> ``mst_eval_c2m_kernels_aot``)."""
    return module.replace(".", "_") + "_aot"


def source_hash(module: str) -> str:
    """SHA-256 of the kernel source, numba's version and the Python version (a change of any of
    them makes an extension stale)."""
    h = hashlib.sha256(_source_file(module).read_bytes())
    # numba's version without importing numba (or importlib.metadata, ~0.03 s): its _version.py
    nb = importlib.util.find_spec("numba")
    ver = Path(nb.origin).parent / "_version.py" if nb is not None and nb.origin else None
    h.update(ver.read_bytes() if ver is not None and ver.is_file() else b"numba ?")
    h.update(f"|python {sys.version}|spec {SPEC_VERSION}".encode())
    return h.hexdigest()


def threads() -> int:
    """Threads for work split over the extension's (GIL-free) calls: ``NUMBA_NUM_THREADS`` when set
    (the suite's and the dask workers' setting), else the CPU count."""
    env = os.environ.get("NUMBA_NUM_THREADS")
    try:
        return max(1, int(env)) if env else max(1, os.cpu_count() or 1)
    except ValueError:
        return max(1, os.cpu_count() or 1)


def _arg_ok(a, spec) -> bool:
    dt, nd = spec
    if nd == 0:
        py, npt = _SCALARS.get(dt, (None, None))
        if py is None:
            return False
        if py is int:
            return (type(a) is int and -(1 << 63) <= a < (1 << 63)) or type(a) is np.int64
        return type(a) is py or type(a) is npt
    return (type(a) is np.ndarray and a.ndim == nd and a.dtype.name == dt and a.dtype.isnative
            and a.flags.c_contiguous and a.flags.aligned)


class _AotFunction:
    """An extension function with its argument specs; other argument types go to the JIT kernel."""

    __slots__ = ("name", "funcs", "fallback")

    def __init__(self, name: str, funcs: list, fallback):
        self.name, self.funcs, self.fallback = name, funcs, fallback

    def __call__(self, *args):
        for fn, specs in self.funcs:
            if len(args) == len(specs) and all(_arg_ok(a, s) for a, s in zip(args, specs)):
                return fn(*args)
        log.debug("%s: argument types not compiled ahead of time; numba JIT", self.name)
        return self.fallback()(*args)


class Kernels:
    """The kernels of the numba module ``module`` by attribute (see the module docstring)."""

    def __init__(self, module: str):
        self._module = module
        self._ext = None  # (extension module, spec) once loaded; False when absent or stale

    def _jit(self):
        return importlib.import_module(self._module)

    def _load(self):
        if self._ext is None:
            self._ext = False
            if os.environ.get("MST_AOT", "1") != "0":
                try:
                    self._ext = _load_extension(self._module) or False
                except Exception as e:  # a broken extension file: the JIT path, said once
                    log.warning("%s: ahead-of-time kernels not loaded (%s); numba JIT", self._module, e)
        return self._ext

    @property
    def aot(self) -> bool:
        """True when the extension of the current source is loaded."""
        return bool(self._load())

    def is_aot(self, name: str) -> bool:
        """True when kernel ``name`` runs from the extension (for calls with the compiled types)."""
        return isinstance(getattr(self, name), _AotFunction)

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        ext = self._load()
        fn = None
        if ext and name in ext[1]["kernels"]:
            mod, spec = ext
            funcs = [(getattr(mod, e["export"]), [tuple(a) for a in e["args"]]) for e in spec["kernels"][name]]
            fn = _AotFunction(name, funcs, lambda: getattr(self._jit(), name))
        if fn is None:
            fn = getattr(self._jit(), name)
        self.__dict__[name] = fn
        return fn


def is_current(module: str) -> bool:
    """True when the extension of ``module`` exists and was built from its current source."""
    d, name = aot_dir(module), ext_name(module)
    try:
        spec = json.loads((d / f"{name}.json").read_text())
    except (OSError, ValueError):
        return False
    return spec.get("source_sha256") == source_hash(module) and (d / (name + sysconfig.get_config_var("EXT_SUFFIX"))).is_file()


def _load_extension(module: str):
    d = aot_dir(module)
    name = ext_name(module)
    spec_path = d / f"{name}.json"
    if not spec_path.is_file():
        return None
    spec = json.loads(spec_path.read_text())
    if spec.get("source_sha256") != source_hash(module):
        log.debug("%s: ahead-of-time kernels are stale (source changed); numba JIT", module)
        return None
    so = d / (name + sysconfig.get_config_var("EXT_SUFFIX"))
    if not so.is_file():
        return None
    loader = importlib.machinery.ExtensionFileLoader(name, str(so))
    mspec = importlib.util.spec_from_file_location(name, str(so), loader=loader)
    mod = importlib.util.module_from_spec(mspec)
    loader.exec_module(mod)
    return mod, spec


def _arg_spec(t) -> list | None:
    """(numpy dtype name, ndim) of a numba argument type; None when not supported ahead of time."""
    from numba.core import types

    if isinstance(t, types.Array):
        if t.layout != "C" or not t.aligned:
            return None
        return [np.dtype(str(t.dtype)).name, int(t.ndim)]
    if isinstance(t, types.Boolean):
        return ["bool", 0]
    if isinstance(t, (types.Integer, types.Float)) and str(t) in ("int64", "float64"):
        return [str(t), 0]
    return None


def build(module: str, out_dir: Path | None = None, target_cpu: str = "") -> dict:
    """Compile the kernels of ``module`` (every module-level dispatcher with compiled signatures that
    is not ``inline="always"``) into its extension; returns the spec written. The signatures are
    those the JIT dispatchers hold, so the warm-up must have run in this process."""
    import warnings

    import numba.core.registry
    import numba.pycc.compiler as pycc_compiler
    from numba.core.compiler import Flags

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from numba.pycc import CC

    class _GilFreeFlags(Flags):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.release_gil = True  # the extension's functions release the GIL (nogil=True of the JIT)
            # array arguments marked noalias, as numba's parfors does for a prange body: LLVM may then
            # keep array pointers and shapes in registers across the loops (3x faster grid searches
            # than without); valid because no kernel writes into an array argument
            self.noalias = True

    src = importlib.import_module(module)
    out_dir = Path(out_dir or aot_dir(module))
    out_dir.mkdir(parents=True, exist_ok=True)
    name = ext_name(module)
    cc = CC(name)
    import tempfile

    tmp_dir = Path(tempfile.mkdtemp(prefix=".aot-", dir=out_dir))  # built aside, then renamed into place
    cc.output_dir = str(tmp_dir)
    cc.target_cpu = target_cpu
    kernels: dict[str, list] = {}
    for attr in sorted(dir(src)):
        d = getattr(src, attr)
        if not isinstance(d, numba.core.registry.CPUDispatcher) or d.targetoptions.get("inline") == "always":
            continue
        entries = []
        for k, cres in enumerate(d.overloads.values()):
            specs = [_arg_spec(t) for t in cres.signature.args]
            if any(s is None for s in specs):
                continue
            export = f"{attr}__{k}"
            cc.export(export, cres.signature)(d.py_func)
            entries.append({"export": export, "args": specs})
        if entries:
            kernels[attr] = entries
    spec = {"module": module, "source_sha256": source_hash(module), "spec_version": SPEC_VERSION, "kernels": kernels}
    spec_path = out_dir / f"{name}.json"
    spec_path.unlink(missing_ok=True)  # a stale spec must not describe the new file while it is written
    saved = pycc_compiler.Flags
    pycc_compiler.Flags = _GilFreeFlags
    try:
        with warnings.catch_warnings():  # "parallel=True but no transformation": as intended here
            warnings.simplefilter("ignore")
            cc.compile()
        so = name + sysconfig.get_config_var("EXT_SUFFIX")
        os.replace(tmp_dir / so, out_dir / so)  # a running process keeps its mapped copy
    finally:
        pycc_compiler.Flags = saved
        import shutil

        shutil.rmtree(tmp_dir, ignore_errors=True)
    tmp = spec_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(spec, indent=1))
    tmp.replace(spec_path)
    return spec
