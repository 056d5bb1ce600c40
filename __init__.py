"""mst: model-based survey tracking.

Subpackages: :mod:`mst.cli` (click commands), :mod:`mst.pipeline` (camera, poses, rendering,
moving edges, pose optimisation, SLAM, fusion), :mod:`mst.meshtools` (model I/O, TIN to polygons),
:mod:`mst.eval` (cloud-to-mesh, trajectory metrics, benchmarks).

This module stays import-light: it holds the version, the error types every stage raises for bad
input, and the atomic-output helper that keeps partial files from ever appearing.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__version__ = "0.1.0"


class MstError(Exception):
    """An error the CLI reports as one line (no traceback) with a non-zero exit."""

    exit_code = 1


class InputError(MstError):
    """Bad input: names the offending file and the problem.

    >>> str(InputError("clicks.txt", "3 clicks, need at least 4"))
    'clicks.txt: 3 clicks, need at least 4'
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


def require_file(path: str | os.PathLike, what: str = "file") -> Path:
    """Return ``Path(path)`` or raise :class:`InputError` when it is missing or not a file."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, f"{what} does not exist")
    if not p.is_file():
        raise InputError(p, f"{what} is not a regular file")
    return p


def _tmp_name(path: Path) -> Path:
    # Reserve a unique name, then free it: a target is renamed into place only if its writer
    # actually created the temporary file (optional side outputs stay absent).
    fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    os.unlink(name)
    return Path(name)


@contextlib.contextmanager
def atomic_outputs(*paths: str | os.PathLike | None) -> Iterator[list[Path | None]]:
    """Write several outputs all-or-nothing.

    Yields temporary paths (same folder and suffix as the targets, so writers that pick a format
    by suffix still work). When the block finishes without an exception every temporary file is
    renamed onto its target; on any exception all of them are deleted and no target is touched.
    ``None`` entries pass through as ``None`` (optional outputs).
    """
    targets = [None if p is None else Path(p) for p in paths]
    for t in targets:
        if t is not None and not t.parent.exists():
            raise InputError(t, "output folder does not exist")
    tmps = [None if t is None else _tmp_name(t) for t in targets]
    try:
        yield tmps
        for t, tmp in zip(targets, tmps):
            if t is not None and tmp is not None and tmp.exists():
                os.replace(tmp, t)
    finally:
        for tmp in tmps:
            if tmp is not None and tmp.exists():
                tmp.unlink()


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Single-file form of :func:`atomic_outputs`."""
    with atomic_outputs(path) as (tmp,):
        yield tmp
