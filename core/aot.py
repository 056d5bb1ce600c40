"""Ahead-of-time compiled numba kernels: the same machine code without numba's start-up (issue #14).

Every process that calls a ``cache=True`` numba kernel pays about 0.45 s before the first call
(measured, CPU, on the 2-core machine: ``import numba`` 0.21-0.23 s, ``numba.np.arraymath`` 0.06 s,
the first cache load 0.11-0.13 s for LLVM's initialisation, a few ms per further kernel). For a
command whose work is 0.2-1 s (``mst c2m`` of 1M points, ``convert-model`` of a 1M-triangle TIN)
that is most of the difference to a C++ tool.

:func:`build` compiles the kernels of a numba module (their Python functions, the single signature
each was compiled for in the warm-up) with ``numba.pycc`` into a CPython extension module beside
numba's cache (``__pycache__`` of the source package, or ``$MST_AOT_DIR``), with a JSON spec of the
argument types, the SHA-256 of the source file (and of the mst modules it imports) and the CPU it
was compiled for (this machine's, as numba's JIT does; :func:`host_id`). :class:`Kernels` gives the
kernels of a module by attribute: the extension's function when it was built from the current
source for this CPU and the call's arguments have exactly the compiled types (a generated check,
~1 us a call), otherwise the JIT dispatcher of the source module (numba imported then, on first
need; :data:`FALLBACKS` counts such calls). The extension does not import numba; its functions
release the GIL (callers may split work over threads, see :func:`threads`). Results are those of
the JIT kernels: same source, same LLVM, the kernels' own error model, no fastmath (prange loops run
serially; no kernel reduces across them).

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
import re
import sys
import sysconfig
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

SPEC_VERSION = 2  # 2: the kernels' error model and the module's AOT_NOALIAS honoured, built for this CPU
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


#: ``from mst.x import ...`` / ``import mst.x`` at the start of a line of a kernel module's source
_MST_IMPORT = re.compile(rb"^\s*(?:from\s+(mst(?:\.\w+)+)\s+import|import\s+(mst(?:\.\w+)+))", re.M)


def source_hash(module: str) -> str:
    """SHA-256 of the kernel source, of the mst modules it imports (a kernel may call another
    module's kernel or read its constants: compiled in, so a change there makes the extension stale
    too), numba's version and the Python version (a change of any of them makes an extension stale)."""
    src = _source_file(module).read_bytes()
    h = hashlib.sha256(src)
    for dep in sorted({a or b for a, b in _MST_IMPORT.findall(src)} - {module.encode()}):
        try:
            h.update(b"|" + dep + b"|" + _source_file(dep.decode()).read_bytes())
        except (ModuleNotFoundError, ImportError, ValueError):  # a name, not a module: its package's source
            h.update(b"|" + dep + b"|?")
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


def _conds(specs: list, env: dict, tag: str) -> list[str] | None:
    """Python conditions on ``a0, a1, ...`` equivalent to :func:`_arg_ok` for each spec (None when a
    spec cannot be checked); their constants go into ``env`` (names suffixed with ``tag``). A native
    dtype is the interned descriptor (``is``); any other equal one passes by ``==``."""
    conds = []
    for i, (dt, nd) in enumerate(specs):
        a = f"a{i}"
        if nd == 0:
            py, npt = _SCALARS.get(dt, (None, None))
            if py is None:
                return None
            if py is int:
                conds.append(f"((type({a}) is _int and -(1 << 63) <= {a} < (1 << 63)) or type({a}) is _i64)")
            else:
                env[f"_p{tag}_{i}"], env[f"_n{tag}_{i}"] = py, npt
                conds.append(f"(type({a}) is _p{tag}_{i} or type({a}) is _n{tag}_{i})")
        else:
            env[f"_D{tag}_{i}"] = np.dtype(dt)
            conds.append(f"(type({a}) is _nd and {a}.ndim == {int(nd)} and ({a}.dtype is _D{tag}_{i} or "
                         f"{a}.dtype == _D{tag}_{i}) and (_f := {a}.flags).c_contiguous and _f.aligned)")
    return conds


#: per kernel name, the calls that went to numba's JIT because their argument types were not compiled
#: ahead of time (tests check that a command's kernels all ran from the extension)
FALLBACKS: dict[str, int] = {}


def _aot_function(name: str, funcs: list, fallback):
    """One generated function for the extension functions ``funcs`` ([(function, argument specs)]) of
    kernel ``name``: calls with exactly the compiled types (:func:`_arg_ok`, checked inline: ~0.7 us
    for 9 arguments, against 25 us for a loop over :func:`_arg_ok`; the edge tracker makes ~35
    kernel calls a frame) go to the extension, others to ``fallback()`` (the JIT kernel), counted in
    :data:`FALLBACKS`. The function has ``__mst_aot__ = True``."""
    env = {"_nd": np.ndarray, "_int": int, "_i64": np.int64}
    lines = ["def call(*args):", "    n = len(args)"]
    for k, (fn, specs) in enumerate(funcs):
        conds = _conds(specs, env, str(k))
        if conds is None:
            continue
        env[f"_fn{k}"] = fn
        lines.append(f"    if n == {len(specs)}:")
        if specs:
            lines.append(f"        {', '.join(f'a{i}' for i in range(len(specs)))}, = args")
        lines.append(f"        if {' and '.join(conds) or 'True'}:")
        lines.append(f"            return _fn{k}(*args)")
    lines.append("    return _slow(args)")

    def slow(args):
        log.debug("%s: argument types not compiled ahead of time; numba JIT", name)
        FALLBACKS[name] = FALLBACKS.get(name, 0) + 1
        return fallback()(*args)

    env["_slow"] = slow
    exec("\n".join(lines) + "\n", env)  # noqa: S102 (generated from the spec's dtype names and ranks only)
    call = env["call"]
    call.__name__ = call.__qualname__ = name
    call.__mst_aot__ = True
    return call


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
        return bool(getattr(getattr(self, name), "__mst_aot__", False))

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        ext = self._load()
        fn = None
        if ext and name in ext[1]["kernels"]:
            mod, spec = ext
            funcs = [(getattr(mod, e["export"]), [tuple(a) for a in e["args"]]) for e in spec["kernels"][name]]
            fn = _aot_function(name, funcs, lambda: getattr(self._jit(), name))
        if fn is None:
            if ext:  # the extension lacks it: no signature of it in the warm-up
                FALLBACKS[name] = FALLBACKS.get(name, 0) + 1
            fn = getattr(self._jit(), name)
        self.__dict__[name] = fn
        return fn


def host_id() -> str:
    """This machine's CPU as the extensions are compiled for it (its model and instruction-set flags):
    an extension built for another CPU may use instructions this one lacks (SIGILL), so it is not
    loaded there (the JIT path, as numba's own cache keys on the CPU). Linux: ``/proc/cpuinfo``'s
    first ``model name`` and ``flags`` lines (no LLVM import); elsewhere LLVM's host CPU name and
    features (``llvmlite``, ~0.06 s)."""
    global _HOST_ID
    if _HOST_ID is None:
        found: dict[str, str] = {}
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
                for line in f:
                    key = line.split(":", 1)[0].strip()
                    if key in ("model name", "flags") and key not in found:
                        found[key] = line.split(":", 1)[1].strip()
                        if len(found) == 2:
                            break
        except OSError:
            pass
        if len(found) == 2:
            text = f"{found['model name']}|{found['flags']}"
        else:
            import llvmlite.binding as ll

            text = f"{ll.get_host_cpu_name()}|{ll.get_host_cpu_features().flatten()}"
        _HOST_ID = hashlib.sha256(f"{sys.platform}|{text}".encode()).hexdigest()[:16]
    return _HOST_ID


_HOST_ID: str | None = None


def _spec_usable(module: str, spec: dict) -> bool:
    """The spec describes an extension of the current source, compiled for this CPU (or generic)."""
    if spec.get("source_sha256") != source_hash(module):
        log.debug("%s: ahead-of-time kernels are stale (source changed); numba JIT", module)
        return False
    if spec.get("target_cpu") and spec.get("host") != host_id():
        log.debug("%s: ahead-of-time kernels built for another CPU (%s); numba JIT", module, spec.get("target_cpu"))
        return False
    return True


def is_current(module: str) -> bool:
    """True when the extension of ``module`` exists, was built from its current source and for this CPU."""
    d, name = aot_dir(module), ext_name(module)
    try:
        spec = json.loads((d / f"{name}.json").read_text())
    except (OSError, ValueError):
        return False
    return _spec_usable(module, spec) and (d / (name + sysconfig.get_config_var("EXT_SUFFIX"))).is_file()


def _load_extension(module: str):
    d = aot_dir(module)
    name = ext_name(module)
    spec_path = d / f"{name}.json"
    if not spec_path.is_file():
        return None
    spec = json.loads(spec_path.read_text())
    if not _spec_usable(module, spec):
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


def jit_signatures(module: str) -> dict[str, list]:
    """Per kernel of ``module`` (not ``inline="always"``) the argument specs of the signatures its JIT
    dispatcher holds (after the warm-up) that can be compiled ahead of time."""
    import numba.core.registry

    src = importlib.import_module(module)
    out: dict[str, list] = {}
    for a in sorted(dir(src)):
        d = getattr(src, a)
        if isinstance(d, numba.core.registry.CPUDispatcher) and d.targetoptions.get("inline") != "always":
            specs = [[_arg_spec(t) for t in cres.signature.args] for cres in d.overloads.values()]
            specs = [sp for sp in specs if all(x is not None for x in sp)]
            if specs:
                out[d.py_func.__name__] = specs
    return out


def covers(module: str) -> bool:
    """True when the built extension of ``module`` holds every signature of :func:`jit_signatures` (a
    warm-up that now calls a kernel more ways, or one more kernel, needs a rebuild)."""
    try:
        spec = json.loads((aot_dir(module) / f"{ext_name(module)}.json").read_text())
    except (OSError, ValueError):
        return False
    have = {k: {json.dumps(e["args"]) for e in v} for k, v in spec.get("kernels", {}).items()}
    return all(json.dumps(sp) in have.get(k, set()) for k, v in jit_signatures(module).items() for sp in v)


def build(module: str, out_dir: Path | None = None, target_cpu: str | None = None) -> dict:
    """Compile the kernels of ``module`` (every module-level dispatcher with compiled signatures that
    is not ``inline="always"``) into its extension; returns the spec written. The signatures are
    those the JIT dispatchers hold, so the warm-up must have run in this process. ``target_cpu``: LLVM's
    CPU name; None = this machine's, as numba's JIT compiles (the extension then loads only on a CPU
    with the same :func:`host_id`); ``""`` = generic x86-64, loadable anywhere but without the newer
    vector instructions (the edge tracker's KLT kernel ran ~0.7 ms a frame slower on the tea box)."""
    import warnings

    import numba.core.registry
    import numba.pycc.compiler as pycc_compiler
    from numba.core.compiler import Flags

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from numba.pycc import CC

    src = importlib.import_module(module)
    dispatchers = [d for d in (getattr(src, a) for a in sorted(dir(src)))
                   if isinstance(d, numba.core.registry.CPUDispatcher) and d.targetoptions.get("inline") != "always"]
    # the error model is one per extension (the compiler's flags): the kernels' own, which must agree
    # ("numpy": x / 0 gives inf or nan, as in the JIT kernels; "python", numba's default, raises)
    models = {d.targetoptions.get("error_model", "python") for d in dispatchers}
    if len(models) > 1:
        raise ValueError(f"{module}: kernels with different error models {sorted(models)}; one extension needs one")
    error_model = models.pop() if models else "python"
    noalias = bool(getattr(src, "AOT_NOALIAS", False))

    class _GilFreeFlags(Flags):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.error_model = error_model
            self.release_gil = True  # the extension's functions release the GIL (nogil=True of the JIT)
            # array arguments marked noalias, as numba's parfors does for a prange body: LLVM may then
            # keep array pointers and shapes in registers across the loops (3x faster grid searches
            # than without); only for a module that declares ``AOT_NOALIAS = True`` (none of its
            # kernels writes into an array argument, so aliased arguments cannot matter)
            self.noalias = noalias

    out_dir = Path(out_dir or aot_dir(module))
    out_dir.mkdir(parents=True, exist_ok=True)
    name = ext_name(module)
    cc = CC(name)
    import tempfile

    tmp_dir = Path(tempfile.mkdtemp(prefix=".aot-", dir=out_dir))  # built aside, then renamed into place
    cc.output_dir = str(tmp_dir)
    if target_cpu is None:
        import llvmlite.binding as ll

        target_cpu = ll.get_host_cpu_name()
    cc.target_cpu = target_cpu
    kernels: dict[str, list] = {}
    for d in dispatchers:
        attr = d.py_func.__name__
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
    spec = {"module": module, "source_sha256": source_hash(module), "spec_version": SPEC_VERSION,
            "target_cpu": target_cpu, "host": host_id() if target_cpu else "", "kernels": kernels}
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
