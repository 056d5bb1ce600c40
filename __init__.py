"""mst: model-based survey tracking.

Packages, dependencies pointing one way (foundation <- stages <- runners <- CLI):
:mod:`mst.core` (the foundation: camera, poses, KLT, file formats, configuration),
:mod:`mst.meshtools` (model I/O, TIN to polygons), :mod:`mst.pipeline` (rendering and visibility,
moving edges, pose optimisation, tracking, SLAM, fusion, synthesis, navigation),
:mod:`mst.eval` (cloud-to-mesh, trajectory metrics, reports; benchmarks in :mod:`mst.eval.bench`),
:mod:`mst.cli` (click commands only).

This module stays import-light: it holds the version, re-exports the error types of
:mod:`mst.errors`, and the input/output helpers (atomic outputs) that keep partial files from ever
appearing. It imports the standard library and :mod:`mst.errors` only.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from mst.errors import ConfigError, InputError, MstError  # noqa: F401  (the public error types)

__version__ = "0.1.0"


def require_file(path: str | os.PathLike, what: str = "file") -> Path:
    """Return ``Path(path)`` or raise :class:`InputError` when it is missing or not a file."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, f"{what} does not exist")
    if not p.is_file():
        raise InputError(p, f"{what} is not a regular file")
    return p


def read_text(path: str | os.PathLike, what: str = "file") -> str:
    """The text of a small input file, decoded as UTF-8; a leading byte-order mark is dropped.

    Raises :class:`InputError` naming the file when it is missing, a folder, unreadable, or not
    UTF-8 text (with the line and byte offset of the first bad byte), so that no reader lets a
    ``UnicodeDecodeError`` escape.
    """
    p = require_file(path, what)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise InputError(p, f"cannot read the {what} ({e.strerror})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise InputError(p, f"not a text {what}: byte 0x{data[e.start]:02x} at offset {e.start} (line {line}) "
                            "is not UTF-8") from None


#: errno values that mean "this output cannot be written" (not a bug): reported as one line
_WRITE_ERRNOS = frozenset(getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG", "EROFS", "EACCES", "EPERM",
                                                      "ENOENT", "ENOTDIR", "EISDIR", "EIO", "EXDEV")
                          if hasattr(errno, n))


def _same_file(a: Path, b: Path) -> bool:
    """True when ``a`` and ``b`` name the same file (``os.path.samefile`` when both exist)."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.normcase(os.path.abspath(a.resolve())) == os.path.normcase(os.path.abspath(b.resolve()))


def check_outputs(outputs: Iterable[str | os.PathLike | None],
                  inputs: Iterable[str | os.PathLike | tuple[str | os.PathLike, Iterable[str]] | None] = (),
                  writable: bool = True) -> None:
    """Refuse outputs that would overwrite an input, or each other, before anything is computed.

    ``outputs`` are the files a command will write, side outputs included (e.g. ``traj.csv`` beside
    ``traj.txt``); ``inputs`` the files it reads. ``None`` entries are skipped; input folders (a
    depth or frames folder) are given as ``(folder, suffixes)``: an existing output in the folder with
    one of those suffixes is one of its frames and is refused; a bare folder is skipped.
    Paths are compared resolved (symbolic links, ``..``) and with ``os.path.samefile`` when both
    exist (hard links). Raises :class:`InputError` naming the output and the input it would replace.
    With ``writable`` each output's folder is also checked now, before any work: it must exist and
    accept a new file (a temporary name is created and removed), so that a read-only folder or a
    missing one fails before minutes of computation, not after.
    """
    outs = [Path(o) for o in outputs if o is not None]
    ins: list[tuple[Path, tuple[str, ...] | None]] = []
    for i in inputs:
        if isinstance(i, tuple):  # (folder, suffixes of the files it contributes)
            ins.append((Path(i[0]), tuple(s.lower() for s in i[1])))
        elif i is not None:
            ins.append((Path(i), None))
    for k, o in enumerate(outs):
        for i, suffixes in ins:
            if i.is_dir():
                if (suffixes is not None and o.suffix.lower() in suffixes and o.is_file()
                        and _same_file(o.parent, i)):
                    raise InputError(o, f"output would overwrite a frame of the input folder {i}")
            elif _same_file(o, i):
                raise InputError(o, f"output would overwrite the input {i}")
        for o2 in outs[:k]:
            if _same_file(o, o2):
                raise InputError(o, f"the same file is given for two outputs ({o2})")
    if writable:
        for o in outs:
            if o.suffix or o.is_file():  # a file output (a folder of overlay PNGs is made by its writer)
                _check_target(o)
                _tmp_name(o)


def _write_problem(e: OSError) -> str:
    why = e.strerror or type(e).__name__
    if e.errno == errno.ENOSPC:
        why = "no space left on the device"
    return f"cannot write the output ({why})"


def _tmp_name(path: Path) -> Path:
    # Reserve a unique name, then free it: a target is renamed into place only if its writer
    # actually created the temporary file (optional side outputs stay absent).
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    except OSError as e:
        raise InputError(path, _write_problem(e)) from None
    os.close(fd)
    os.unlink(name)
    return Path(name)


def _check_target(t: Path) -> None:
    if not t.parent.exists():
        raise InputError(t, "output folder does not exist")
    if not t.parent.is_dir():
        raise InputError(t, f"output folder {t.parent} is not a folder")
    if t.is_dir():
        raise InputError(t, "output is a folder, expected a file name")
    if t.exists() and not t.is_file():
        raise InputError(t, "output exists and is not a regular file")


@contextlib.contextmanager
def atomic_outputs(*paths: str | os.PathLike | None) -> Iterator[list[Path | None]]:
    """Write several outputs all-or-nothing.

    Yields temporary paths (same folder and suffix as the targets, so writers that pick a format
    by suffix still work). When the block finishes without an exception every temporary file is
    renamed onto its target; on any exception all of them are deleted and no target is touched.
    ``None`` entries pass through as ``None`` (optional outputs).

    An output that cannot be written (missing or read-only folder, ``/proc``, a full disk, a
    folder where a file is expected) raises :class:`InputError` naming the *target*, not the
    temporary file, whether it shows when the temporary name is reserved, while the block writes
    it (an ``OSError`` on a temporary path, or a full disk) or when it is renamed into place.
    """
    targets = [None if p is None else Path(p) for p in paths]
    for t in targets:
        if t is not None:
            _check_target(t)
    tmps: list[Path | None] = []
    try:
        for t in targets:
            tmps.append(None if t is None else _tmp_name(t))
        by_tmp = {str(tmp): t for t, tmp in zip(targets, tmps) if tmp is not None}
        try:
            yield tmps
        except OSError as e:
            target = by_tmp.get(str(e.filename)) if e.filename is not None else None
            if target is None and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) and len(by_tmp) == 1:
                target = next(iter(by_tmp.values()))
            if target is None and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                target = ", ".join(str(t) for t in by_tmp.values())
            if target is None or e.errno not in _WRITE_ERRNOS:
                raise
            raise InputError(target, _write_problem(e)) from None
        for t, tmp in zip(targets, tmps):
            if t is not None and tmp is not None and tmp.exists():
                try:
                    os.replace(tmp, t)
                except OSError as e:
                    raise InputError(t, _write_problem(e)) from None
    finally:
        for tmp in tmps:
            if tmp is not None and tmp.exists():
                tmp.unlink()


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Single-file form of :func:`atomic_outputs`."""
    with atomic_outputs(path) as (tmp,):
        yield tmp
