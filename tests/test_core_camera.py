"""Camera files and projection (mst.core.camera)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst import InputError
from mst.core.camera import Camera, read_camera, write_camera


def test_visp_tracker_xml(shared_data):
    cam = read_camera(shared_data / "visp-teabox" / "teabox.xml")
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (839.21470, 839.44555, 325.66776, 243.69727)
    assert not cam.has_distortion


def test_visp_camera_model_xml(tmp_path):
    f = tmp_path / "cam.xml"
    f.write_text("""<?xml version="1.0"?><root><camera><name>Camera</name><image_width>640</image_width>
    <image_height>480</image_height><model><type>perspectiveProjWithoutDistortion</type><px>600.5</px><py>601</py>
    <u0>320</u0><v0>240</v0></model><model><type>perspectiveProjWithDistortion</type><px>610</px><py>611</py>
    <u0>321</u0><v0>241</v0><kud>-0.1</kud><kdu>0.1</kdu></model></camera></root>""")
    cam = read_camera(f)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (600.5, 601.0, 320.0, 240.0, 640, 480)


def test_opencv_yaml_and_json_with_distortion(tmp_path):
    import cv2

    K = np.array([[500.0, 0, 319.5], [0, 505.0, 239.5], [0, 0, 1]])
    D = np.array([0.1, -0.05, 0.001, -0.002, 0.01])
    f = tmp_path / "cam.yaml"
    fs = cv2.FileStorage(str(f), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", D)
    fs.release()
    cam = read_camera(f)
    assert np.allclose(cam.K, K) and np.allclose(cam.dist, D) and (cam.width, cam.height) == (640, 480)
    # projection with distortion equals OpenCV's
    X = np.random.default_rng(1).uniform([-1, -1, 2], [1, 1, 5], (100, 3))
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, D)
    assert np.abs(cam.project(X) - ref.reshape(-1, 2)).max() < 1e-9
    # and the undistortion inverts it
    assert np.abs(cam.unproject(cam.project(X)) - X[:, :2] / X[:, 2:]).max() < 1e-6
    j = tmp_path / "cam.json"
    j.write_text(json.dumps({"camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
                             "distortion_coefficients": D.tolist(), "image_width": 640, "image_height": 480}))
    cam2 = read_camera(j)
    assert np.allclose(cam2.K, K) and np.allclose(cam2.dist, D)


def test_mst_json_roundtrip_and_scaling(tmp_path):
    cam = Camera(800, 801, 319.5, 239.5, 640, 480)
    f = tmp_path / "camera.json"
    write_camera(f, cam)
    back = read_camera(f)
    assert np.allclose(back.K, cam.K) and (back.width, back.height) == (640, 480) and len(back.dist) == 0
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    # a point at pixel centre (319.5, 239.5) maps to the half-size image centre (159.5, 119.5)
    assert np.allclose(half.project(np.array([[0.0, 0.0, 1.0]])), [[159.5, 119.5]])


@pytest.mark.parametrize("content, msg", [("<conf><camera><px>1</px></camera></conf>", "no <py>"),
                                           ("{not json", "not valid JSON"), ("hello", "unknown camera format"),
                                           ('{"fx": -1, "fy": 1, "cx": 0, "cy": 0}', "bad camera parameters")])
def test_bad_camera_files(tmp_path, content, msg):
    f = tmp_path / "bad.cam"
    f.write_text(content)
    with pytest.raises(InputError, match=msg):
        read_camera(f)
