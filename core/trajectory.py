"""Trajectory and pose files: TUM, KITTI, CSV columns and ViSP cMo, read and written in one place.

* TUM: one pose per line ``t tx ty tz qx qy qz qw`` (camera pose ``T_model_cam``, metres, a unit
  quaternion); ``#`` lines are comments.
* KITTI: 12 numbers per line, the 3x4 pose matrix row-major; time = line index (or index / fps).
* CSV: a header row; the columns of ``t x y z`` and optionally ``qx qy qz qw`` named by a
  ``key=column`` spec (``"t=time,x=e,y=n,z=h"``); without quaternion columns the rotation is unknown.
* ViSP cMo: one pose as a 4x4 (or 3x4) model-to-camera matrix, a TUM line or 7 numbers
  (:func:`read_pose_file`); :func:`write_pose_file` writes a TUM line with the cMo as a comment.

Every reader takes UTF-8 text (a byte-order mark is accepted) and refuses, with an
:class:`mst.InputError` naming the file and line, NaN/inf, positions beyond
:data:`~mst.core.poses.MAX_POSITION_M`, quaternions that are not unit and rotations that are not
rotations. Imports numpy, :mod:`mst.core.poses` and :mod:`mst.errors` only.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst import InputError, read_text
from mst.core.poses import (
    MAX_POSITION_M,
    R_from_quat,
    inv_T,
    make_T,
    quat_from_R,
    read_numbers,
    rigid_from_rows,
)
from mst.errors import ConfigError

log = logging.getLogger(__name__)

#: accepted deviation of a file quaternion's norm from 1: files print >= 3 decimals (rounding <= 2e-3),
#: a norm far from 1 (0 0 0 0, 1e-310) is not a rotation and must not be normalised into one
QUAT_NORM_TOL = 0.01

#: the keys of a CSV column spec: position columns are required, quaternion columns optional
CSV_KEYS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
TRAJECTORY_FORMATS = ("auto", "tum", "kitti", "csv")


# ------------------------------------------------------------------------------ TUM rows
def tum_to_T(rows: np.ndarray) -> np.ndarray:
    """(N, 7) rows ``tx ty tz qx qy qz qw`` -> (N, 4, 4) ``T_model_cam``."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    return make_T(R_from_quat(rows[:, 3:]), rows[:, :3])


def T_to_tum(T_model_cam: np.ndarray) -> np.ndarray:
    """(N, 4, 4) -> (N, 7) rows ``tx ty tz qx qy qz qw``."""
    T = np.asarray(T_model_cam, dtype=np.float64).reshape(-1, 4, 4)
    return np.concatenate([T[:, :3, 3], quat_from_R(T[:, :3, :3])], axis=1)


def check_pose_rows(p: Path, rows: np.ndarray, line_numbers: np.ndarray | None, quat_cols: slice | None = slice(3, 7),
                    pos_cols: slice = slice(0, 3)) -> None:
    """Validate pose rows ``(N, k)`` read from file ``p`` (``line_numbers`` (N,) 1-based).

    Raises :class:`mst.InputError` naming the file and the first offending line for NaN/inf, a
    position beyond :data:`MAX_POSITION_M`, or a quaternion whose norm is not 1 within
    :data:`QUAT_NORM_TOL`.
    """
    rows = np.asarray(rows, np.float64)

    def at(k) -> str:
        return "" if line_numbers is None else f"line {line_numbers[k]}: "

    bad = ~np.isfinite(rows).all(axis=1)
    if bad.any():
        raise InputError(p, f"{at(np.argmax(bad))}NaN or infinite value")
    far = (np.abs(rows[:, pos_cols]) > MAX_POSITION_M).any(axis=1)
    if far.any():
        raise InputError(p, f"{at(np.argmax(far))}position beyond {MAX_POSITION_M:g} m "
                            "(corrupt value?)")
    if quat_cols is not None:
        qn = np.linalg.norm(rows[:, quat_cols], axis=1)
        off = np.abs(qn - 1.0) > QUAT_NORM_TOL
        if off.any():
            k = np.argmax(off)
            raise InputError(p, f"{at(k)}quaternion norm {qn[k]:.3g} is not 1: not a rotation")


def _number_rows(p: Path, text: str, n: int, count_problem: str, inline_comments: bool, commas: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``n`` numbers of a line-per-pose text (TUM, KITTI): ``(rows (N, n), line numbers)``.

    Blank lines and ``#`` comment lines are skipped (with ``inline_comments`` also the rest of a line
    after ``#``); ``commas`` separate like spaces. ``count_problem`` formats the error of a line with
    another count (``{got}``). Raises :class:`mst.InputError` naming the file and line.
    """
    rows, lines = [], []
    for ln, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].strip() if inline_comments else line.strip()
        if not s or s.startswith("#"):
            continue
        parts = (s.replace(",", " ") if commas else s).split()
        if len(parts) != n:
            raise InputError(p, f"line {ln}: " + count_problem.format(got=len(parts)))
        try:
            rows.append([float(x) for x in parts])
        except ValueError:
            raise InputError(p, f"line {ln}: not a number") from None
        lines.append(ln)
    if not rows:
        raise InputError(p, "trajectory has no poses")
    return np.asarray(rows), np.asarray(lines)


# ------------------------------------------------------------------------------------ TUM
def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: returns ``(t (N,) seconds, T_model_cam (N, 4, 4))``.

    Lines starting with ``#`` and blank lines are ignored; every other line needs 8 numbers
    ``t tx ty tz qx qy qz qw`` (metres; a unit quaternion). UTF-8 text, a byte-order mark is
    accepted. Raises :class:`mst.InputError` naming the file and line for anything else (see
    :func:`check_pose_rows`).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "trajectory file does not exist")
    return _tum_from_text(p, read_text(p, "trajectory file"))


def _tum_from_text(p: Path, text: str) -> tuple[np.ndarray, np.ndarray]:
    a, lines = _number_rows(p, text, 8, "expected 8 values 't tx ty tz qx qy qz qw', got {got}",
                            inline_comments=False, commas=True)
    bad_t = ~np.isfinite(a[:, 0])
    if bad_t.any():
        raise InputError(p, f"line {lines[int(np.argmax(bad_t))]}: the timestamp is NaN or infinite")
    check_pose_rows(p, a[:, 1:], lines)
    return a[:, 0], tum_to_T(a[:, 1:])


def format_tum(t: np.ndarray, T_model_cam: np.ndarray) -> str:
    """TUM text for times ``t`` (seconds) and poses (N, 4, 4)."""
    rows = T_to_tum(T_model_cam)
    return "".join(f"{ti:.6f} " + " ".join(f"{v:.9f}" for v in r) + "\n" for ti, r in zip(np.atleast_1d(t), rows))


def write_tum(path: str | os.PathLike, t: np.ndarray, T_model_cam: np.ndarray, header: str | None = None) -> None:
    """Write a TUM trajectory (call inside :func:`mst.atomic_output` for atomicity)."""
    text = format_tum(t, T_model_cam)
    if header:
        text = "".join(f"# {h}\n" for h in header.splitlines()) + text
    Path(path).write_text(text)


# ---------------------------------------------------------------------------------- KITTI
def _kitti_from_text(p: Path, text: str, fps: float | None) -> tuple[np.ndarray, np.ndarray]:
    """KITTI poses (12 numbers per line, 3x4 row-major): ``(t = index (/ fps), T_model_cam)``."""
    a, lines = _number_rows(p, text, 12, "KITTI poses need 12 numbers per line, got {got}",
                            inline_comments=True, commas=False)
    check_pose_rows(p, a, lines, quat_cols=None, pos_cols=slice(3, 12, 4))
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :] = a.reshape(-1, 3, 4)
    # KITTI prints >= 6 significant digits: a rotation block off by more than 1e-2 (or a
    # reflection) is not a rotation; it must not be re-orthonormalised into an arbitrary one
    R = T[:, :3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # entries of 1e308 overflow: not a rotation
        off = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
        bad = ~(off <= 1e-2) | ~(np.linalg.det(R) > 0)
    if bad.any():
        raise InputError(p, f"line {lines[int(np.argmax(bad))]}: the 3x3 rotation block is not a rotation")
    U, _, Vt = np.linalg.svd(T[:, :3, :3])
    T[:, :3, :3] = U @ Vt
    return np.arange(len(a), dtype=np.float64) / (fps or 1.0), T


def read_kitti(path: str | os.PathLike, fps: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI trajectory: ``(t (N,) = line index, or index / fps, T_model_cam (N, 4, 4))``."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "trajectory file does not exist")
    return _kitti_from_text(p, read_text(p, "trajectory file"), fps)


# ------------------------------------------------------------------------------------ CSV
def parse_csv_columns(spec: str | Mapping[str, str] | None) -> dict[str, str]:
    """The column of each key ``t x y z qx qy qz qw`` from a ``"key=column,..."`` spec (unnamed keys:
    the column of the same name). A bad spec is a :class:`~mst.errors.ConfigError` of ``csv_columns``."""
    mapping = {k: k for k in CSV_KEYS}
    if not spec:
        return mapping
    items = spec.items() if isinstance(spec, Mapping) else None
    if items is None:
        pairs = []
        for item in spec.split(","):
            if "=" not in item:
                raise ConfigError("csv_columns", f"{item!r} is not key=column")
            pairs.append(tuple(s.strip() for s in item.split("=", 1)))
        items = pairs
    for k, v in items:
        if k not in mapping:
            raise ConfigError("csv_columns", f"unknown key {k!r} (use t x y z qx qy qz qw)")
        mapping[k] = v
    return mapping


def _csv_from_text(p: Path, text: str, spec: str | Mapping[str, str] | None) -> tuple[np.ndarray, np.ndarray, bool]:
    import csv
    import io

    try:
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r and not r[0].lstrip().startswith("#")]
    except csv.Error as e:
        raise InputError(p, f"not a CSV file ({e})") from None
    if len(rows) < 2:
        raise InputError(p, "CSV trajectory needs a header row and at least one pose")
    header = [h.strip() for h in rows[0]]
    mapping = parse_csv_columns(spec)
    missing = [mapping[k] for k in ("t", "x", "y", "z") if mapping[k] not in header]
    if missing:
        raise InputError(p, f"CSV lacks column(s) {', '.join(missing)} (header: {', '.join(header)}); "
                         "name them in the csv columns: t=..,x=..,y=..,z=..")
    has_rot = all(mapping[k] in header for k in ("qx", "qy", "qz", "qw"))
    keys = ["t", "x", "y", "z"] + (["qx", "qy", "qz", "qw"] if has_rot else [])
    cols = [header.index(mapping[k]) for k in keys]
    try:
        a = np.array([[float(r[c]) for c in cols] for r in rows[1:]], np.float64)
    except (ValueError, IndexError):
        raise InputError(p, "CSV row with a missing or non-numeric value") from None
    check_pose_rows(p, a[:, 1:], np.arange(2, len(a) + 2), quat_cols=slice(3, 7) if has_rot else None)
    R = R_from_quat(a[:, 4:8]) if has_rot else np.tile(np.eye(3), (len(a), 1, 1))
    return a[:, 0], make_T(R, a[:, 1:4]), has_rot


# ------------------------------------------------------------------------------- any format
@dataclass(frozen=True)
class Trajectory:
    """A trajectory read from a file: times (seconds), camera poses ``T_model_cam`` and whether the
    file held orientations (a CSV without quaternion columns does not: identity rotations)."""

    t: np.ndarray
    T_model_cam: np.ndarray
    has_rotation: bool = True
    duplicates_dropped: int = 0


def read_trajectory(path: str | os.PathLike, fmt: str = "auto", csv_columns: str | Mapping[str, str] | None = None,
                    fps: float | None = None) -> Trajectory:
    """Read a trajectory file of any supported format, checked as a time series.

    ``fmt``: ``tum``, ``kitti`` (``fps``: time = index / fps), ``csv`` (columns by ``csv_columns``) or
    ``auto``: ``.csv`` is CSV, otherwise TUM for 8 numbers per line and KITTI for 12. Besides each
    format's checks, refused with :class:`mst.InputError`: NaN/inf, timestamps out of order, and two
    poses with the same timestamp that differ; identical duplicates are dropped (counted in
    ``duplicates_dropped``, and a note is logged).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "trajectory file does not exist")
    text = read_text(p, "trajectory file")
    if fmt == "auto":
        if p.suffix.lower() == ".csv":
            fmt = "csv"
        else:
            first = next((ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), "")
            fmt = "kitti" if len(first.replace(",", " ").split()) == 12 else "tum"
    has_rot = True
    if fmt == "tum":
        t, T = _tum_from_text(p, text)
    elif fmt == "kitti":
        t, T = _kitti_from_text(p, text, fps)
    elif fmt == "csv":
        t, T, has_rot = _csv_from_text(p, text, csv_columns)
    else:
        raise InputError(p, f"unknown trajectory format {fmt!r}")
    return _checked_series(p, t, T, has_rot)


def _checked_series(p: Path, t: np.ndarray, T: np.ndarray, has_rot: bool) -> Trajectory:
    if not np.isfinite(T).all() or not np.isfinite(t).all():
        raise InputError(p, "trajectory holds NaN or infinite values")
    dt = np.diff(t)
    if len(t) > 1 and (dt < 0).any():
        k = int(np.argmax(dt < 0))
        raise InputError(p, f"timestamps are not sorted in increasing order (pose {k + 2}: {t[k + 1]:.6f} s after "
                            f"{t[k]:.6f} s)")
    dup = np.flatnonzero(dt == 0)
    if len(dup):
        # same time twice: identical poses are a harmless repeat, different ones are a conflict that
        # must not be averaged or picked silently (evo associates one of them at random)
        differ = np.abs(T[dup + 1] - T[dup]).max(axis=(1, 2)) > 1e-9
        if differ.any():
            k = int(dup[np.argmax(differ)])
            raise InputError(p, f"two different poses at the same timestamp {t[k]:.6f} s (poses {k + 1} and {k + 2})")
        keep = np.ones(len(t), bool)
        keep[dup + 1] = False
        t, T = t[keep], T[keep]
        log.info("%s: %d identical duplicate pose(s) dropped", p, len(dup))
    return Trajectory(t, T, has_rot, int(len(dup)))


# ------------------------------------------------------------------------------- ViSP cMo
def read_pose_file(path: str | os.PathLike) -> np.ndarray:
    """Read one pose and return ``T_cam_model`` (ViSP's cMo), 4x4.

    Accepted, detected by the count of numbers (``#`` comments ignored):

    * 16 (or 12): a 4x4 (or 3x4) model-to-camera matrix ``cMo``, row-major;
    * 8: one TUM line ``t tx ty tz qx qy qz qw`` (camera pose in model coordinates);
    * 7: ``tx ty tz qx qy qz qw`` (camera pose in model coordinates).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "pose file does not exist")
    a = read_numbers(p, "pose file")
    if len(a) in (16, 12):
        widths = [len(ln.split("#", 1)[0].replace(",", " ").split()) for ln in read_text(p, "pose file").splitlines()]
        if [w for w in widths if w] == [8, 8]:  # two TUM lines are 16 numbers too: not a matrix
            raise InputError(p, "holds 2 TUM poses: give one pose (the first frame's), or a 4x4 cMo matrix")
        return rigid_from_rows(a, p)
    if len(a) in (7, 8):
        check_pose_rows(p, a[None, -7:], None)
        return inv_T(tum_to_T(a[-7:])[0])
    raise InputError(p, f"{len(a)} numbers: expected 16 (4x4 cMo matrix), 8 (TUM line) or 7")


def write_pose_file(path: str | os.PathLike, T_cam_model: np.ndarray, t: float = 0.0) -> None:
    """Write one pose as a TUM line (camera pose in model frame) with a cMo comment."""
    T = np.asarray(T_cam_model, dtype=np.float64)
    cmo = "\n".join("# " + " ".join(f"{v: .9f}" for v in row) for row in T)
    Path(path).write_text(
        "# mst pose: TUM line 't tx ty tz qx qy qz qw' (camera pose in model frame)\n"
        "# cMo (model-to-camera, 4x4) for reference:\n" + cmo + "\n" + format_tum(np.array([t]), inv_T(T)[None])
    )
