"""Property tests (hypothesis, derandomised: the same examples every run) of the non-mesh parsers:
pose, trajectory (TUM/KITTI/CSV), rigid-transform, clicks, .init points and camera files.

1. Round trips: what mst writes, mst reads back (poses within the printed precision).
2. Mutations of valid files (bytes replaced, inserted, deleted; lines dropped or duplicated) end
   in a value or in :class:`mst.InputError`, never in another exception; and whatever is accepted
   is finite (no NaN pose, camera or click slips through).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from bad_input_fixtures import build
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mst import InputError
from mst.core.camera import Camera, read_camera, write_camera
from mst.core.poses import inv_T, look_at, read_rigid_transform
from mst.core.trajectory import format_tum, read_pose_file, read_trajectory, read_tum, write_pose_file
from mst.pipeline.depth_io import read_depth
from mst.pipeline.init_pose import read_clicks, read_init_points

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict[str, bytes]:
    d = tmp_path_factory.mktemp("fuzz")
    f = build(d)
    kitti = d / "k.txt"
    T = np.stack([look_at([1.0 + k, -1.0, 0.5], [0.2, 0.1, 0.1]) for k in range(3)])
    kitti.write_text("".join(" ".join(f"{v:.6f}" for v in t[:3].ravel()) + "\n" for t in T))
    csv = d / "t.csv"
    csv.write_text("t,x,y,z,qx,qy,qz,qw\n0,1,2,3,0,0,0,1\n1,1.1,2,3,0,0,0.0998,0.995\n")
    import cv2

    rng = np.random.default_rng(3)
    depth_mm = rng.integers(0, 5000, (12, 16)).astype(np.uint16)
    cv2.imwrite(str(d / "d.png"), depth_mm)
    (d / "d.bin").write_bytes(np.array([12, 16], "<u4").tobytes() + depth_mm.astype("<u2").tobytes())
    np.save(d / "d.npy", depth_mm.astype(np.float32) / 1000)
    depth = {f"depth-{s}": (d / f"d.{s}").read_bytes() for s in ("png", "bin", "npy")}
    return depth | {k: f[k].read_bytes() for k in ("pose", "traj", "extrinsic", "clicks", "points", "camera")} | {
        "kitti": kitti.read_bytes(), "csv": csv.read_bytes(), "uv": f["uv"].read_bytes()}


def _finite(x) -> bool:
    if isinstance(x, tuple):
        return all(_finite(v) for v in x)
    if isinstance(x, Camera):
        return bool(np.isfinite([x.fx, x.fy, x.cx, x.cy]).all() and np.isfinite(x.dist).all())
    return bool(np.isfinite(np.asarray(x, np.float64)).all())


def _parse(kind: str, p: Path, valid: dict[str, bytes]):
    if kind == "pose":
        return read_pose_file(p)
    if kind == "traj":
        return read_tum(p)
    if kind == "extrinsic":
        return read_rigid_transform(p)
    if kind == "clicks":
        return read_clicks(p)
    if kind == "points":
        return read_init_points(p)
    if kind == "uv":
        pts = p.with_name("pts.init")
        pts.write_bytes(valid["points"])
        return read_clicks(p, pts)
    if kind == "camera":
        return read_camera(p)
    if kind.startswith("depth-"):
        return read_depth(p)
    if kind == "kitti":
        tr = read_trajectory(p, "kitti")
        return tr.t, tr.T_model_cam
    if kind == "csv":
        tr = read_trajectory(p.with_suffix(".csv") if p.suffix != ".csv" else p, "csv")
        return tr.t, tr.T_model_cam
    raise AssertionError(kind)


@st.composite
def mutated(draw, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["replace", "insert", "delete", "truncate", "dup_line", "drop_line", "token", "token"]))
        if not b:
            break
        i = draw(st.integers(0, len(b) - 1))
        if op == "replace":
            b[i] = draw(st.integers(0, 255))
        elif op == "insert":
            b[i:i] = draw(st.binary(min_size=1, max_size=6))
        elif op == "delete":
            del b[i: i + draw(st.integers(1, 8))]
        elif op == "truncate":
            del b[i:]
        elif op in ("dup_line", "drop_line"):
            lines = bytes(b).split(b"\n")
            k = draw(st.integers(0, len(lines) - 1))
            lines[k:k + 1] = [lines[k]] * 2 if op == "dup_line" else []
            b = bytearray(b"\n".join(lines))
        else:  # a whole number replaced by a special value
            nums = [m.span() for m in re.finditer(rb"[-+]?[0-9][0-9.eE+-]*", bytes(b))]
            if nums:
                lo, hi = nums[draw(st.integers(0, len(nums) - 1))]
                b[lo:hi] = draw(st.sampled_from([b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"0", b"1e-320", b"x",
                                                 b"", b"1,5", b"1e30"]))
    return bytes(b)


def _name(kind: str) -> str:
    return "f.csv" if kind == "csv" else (f"f.{kind[6:]}" if kind.startswith("depth-") else "f.txt")


KINDS = ["pose", "traj", "extrinsic", "clicks", "points", "uv", "camera", "kitti", "csv", "depth-png", "depth-bin",
         "depth-npy"]


@pytest.mark.parametrize("kind", KINDS)
def test_valid_files_parse(kind, valid, tmp_path):
    p = tmp_path / _name(kind)
    p.write_bytes(valid[kind])
    assert _finite(_parse(kind, p, valid))


@pytest.mark.parametrize("kind", KINDS)
def test_mutations_raise_only_input_error(kind, valid, tmp_path):
    p = tmp_path / _name(kind)

    @settings(SETTINGS, max_examples=120)
    @given(data=mutated(valid[kind]))
    def check(data):
        p.write_bytes(data)
        try:
            r = _parse(kind, p, valid)
        except InputError as e:
            assert str(p) in str(e) or "pts.init" in str(e), f"error names no file: {e}"
            return
        assert _finite(r), f"accepted a non-finite value from {data!r}"

    check()


@SETTINGS
@given(eye=st.tuples(*[st.floats(-1e4, 1e4) for _ in range(3)]), t=st.floats(0, 1e6))
def test_pose_round_trip(tmp_path_factory, eye, t):
    """write_pose_file -> read_pose_file: the same cMo within the 9 printed decimals (relative to |eye|)."""
    if np.linalg.norm(eye) < 1e-3:
        return
    d = tmp_path_factory.mktemp("rt")
    T = inv_T(look_at(np.asarray(eye), [0.0, 0.0, 0.0], up=(0.3, 0.2, 0.93)))
    write_pose_file(d / "p.txt", T, t)
    T2 = read_pose_file(d / "p.txt")
    # 9 decimals: quaternion error <= 1e-9 rad-ish -> translation error <= |eye| * 1e-8, plus 1e-9 printing
    assert np.abs(T2[:3, :3] - T[:3, :3]).max() < 1e-8
    assert np.abs(T2[:3, 3] - T[:3, 3]).max() < 1e-8 * (1 + np.linalg.norm(eye))


@SETTINGS
@given(n=st.integers(1, 20), seed=st.integers(0, 2**16))
def test_tum_round_trip(tmp_path_factory, n, seed):
    rng = np.random.default_rng(seed)
    T = np.stack([look_at(rng.uniform(-50, 50, 3) + [100, 0, 0], rng.uniform(-1, 1, 3)) for _ in range(n)])
    t = np.cumsum(rng.uniform(0.01, 1.0, n))
    d = tmp_path_factory.mktemp("tum")
    (d / "t.txt").write_text(format_tum(t, T))
    t2, T2 = read_tum(d / "t.txt")
    assert np.abs(t2 - t).max() <= 5e-7  # 6 decimals
    assert np.abs(T2 - T).max() < 1e-6   # 9 decimals of 150 m positions and of the quaternion


@SETTINGS
@given(fx=st.floats(1, 1e5), cx=st.floats(-1e3, 1e4), w=st.integers(0, 10000),
       dist=st.lists(st.floats(-10, 10), max_size=5))
def test_camera_round_trip(tmp_path_factory, fx, cx, w, dist):
    d = tmp_path_factory.mktemp("cam")
    c = Camera(fx, fx * 1.01, cx, cx * 0.5, w, w // 2, np.asarray(dist))
    write_camera(d / "c.json", c)
    c2 = read_camera(d / "c.json")
    assert (c2.fx, c2.fy, c2.cx, c2.cy, c2.width, c2.height) == (c.fx, c.fy, c.cx, c.cy, c.width, c.height)
    assert np.array_equal(c2.dist, c.dist)
