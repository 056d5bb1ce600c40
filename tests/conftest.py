"""Shared fixtures: the real data in ../shared/data (skipped cleanly when absent) and run helpers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MST_SHARED_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data``; the test is skipped when the folder is absent (a user's clone)."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data not available at {SHARED}")
    return SHARED


def run_mst(*args: str, check: bool = True, input: str | None = None, cwd: str | Path | None = None) -> subprocess.CompletedProcess:
    """Run the ``mst`` CLI in a subprocess (the way users run it) and capture stdout/stderr."""
    cmd = [sys.executable, "-m", "mst.cli.main", *map(str, args)]
    r = subprocess.run(cmd, capture_output=True, text=True, input=input, cwd=cwd)
    if check and r.returncode != 0:
        raise AssertionError(f"mst {' '.join(map(str, args))} failed ({r.returncode}):\n{r.stderr}")
    return r


@pytest.fixture
def mst():
    return run_mst
