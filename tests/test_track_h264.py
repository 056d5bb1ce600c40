"""Issue 11: the FPV facade pass written as an H.264 video (``mst synth --video-codec h264``:
libx264 at crf 23, yuv420p, as a drone records it) and tracked from the decoded video in the default
mode: every frame, as accurately as the pose's own covariance allows, the yaw within 0.1 deg.
"""

from __future__ import annotations

import json

import numpy as np

from tests.test_track_uav import _cli, _prepare, _rms, _run, _view_distance


def test_h264_fpv_pass_tracked_from_the_decoded_video(tmp_path):
    import cv2

    from mst.meshtools.formats import load_model, save_model
    from mst.meshtools.generate import city_block_model

    city = tmp_path / "city.wrl"
    save_model(city, city_block_model(36, seed=0))
    seq = tmp_path / "seq"
    _cli("synth", "fpv", "--model", city, "-o", seq, "--frames", 30, "--fps", 10, "--width", 320, "--height", 240,
         "--no-depth", "--aa", 4, "--texture-size", 512, "--video", "--video-codec", "h264", "-q")
    cap = cv2.VideoCapture(str(seq / "video.mp4"))
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode(errors="replace").lower()
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, first = cap.read()
    cap.release()
    assert fourcc in ("avc1", "h264") and n == 30 and ok
    png = cv2.imread(str(seq / "rgb" / "000000.png"))
    # lossy, not broken: the decoded frame is the rendered one up to compression noise
    # (crf 23 on a textured render: a few gray levels RMS; a wrong size/colour order would be ~50)
    assert first.shape == png.shape and float(np.sqrt(np.mean((first.astype(float) - png) ** 2))) < 12.0

    m = _prepare(seq, tmp_path, model=city)
    vid = seq / "as_video"
    vid.mkdir()
    (vid / "rgb").symlink_to(seq / "video.mp4")  # _run tracks seq/rgb: here the video file
    for f in ("camera.json", "gt.txt"):
        (vid / f).symlink_to(seq / f)
    d = _run(vid, tmp_path, m, "auto", 10.0)
    s = d["summary"]
    assert s["tracked"] == s["frames"] == 30 and set(d["status"].values()) == {"model"}
    cam = json.loads((seq / "camera.json").read_text())
    dist = _view_distance(d["Tg"], load_model(city).vertices, cam, range(30), q=0.0)
    sig = np.array(list(d["cov"].values()))
    # the same error budget as the lossless pass (test_track_uav): 5 sigma RMS of the pose's own covariance
    budget = 5.0 * float(np.sqrt(np.mean(np.sum(sig**2, axis=1))))
    ate, yaw = _rms(d["err"]), _rms(d["dyaw"])
    print(f"h264 fpv: ATE {ate:.3f} m ({100 * ate / dist:.3f} % of {dist:.1f} m), budget {budget:.3f} m, "
          f"yaw RMS {yaw:.4f} deg")
    assert ate <= budget, (ate, budget)
    assert yaw <= 0.1, yaw
