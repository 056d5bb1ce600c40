"""Ahead-of-time kernels (mst.core.aot, issue #14): the extension built by the warm-up gives the JIT
kernels' results bit for bit, is refused when its source changed, sends other argument types to
the JIT, and lets ``mst c2m`` / ``mst convert-model`` run without importing numba.

The tests of a built extension use the one ``make setup`` (``python -m mst.eval.c2m.warmup``) left
beside the sources and skip when there is none; the slow test builds one into a temporary folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mst.core import aot

C2M = "mst.eval.c2m.kernels"
CONVERT = "mst.meshtools.kernels"
built = pytest.mark.skipif(not (aot.is_current(C2M) and aot.is_current(CONVERT)),
                           reason="ahead-of-time kernels not built for this source (python -m mst.eval.c2m.warmup)")


def _c2m_cases():
    """A small building (dense grid) and the same as binned grid; points near, inside and far (1e5 m)."""
    from mst.meshtools.generate import courtyard

    V, F = (np.asarray(a) for a in courtyard()[:2])
    rng = np.random.default_rng(3)
    P = rng.uniform(V.min(0) - 3, V.max(0) + 3, (20000, 3))
    P[:50] += 1e5
    return V.astype(float), F, P


def _c2m_all(V, F, P):
    from mst.eval.c2m import C2MConfig, c2m, prepare_mesh

    out = []
    for small in (5000, 0):  # dense grid, binned grid
        for signed, md in ((False, None), (True, 0.5)):
            idx = prepare_mesh(V, F, signed=signed, engine="grid", small_mesh_triangles=small)
            r = c2m(P, idx, C2MConfig(signed=signed, max_dist_m=md, chunk_points=150_000))
            out.append((r.distances.copy(), json.dumps(r.to_json(), sort_keys=True, default=str)))
    return out


def _assert_same(a, b):
    for (da, ja), (db, jb) in zip(a, b):
        np.testing.assert_array_equal(da, db)  # bit for bit, NaN where beyond max_dist
        assert json.loads(ja)["unsigned"] == json.loads(jb)["unsigned"]


@built
def test_c2m_extension_matches_the_jit_kernels(monkeypatch):
    import importlib

    import mst.eval.c2m.compiled as compiled

    assert compiled.kernels.aot and compiled.kernels.is_aot("grid_query") and compiled.kernels.is_aot("bins_query")
    V, F, P = _c2m_cases()
    ahead = _c2m_all(V, F, P)
    monkeypatch.setattr(compiled, "kernels", importlib.import_module(C2M))  # the numba JIT kernels
    _assert_same(ahead, _c2m_all(V, F, P))


@built
def test_convert_extension_matches_the_jit_kernels(monkeypatch):
    import importlib

    from mst.meshtools import compiled
    from mst.meshtools.convert import tin_to_polygons
    from mst.meshtools.generate import city_block

    V, F = city_block(n_triangles=20000, buildings=6, seed=2)
    F2 = np.asarray(F).copy()
    F2[::5] = F2[::5, ::-1]  # inconsistent winding: the orientation pass too
    assert compiled.kernels.is_aot("edge_groups")
    ahead = [tin_to_polygons(V, f) for f in (F, F2)]
    monkeypatch.setattr(compiled, "kernels", importlib.import_module(CONVERT))
    jit = [tin_to_polygons(V, f) for f in (F, F2)]
    for a, b in zip(ahead, jit):
        assert repr(a) == repr(b)


@built
def test_other_argument_types_go_to_the_jit():
    """A float32 (or non-contiguous) array would be read as float64 C-order memory by the extension
    (wrong numbers or a crash): such calls go to the JIT kernel, which specialises on them."""
    import mst.eval.c2m.compiled as compiled
    from mst.eval.c2m import kernels as jit

    d = np.random.default_rng(0).uniform(0, 2, 1001)
    thr = np.array([0.1, 0.5, 1.0])
    ref = jit.threshold_sums(d, thr)
    for arg in (d.astype(np.float32), d):
        got = compiled.kernels.threshold_sums(arg, thr)
        exp = jit.threshold_sums(arg, thr)
        for g, e in zip(got, exp):
            np.testing.assert_array_equal(g, e)
    assert ref[0][-1] == 1001


def test_stale_or_absent_extension_is_not_loaded(tmp_path, monkeypatch):
    """A spec whose source hash differs (the kernels were edited after the build) is refused: the
    JIT dispatchers are used, never machine code of another source."""
    monkeypatch.setenv("MST_AOT_DIR", str(tmp_path))
    assert not aot.is_current(CONVERT)
    assert not aot.Kernels(CONVERT).aot  # absent
    name = aot.ext_name(CONVERT)
    (tmp_path / f"{name}.json").write_text(json.dumps({"source_sha256": "0" * 64, "kernels": {"edge_groups": []}}))
    import sysconfig

    (tmp_path / (name + sysconfig.get_config_var("EXT_SUFFIX"))).write_bytes(b"not an extension")
    k = aot.Kernels(CONVERT)
    assert not k.aot and not aot.is_current(CONVERT)
    import numba.core.registry

    assert isinstance(k.edge_groups, numba.core.registry.CPUDispatcher)
    monkeypatch.setenv("MST_AOT", "0")  # and the switch
    monkeypatch.delenv("MST_AOT_DIR")
    assert not aot.Kernels(CONVERT).aot


@built
def test_commands_run_without_importing_numba(tmp_path):
    from mst.meshtools import generate
    from mst.meshtools.formats import save_triangles

    V, F = generate.courtyard()[:2]
    save_triangles(tmp_path / "m.obj", np.asarray(V, float), np.asarray(F))
    np.savetxt(tmp_path / "c.xyz", np.random.default_rng(1).uniform(np.min(V, 0), np.max(V, 0), (3000, 3)))
    code = ("import sys; from mst.cli.main import cli\n"
            "for args in (['c2m', sys.argv[1], sys.argv[2], '-q', '--signed', '-o', sys.argv[3]],\n"
            "             ['convert-model', sys.argv[2], '-o', sys.argv[4], '-q']):\n"
            "    try:\n        cli(args)\n    except SystemExit as e:\n        assert not e.code, e.code\n"
            "print('numba' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k not in ("MST_AOT", "MST_AOT_DIR")}
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "c.xyz"), str(tmp_path / "m.obj"),
                        str(tmp_path / "o.ply"), str(tmp_path / "m.wrl")], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "False", "numba was imported"
    assert (tmp_path / "o.ply").stat().st_size > 3000 * 16 and (tmp_path / "m.wrl").stat().st_size > 0


def test_generated_dispatch_accepts_exactly_the_compiled_argument_types():
    """The generated check of :func:`mst.core.aot._aot_function` agrees with the reference rule
    :func:`mst.core.aot._arg_ok` on every kind of mismatch (an argument the extension was not compiled
    for would be read with the wrong layout or type: silent garbage, not an error), and picks the right
    one of several signatures; the rest goes to the JIT and is counted."""
    specs = [("float64", 2), ("float64", 1), ("int64", 1), ("float64", 0), ("int64", 0), ("bool", 0), ("bool", 1)]
    f = aot._aot_function("t_gen", [(lambda *a: "aot", specs)], lambda: (lambda *a: "jit"))
    A = (np.zeros((4, 3)), np.zeros(4), np.zeros(4, np.int64), 0.5, 3, True, np.zeros(4, np.bool_))
    variants = [A, A[:-1], A + (1,), (),
                (np.zeros((3, 4)).T,) + A[1:],                       # not C-contiguous
                (np.zeros((4, 3), np.float32),) + A[1:],             # dtype
                (np.zeros(12),) + A[1:],                             # rank
                A[:1] + (np.zeros(8)[::2],) + A[2:],                 # strided 1-D
                A[:2] + (np.zeros(4, ">i8"),) + A[3:],               # byte order
                A[:2] + (np.zeros(4, np.int32),) + A[3:],
                A[:3] + (1,) + A[4:], A[:3] + (np.float64(0.5),) + A[4:], A[:3] + (np.float32(0.5),) + A[4:],
                A[:4] + (2 ** 63,) + A[5:], A[:4] + (np.int64(-3),) + A[5:], A[:4] + (True,) + A[5:], A[:4] + (3.0,) + A[5:],
                A[:5] + (1,) + A[6:], A[:5] + (np.bool_(False),) + A[6:],
                A[:6] + (np.frombuffer(np.zeros(5, np.uint8).tobytes(), np.bool_)[1:],) + A[7:],  # read-only view
                A[:6] + ([True] * 4,)]
    aot.FALLBACKS.pop("t_gen", None)
    expect_jit = 0
    for v in variants:
        ref = len(v) == len(specs) and all(aot._arg_ok(a, s) for a, s in zip(v, specs))
        assert (f(*v) == "aot") == ref, (len(v), [type(a) for a in v])
        expect_jit += not ref
    assert expect_jit >= 15 and aot.FALLBACKS["t_gen"] == expect_jit
    g = aot._aot_function("t_two", [(lambda *a: "i", [("int64", 0)]), (lambda *a: "f", [("float64", 1)])],
                          lambda: (lambda *a: "jit"))
    assert (g(1), g(np.zeros(2)), g(np.zeros(2, np.float32)), g(1.0)) == ("i", "f", "jit", "jit")


def _with_and_without_aot(code: str, argv) -> dict[str, str]:
    """The last stdout line of ``python -c code *argv(flag)`` in a fresh interpreter with the extensions
    (``MST_AOT=1``) and with numba's JIT (``"0"``), per flag."""
    base = {k: v for k, v in os.environ.items() if k not in ("MST_AOT", "MST_AOT_DIR")}
    last = {}
    for flag in ("1", "0"):
        r = subprocess.run([sys.executable, "-c", code, *argv(flag)], capture_output=True, text=True,
                           env=dict(base, MST_AOT=flag), timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        last[flag] = r.stdout.strip().splitlines()[-1]
    return last


TRACKING = ("mst.pipeline.tracking.kernels", "mst.pipeline.tracking.covariance_kernels",
            "mst.pipeline.tracking.exact_kernels", "mst.pipeline.zbuffer_kernels", "mst.core.klt_kernels")


@pytest.mark.skipif(not all(aot.is_current(m) for m in TRACKING),
                    reason="tracking kernels not built ahead of time for this source and CPU (python -m mst.eval.c2m.warmup)")
def test_track_runs_without_importing_numba_and_gives_the_jit_poses(tmp_path):
    """``mst track`` of a polygon model, in the default mode (edges + KLT, the mono aid on standby) and edges
    only: with the warm-up's extensions no kernel call goes to numba's JIT (every kernel and argument type
    the tracker uses was compiled ahead of time: numba is not even imported, ~0.8 s of start-up), and the
    trajectories are those of the JIT kernels bit for bit (``MST_AOT=0``)."""
    from mst.eval.bench.slam import SAMPLE_MODEL
    from mst.pipeline.synth import SynthConfig, synthesize

    seq = tmp_path / "seq"
    synthesize("orbit", SAMPLE_MODEL, seq, SynthConfig(frames=6, width=320, height=240, depth=False, aa_samples=4,
                                                       texture_size=512))
    code = ("import sys; from mst.cli.main import cli\n"
            "for slam in ('auto', 'off'):\n"
            "    try:\n"
            "        cli(['track', sys.argv[1] + '/rgb', '--model', sys.argv[1] + '/model.obj', '--camera',\n"
            "             sys.argv[1] + '/camera.json', '--init', sys.argv[1] + '/cMo/000000.txt', '--fps', '30',\n"
            "             '-o', sys.argv[2] + '/' + slam + '.txt', '--slam', slam, '-q'])\n"
            "    except SystemExit as e:\n        assert not e.code, e.code\n"
            "from mst.core import aot\n"
            "print('numba' in sys.modules, sorted(aot.FALLBACKS))")
    for flag in ("1", "0"):
        (tmp_path / f"aot{flag}").mkdir()
    last = _with_and_without_aot(code, lambda flag: [str(seq), str(tmp_path / f"aot{flag}")])
    assert last["1"] == "False []", last["1"]  # no numba, no call to the JIT
    assert last["0"].startswith("True"), last["0"]  # the JIT run is one (the comparison is not vacuous)
    for slam in ("auto", "off"):
        a, j = ((tmp_path / f"aot{f}" / f"{slam}.txt").read_text() for f in ("1", "0"))
        assert len(a.splitlines()) >= 5 and a == j, slam


@pytest.mark.skipif(not aot.is_current("mst.pipeline.nav.kernels"),
                    reason="navigation kernels not built ahead of time for this source and CPU")
def test_nav_fusion_runs_without_importing_numba_and_gives_the_jit_result():
    """``mst nav fuse``'s estimator (smoother and filter, a vision gap) from the extension: numba not
    imported, no JIT call, every output array byte-equal to the ``MST_AOT=0`` run's."""
    code = ("import sys, hashlib, numpy as np\n"
            "from mst.core.poses import look_at\n"
            "from mst.pipeline.nav.fusion import FusionConfig, fuse_navigation\n"
            "from mst.pipeline.nav.log import NavSimConfig, simulate_nav\n"
            "t = np.arange(0.0, 30.0, 0.1)\n"
            "T = np.stack([look_at(np.array([30 * np.cos(0.1 * a), 30 * np.sin(0.1 * a), 20.0]), np.zeros(3)) for a in t])\n"
            "keep = (t < 10.0) | (t >= 16.0)\n"
            "C = np.tile(np.diag([0.05 ** 2] * 3 + [np.radians(0.2) ** 2] * 3), (int(keep.sum()), 1, 1))\n"
            "nav = simulate_nav(t, T, NavSimConfig(seed=3)).nav\n"
            "h = hashlib.sha256()\n"
            "for mode in ('smoother', 'filter'):\n"
            "    r = fuse_navigation(t[keep], T[keep], C, nav, FusionConfig(mode=mode))\n"
            "    for k, v in sorted(vars(r).items()):\n"
            "        if isinstance(v, np.ndarray):\n"
            "            h.update(np.ascontiguousarray(v).tobytes())\n"
            "from mst.core import aot\n"
            "print('numba' in sys.modules, sorted(aot.FALLBACKS), h.hexdigest())")
    out = {f: line.split() for f, line in _with_and_without_aot(code, lambda flag: []).items()}
    assert out["1"][:2] == ["False", "[]"], out["1"]
    assert out["0"][0] == "True" and out["1"][-1] == out["0"][-1]


@pytest.mark.slow
def test_build_from_scratch_matches_the_jit(tmp_path, monkeypatch):
    """The whole build (warm-up signatures -> extension) into an empty folder, then the results."""
    import importlib

    from mst.eval.c2m import warmup

    monkeypatch.setenv("MST_AOT", "0")
    warmup.warm_c2m()
    spec = aot.build(C2M, tmp_path)
    assert {"grid_query", "bins_query", "refine_cells", "missing_cells", "shift_points"} <= set(spec["kernels"])
    monkeypatch.setenv("MST_AOT_DIR", str(tmp_path))
    monkeypatch.delenv("MST_AOT")
    import mst.eval.c2m.compiled as compiled

    k = aot.Kernels(C2M)
    assert k.aot and aot.is_current(C2M)
    V, F, P = _c2m_cases()
    monkeypatch.setattr(compiled, "kernels", k)
    ahead = _c2m_all(V, F, P)
    monkeypatch.setattr(compiled, "kernels", importlib.import_module(C2M))
    _assert_same(ahead, _c2m_all(V, F, P))
