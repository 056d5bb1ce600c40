"""The bad-input campaign of issue 9 (CLI and non-mesh parsers), as regression cases.

Every case starts from the small valid fixture set of :mod:`bad_input_fixtures` (copied per case),
breaks one thing -- a file (missing, empty, garbage, truncated, non-UTF-8, NaN/inf, wrong counts,
degenerate values), an option, or an output (equal to an input, unwritable) -- and runs the
command in-process. It asserts the README's promise: exit code 1, exactly one ``mst ...: error:``
line on stderr that names the culprit (the file, or the option), no traceback, no output file
created, and every input byte-identical afterwards. The valid set itself runs clean first
(``test_valid_fixtures_run``), so a case fails for its own reason and not for a broken fixture.

Mesh and cloud *format* cases live in tests/test_bad_input_formats.py.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import pathlib
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from bad_input_fixtures import build, run_cli

SEED = 9


@pytest.fixture(scope="module")
def fixture_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("valid")
    build(d)
    return d


@pytest.fixture
def case_dir(fixture_dir, tmp_path) -> tuple[dict[str, Path], Path]:
    """A private copy of the valid set (so a case that overwrote an input cannot spoil others) and an
    empty output folder ``out``."""
    d = tmp_path / "in"
    shutil.copytree(fixture_dir, d)
    f = {k: d / v.relative_to(fixture_dir) for k, v in build_names(fixture_dir).items()}
    out = tmp_path / "out"
    out.mkdir()
    return f, out


def build_names(d: Path) -> dict[str, Path]:
    names = {"model": "box.obj", "camera": "cam.json", "pose": "pose0.txt", "clicks": "clicks.txt",
             "uv": "uv.clicks", "points": "box.init", "frames": "frames", "image": "frames/000000.png",
             "traj": "traj.txt", "gt": "gt.txt", "depth": "depth", "extrinsic": "depth_M_color.txt",
             "cloud": "cloud.ply", "xyz": "cloud.xyz"}
    return {k: d / v for k, v in names.items()}


# ------------------------------------------------------------------------- commands (valid args)
def init_args(f, o):
    return ["init", "--model", f["model"], "--camera", f["camera"], "--clicks", f["clicks"], "-o", o / "pose.txt"]


def init_uv_args(f, o):
    return ["init", "--model", f["model"], "--camera", f["camera"], "--clicks", f["uv"], "--points", f["points"],
            "-o", o / "pose.txt"]


def track_args(f, o):
    return ["track", f["frames"], "--model", f["model"], "--camera", f["camera"], "--init", f["pose"],
            "-o", o / "traj.txt", "--slam", "off", "-q"]


def fuse_args(f, o):
    return ["fuse", "--traj", f["traj"], "--depth", f["depth"], "--camera", f["camera"], "-o", o / "cloud.ply", "-q"]


def c2m_args(f, o):
    return ["c2m", f["cloud"], f["model"], "-q"]


def eval_args(f, o):
    return ["eval", "traj", f["traj"], f["gt"], "-q", "--align", "first"]


def convert_args(f, o):
    return ["convert-model", f["model"], "-o", o / "box.wrl", "-q"]


COMMANDS: dict[str, Callable] = {"init": init_args, "init-uv": init_uv_args, "track": track_args, "fuse": fuse_args,
                                 "c2m": c2m_args, "eval": eval_args, "convert-model": convert_args}


def _snapshot(d: Path) -> dict[str, str]:
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()}


def assert_one_error(code: int, err: str, names: list[str]) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 1, f"exit {code}, stderr:\n{err}"
    assert "Traceback" not in err, err
    assert len(lines) == 1, f"expected one stderr line, got:\n{err}"
    line = lines[0]
    assert re.match(r"mst( [a-z0-9-]+)*: error: ", line), line
    for n in names:
        assert n in line, f"{n!r} not named in: {line}"
    return line


# ------------------------------------------------------------------------------ file mutations
def _rng():
    return np.random.default_rng(SEED)


def m_missing(p: Path):
    p.unlink()


def m_empty(p: Path):
    p.write_bytes(b"")


def m_garbage(p: Path):
    p.write_bytes(_rng().integers(0, 256, 400, dtype=np.uint8).tobytes())


def m_truncate(p: Path):
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2])


def m_non_utf8(p: Path):
    b = p.read_bytes()
    lines = b.split(b"\n")
    lines[-2 if len(lines) > 1 else 0] += b" \xff\xfe\xc3"
    p.write_bytes(b"\n".join(lines))


def m_dir(p: Path):
    p.unlink()
    p.mkdir()


def m_replace_number(k: int, new: str):
    """Replace the k-th number token of the first non-comment line holding numbers."""

    def m(p: Path):
        lines = p.read_text().splitlines()
        for i, ln in enumerate(lines):
            if ln.strip() and not ln.lstrip().startswith("#"):
                tok = ln.split()
                tok[k] = new
                lines[i] = " ".join(tok)
                break
        p.write_text("\n".join(lines) + "\n")

    return m


def m_text(text: str):
    def m(p: Path):
        p.write_text(text)

    return m


def m_keep_lines(n: int):
    def m(p: Path):
        lines = [ln for ln in p.read_text().splitlines() if ln.strip()]
        p.write_text("\n".join(lines[:n]) + "\n")

    return m


def m_dup_line(i: int, j: int):
    """Line j becomes a copy of line i."""

    def m(p: Path):
        lines = p.read_text().splitlines()
        lines[j] = lines[i]
        p.write_text("\n".join(lines) + "\n")

    return m


def m_json(**changes):
    def m(p: Path):
        d = json.loads(p.read_text())
        d.update(changes)
        p.write_text(json.dumps(d))

    return m


# ------------------------------------------------------------------------------------- the table
@dataclass
class Case:
    id: str
    cmd: str
    target: str | None = None               # key of the fixture file to break
    mutate: Callable | None = None
    extra: Callable | None = None           # (f, o) -> extra args appended
    replace: Callable | None = None         # (f, o, args) -> args (for output==input etc.)
    names: Callable = None                  # (f, o) -> list of strings the line must contain
    monkey: Callable | None = None          # (monkeypatch, f, o) -> None
    marks: list = field(default_factory=list)


def _named(key):
    return lambda f, o: [str(f[key])]


CASES: list[Case] = []


def add(*a, **k):
    c = Case(*a, **k)
    if c.names is None and c.target is not None:
        c.names = _named(c.target)
    CASES.append(c)


# ---- pose files (mst track --init)
POSE_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "non_utf8": m_non_utf8, "dir": m_dir,
    "nan": m_replace_number(1, "nan"), "inf": m_replace_number(2, "inf"), "huge_t": m_replace_number(1, "1e308"),
    "zero_quat": m_text("0 0.1 0.2 1.0 0 0 0 0\n"), "five_numbers": m_text("1 2 3 4 5\n"),
    "word": m_text("0 0.1 0.2 one 0 0 0 1\n"), "not_rigid": m_text("2 0 0 0\n0 1 0 0\n0 0 1 1\n0 0 0 1\n"),
    "last_row": m_text("1 0 0 0\n0 1 0 0\n0 0 1 1\n0 0 1 1\n"),
    "behind_camera": m_text("1 0 0 0\n0 1 0 0\n0 0 1 -5\n0 0 0 1\n"),
    "denormal_quat": m_text("0 0.1 0.2 1.0 1e-310 0 0 0\n"),
    "two_tum_lines": m_text("0 0.1 0.2 1.0 0 0 0 1\n1 0.1 0.2 1.0 0 0 0 1\n"),
    "trajectory": m_text("".join(f"{k} 0.1 0.2 1.0 0 0 0 1\n" for k in range(3))),
}
for name, mut in POSE_BAD.items():
    add(f"track-pose-{name}", "track", "pose", mut)

# ---- clicks and points (mst init)
CLICKS_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "non_utf8": m_non_utf8, "dir": m_dir,
    "three": m_keep_lines(3), "nan": m_replace_number(3, "nan"), "inf": m_replace_number(4, "-inf"),
    "word": m_replace_number(0, "x0"), "four_columns": m_text("0 0 0 1\n1 0 0 2\n0 1 0 3\n1 1 0 4\n"),
    "mixed_widths": m_text("0 0 0 10 10\n1 0 0 20 10\n0 1 0 10 20\n1 1 1 20 20 5\n"),
    "uv_only": m_text("10 10\n20 10\n10 20\n20 20\n"),
    "identical": m_text("0.4 0.3 0.2 80 60\n" * 4),
    "identical_uv": m_text("0 0 0 80 60\n0.4 0 0 80 60\n0 0.3 0 80 60\n0.4 0.3 0.2 80 60\n"),
    "collinear": m_text("0 0 0 10 60\n0.1 0 0 30 60\n0.2 0 0 50 60\n0.3 0 0 70 60\n0.4 0 0 90 60\n"),
    "collinear_uv": m_text("0 0 0 10 60\n0.4 0 0 30 60\n0 0.3 0 50 60\n0.4 0.3 0.2 70 60\n"),
    "huge": m_replace_number(0, "1e308"),
}
for name, mut in CLICKS_BAD.items():
    add(f"init-clicks-{name}", "init", "clicks", mut)

POINTS_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "non_utf8": m_non_utf8,
    "count_mismatch": m_text("7\n0 0 0\n0.4 0 0\n0 0.3 0\n0.4 0.3 0\n0 0 0.2\n0.4 0 0.2\n"),
    "no_count": m_text("0 0 0\n0.4 0 0\n0 0.3 0\n0.4 0.3 0\n0 0 0.2\n0.4 0 0.2\n"),
    "nan": m_text("6\n0 0 0\nnan 0 0\n0 0.3 0\n0.4 0.3 0\n0 0 0.2\n0.4 0 0.2\n"),
    "two_columns": m_text("6\n0 0\n0.4 0\n0 0.3\n0.4 0.3\n0 0\n0.4 0\n"),
    "identical": m_text("6\n" + "0.4 0.3 0.2\n" * 6),
    "collinear": m_text("6\n" + "".join(f"{0.05 * k} 0 0\n" for k in range(6))),
    "negative_count": m_text("-6\n0 0 0\n"),
    "fractional_count": m_text("5.5\n0 0 0\n0.4 0 0\n0 0.3 0\n0.4 0.3 0\n0 0 0.2\n"),
}
for name, mut in POINTS_BAD.items():
    add(f"init-points-{name}", "init-uv", "points", mut)

add("init-uv-count-mismatch", "init-uv", "uv", m_keep_lines(5))
add("init-uv-nan", "init-uv", "uv", m_replace_number(0, "nan"))

# ---- camera files (init and track: blamed on the camera, never on the pose)
CAMERA_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "dir": m_dir,
    "bad_json": m_text('{"fx": 200, "fy": '), "nan_fx": m_text('{"fx": NaN, "fy": 200, "cx": 79.5, "cy": 59.5}'),
    "huge_fx": m_json(fx=1e308, fy=1e308), "negative_fx": m_json(fx=-200.0),
    "nan_dist": m_json(dist=[float("nan"), 0, 0, 0]), "inf_dist": m_json(dist=[0, float("inf"), 0, 0]),
    "no_fx": m_text('{"width": 160}'), "string_fx": m_json(fx="two hundred"),
    "negative_size": m_json(width=-160), "list": m_text("[1, 2, 3]"),
    "huge_dist": m_json(dist=[1e300, 0, 0, 0]),
}
_K = "camera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [200, 0, 80, 0, 200, 60, 0, 0, 1]\n"
CAMERA_BAD |= {
    "yaml-garbage": m_text("%YAML:1.0\ncamera_matrix: [garbage"),
    "yaml-count": m_text("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1, 2]\n"),
    "yaml-2x2": m_text("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 2\n  cols: 2\n  dt: d\n  data: [1, 0, 0, 1]\n"),
    "yaml-width-word": m_text("%YAML:1.0\n" + _K + "image_width: abc\n"),
    "yaml-nan-dist": m_text("%YAML:1.0\n" + _K + "distortion_coefficients: !!opencv-matrix\n  rows: 1\n  cols: 4\n"
                            "  dt: d\n  data: [.nan, 0, 0, 0]\n"),
    "json-non-utf8": lambda p: p.write_bytes(b'{"fx": 200, "fy": 200, "cx": 79.5, "cy": 59.5, "\xff": 1}'),
}
for name, mut in CAMERA_BAD.items():
    add(f"init-camera-{name}", "init", "camera", mut)
for name in ("missing", "garbage", "nan_fx", "huge_fx", "nan_dist", "negative_fx"):
    add(f"track-camera-{name}", "track", "camera", CAMERA_BAD[name])
add("track-camera-xml-nan", "track", "camera",
    m_text("<conf><camera><u0>79.5</u0><v0>59.5</v0><px>nan</px><py>200</py></camera></conf>"))
add("track-camera-xml-broken", "track", "camera", m_text("<conf><camera><u0>79.5</u0>"))

# ---- model: blamed on the model file, never on the pose
MODEL_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "dir": m_dir,
    "one_point": m_text("v 0.2 0.15 0.1\nv 0.2 0.15 0.1\nv 0.2 0.15 0.1\nf 1 2 3\n"),
    "nan_vertex": m_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
}
for name, mut in MODEL_BAD.items():
    add(f"track-model-{name}", "track", "model", mut)
add("init-model-missing", "init", "model", m_missing)

# ---- trajectories (fuse --traj, eval traj)
TRAJ_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "non_utf8": m_non_utf8, "dir": m_dir,
    "truncated_line": m_text("0 0.1 0.2 1.0 0 0 0 1\n1 0.1 0.2\n"),
    "nan": m_replace_number(2, "nan"), "inf": m_replace_number(3, "inf"), "huge_t": m_replace_number(1, "1e308"),
    "zero_quat": m_text("0 0.1 0.2 1.0 0 0 0 1\n1 0.1 0.2 1.0 0 0 0 0\n"),
    "word": m_replace_number(4, "q"), "comments_only": m_text("# nothing\n# here\n"),
    "unsorted": m_text("1 0.1 0.2 1.0 0 0 0 1\n0 0.1 0.2 1.0 0 0 0 1\n"),
}
for name, mut in TRAJ_BAD.items():
    if name != "unsorted":  # fuse maps each pose to its frame: the order does not matter
        add(f"fuse-traj-{name}", "fuse", "traj", mut)
add("fuse-traj-two-poses-one-frame", "fuse", "traj", m_dup_line(0, 1))
add("fuse-traj-huge-time", "fuse", "traj", m_replace_number(0, "1e300"))
for name, mut in TRAJ_BAD.items():
    add(f"eval-est-{name}", "eval", "traj", mut)
for name in ("missing", "garbage", "non_utf8", "nan", "zero_quat", "huge_t"):
    add(f"eval-ref-{name}", "eval", "gt", TRAJ_BAD[name])
add("eval-est-duplicate-conflict", "eval", "traj", lambda p: p.write_text(
    p.read_text() + p.read_text().splitlines()[-1].replace(" 0.", " 0.5", 1) + "\n"))
add("eval-ref-duplicate-conflict", "eval", "gt", lambda p: p.write_text(
    "\n".join(p.read_text().splitlines()[:3] + [p.read_text().splitlines()[2].split(" ", 1)[0] + " 9 9 9 0 0 0 1"]
              + p.read_text().splitlines()[3:]) + "\n"))
add("eval-kitti-11", "eval", "traj", m_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n"),
    extra=lambda f, o: ["--format", "kitti"])
add("eval-kitti-zero-rotation", "eval", "traj", m_text("1 0 0 0 0 1 0 0 0 0 1 0\n0 0 0 1 0 0 0 2 0 0 0 3\n"),
    extra=lambda f, o: ["--format", "kitti"])
add("eval-kitti-reflection", "eval", "traj", m_text("1 0 0 0 0 1 0 0 0 0 1 0\n-1 0 0 0 0 1 0 0 0 0 1 0\n"),
    extra=lambda f, o: ["--format", "kitti"])
add("eval-kitti-nan", "eval", "traj", m_text("1 0 0 0 0 1 0 0 0 0 1 nan\n1 0 0 0 0 1 0 0 0 0 1 0\n"),
    extra=lambda f, o: ["--format", "kitti"])
add("eval-kitti-non-utf8", "eval", "traj", lambda p: p.write_bytes(b"1 0 0 0 0 1 0 0 0 0 1 0\n\xff\xfe 0 0\n"),
    extra=lambda f, o: ["--format", "kitti"])
add("eval-csv-non-utf8", "eval", "traj", lambda p: p.write_bytes(b"t,x,y,z\n0,1,2,3\n\xff,\xfe,0,0\n"),
    extra=lambda f, o: ["--format", "csv"])
add("eval-csv-zero-quat", "eval", "traj", m_text("t,x,y,z,qx,qy,qz,qw\n0,1,2,3,0,0,0,1\n1,1,2,3,0,0,0,0\n"),
    extra=lambda f, o: ["--format", "csv"])
add("eval-csv-missing-column", "eval", "traj", m_text("t,x,y\n0,1,2\n"), extra=lambda f, o: ["--format", "csv"])

# ---- rigid transforms (fuse / track --depth-to-color)
EXTR_BAD = {
    "missing": m_missing, "empty": m_empty, "garbage": m_garbage, "non_utf8": m_non_utf8,
    "three_numbers": m_text("1 2 3\n"), "nan": m_replace_number(3, "nan"),
    "not_rigid": m_text("1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n"), "huge": m_replace_number(3, "1e308"),
}
for name, mut in EXTR_BAD.items():
    add(f"fuse-extrinsic-{name}", "fuse", "extrinsic", mut, extra=lambda f, o: ["--depth-to-color", f["extrinsic"]])
for name in ("missing", "non_utf8", "not_rigid"):
    add(f"track-extrinsic-{name}", "track", "extrinsic", EXTR_BAD[name],
        extra=lambda f, o: ["--depth-to-color", f["extrinsic"], "--depth", f["depth"], "--slam", "rgbd"])

# ---- fuse camera and depth
for name in ("missing", "garbage", "nan_fx", "nan_dist"):
    add(f"fuse-camera-{name}", "fuse", "camera", CAMERA_BAD[name])


def _npy_nan(p: Path):
    d = np.load(p)
    d[3, 3] = np.nan  # NaN depth is "no depth": must be accepted... so corrupt the header instead
    p.write_bytes(b"\x93NUMPY garbage")


add("fuse-depth-corrupt-npy", "fuse", "depth", lambda p: _npy_nan(p / "000001.npy"),
    names=lambda f, o: [str(f["depth"] / "000001.npy")])
add("fuse-depth-corrupt-npy-no-quiet", "fuse", "depth", lambda p: _npy_nan(p / "000001.npy"),
    replace=lambda f, o, a: [x for x in a if x != "-q"], names=lambda f, o: [str(f["depth"] / "000001.npy")])
add("track-frame-corrupt-no-quiet", "track", "frames", lambda p: (p / "000002.png").write_bytes(b"\x89PNG garbage"),
    replace=lambda f, o, a: [x for x in a if x != "-q"], names=lambda f, o: [str(f["frames"] / "000002.png")])
add("track-pose-bad-no-quiet", "track", "pose", m_text("1 2 3\n"), replace=lambda f, o, a: [x for x in a if x != "-q"])


def _one_depth(name: str, data: bytes | Callable):
    """The depth folder holds one bad frame, 000000.<ext> (a folder's frames share one suffix)."""

    def m(p: Path):
        for old in p.iterdir():
            old.unlink()
        q = p / name
        if callable(data):
            data(q)
        else:
            q.write_bytes(data)
    return m


DEPTH_BAD = {
    "bin-truncated": ("000001.bin", b"\x02\x00\x00"),
    "bin-huge-header": ("000001.bin", np.array([100000, 100000], "<u4").tobytes() + b"\x00" * 16),
    "bin-short-body": ("000001.bin", np.array([120, 160], "<u4").tobytes() + b"\x00" * 100),
    "png-garbage": ("000001.png", b"\x89PNG\r\n\x1a\n garbage"),
    "png-8bit": ("000001.png", lambda q: __import__("cv2").imwrite(str(q), np.zeros((120, 160), np.uint8))),
    "png-colour": ("000001.png", lambda q: __import__("cv2").imwrite(str(q), np.zeros((120, 160, 3), np.uint16))),
    "npy-3d": ("000001.npy", lambda q: np.save(q, np.zeros((2, 120, 160), np.float32))),
    "npy-strings": ("000001.npy", lambda q: np.save(q, np.array(["a", "b"]))),
    "npy-truncated": ("000001.npy", lambda q: q.write_bytes(_npy_bytes()[:200])),
    "exr-garbage": ("000001.exr", b"v/1\x01 not an exr"),
    "npy-huge-header": ("000001.npy", lambda q: q.write_bytes(_npy_header((300000, 300000)) + b"\x00" * 64)),
    "npy-short-body": ("000001.npy", lambda q: q.write_bytes(_npy_header((120, 160)) + b"\x00" * 64)),
}


def _npy_header(shape) -> bytes:
    import io as _io

    b = _io.BytesIO()
    np.lib.format.write_array_header_1_0(b, {"descr": "<f4", "fortran_order": False, "shape": shape})
    return b.getvalue()


def _npy_bytes() -> bytes:
    import io as _io

    b = _io.BytesIO()
    np.save(b, np.ones((120, 160), np.float32))
    return b.getvalue()


for name, (fname, data) in DEPTH_BAD.items():
    fname = fname.replace("000001", "000000")
    add(f"fuse-depth-{name}", "fuse", "depth", _one_depth(fname, data),
        names=lambda f, o, fname=fname: [str(f["depth"] / fname)])

add("track-video-garbage", "track", replace=lambda f, o, a: ["track", _garbage_file(f["model"].parent / "v.mp4")] + a[2:],
    names=lambda f, o: [str(f["model"].parent / "v.mp4")])
add("track-frames-missing", "track", "frames", lambda p: shutil.rmtree(p))
add("track-frames-empty-folder", "track", "frames", lambda p: [q.unlink() for q in p.iterdir()])
add("track-depth-camera-bad", "track", "extrinsic", m_text('{"fx": -1}'),
    extra=lambda f, o: ["--depth-camera", f["extrinsic"], "--depth", f["depth"], "--slam", "rgbd"])
add("track-depth-folder-missing", "track", "depth", lambda p: shutil.rmtree(p),
    extra=lambda f, o: ["--depth", f["depth"], "--slam", "rgbd"])
add("init-from-pose-looking-away", "init", replace=lambda f, o, a: ["init", "--model", f["model"], "--camera", f["camera"],
    "--from-pose", "5", "5", "5", "45", "0", "0", "-o", o / "pose.txt"], names=lambda f, o: ["--from-pose"])
add("init-overlay-without-image", "init", extra=lambda f, o: ["--overlay", o / "ov.png"],
    names=lambda f, o: [str(o / "ov.png"), "--image"])
add("init-image-garbage", "init", "image", m_garbage, extra=lambda f, o: ["--image", f["image"]])
add("init-image-missing", "init", "image", m_missing, extra=lambda f, o: ["--image", f["image"]])
add("init-image-wrong-size", "init", "image",
    lambda p: __import__("cv2").imwrite(str(p), np.zeros((50, 70, 3), np.uint8)), extra=lambda f, o: ["--image", f["image"]],
    names=lambda f, o: [str(f["camera"])])
add("init-clicks-outside-image", "init", "clicks", m_replace_number(3, "500"), extra=lambda f, o: ["--image", f["image"]])
add("fuse-landmarks-garbage", "fuse", "cloud", m_garbage, extra=lambda f, o: ["--landmarks", f["cloud"]])
add("fuse-color-folder-missing", "fuse", extra=lambda f, o: ["--color", o / "no-such-folder"],
    names=lambda f, o: [str(o / "no-such-folder")])
add("eval-csv-columns-bad-spec", "eval", "traj", m_text("t,x,y,z\n0,1,2,3\n"),
    extra=lambda f, o: ["--format", "csv", "--csv-columns", "t:time"], names=lambda f, o: ["--csv-columns"])
add("track-settings-nan", "track", "extrinsic",
    m_text("<conf><ecm><range><tracking>nan</tracking></range></ecm></conf>"),
    extra=lambda f, o: ["--settings", f["extrinsic"]])


def _garbage_file(p: Path) -> Path:
    p.write_bytes(_rng().integers(0, 256, 2000, dtype=np.uint8).tobytes())
    return p


add("fuse-depth-empty-folder", "fuse", "depth", lambda p: [q.unlink() for q in p.iterdir()])

# ---- c2m clouds with non-finite or overflowing coordinates: refused with the count
add("c2m-cloud-all-nan", "c2m", "cloud", lambda p: p.write_text(
    p.read_text().split("end_header\n")[0].replace("element vertex 600", "element vertex 2")
    + "end_header\nnan 0 0\n0 inf 0\n"))
add("c2m-cloud-huge", "c2m", "xyz", m_text("1e308 1e308 1e308\n-1e308 -1e308 -1e308\n0.1 0.1 0.1\n"),
    replace=lambda f, o, a: ["c2m", f["xyz"], f["model"], "-q"])
add("c2m-cloud-huge-json", "c2m", "xyz", m_text("1e308 1e308 1e308\n-1e308 -1e308 -1e308\n0.1 0.1 0.1\n"),
    replace=lambda f, o, a: ["c2m", f["xyz"], f["model"], "-q", "--json"])
add("c2m-cloud-non-utf8", "c2m", "xyz", lambda p: p.write_bytes(b"0 0 0\n0.1 \xff\xfe 0\n"),
    replace=lambda f, o, a: ["c2m", f["xyz"], f["model"], "-q"])

# ---- options: negative, zero, NaN values are option problems (named as options)
OPTION_BAD = [
    ("fuse", ["--voxel", "-1"], "--voxel"), ("fuse", ["--voxel", "nan"], "--voxel"),
    ("fuse", ["--stride", "0"], "--stride"), ("fuse", ["--min-depth", "-1"], "--min-depth"),
    ("fuse", ["--max-depth", "0"], "--max-depth"), ("fuse", ["--depth-scale", "0"], "--depth-scale"),
    ("fuse", ["--depth-scale", "-5"], "--depth-scale"), ("fuse", ["--fps", "-30"], "--fps"),
    ("fuse", ["--edge-k", "-1"], "--edge-k"), ("fuse", ["--max-angle", "-5"], "--max-angle"),
    ("fuse", ["--smooth", "-3"], "--smooth"), ("fuse", ["--smooth-rel", "-0.1"], "--smooth-rel"),
    ("track", ["--scale", "0"], "--scale"), ("track", ["--scale", "-1"], "--scale"),
    ("track", ["--scale", "1e-6"], "--scale"), ("track", ["--scale", "1000"], "--scale"),
    ("track", ["--frames", "0:3:0"], "--frames"), ("track", ["--frames", "x"], "--frames"),
    ("track", ["--frames", "7:9"], "--frames"),
    ("track", ["--fps", "0"], "--fps"), ("track", ["--fps", "nan"], "--fps"),
    ("track", ["--range", "-4"], "--range"), ("track", ["--step", "0"], "--step"),
    ("track", ["--pyramid", "0"], "--pyramid"), ("track", ["--frames", "5:2"], "--frames"),
    ("init", ["--max-residual", "-1"], "--max-residual"), ("init", ["--max-residual", "nan"], "--max-residual"),
    ("eval", ["--t-max-diff", "-0.1"], "--t-max-diff"), ("eval", ["--t-max-diff", "nan"], "--t-max-diff"),
    ("eval", ["--fps", "0"], "--fps"), ("eval", ["--yaw-offset", "nan"], "--yaw-offset"),
    ("eval", ["--t-offset", "inf"], "--t-offset"), ("eval", ["--delta", "0"], "--delta"),
    ("c2m", ["--max-dist", "-1"], "--max-dist"), ("c2m", ["--thresholds", "0.1,-2"], "--thresholds"),
    ("c2m", ["--chunk", "10"], "--chunk"), ("convert-model", ["--angle-tol", "-1"], "--angle-tol"),
    ("convert-model", ["--dist-tol", "nan"], "--dist-tol"), ("convert-model", ["--weld-tol", "-1e-6"], "--weld-tol"),
]
for cmd, opt, name in OPTION_BAD:
    add(f"{cmd}-option-{name.strip('-')}-{opt[1]}", cmd, extra=lambda f, o, opt=opt: opt,
        names=lambda f, o, name=name: [name])

# ---- usage errors: every error exits 1 (click's own code 2 included)
USAGE_BAD = [
    ("track-invalid-choice", "track", lambda f, o, a: a + ["--slam", "bogus"], "--slam"),
    ("eval-invalid-choice", "eval", lambda f, o, a: a + ["--align", "bogus"], "--align"),
    ("c2m-invalid-choice", "c2m", lambda f, o, a: a + ["--engine", "bogus"], "--engine"),
    ("init-camera-is-dir", "init", lambda f, o, a: [f["depth"] if x == f["camera"] else x for x in a], "--camera"),
    ("c2m-cloud-is-dir", "c2m", lambda f, o, a: ["c2m", f["depth"], f["model"]], "CLOUD"),
    ("track-missing-option", "track", lambda f, o, a: [x for x in a if x not in ("--init", f["pose"])], "--init"),
    ("fuse-unknown-option", "fuse", lambda f, o, a: a + ["--no-such-option"], "--no-such-option"),
    ("init-not-a-number", "init", lambda f, o, a: a + ["--max-residual", "four"], "--max-residual"),
    ("unknown-command", "init", lambda f, o, a: ["no-such-command"], "no-such-command"),
    ("eval-unknown-subcommand", "eval", lambda f, o, a: ["eval", "nope"], "nope"),
    ("init-from-pose-missing-values", "init", lambda f, o, a: a[:-2] + ["--from-pose", "1", "2"], "--from-pose"),
    ("fuse-depth-without-traj", "fuse", lambda f, o, a: [x for x in a if x not in ("--traj", f["traj"])], "--traj"),
]
for cid, cmd, rep, name in USAGE_BAD:
    add(f"usage-{cid}", cmd, replace=rep, names=lambda f, o, name=name: [name])


# ---- output equal to an input (or to another output): refused, input untouched
def _swap_output(new: Callable):
    def rep(f, o, a):
        a = list(a)
        i = a.index("-o")
        a[i + 1] = new(f, o)
        return a
    return rep


SAME = [
    ("init-o-clicks", "init", _swap_output(lambda f, o: f["clicks"]), "clicks"),
    ("init-o-camera", "init", _swap_output(lambda f, o: f["camera"]), "camera"),
    ("init-o-model", "init", _swap_output(lambda f, o: f["model"]), "model"),
    ("init-o-points", "init-uv", _swap_output(lambda f, o: f["points"]), "points"),
    ("init-overlay-clicks", "init", lambda f, o, a: a + ["--image", f["image"], "--overlay", f["clicks"]], "clicks"),
    ("init-overlay-image", "init", lambda f, o, a: a + ["--image", f["image"], "--overlay", f["image"]], "image"),
    ("init-overlay-is-output", "init", lambda f, o, a: a + ["--image", f["image"], "--overlay", o / "pose.txt"], None),
    ("init-show-points-image", "init-uv", lambda f, o, a: _swap_output(lambda f, o: f["image"])(f, o, a)
     + ["--image", f["image"], "--show-points"], "image"),
    ("track-o-init", "track", _swap_output(lambda f, o: f["pose"]), "pose"),
    ("track-o-camera", "track", _swap_output(lambda f, o: f["camera"]), "camera"),
    ("track-o-model", "track", _swap_output(lambda f, o: f["model"]), "model"),
    ("track-o-frame", "track", _swap_output(lambda f, o: f["image"]), "image"),
    ("track-side-json-is-camera", "track", lambda f, o, a: _swap_output(lambda f, o: f["camera"].with_suffix(".txt"))(
        f, o, a) + ["--json"], "camera"),
    ("track-side-csv-is-init", "track", lambda f, o, a: _side_csv_init(f, a), "pose_csv"),
    ("track-o-is-csv", "track", _swap_output(lambda f, o: o / "traj.csv"), None),
    ("track-landmarks-is-init", "track", lambda f, o, a: [x for x in a if x not in ("--slam", "off")]
     + ["--slam", "mono", "--landmarks", f["pose"]], "pose"),
    ("track-landmarks-is-side-csv", "track", lambda f, o, a: [x for x in a if x not in ("--slam", "off")]
     + ["--slam", "mono", "--landmarks", o / "traj.csv"], None),
    ("track-overlay-is-model", "track", lambda f, o, a: a + ["--overlay", f["model"]], "model"),
    ("fuse-o-traj", "fuse", _swap_output(lambda f, o: f["traj"]), "traj"),
    ("fuse-o-camera", "fuse", _swap_output(lambda f, o: f["camera"]), "camera"),
    ("fuse-o-extrinsic", "fuse", lambda f, o, a: _swap_output(lambda f, o: f["extrinsic"])(f, o, a)
     + ["--depth-to-color", f["extrinsic"]], "extrinsic"),
    ("fuse-o-landmarks", "fuse", lambda f, o, a: _swap_output(lambda f, o: f["cloud"])(f, o, a)
     + ["--landmarks", f["cloud"]], "cloud"),
    ("fuse-o-depth-frame", "fuse", _swap_output(lambda f, o: f["depth"] / "000000.npy"), None),
    ("c2m-o-cloud", "c2m", lambda f, o, a: a + ["-o", f["cloud"]], "cloud"),
    ("c2m-markdown-mesh", "c2m", lambda f, o, a: a + ["--markdown", f["model"]], "model"),
    ("c2m-plot-cloud", "c2m", lambda f, o, a: a + ["--plot", f["cloud"]], "cloud"),
    ("c2m-plot-is-markdown", "c2m", lambda f, o, a: a + ["--plot", o / "x.png", "--markdown", o / "x.png"], None),
    ("eval-plot-est", "eval", lambda f, o, a: a + ["--plot", f["traj"]], "traj"),
    ("eval-plot-ref", "eval", lambda f, o, a: a + ["--plot", f["gt"]], "gt"),
    ("convert-o-input", "convert-model", _swap_output(lambda f, o: f["model"]), "model"),
    ("convert-o-input-dotdot", "convert-model",
     _swap_output(lambda f, o: f["model"].parent / "frames" / ".." / f["model"].name), None),
    ("convert-o-symlink", "convert-model", _swap_output(lambda f, o: _link(f["model"], o / "link.obj", True)), None),
    ("convert-o-hardlink", "convert-model", _swap_output(lambda f, o: _link(f["model"], f["model"].parent / "hard.obj",
                                                                              False)), None),
]


def _side_csv_init(f, a):
    """--init new.csv and -o new.txt: the side output new.csv would overwrite the initial pose."""
    f["pose_csv"] = _copy(f["pose"], f["pose"].parent / "new.csv")
    a = [f["pose_csv"] if x == f["pose"] else x for x in a]
    a[a.index("-o") + 1] = f["pose"].parent / "new.txt"
    return a


def _copy(src: Path, dst: Path) -> Path:
    shutil.copy(src, dst)
    return dst


def _link(src: Path, dst: Path, symbolic: bool) -> Path:
    if symbolic:
        dst.symlink_to(src)
    else:
        os.link(src, dst)
    return dst


for cid, cmd, rep, key in SAME:
    add(f"same-{cid}", cmd, replace=rep, names=lambda f, o, key=key: [str(f[key])] if key else [])


# ---- unwritable outputs
def _enospc(monkeypatch, f, o):
    real_open = pathlib.Path.open
    real_write_text = pathlib.Path.write_text

    def full(self, *a, **k):
        if self.parent == o:
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return real_write_text(self, *a, **k)

    def full_open(self, mode="r", *a, **k):
        if self.parent == o and any(c in mode for c in "wax"):
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return real_open(self, mode, *a, **k)

    monkeypatch.setattr(pathlib.Path, "write_text", full)
    monkeypatch.setattr(pathlib.Path, "open", full_open)


def _readonly(monkeypatch, f, o):
    import tempfile

    real = tempfile.mkstemp

    def ro(*a, dir=None, **k):
        if dir is not None and Path(dir) == o:
            raise PermissionError(errno.EACCES, "Permission denied", str(Path(dir) / "tmpXXXX"))
        return real(*a, dir=dir, **k)

    monkeypatch.setattr(tempfile, "mkstemp", ro)


UNWRITABLE = {
    "proc": lambda f, o: Path("/proc/mst-no-such/out.txt"),
    "sys": lambda f, o: Path("/sys/mst-out.txt"),
    "missing-parent": lambda f, o: o / "no" / "such" / "out.txt",
    "is-dir": lambda f, o: o,
    "parent-is-file": lambda f, o: f["clicks"] / "out.txt",
}
for cmd in ("init", "track", "fuse", "convert-model"):
    for name, where in UNWRITABLE.items():
        add(f"unwritable-{cmd}-{name}", cmd, replace=lambda f, o, a, where=where: _swap_output(where)(f, o, a),
            names=lambda f, o, where=where: [str(where(f, o))])
for name, where in UNWRITABLE.items():
    add(f"unwritable-eval-plot-{name}", "eval", replace=lambda f, o, a, where=where: a + ["--plot", where(f, o)],
        names=lambda f, o, where=where: [str(where(f, o))])
    add(f"unwritable-c2m-markdown-{name}", "c2m",
        replace=lambda f, o, a, where=where: a + ["--markdown", where(f, o)],
        names=lambda f, o, where=where: [str(where(f, o))])
for cmd in ("init", "track", "convert-model"):
    add(f"unwritable-{cmd}-readonly-folder", cmd, monkey=_readonly, names=lambda f, o: [str(o)])
for cmd in ("init", "track"):
    add(f"unwritable-{cmd}-disk-full", cmd, monkey=_enospc, names=lambda f, o: [str(o), "space"])
add("unwritable-c2m-markdown-disk-full", "c2m", monkey=_enospc, replace=lambda f, o, a: a + ["--markdown", o / "t.md"],
    names=lambda f, o: [str(o / "t.md"), "space"])


# ------------------------------------------------------------------------------------ the runner
@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=c.marks) for c in CASES])
def test_bad_input(case: Case, case_dir, monkeypatch):
    f, o = case_dir
    root = f["model"].parent
    if case.mutate is not None:
        case.mutate(f[case.target])
    args = COMMANDS[case.cmd](f, o)
    if case.extra is not None:
        args = args + case.extra(f, o)
    if case.replace is not None:
        args = case.replace(f, o, args)
    if case.monkey is not None:
        case.monkey(monkeypatch, f, o)
    before = _snapshot(root)
    out_before = set(o.rglob("*"))
    code, stdout, err = run_cli(args)
    monkeypatch.undo()
    line = assert_one_error(code, err, case.names(f, o) if case.names else [])
    assert stdout == "", f"stdout on error: {stdout!r}"
    assert _snapshot(root) == before, f"an input was modified ({line})"
    assert set(o.rglob("*")) == out_before, f"output left behind: {sorted(set(o.rglob('*')) - out_before)}"


def test_enough_cases():
    assert len(CASES) >= 120


# --------------------------------------------------------------------------- the valid set runs
@pytest.mark.parametrize("cmd", list(COMMANDS))
def test_valid_fixtures_run(cmd, case_dir):
    f, o = case_dir
    root = f["model"].parent
    before = _snapshot(root)
    code, _, err = run_cli(COMMANDS[cmd](f, o))
    assert code == 0, err
    assert _snapshot(root) == before


# ------------------------------------------------------------------------ accepted odd-but-valid
def _bom(p: Path):
    p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())


@pytest.mark.parametrize("cmd,key", [("track", "pose"), ("init", "clicks"), ("init-uv", "points"), ("fuse", "traj"),
                                     ("eval", "traj"), ("eval", "gt"), ("init", "camera")])
def test_utf8_bom_accepted(cmd, key, case_dir):
    f, o = case_dir
    _bom(f[key])
    code, _, err = run_cli(COMMANDS[cmd](f, o))
    assert code == 0, err


def test_bom_extrinsic_accepted(case_dir):
    f, o = case_dir
    _bom(f["extrinsic"])
    code, _, err = run_cli(fuse_args(f, o) + ["--depth-to-color", f["extrinsic"]])
    assert code == 0, err


def test_identical_duplicate_timestamps_dropped_with_note(case_dir):
    f, o = case_dir
    lines = f["gt"].read_text().splitlines()
    f["gt"].write_text("\n".join(lines[:3] + [lines[2]] + lines[3:]) + "\n")
    code, out, err = run_cli(["eval", "traj", f["traj"], f["gt"], "--json", "--align", "first"])
    assert code == 0, err
    assert code == 0, err
    assert "duplicate" in err and str(f["gt"]) in err
    assert json.loads(out)["poses_reference"] == len(lines)


def test_c2m_nonfinite_points_counted_and_excluded(case_dir):
    """NaN/inf points are counted, excluded and reported; the statistics stay finite (JSON valid)."""
    f, o = case_dir
    lines = f["xyz"].read_text().splitlines()
    f["xyz"].write_text("\n".join(lines + ["nan 0 0", "0 inf 0", "-inf 1 2"]) + "\n")
    code, out, err = run_cli(["c2m", f["xyz"], f["model"], "--json"])
    assert code == 0, err
    s = json.loads(out)
    assert s["points_nonfinite"] == 3 and s["points_valid"] == len(lines)
    assert np.isfinite(s["unsigned"]["median"]) and s["unsigned"]["max"] < 0.01  # 1 mm noise on the faces
    code, out, err = run_cli(["c2m", f["xyz"], f["model"]])
    assert code == 0 and "3 NaN/inf points excluded" in err, err


# --------------------------------------------------------------------------------------- synth
def _scene(d: Path, version: int = 1) -> Path:
    seq = d / "seq"
    seq.mkdir()
    shutil.copy(d / "box.obj", seq / "model.obj")
    (seq / "scene.json").write_text(json.dumps({
        "format": "mst-synth-scene", "version": version, "scenario": "orbit", "model": {"file": "model.obj"},
        "config": {"frames": 1, "width": 32, "height": 24, "aa_samples": 0, "texture_size": 64}}))
    return seq


def _no_render(monkeypatch):
    import mst.pipeline.synth as ps

    def refuse(*a, **k):
        raise RuntimeError("rendering started: the input checks let a bad input through")

    monkeypatch.setattr(ps, "synthesize", refuse)


@pytest.mark.parametrize("how", ["model-in-out", "scene-in-out", "model-in-rgb"])
def test_synth_output_folder_holding_an_input(how, case_dir, monkeypatch):
    """--overwrite replaces OUT's sequence files (model.obj, scene.json, rgb/ ...): never an input."""
    f, o = case_dir
    root = f["model"].parent
    seq = _scene(root)
    if how == "model-in-out":
        args, culprit = ["synth", "orbit", "--model", seq / "model.obj", "-o", seq, "--overwrite", "-q"], seq / "model.obj"
    elif how == "scene-in-out":
        args, culprit = ["synth", "--from-scene", seq / "scene.json", "-o", seq, "--overwrite", "-q"], seq / "scene.json"
    else:
        (seq / "rgb").mkdir()
        shutil.copy(f["model"], seq / "rgb" / "m.obj")
        args, culprit = ["synth", "orbit", "--model", seq / "rgb" / "m.obj", "-o", seq, "--overwrite", "-q"], seq / "rgb"
    _no_render(monkeypatch)
    before = _snapshot(root)
    code, _, err = run_cli(args)
    assert_one_error(code, err, [str(culprit)])
    assert _snapshot(root) == before


def test_synth_scene_of_unknown_version(case_dir, monkeypatch):
    f, o = case_dir
    seq = _scene(f["model"].parent, version=99)
    _no_render(monkeypatch)
    code, _, err = run_cli(["synth", "--from-scene", seq / "scene.json", "-o", o / "seq2", "-q"])
    assert_one_error(code, err, [str(seq / "scene.json"), "version"])


# ------------------------------------------------------------------------------- exit-code rule
def test_interrupt_exits_130(case_dir, monkeypatch):
    f, o = case_dir
    import mst.pipeline.init_pose as ip

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ip, "run_init", interrupted)
    code, _, err = run_cli(init_args(f, o))
    assert code == 130 and err.strip() == "mst init: interrupted"


def test_usage_error_exit_code_in_a_subprocess(tmp_path):
    """The console entry point itself (not only in-process): an invalid choice exits 1, one line."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "mst.cli.main", "eval", "traj", str(tmp_path / "a.txt"),
                        str(tmp_path / "b.txt"), "--align", "bogus"], capture_output=True, text=True)
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "--align" in r.stderr


def test_no_runtime_warning_before_the_error_line(case_dir):
    """numpy warnings raised on the way to an error are not printed: the error line stays alone."""
    f, o = case_dir
    import warnings

    from mst.cli import main as climain

    def noisy(*a, **k):
        warnings.warn("overflow encountered in multiply", RuntimeWarning, stacklevel=2)
        raise __import__("mst").InputError(f["traj"], "bad")

    import mst.eval.traj as et

    real = et.evaluate_trajectories
    et.evaluate_trajectories = noisy
    try:
        code, _, err = run_cli(eval_args(f, o))
    finally:
        et.evaluate_trajectories = real
    assert climain is not None
    assert_one_error(code, err, [str(f["traj"])])


@pytest.mark.parametrize("which", ["traj", "gt"])
def test_eval_degenerate_alignment_names_the_file(which, case_dir):
    f, o = case_dir
    lines = f[which].read_text().splitlines()
    f[which].write_text("".join(f"{ln.split()[0]} 1 2 3 0 0 0 1\n" for ln in lines))  # one position for all
    code, out, err = run_cli(["eval", "traj", f["traj"], f["gt"], "--align", "se3", "-q"])
    assert_one_error(code, err, [str(f[which]), "alignment se3"])


def test_emit_json_writes_null_for_nan(capsys):
    from mst.cli.common import emit_json

    emit_json({"a": float("nan"), "b": [1.0, np.float64("inf")], "c": np.array([np.nan, 2.0]), "d": "x"})
    assert json.loads(capsys.readouterr().out) == {"a": None, "b": [1.0, None], "c": [None, 2.0], "d": "x"}


# ------------------------------------------------------------------ the atomic-output helper itself
def test_atomic_outputs_disk_full_names_the_target(tmp_path):
    from mst import InputError, atomic_outputs

    a, b = tmp_path / "a.txt", tmp_path / "b.csv"
    with pytest.raises(InputError) as ei:
        with atomic_outputs(a, b) as (ta, tb):
            ta.write_text("x")
            raise OSError(errno.ENOSPC, "No space left on device", str(tb))
    assert str(b) in str(ei.value) and "space" in str(ei.value)
    assert list(tmp_path.iterdir()) == []  # no target, no temporary file left


def test_atomic_outputs_rename_failure_names_the_target(tmp_path, monkeypatch):
    from mst import InputError, atomic_outputs

    def fail(src, dst):
        raise PermissionError(errno.EACCES, "Permission denied", str(dst))

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(InputError, match="a.txt: cannot write the output"):
        with atomic_outputs(tmp_path / "a.txt") as (ta,):
            ta.write_text("x")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("target", ["/dev/full", "/dev/null"])
def test_atomic_outputs_refuse_a_device(target):
    """Never rename a file over a device node (as root that would replace /dev/null itself)."""
    from mst import InputError, atomic_outputs

    if not Path(target).exists():
        pytest.skip(f"{target} absent")
    with pytest.raises(InputError, match="not a regular file"):
        with atomic_outputs(target):
            pass


def test_other_oserrors_are_not_hidden(tmp_path):
    """An OSError unrelated to the outputs (a bug, or an input problem) is not relabelled as one."""
    from mst import atomic_outputs

    with pytest.raises(OSError, match="unrelated"):
        with atomic_outputs(tmp_path / "a.txt"):
            raise OSError(errno.EINVAL, "unrelated", str(tmp_path / "input.bin"))


def test_fuse_bad_landmarks_fail_before_any_frame(case_dir, monkeypatch):
    f, o = case_dir
    m_garbage(f["cloud"])
    import mst.pipeline.fusion.runner as fu

    def no_frames(*a, **k):
        raise AssertionError("a depth frame was read before the landmarks file was checked")

    monkeypatch.setattr(fu, "read_depth", no_frames)
    code, _, err = run_cli(fuse_args(f, o) + ["--landmarks", f["cloud"]])
    assert_one_error(code, err, [str(f["cloud"])])


def test_output_beside_the_frames_is_not_an_input(case_dir):
    """Only the frames of an input folder are inputs: a trajectory written into it (a rerun) is fine."""
    f, o = case_dir
    (f["frames"] / "traj.txt").write_text("old run\n")
    code, _, err = run_cli(_swap_output(lambda f, o: f["frames"] / "traj.txt")(f, o, track_args(f, o)))
    assert code == 0, err
    assert (f["frames"] / "traj.txt").read_text() != "old run\n"


@pytest.mark.parametrize("opt,value", [("--frames", "-1"), ("--fps", "0"), ("--distance", "nan")])
def test_synth_bad_option_names_the_option(opt, value, case_dir, monkeypatch):
    f, o = case_dir
    _no_render(monkeypatch)
    code, _, err = run_cli(["synth", "orbit", "--model", f["model"], "-o", o / "seq", "-q", opt, value])
    assert_one_error(code, err, [opt])
