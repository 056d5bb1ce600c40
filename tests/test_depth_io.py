"""Depth frame reading: every format gives the same metres, bad files name themselves."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mst import InputError
from mst.pipeline.depth_io import list_depth_frames, metres_per_unit, read_depth


def _depth_mm(h: int = 6, w: int = 7, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.integers(300, 5000, size=(h, w)).astype(np.uint16)
    d[0, 0] = 0
    return d


def _write_bin(path: Path, d_mm: np.ndarray) -> None:
    h, w = d_mm.shape
    path.write_bytes(np.array([h, w], "<u4").tobytes() + d_mm.astype("<u2").tobytes())


def test_png_bin_npy_exr_agree(tmp_path):
    import cv2

    d = _depth_mm()
    expect = d.astype(np.float32) / 1000
    cv2.imwrite(str(tmp_path / "a.png"), d)
    _write_bin(tmp_path / "a.bin", d)
    np.save(tmp_path / "a.npy", np.where(d == 0, np.nan, expect).astype(np.float32))
    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
    exr = expect.copy()
    exr[0, 0] = 65504.0  # Blender's "no surface"
    assert cv2.imwrite(str(tmp_path / "a.exr"), exr)
    for name in ("a.png", "a.bin", "a.npy", "a.exr"):
        got = read_depth(tmp_path / name)
        assert got.dtype == np.float32 and got.shape == d.shape, name
        np.testing.assert_allclose(got, expect, rtol=0, atol=1e-6, err_msg=name)
        assert got[0, 0] == 0.0, name


def test_half_float_exr_no_surface(tmp_path):
    import cv2

    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
    d = np.full((4, 5, 3), 0.5, np.float32)
    d[1, 2] = 65504.0
    assert cv2.imwrite(str(tmp_path / "h.exr"), d, [cv2.IMWRITE_EXR_TYPE, cv2.IMWRITE_EXR_TYPE_HALF])
    got = read_depth(tmp_path / "h.exr")
    assert got.shape == (4, 5)
    assert got[1, 2] == 0 and np.count_nonzero(got) == 19
    np.testing.assert_allclose(got[got > 0], 0.5)


def test_depth_scale_both_conventions(tmp_path):
    import cv2

    d = _depth_mm()
    cv2.imwrite(str(tmp_path / "t.png"), d)
    tum = read_depth(tmp_path / "t.png", depth_scale=5000)  # TUM RGB-D: 5000 units per metre
    visp = read_depth(tmp_path / "t.png", depth_scale=0.0002)  # same as metres per unit
    np.testing.assert_allclose(tum, d / 5000.0, rtol=1e-6)
    np.testing.assert_array_equal(tum, visp)
    assert metres_per_unit(1000) == 0.001 and metres_per_unit(0.001) == 0.001 and metres_per_unit(1) == 1
    with pytest.raises(InputError, match="positive"):
        read_depth(tmp_path / "t.png", depth_scale=0)


def test_bad_files_name_themselves(tmp_path):
    import cv2

    d = _depth_mm()
    _write_bin(tmp_path / "trunc.bin", d)
    raw = (tmp_path / "trunc.bin").read_bytes()
    (tmp_path / "trunc.bin").write_bytes(raw[:-10])
    with pytest.raises(InputError, match=r"trunc\.bin: ViSP raw depth is truncated"):
        read_depth(tmp_path / "trunc.bin")
    (tmp_path / "tiny.bin").write_bytes(b"\x01\x02")
    with pytest.raises(InputError, match="tiny.bin"):
        read_depth(tmp_path / "tiny.bin")
    cv2.imwrite(str(tmp_path / "ok.png"), d)
    (tmp_path / "cut.png").write_bytes((tmp_path / "ok.png").read_bytes()[:40])
    with pytest.raises(InputError, match=r"cut\.png: cannot decode"):
        read_depth(tmp_path / "cut.png")
    cv2.imwrite(str(tmp_path / "rgb8.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(InputError, match="8-bit"):
        read_depth(tmp_path / "rgb8.png")
    (tmp_path / "bad.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(InputError, match=r"bad\.npy"):
        read_depth(tmp_path / "bad.npy")
    with pytest.raises(InputError, match="does not exist"):
        read_depth(tmp_path / "missing.png")
    with pytest.raises(InputError, match="unknown depth format"):
        (tmp_path / "x.jpg").write_bytes(b"x")
        read_depth(tmp_path / "x.jpg")


def test_list_depth_frames_natural_and_preferred_format(tmp_path):
    for i in (0, 2, 10, 1):
        np.save(tmp_path / f"d{i}.npy", np.zeros((2, 2), np.float32))
        (tmp_path / f"d{i}.png").write_bytes(b"")
    (tmp_path / "color_0.jpg").write_bytes(b"")
    names = [p.name for p in list_depth_frames(tmp_path)]
    assert names == ["d0.npy", "d1.npy", "d2.npy", "d10.npy"]
    assert [p.name for p in list_depth_frames(tmp_path, suffix="png")] == ["d0.png", "d1.png", "d2.png", "d10.png"]
    assert [p.name for p in list_depth_frames(str(tmp_path / "d1*.png"))] == ["d1.png", "d10.png"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no depth frames"):
        list_depth_frames(tmp_path / "empty")
    with pytest.raises(InputError, match="does not exist"):
        list_depth_frames(tmp_path / "nope")


def test_real_visp_cube_bin(shared_data):
    cube = shared_data / "visp-cube-rgbd"
    frames = list_depth_frames(cube)
    assert [p.name for p in frames] == [f"depth_image_{i:04d}.bin" for i in range(10)]
    d = read_depth(frames[0])
    assert d.shape == (480, 640) and d.dtype == np.float32
    valid = d[d > 0]
    # a RealSense frame of a small cube on a table, 0.2-2 m away, mostly valid
    assert valid.size > 0.5 * d.size
    assert 0.1 < np.median(valid) < 2.0
