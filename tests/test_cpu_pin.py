"""mst.cpu: which OpenBLAS core type the ``mst`` command pins (the SLAM aid's reproducibility across
CPUs is tested in test_reproducibility_cpu.py)."""

from __future__ import annotations

import subprocess
import sys

from mst.cpu import BLAS_CORETYPE, _cpu_flags, blas_coretype, pin_blas_kernels

AVX2_CPU = {"sse2", "avx", "avx2", "fma", "avx512f"}


def test_pins_haswell_kernels_on_a_cpu_with_avx2_and_fma():
    assert blas_coretype({}, AVX2_CPU) == BLAS_CORETYPE == "Haswell"


def test_leaves_a_cpu_without_the_instructions_to_openblas():
    # a Sandy Bridge (AVX, no AVX2/FMA) would die of SIGILL in Haswell kernels
    assert blas_coretype({}, {"sse2", "avx"}) is None
    assert blas_coretype({}, {"sse2", "avx", "avx2"}) is None
    assert blas_coretype({}, set()) is None


def test_flags_that_cannot_be_read_leave_the_choice_to_openblas(tmp_path):
    assert _cpu_flags(str(tmp_path / "missing")) is None
    p = tmp_path / "cpuinfo"
    p.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 fma\n\nprocessor\t: 1\nflags\t\t: fpu\n")
    assert _cpu_flags(str(p)) == {"fpu", "sse2", "avx2", "fma"}  # the first processor's


def test_the_user_chooses_another_core_type_or_none():
    assert blas_coretype({"MST_BLAS_CORETYPE": "Zen"}, set()) == "Zen"
    assert blas_coretype({"MST_BLAS_CORETYPE": ""}, AVX2_CPU) is None
    assert blas_coretype({"MST_BLAS_CORETYPE": "  "}, AVX2_CPU) is None


def test_the_pin_overrides_openblas_own_variable():
    env = {"OPENBLAS_CORETYPE": "SkylakeX", "MST_BLAS_CORETYPE": "Haswell"}
    pin_blas_kernels(env)
    assert env["OPENBLAS_CORETYPE"] == "Haswell"
    env = {"OPENBLAS_CORETYPE": "SkylakeX", "MST_BLAS_CORETYPE": ""}
    assert pin_blas_kernels(env) is False and env["OPENBLAS_CORETYPE"] == "SkylakeX"  # left alone


def test_the_mst_command_pins_before_numpy_loads():
    """A fresh ``mst`` process: the pin is set in its environment before numpy is imported (what makes
    OpenBLAS read it), and ``mst --help`` still loads no numpy."""
    code = ("import os, sys; import mst.cli.main; "
            "print(os.environ.get('OPENBLAS_CORETYPE'), 'numpy' in sys.modules)")
    env = {"PATH": "/usr/bin:/bin", "MST_BLAS_CORETYPE": "Nehalem"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert r.stdout.split() == ["Nehalem", "False"]
