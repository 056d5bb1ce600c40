"""Trajectory and pose files (mst.core.trajectory): TUM, KITTI, CSV columns, ViSP cMo; the checks
every reader shares (twins of one line reader), duplicates, format detection."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from mst import ConfigError, InputError
from mst.core import poses as P
from mst.core import trajectory as TR

RNG = np.random.default_rng(0)


def random_T(n: int) -> np.ndarray:
    xi = np.concatenate([RNG.normal(0, 2, (n, 3)), RNG.uniform(-np.pi, np.pi, (n, 3)) * 0.57], axis=1)
    return P.se3_exp(xi)


def test_tum_write_read_roundtrip(tmp_path):
    T = random_T(50)
    t = np.arange(50) / 30.0
    f = tmp_path / "traj.txt"
    TR.write_tum(f, t, T, header="generated")
    t2, T2 = TR.read_tum(f)
    assert np.allclose(t2, t, atol=1e-6)
    assert np.abs(T2 - T).max() < 1e-8
    assert f.read_text().startswith("# generated\n")


def test_pose_file_tum_and_cmo_forms_agree(tmp_path):
    T_cam_model = random_T(1)[0]
    a = tmp_path / "pose.txt"
    TR.write_pose_file(a, T_cam_model)
    assert np.abs(TR.read_pose_file(a) - T_cam_model).max() < 1e-8
    b = tmp_path / "cMo.txt"
    b.write_text("\n".join(" ".join(f"{v:.12f}" for v in row) for row in T_cam_model))
    assert np.abs(TR.read_pose_file(b) - T_cam_model).max() < 1e-10


@pytest.mark.parametrize(
    "content, msg",
    [("1 2 3\n", "3 numbers"), ("a b c d e f g h\n", "not a number"), ("0 0 0 0 0 0 0 nan\n", "NaN"),
     ("\n".join(["2 0 0 0", "0 1 0 0", "0 0 1 0", "0 0 0 1"]), "not a rigid transform")],
)
def test_bad_pose_files_raise_input_error(tmp_path, content, msg):
    f = tmp_path / "bad.txt"
    f.write_text(content)
    with pytest.raises(InputError, match=msg):
        TR.read_pose_file(f)


def test_read_tum_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        TR.read_tum(tmp_path / "missing.txt")
    f = tmp_path / "t.txt"
    f.write_text("# only a comment\n")
    with pytest.raises(InputError, match="no poses"):
        TR.read_tum(f)
    f.write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(InputError, match="line 1: expected 8 values"):
        TR.read_tum(f)


def test_kitti_reader_and_format_detection(tmp_path):
    T = random_T(6)
    k = tmp_path / "poses.txt"
    k.write_text("# KITTI\n" + "".join(" ".join(repr(float(v)) for v in Ti[:3].ravel()) + "\n" for Ti in T))
    t, Tk = TR.read_kitti(k, fps=10.0)
    np.testing.assert_allclose(t, np.arange(6) / 10.0)
    np.testing.assert_allclose(Tk, T, atol=1e-12 * max(1.0, np.abs(T).max()))
    auto = TR.read_trajectory(k, fps=10.0)  # 12 numbers per line: KITTI
    assert auto.has_rotation and np.array_equal(auto.T_model_cam, Tk) and np.array_equal(auto.t, t)
    k.write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match="line 1: KITTI poses need 12 numbers per line, got 11"):
        TR.read_kitti(k)


def test_csv_columns_spec_and_positions_only(tmp_path):
    c = tmp_path / "gps.csv"
    c.write_text("time,e,n,h\n0,1,2,3\n1,4,5,6\n")
    tr = TR.read_trajectory(c, csv_columns="t=time,x=e,y=n,z=h")
    assert not tr.has_rotation and tr.t.tolist() == [0.0, 1.0]
    np.testing.assert_array_equal(tr.T_model_cam[:, :3, 3], [[1, 2, 3], [4, 5, 6]])
    assert TR.parse_csv_columns({"t": "time"})["t"] == "time"
    with pytest.raises(ConfigError, match="csv_columns: 't:time' is not key=column"):
        TR.parse_csv_columns("t:time")
    with pytest.raises(ConfigError, match="unknown key 'w'"):
        TR.parse_csv_columns("w=x")
    with pytest.raises(InputError, match="lacks column"):
        TR.read_trajectory(c)


def test_identical_duplicates_dropped_with_a_note_different_ones_refused(tmp_path):
    T = random_T(3)
    f = tmp_path / "t.txt"
    TR.write_tum(f, np.array([0.0, 1.0, 2.0]), T)
    lines = f.read_text().splitlines()
    f.write_text("\n".join([lines[0], lines[0], lines[1], lines[2]]) + "\n")
    notes: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            notes.append(record.getMessage())

    log = logging.getLogger("mst.core.trajectory")
    h, level = Keep(logging.INFO), log.level
    log.addHandler(h)
    log.setLevel(logging.INFO)
    try:
        tr = TR.read_trajectory(f)
    finally:
        log.removeHandler(h)
        log.setLevel(level)
    assert tr.duplicates_dropped == 1 and len(tr.t) == 3
    assert notes == [f"{f}: 1 identical duplicate pose(s) dropped"]
    f.write_text("\n".join([lines[0], lines[1].replace(lines[1].split()[0], lines[0].split()[0], 1), lines[2]]) + "\n")
    with pytest.raises(InputError, match="two different poses at the same timestamp"):
        TR.read_trajectory(f)
