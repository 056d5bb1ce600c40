"""Shared fixtures: the real data in ../shared/data (skipped cleanly when absent), the gabled-house
model of the synthetic tests, and the run helpers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from mst.cpu import pin_blas_kernels

#: the suite's in-process runs use the BLAS kernels of the ``mst`` command (mst.cpu), when numpy is not
#: loaded yet (a plugin may have loaded it: the in-process SLAM runs then keep OpenBLAS's own choice)
BLAS_PINNED = pin_blas_kernels()

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MST_SHARED_DATA", ROOT.parent / "shared" / "data"))

#: the one gabled house of the synthetic tests: 4 x 3 m, eaves at 2.4 m, ridge 1.4 m above them (m)
HOUSE_M = dict(length=4.0, width=3.0, eaves=2.4, ridge=1.4)


@pytest.fixture(scope="session")
def gabled_house_tin(tmp_path_factory):
    """Factory ``(scale=1.0) -> Path``: the gabled-house TIN (OBJ, faces split twice, so a TIN with
    coplanar triangles) with every dimension of ``HOUSE_M`` times ``scale``; written once per scale."""
    from mst.meshtools.formats import save_triangles
    from mst.meshtools.generate import gabled_house

    made: dict[float, Path] = {}

    def make(scale: float = 1.0) -> Path:
        if scale not in made:
            p = tmp_path_factory.mktemp("models") / f"house_x{scale:g}.obj"
            V, F = gabled_house(split=2, **{k: v * scale for k, v in HOUSE_M.items()})
            save_triangles(p, V, F)
            made[scale] = p
        return made[scale]

    return make


@pytest.fixture(scope="module")
def house(gabled_house_tin) -> Path:
    """The gabled house at its full size (``HOUSE_M``)."""
    return gabled_house_tin(1.0)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data``; the test is skipped when the folder is absent (a user's clone)."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data not available at {SHARED}")
    return SHARED


#: MST_TEST_SUBPROCESS=1 runs every ``mst`` call of the suite in a fresh interpreter (the way users
#: run it). The default runs it in-process through the same entry point (``mst.cli.main.main``, with
#: its error handling and exit codes) with stdout/stderr captured: the suite then pays the ~1 s import
#: of open3d/cv2/numba once instead of once per call. Tests of what a fresh process imports
#: (test_core_cli.py) start their own subprocesses either way.
SUBPROCESS = os.environ.get("MST_TEST_SUBPROCESS", "0") == "1"


def _run_in_process(args: list[str], input: str | None, cwd: str | Path | None) -> subprocess.CompletedProcess:
    import traceback

    from click.testing import CliRunner

    from mst.cli.main import main

    old_cwd = os.getcwd()
    code = 0
    with CliRunner().isolation(input=input) as (out, err, _):
        try:
            if cwd is not None:
                os.chdir(cwd)
            main(args)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except BaseException:  # what a subprocess would print as an uncaught traceback
            traceback.print_exc(file=sys.stderr)
            code = 1
        finally:
            os.chdir(old_cwd)
            sys.stdout.flush()
            sys.stderr.flush()
        stdout, stderr = out.getvalue().decode("utf-8", "replace"), err.getvalue().decode("utf-8", "replace")
    return subprocess.CompletedProcess(["mst", *args], code, stdout, stderr)


def run_mst(*args: str, check: bool = True, input: str | None = None, cwd: str | Path | None = None) -> subprocess.CompletedProcess:
    """Run the ``mst`` CLI and capture stdout/stderr (in-process, or in a subprocess with
    ``MST_TEST_SUBPROCESS=1``); returns a ``CompletedProcess``."""
    argv = [str(a) for a in args]
    if SUBPROCESS:
        cmd = [sys.executable, "-m", "mst.cli.main", *argv]
        r = subprocess.run(cmd, capture_output=True, text=True, input=input, cwd=cwd)
    else:
        r = _run_in_process(argv, input, cwd)
    if check and r.returncode != 0:
        raise AssertionError(f"mst {' '.join(argv)} failed ({r.returncode}):\n{r.stderr}")
    return r


@pytest.fixture
def mst():
    return run_mst
