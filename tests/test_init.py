"""`mst init`: PnP from clicks on the real tea box and on rendered views; diagnoses; --from-pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synth_helpers import look_at

from mst.core.camera import Camera, write_camera
from mst.core.poses import inv_T, pose_error
from mst.core.trajectory import read_pose_file
from mst.pipeline.init_pose import init_from_clicks, pose_from_gps, project


def _teabox_args(d: Path) -> list[str]:
    t = d / "visp-teabox"
    return ["--model", t / "teabox.cao", "--camera", t / "teabox.xml", "--clicks", t / "teabox.clicks", "--points", t / "teabox.init"]


def test_init_teabox_residuals(shared_data, mst, tmp_path):
    out = tmp_path / "pose0.txt"
    ov = tmp_path / "check.png"
    r = mst("init", *_teabox_args(shared_data), "-o", out, "--image", shared_data / "visp-teabox/teabox.mp4",
            "--overlay", ov, "--json")
    import json

    s = json.loads(r.stdout)
    res = np.array(s["residual_px"])
    assert res.shape == (4,)
    assert res.max() < 3.0 and s["rms_px"] < 2.0  # hand clicks: a few px at most
    T = read_pose_file(out)
    # the box (16.5 x 6.8 x 8 cm) is in front of the camera, 40-80 cm away
    Xc = np.array([[0, 0, 0], [0.165, 0.068, -0.08]]) @ T[:3, :3].T + T[:3, 3]
    assert (0.3 < Xc[:, 2]).all() and (Xc[:, 2] < 0.9).all()
    assert ov.stat().st_size > 1000
    assert "RMS" in r.stderr


def test_init_swapped_clicks_named(tmp_path, mst):
    from mst.meshtools.generate import l_shape_model

    m = l_shape_model()
    cam = Camera(300, 300, 159.5, 119.5, 320, 240)
    T = look_at([26, -14, 9], m.vertices.mean(0))
    X = m.vertices[[0, 1, 2, 5, 7, 8, 9, 11]]
    uv = project(T, cam.K, X)
    # correct clicks: exact pose
    r = init_from_clicks(X, uv, cam.K)
    dt, dr = pose_error(inv_T(r.T_cam_model), inv_T(T))
    assert dt < 1e-6 and dr < 1e-6 and r.diagnosis == ""
    uv_sw = uv.copy()
    uv_sw[[2, 5]] = uv_sw[[5, 2]]
    rows = np.column_stack([X, uv_sw])
    clicks = tmp_path / "clicks.txt"
    clicks.write_text("".join(" ".join(f"{v:.4f}" for v in row) + "\n" for row in rows))
    model = tmp_path / "m.obj"
    model.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in m.vertices) + "".join(
        "f " + " ".join(str(i + 1) for i in f) + "\n" for f in m.faces))
    camf = tmp_path / "cam.json"
    write_camera(camf, cam)
    out = tmp_path / "pose.txt"
    res = mst("init", "--model", model, "--camera", camf, "--clicks", clicks, "-o", out, check=False)
    assert res.returncode == 1
    assert "clicks 3 and 6 look swapped" in res.stderr
    assert res.stderr.count("\n") == 1 and not out.exists()
    # a wrong focal length (x0.5): the camera is named as the suspect
    rows = np.column_stack([X, uv])
    clicks.write_text("".join(" ".join(f"{v:.4f}" for v in row) + "\n" for row in rows))
    write_camera(camf, Camera(150, 150, 159.5, 119.5, 320, 240))
    res = mst("init", "--model", model, "--camera", camf, "--clicks", clicks, "-o", out, check=False)
    assert res.returncode == 1 and "camera intrinsics" in res.stderr and not out.exists()


def test_init_config_file_sets_the_residual_bound(tmp_path, mst):
    """max_residual_px from a --config file: swapped clicks (refused by default) are accepted under a
    bound of 1000 px; an unknown key fails naming it."""
    import json

    from mst.meshtools.generate import l_shape_model

    m = l_shape_model()
    cam = Camera(300, 300, 159.5, 119.5, 320, 240)
    X = m.vertices[[0, 1, 2, 5, 7, 8, 9, 11]]
    uv = project(look_at([26, -14, 9], m.vertices.mean(0)), cam.K, X)
    uv[[2, 5]] = uv[[5, 2]]
    (tmp_path / "clicks.txt").write_text("".join(" ".join(f"{v:.4f}" for v in row) + "\n" for row in np.column_stack([X, uv])))
    (tmp_path / "m.obj").write_text("".join(f"v {a} {b} {c}\n" for a, b, c in m.vertices) + "".join(
        "f " + " ".join(str(i + 1) for i in f) + "\n" for f in m.faces))
    write_camera(tmp_path / "cam.json", cam)
    args = ["init", "--model", tmp_path / "m.obj", "--camera", tmp_path / "cam.json", "--clicks", tmp_path / "clicks.txt"]
    assert mst(*args, "-o", tmp_path / "p0.txt", check=False).returncode == 1
    (tmp_path / "loose.yaml").write_text("max_residual_px: 1000\n")
    r = mst(*args, "--config", tmp_path / "loose.yaml", "-o", tmp_path / "p1.txt", "--json", "-q")
    assert json.loads(r.stdout)["config"]["max_residual_px"] == 1000 and (tmp_path / "p1.txt").exists()
    (tmp_path / "bad.yaml").write_text("max_residual: 1000\n")
    r = mst(*args, "--config", tmp_path / "bad.yaml", "-o", tmp_path / "p2.txt", check=False)
    assert r.returncode == 1 and "max_residual: unknown key" in r.stderr and not (tmp_path / "p2.txt").exists()


@pytest.mark.parametrize("case", ["three", "mismatch", "uv_only"])
def test_init_bad_clicks(shared_data, mst, tmp_path, case):
    t = shared_data / "visp-teabox"
    clicks = tmp_path / "c.txt"
    lines = (t / "teabox.clicks").read_text().splitlines()
    uv = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    args = ["--model", t / "teabox.cao", "--camera", t / "teabox.xml", "--clicks", clicks]
    if case == "three":
        clicks.write_text("\n".join(uv[:3]) + "\n")
        pts = tmp_path / "p.init"
        pts.write_text("3\n" + "\n".join((t / "teabox.init").read_text().splitlines()[1:4]) + "\n")
        args += ["--points", pts]
        expect = "3 clicks, need at least 4"
    elif case == "mismatch":
        clicks.write_text("\n".join(uv[:3]) + "\n")
        args += ["--points", t / "teabox.init"]
        expect = "3 clicks but 4 points"
    else:
        clicks.write_text("\n".join(uv) + "\n")
        expect = "'u v' only: their model points come from a ViSP .init points file"  # the library names no flag
    out = tmp_path / "pose.txt"
    r = mst("init", *args, "-o", out, check=False)
    assert r.returncode == 1
    assert expect in r.stderr and r.stderr.startswith("mst init: error:")
    assert not out.exists()


def test_from_pose_conventions(tmp_path, mst):
    # yaw 0: the camera looks east (+x), level; north (+y) is image left, up (+z) is image top
    T = pose_from_gps(np.zeros(3), 0, 0, 0)
    K = np.array([[100, 0, 50], [0, 100, 40], [0, 0, 1.0]])
    uv = project(T, K, np.array([[10, 0, 0], [10, 1, 0], [10, 0, 1]], float))
    assert np.allclose(uv[0], [50, 40])
    assert uv[1, 0] < 50 and abs(uv[1, 1] - 40) < 1e-9
    assert uv[2, 1] < 40 and abs(uv[2, 0] - 50) < 1e-9
    # yaw 90 looks north; pitch -30 looks down 30 degrees
    T = pose_from_gps(np.array([0, 0, 10.0]), 90, -30, 0)
    ahead = np.array([[0, 10 / np.tan(np.radians(30)), 0.0]])
    assert np.allclose(project(T, K, ahead), [[50, 40]], atol=1e-6)
    # nadir mount: pitch the camera -90 relative to the body; a point below projects at the centre
    T = pose_from_gps(np.array([3, 4, 50.0]), 37, 0, 0, mount_ypr_deg=(0, -90, 0))
    assert np.allclose(project(T, K, np.array([[3, 4, 0.0]])), [[50, 40]], atol=1e-6)
    # CLI: writes a pose file readable back
    from mst.meshtools.generate import box_model

    m = box_model((4, 4, 4), origin=(20, -2, 0))
    model = tmp_path / "b.obj"
    model.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in m.vertices) + "".join(
        "f " + " ".join(str(i + 1) for i in f) + "\n" for f in m.faces))
    camf = tmp_path / "cam.json"
    write_camera(camf, Camera(300, 300, 159.5, 119.5, 320, 240))
    out = tmp_path / "p.txt"
    mst("init", "--model", model, "--camera", camf, "--from-pose", "0", "0", "2", "0", "0", "0", "-o", out)
    Tf = read_pose_file(out)
    assert np.allclose(Tf, pose_from_gps(np.array([0, 0, 2.0]), 0, 0, 0), atol=1e-6)
    # looking west (yaw 180) puts the box behind the camera: one clear error, no file
    out2 = tmp_path / "p2.txt"
    r = mst("init", "--model", model, "--camera", camf, "--from-pose", "0", "0", "2", "180", "0", "0", "-o", out2, check=False)
    assert r.returncode == 1 and "behind the camera" in r.stderr and not out2.exists()


def test_show_points_picture(shared_data, mst, tmp_path):
    import cv2

    t = shared_data / "visp-teabox"
    out = tmp_path / "where.png"
    mst("init", "--model", t / "teabox.cao", "--camera", t / "teabox.xml", "--points", t / "teabox.init",
        "--show-points", "-o", out)
    img = cv2.imread(str(out))
    assert img is not None and img.shape[:2] == (488, 652)  # no image: size from the principal point (2 c + 1)
    # red numbered points drawn on the white canvas
    red = (img[..., 2] > 200) & (img[..., 1] < 60) & (img[..., 0] < 60)
    assert red.sum() > 4 * 20
