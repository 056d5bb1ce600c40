"""Depth frames: read any supported depth file as metres, list the frames of a folder.

Formats (picked by file suffix), all returned as float32 ``(H, W)`` metres with **0 where there is
no depth** (no surface, invalid, NaN, negative):

* ``.png`` / ``.tif`` / ``.tiff``: 16-bit integer depth (millimetres by default, see ``depth_scale``);
  a float32 TIFF holds metres;
* ``.npy``: float array in metres (NaN or 0 = no depth); an integer array is scaled like a PNG;
* ``.exr``: OpenEXR depth in metres, read with OpenCV (``OPENCV_IO_ENABLE_OPENEXR=1`` is set here
  before the first read); Blender's "no surface" value 65504 (the largest half float) and above
  become 0; a 3-channel file (Blender writes B = G = R) gives its first channel;
* ``.bin``: ViSP's raw depth (the RGB-D tutorials): little-endian ``uint32`` height, ``uint32``
  width, then height x width little-endian ``uint16`` values, row-major, in the same integer units
  as a PNG (millimetres by default).

``depth_scale`` for integer formats follows the Open3D / TUM RGB-D convention: **raw units per
metre** (1000 = millimetres, the default; 5000 for the TUM RGB-D benchmark PNGs). A value below 1
is read the other way round, as metres per raw unit (ViSP's ``0.001``), so both conventions work;
the two agree at 1.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.config import Config, param


@dataclass
class DepthConfig(Config):
    """How depth frames are read and which depths are trusted (shared by ``track`` and ``fuse``).

    ``scale``: raw integer units per metre (1000 = millimetres; 5000 = TUM RGB-D; a value below 1
    is read as metres per unit, ViSP's 0.001); ``min_m``/``max_m``: depths outside are invalid;
    ``edge_rel``: a pixel whose local depth spread exceeds this x its depth lies on a depth
    discontinuity and is dropped (0: off).
    """

    scale: float = param(1000.0, min=0, min_open=True, help="raw depth units per metre (TUM RGB-D: 5000)")
    min_m: float = param(0.1, min=0, help="nearer depths are invalid, m")
    max_m: float = param(50.0, min=0, min_open=True, help="farther depths are invalid, m")
    edge_rel: float = param(0.03, min=0, max=10, help="depth-discontinuity bound, x depth (0: off)")

    def check(self) -> None:
        from mst.errors import ConfigError

        if not self.min_m < self.max_m:
            raise ConfigError("min_m", f"must be below max_m ({self.max_m:g} m), got {self.min_m:g}")

#: suffixes read as depth, in the order preferred when a folder holds several formats of the same
#: frames (a ``mst synth`` ``depth/`` folder holds both ``000000.npy`` and ``000000.png``): exact
#: float metres first.
DEPTH_SUFFIXES = (".npy", ".exr", ".bin", ".png", ".tif", ".tiff")

#: Blender / half-float "no surface" value in EXR depth (metres); values at or above it become 0
EXR_NO_SURFACE = 65504.0


def metres_per_unit(depth_scale: float) -> float:
    """Metres per raw integer unit for ``depth_scale`` (units per metre if >= 1, else metres per unit)."""
    s = float(depth_scale)
    if not np.isfinite(s) or s <= 0:
        raise ValueError(f"depth scale must be a positive number, got {depth_scale}")
    return 1.0 / s if s >= 1.0 else s


def units_to_metres(raw: np.ndarray, m_per_unit: float) -> np.ndarray:
    """Integer depth ``raw`` (H, W) in units of ``m_per_unit`` metres -> float32 metres (H, W).

    The float32 quotient ``raw / units_per_metre`` (correctly rounded), not a product with the
    rounded reciprocal: the same depth stored in millimetres (``d``, scale 1000) or in TUM's 1/5000 m
    (``5 d``, scale 5000) then gives bit-identical metres, so a run does not depend on the unit its
    depth was written in (with the reciprocal the two differed in the last bit of some pixels, and a
    flipped RANSAC decision in the SLAM aid turned that into millimetres on one CPU).
    """
    return raw.astype(np.float32) / np.float32(1.0 / m_per_unit)


def natural_key(path: str | os.PathLike) -> list:
    """Sort key that orders ``frame2`` before ``frame10`` (digit runs compared as numbers)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", Path(path).name)]


def _finish(depth_m: np.ndarray, path: Path) -> np.ndarray:
    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim == 3 and d.shape[2] >= 1:
        d = d[:, :, 0]
    if d.ndim != 2 or d.size == 0:
        raise InputError(path, f"depth must be a 2D image, got shape {tuple(np.shape(depth_m))}")
    d = np.where(np.isfinite(d) & (d > 0), d, np.float32(0)).astype(np.float32, copy=False)
    return np.ascontiguousarray(d)


def _read_bin(path: Path, m_per_unit: float) -> np.ndarray:
    raw = path.read_bytes()
    if len(raw) < 8:
        raise InputError(path, f"ViSP raw depth is truncated: {len(raw)} bytes, need an 8-byte header")
    h, w = (int(v) for v in np.frombuffer(raw[:8], dtype="<u4"))
    need = 8 + 2 * h * w
    if h == 0 or w == 0 or h > 100_000 or w > 100_000:
        raise InputError(path, f"ViSP raw depth header says {w}x{h} pixels: not a depth frame")
    if len(raw) != need:
        what = "truncated" if len(raw) < need else "longer than its header says"
        raise InputError(path, f"ViSP raw depth is {what}: {len(raw)} bytes, expected {need} for {w}x{h}")
    d = np.frombuffer(raw, dtype="<u2", offset=8).reshape(h, w)
    return units_to_metres(d, m_per_unit)


def _read_cv(path: Path, m_per_unit: float) -> np.ndarray:
    # OpenCV reads this variable at the first EXR decode, so setting it here (before any EXR read)
    # works even when cv2 is already imported.
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "cannot decode the depth image (corrupt, truncated or unsupported)")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        img = img.astype(np.float32, copy=False)
        if img.ndim == 3:
            img = img[:, :, 0]
        img = np.where(img >= np.float32(EXR_NO_SURFACE * 0.999), np.float32(0), img)
        return img
    if img.ndim == 3:
        raise InputError(path, f"depth image has {img.shape[2]} channels; expected a single-channel 16-bit image")
    if img.dtype == np.uint8:
        raise InputError(path, "8-bit image: depth must be 16-bit integer (or float)")
    if np.issubdtype(img.dtype, np.integer):
        return units_to_metres(img, m_per_unit)
    return img.astype(np.float32)  # float TIFF: metres


def _check_npy_header(path: Path) -> None:
    """Refuse a .npy whose header promises more data than the file holds, or a shape no depth frame
    has, before ``np.load`` allocates it (a corrupt header asked for 671 GiB)."""
    with open(path, "rb") as fh:
        try:
            version = np.lib.format.read_magic(fh)
            reader = np.lib.format.read_array_header_2_0 if version == (2, 0) else np.lib.format.read_array_header_1_0
            shape, _, dtype = reader(fh)
        except (ValueError, OSError, EOFError, SyntaxError, TypeError) as e:
            raise InputError(path, f"cannot read the .npy depth ({e})") from None
        start = fh.tell()
    if len(shape) not in (2, 3) or any(n > 100_000 for n in shape[:2]) or (len(shape) == 3 and shape[2] > 4):
        raise InputError(path, f"depth .npy has shape {shape}: not a depth frame (H, W)")
    need = start + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    size = path.stat().st_size
    if size < need:
        raise InputError(path, f"depth .npy is truncated: {size} bytes, its header needs {need} for shape {shape}")


def _read_npy(path: Path, m_per_unit: float) -> np.ndarray:
    _check_npy_header(path)
    try:
        a = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise InputError(path, f"cannot read the .npy depth ({e})") from None
    if not isinstance(a, np.ndarray) or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputError(path, f"depth .npy must hold numbers, got dtype {getattr(a, 'dtype', type(a))}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if np.issubdtype(a.dtype, np.integer):
        return units_to_metres(a, m_per_unit)
    return a.astype(np.float32, copy=False)


def read_depth(path: str | os.PathLike, depth_scale: float = 1000.0) -> np.ndarray:
    """Read one depth frame as float32 ``(H, W)`` metres, 0 where there is no depth.

    ``depth_scale``: raw units per metre for integer formats (16-bit PNG/TIFF, ViSP ``.bin``,
    integer ``.npy``); default 1000 (millimetres). Below 1 it is taken as metres per unit.
    Float formats (``.npy``, ``.exr``, float TIFF) are metres and ignore it.
    Raises :class:`mst.InputError` naming the file when it is missing, corrupt or truncated.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "depth frame does not exist")
    try:
        mpu = metres_per_unit(depth_scale)
    except ValueError as e:
        raise InputError(p, str(e)) from None
    suffix = p.suffix.lower()
    if suffix == ".bin":
        d = _read_bin(p, mpu)
    elif suffix == ".npy":
        d = _read_npy(p, mpu)
    elif suffix in (".png", ".tif", ".tiff", ".exr"):
        d = _read_cv(p, mpu)
    else:
        raise InputError(p, f"unknown depth format {suffix!r} (expected {', '.join(DEPTH_SUFFIXES)})")
    return _finish(d, p)


def list_depth_frames(folder: str | os.PathLike, suffix: str | None = None) -> list[Path]:
    """Depth frames of a folder, sorted naturally (``d2`` before ``d10``); frame index = list position.

    ``folder`` may also be a glob pattern (``seq/depth/*.png``). With no ``suffix``, the folder's
    first format in :data:`DEPTH_SUFFIXES` order is used (``.npy`` before ``.png`` when a folder
    holds both, as ``mst synth`` writes), so each frame is listed once. Other files (colour
    ``.jpg``, text) are ignored. Raises :class:`mst.InputError` when nothing is found.
    """
    spec = str(folder)
    if any(c in spec for c in "*?["):
        import glob

        files = [Path(f) for f in glob.glob(spec) if Path(f).is_file()]
        files = [f for f in files if f.suffix.lower() in DEPTH_SUFFIXES]
        where: Path = Path(spec).parent
    else:
        where = Path(spec)
        if not where.is_dir():
            raise InputError(where, "depth folder does not exist" if not where.exists() else "not a folder")
        files = [f for f in where.iterdir() if f.is_file() and f.suffix.lower() in DEPTH_SUFFIXES
                 and not f.name.startswith(".")]
    if suffix is not None:
        want = suffix.lower() if suffix.startswith(".") else "." + suffix.lower()
        files = [f for f in files if f.suffix.lower() == want]
    else:
        present = {f.suffix.lower() for f in files}
        for s in DEPTH_SUFFIXES:
            if s in present:
                files = [f for f in files if f.suffix.lower() == s]
                break
    if not files:
        raise InputError(folder, f"no depth frames ({', '.join(DEPTH_SUFFIXES)}) found")
    return sorted(files, key=natural_key)


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def list_image_frames(folder: str | os.PathLike) -> list[Path]:
    """Colour frames of a folder (or glob), sorted naturally; frame index = list position."""
    spec = str(folder)
    if any(c in spec for c in "*?["):
        import glob

        files = [Path(f) for f in glob.glob(spec) if Path(f).is_file()]
    else:
        d = Path(spec)
        if not d.is_dir():
            raise InputError(d, "colour image folder does not exist" if not d.exists() else "not a folder")
        files = [f for f in d.iterdir() if f.is_file() and not f.name.startswith(".")]
    files = [f for f in files if f.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise InputError(folder, f"no colour images ({', '.join(IMAGE_SUFFIXES)}) found")
    return sorted(files, key=natural_key)
