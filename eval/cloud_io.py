"""Point-cloud reading and writing, streamed in chunks (bounded memory).

Formats (picked by suffix):

* ``.ply``: through :mod:`mst.core.ply`: binary (little/big endian, read chunk by chunk) or ascii;
  the ``vertex`` element with ``x y z`` properties of any numeric type.
* ``.pcd``: PCL point clouds, ``DATA ascii`` or ``binary`` (``binary_compressed`` is refused).
* ``.xyz``, ``.txt``, ``.csv``, ``.asc``, ``.pts``: text, the first three numeric columns are x y z;
  separators space, tab, comma or semicolon; ``#``/``//`` comment lines and a non-numeric header line
  are skipped.
* ``.las``, ``.laz``: with laspy (LAZ through lazrs), scaled coordinates in float64.

Coordinates come back as float64 (N, 3) arrays in the file's units (metres for survey data), so
georeferenced clouds (1e6 m) keep their precision. Non-finite rows are passed through; callers decide.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError, require_file
from mst.core.ply import PlyVertexWriter, ascii_rows, open_vertices

TEXT_SUFFIXES = {".xyz", ".txt", ".csv", ".asc", ".pts"}
CLOUD_SUFFIXES = {".ply", ".pcd", ".las", ".laz"} | TEXT_SUFFIXES


@dataclass
class CloudSource:
    """An opened cloud: ``count`` rows, read in chunks with :meth:`chunks`.

    ``xyz_dtype`` is the numpy dtype of the stored coordinates (``f4`` or ``f8``), so writers can
    keep float32 clouds float32.
    """

    path: Path
    count: int
    xyz_dtype: np.dtype
    _reader: object = field(repr=False, default=None)

    def chunks(self, size: int = 1_000_000) -> Iterator[np.ndarray]:
        """Yield float64 (n, 3) coordinate blocks of at most ``size`` rows, in file order."""
        yield from self._reader(size)  # type: ignore[misc]

    def read_all(self) -> np.ndarray:
        """All coordinates as one float64 (N, 3) array."""
        parts = list(self.chunks(min(max(self.count, 1), 1 << 20)))  # memory follows the data, not the header
        return np.concatenate(parts) if parts else np.zeros((0, 3))


def open_cloud(path: str | os.PathLike) -> CloudSource:
    """Open a cloud file for chunked reading (see the module docstring for formats).

    Raises :class:`mst.InputError` for a missing, unknown or corrupt file.
    """
    p = require_file(path, "cloud file")
    suf = p.suffix.lower()
    if suf == ".ply":
        return _open_ply(p)
    if suf == ".pcd":
        return _open_pcd(p)
    if suf in (".las", ".laz"):
        return _open_las(p)
    if suf in TEXT_SUFFIXES:
        return _open_text(p)
    raise InputError(p, f"unknown cloud format {suf!r} (use .ply .pcd .xyz .txt .csv .las .laz)")


def read_cloud(path: str | os.PathLike) -> np.ndarray:
    """Read a whole cloud: float64 (N, 3) coordinates (file units, usually metres)."""
    return open_cloud(path).read_all()


# ----------------------------------------------------------------------------------------- PLY
def _open_ply(p: Path) -> CloudSource:
    # the one PLY module: strict header (counts, types, lists, vertex x/y/z, body size), chunked reads
    vs = open_vertices(p)
    xyz_dtype = np.dtype(max((vs.types[k] for k in "xyz"), key=lambda s: np.dtype(s).itemsize))
    return CloudSource(p, vs.count, xyz_dtype, lambda size: vs.chunks(size, ("x", "y", "z")))


# ----------------------------------------------------------------------------------------- PCD
def _open_pcd(p: Path) -> CloudSource:
    with open(p, "rb") as f:
        head = f.read(1 << 16)
    hdr: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = head.find(b"\n", pos)
        if nl < 0:
            raise InputError(p, "truncated or corrupt PCD header (no DATA line)")
        line = head[pos:nl].decode("ascii", "replace").strip()
        pos = nl + 1
        if not line or line.startswith("#"):
            continue
        tok = line.split()
        hdr[tok[0].upper()] = tok[1:]
        if tok[0].upper() == "DATA":
            break

    def ints(key: str, default: list[str]) -> list[int]:
        vals = hdr.get(key, default)
        if not vals or not all(re.fullmatch(r"\d+", v) for v in vals):
            raise InputError(p, f"PCD header: {key} must hold integers >= 0 (got {' '.join(vals)[:40]!r})")
        return [int(v) for v in vals]

    if "FIELDS" not in hdr or "DATA" not in hdr or not hdr["DATA"] or not ("POINTS" in hdr or "WIDTH" in hdr):
        raise InputError(p, "PCD header lacks FIELDS/POINTS/DATA")
    fields = hdr["FIELDS"]
    n = ints("POINTS", [])[0] if "POINTS" in hdr else ints("WIDTH", [])[0] * ints("HEIGHT", ["1"])[0]
    data = hdr["DATA"][0].lower()
    if not {"x", "y", "z"} <= set(fields) or len(set(fields)) != len(fields):
        raise InputError(p, "PCD has no x, y, z fields (or a field twice)")
    sizes = ints("SIZE", ["4"] * len(fields))
    types = [t.upper() for t in hdr.get("TYPE", ["F"] * len(fields))]
    counts = ints("COUNT", ["1"] * len(fields))
    if not (len(sizes) == len(types) == len(counts) == len(fields)):
        raise InputError(p, "PCD header: FIELDS, SIZE, TYPE and COUNT differ in length")
    kind = {"F": "f", "I": "i", "U": "u"}
    for nm, sz, t in zip(fields, sizes, types):
        if t not in kind or sz not in ((4, 8) if t == "F" else (1, 2, 4, 8)):
            raise InputError(p, f"PCD header: field {nm!r} has TYPE {t} SIZE {sz} (not a number type)")
    if any(counts[fields.index(k)] != 1 for k in "xyz"):
        raise InputError(p, "PCD header: x, y, z must have COUNT 1")
    xyz_dtype = np.dtype("f8") if max(sizes[fields.index(k)] for k in "xyz") > 4 else np.dtype("f4")
    if data == "ascii":
        col, cols = 0, {}
        for nm, c in zip(fields, counts):
            cols[nm] = col
            col += c

        return CloudSource(p, n, xyz_dtype, ascii_rows(p, pos, n, [cols[c] for c in "xyz"], "ascii PCD data", "points"))
    if data != "binary":
        raise InputError(p, f"PCD DATA {data!r} not supported (use ascii or binary)")
    dt = np.dtype([(nm, "<" + kind[t] + str(s), (c,)) if c > 1 else (nm, "<" + kind[t] + str(s))
                   for nm, s, t, c in zip(fields, sizes, types, counts)])
    if p.stat().st_size < pos + n * dt.itemsize:
        raise InputError(p, "file is truncated")

    def reader(size: int) -> Iterator[np.ndarray]:
        with open(p, "rb") as f:
            f.seek(pos)
            for s in range(0, n, size):
                blk = np.fromfile(f, dtype=dt, count=min(size, n - s))
                with np.errstate(invalid="ignore"):  # signalling NaNs pass through as NaN
                    yield np.stack([blk[k].astype(np.float64) for k in "xyz"], axis=1)

    return CloudSource(p, n, xyz_dtype, reader)


# ----------------------------------------------------------------------------------------- LAS
def _open_las(p: Path) -> CloudSource:
    import laspy

    try:
        with laspy.open(p) as f:
            n = int(f.header.point_count)
            start = int(f.header.offset_to_point_data)
            rec = int(f.header.point_format.size)
            compressed = bool(getattr(f.header, "are_points_compressed", p.suffix.lower() == ".laz"))
    except Exception as e:  # laspy raises several types for corrupt files
        raise InputError(p, f"cannot read LAS/LAZ header ({e})") from None
    size = p.stat().st_size
    # the header's count must fit the file (a corrupt count would make laspy allocate it); LAZ
    # compresses, so only an absurd ratio is refused there (LASzip reaches ~10x on real clouds)
    if (not compressed and start + n * rec > size) or (compressed and n * rec > 1000 * size):
        raise InputError(p, f"LAS/LAZ header announces {n} points of {rec} bytes; the file has {size} bytes (truncated or corrupt)")

    def reader(size: int) -> Iterator[np.ndarray]:
        try:
            with laspy.open(p) as f:
                for pts in f.chunk_iterator(size):
                    yield np.stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                    np.asarray(pts.z, np.float64)], axis=1)
        except InputError:
            raise
        except Exception as e:
            raise InputError(p, f"cannot read LAS/LAZ points ({e})") from None

    return CloudSource(p, n, np.dtype("f8"), reader)


# ---------------------------------------------------------------------------------------- text
_SPLIT = re.compile(rb"[,;\t ]+")


def _open_text(p: Path) -> CloudSource:
    """Text clouds are parsed once, whole (text is not used for very large clouds)."""
    raw = p.read_bytes()
    lines = [ln.strip() for ln in raw.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith((b"#", b"//"))]
    if lines:
        try:
            [float(x) for x in _SPLIT.split(lines[0])[:3]]
        except ValueError:
            lines = lines[1:]  # a header line with column names
    if not lines:
        a = np.zeros((0, 3))
    else:
        try:
            first = len(_SPLIT.split(lines[0]))
            if first < 3:
                raise InputError(p, "fewer than 3 columns (need x y z)")
            body = b"\n".join(_SPLIT.sub(b" ", ln) for ln in lines)
            a = np.array(body.split(), dtype=np.float64)
            if a.size % first:
                raise InputError(p, "rows have different numbers of columns")
            a = a.reshape(-1, first)[:, :3]
        except ValueError as e:
            raise InputError(p, f"not a number in the cloud ({e})") from None

    def reader(size: int) -> Iterator[np.ndarray]:
        for s in range(0, len(a), size):
            yield a[s : s + size]

    return CloudSource(p, len(a), np.dtype("f8"), reader)


# --------------------------------------------------------------------------------------- write
class PlyChunkWriter(PlyVertexWriter):
    """Write a binary little-endian PLY vertex cloud chunk by chunk (:class:`mst.core.ply.PlyVertexWriter`).

    ``fields`` are extra float32 scalar fields named ``scalar_<name>`` in the file, the convention
    CloudCompare reads as scalar fields (e.g. ``C2M_absolute_distances``). Coordinates are written as
    ``xyz_dtype`` (float32 or float64: keep float64 for georeferenced clouds). The vertex count must
    be known up front (``count``); :meth:`close` checks it.
    """

    def __init__(self, path: str | os.PathLike, count: int, fields: list[str], xyz_dtype=np.float64):
        self.fields = list(fields)
        xt = {4: "f4", 8: "f8"}[np.dtype(xyz_dtype).itemsize]
        super().__init__(path, count, [(k, xt) for k in "xyz"] + [(f"scalar_{f}", "f4") for f in self.fields],
                         comments=["written by mst"])

    def write(self, xyz: np.ndarray, **scalars: np.ndarray) -> None:
        super().write([xyz[:, 0], xyz[:, 1], xyz[:, 2], *[scalars[f] for f in self.fields]])


def write_cloud(path: str | os.PathLike, xyz: np.ndarray, scalars: dict[str, np.ndarray] | None = None,
                xyz_dtype=np.float64) -> None:
    """Write a cloud with optional scalar fields.

    ``.ply`` (binary, fields as ``scalar_<name>``), ``.xyz``/``.txt``/``.csv`` (x y z then the fields,
    with a ``//X,Y,Z,...`` header line for CSV), ``.las``/``.laz`` (fields as extra float32 dimensions).
    Call it inside :func:`mst.atomic_output` for atomicity.
    """
    p = Path(path)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    scalars = scalars or {}
    suf = p.suffix.lower()
    if suf == ".ply":
        with PlyChunkWriter(p, len(xyz), list(scalars), xyz_dtype) as w:
            w.write(xyz, **scalars)
    elif suf in TEXT_SUFFIXES:
        cols = np.column_stack([xyz] + [np.asarray(v, np.float64) for v in scalars.values()])
        delim = "," if suf == ".csv" else " "
        header = delim.join(["X", "Y", "Z", *scalars]) if suf == ".csv" else ""
        np.savetxt(p, cols, fmt="%.9g" if xyz_dtype == np.float32 else "%.10f", delimiter=delim,
                   header=header, comments="//")
    elif suf in (".las", ".laz"):
        import laspy

        hdr = laspy.LasHeader(point_format=3, version="1.2")
        lo = np.nanmin(xyz, axis=0) if len(xyz) else np.zeros(3)
        hdr.offsets = np.floor(lo)
        hdr.scales = np.array([1e-4, 1e-4, 1e-4])
        for k in scalars:
            hdr.add_extra_dim(laspy.ExtraBytesParams(name=k, type=np.float32))
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        for k, v in scalars.items():
            las[k] = np.asarray(v, np.float32)
        las.write(p)
    else:
        raise InputError(p, f"unknown cloud format {suf!r} for writing")
