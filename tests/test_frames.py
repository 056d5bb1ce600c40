"""Frame sources: video, image folder, glob, printf pattern, --frames, --scale, times, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from mst import ConfigError, InputError
from mst.core.camera import Camera
from mst.pipeline.frames import check_camera_size, open_frames, parse_range


def _write_seq(d, n=5, w=32, h=24):
    import cv2

    d.mkdir()
    for k in range(n):
        img = np.full((h, w, 3), 10 * k, np.uint8)
        cv2.imwrite(str(d / f"{k:06d}.png"), img)
    return d


def test_parse_range():
    assert parse_range(None) == (0, None, 1)
    assert parse_range("2:10:3") == (2, 10, 3)
    assert parse_range("5") == (5, None, 1)
    assert parse_range("::2") == (0, None, 2)
    # a bad range is a setting's problem, named by its field (the CLI shows it as --frames)
    with pytest.raises(ConfigError, match="need 0 <= a < b") as e:
        parse_range("5:2")
    assert e.value.field == "frames"
    with pytest.raises(ConfigError, match="not integers"):
        parse_range("a:b")


def test_image_folder_glob_printf(tmp_path):
    d = _write_seq(tmp_path / "rgb")
    for spec in (d, str(d / "*.png"), str(d / "%06d.png")):
        src = open_frames(spec, "1:5:2")
        got = [(i, t, int(img[0, 0, 0])) for i, t, img in src]
        assert got == [(1, 1.0, 10), (3, 3.0, 30)]  # image sequences: t = index
    src = open_frames(d, None, scale=0.5, fps=10)
    frames = list(src)
    assert len(frames) == 5 and frames[2][1] == pytest.approx(0.2)
    assert frames[0][2].shape == (12, 16, 3) and (src.width, src.height) == (16, 12)
    cam = check_camera_size(src, Camera(40, 40, 15.5, 11.5, 32, 24), "cam.json")
    assert (cam.width, cam.height, cam.fx, cam.cx) == (16, 12, 20, 7.5)
    with pytest.raises(InputError, match="camera is for 64x48 images but the frames are 32x24"):
        check_camera_size(src, Camera(40, 40, 15.5, 11.5, 64, 48), "cam.json")


def test_video_times_and_bad_video(shared_data, tmp_path):
    src = open_frames(shared_data / "visp-teabox/teabox.mp4", "30:39:4")
    got = [(i, t) for i, t, _ in src]
    assert got == [(30, 30 / 25), (34, 34 / 25), (38, 38 / 25)]
    bad = tmp_path / "broken.mp4"
    bad.write_text("not a video")
    with pytest.raises(InputError, match="could not be decoded"):
        open_frames(bad)
    with pytest.raises(InputError, match="does not exist"):
        open_frames(tmp_path / "missing.mp4")


def test_image_folder_order_is_natural_and_matches_fuse(tmp_path):
    """Unpadded names: img2 comes before img10 in `mst track` and in `mst fuse` alike (frame k = k-th file)."""
    import cv2
    import numpy as np

    from mst.pipeline.depth_io import list_image_frames
    from mst.pipeline.frames import open_frames

    for i in (0, 1, 2, 10, 11):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), np.full((8, 8), i * 10, np.uint8))
    vals = [int(img[0, 0, 0]) for _, _, img in open_frames(tmp_path)]
    assert vals == [0, 10, 20, 100, 110]
    assert [f.name for f in list_image_frames(tmp_path)] == ["img0.png", "img1.png", "img2.png", "img10.png", "img11.png"]
    vals_glob = [int(img[0, 0, 0]) for _, _, img in open_frames(str(tmp_path / "img*.png"))]
    assert vals_glob == vals


def test_prefetched_frames_same_items_errors_and_early_stop(tmp_path):
    """``prefetched`` gives the source's items in order; an error raised while producing item k is raised at
    item k (after the k items before it); breaking off stops the producer and runs the source's cleanup."""
    import threading

    from mst.pipeline.frames import prefetched

    assert list(prefetched(range(50))) == list(range(50))
    assert list(prefetched([])) == []

    def failing():
        yield from range(5)
        raise InputError(tmp_path / "frame_5.png", "image could not be read")

    got = []
    with pytest.raises(InputError, match="frame_5.png: image could not be read"):
        for x in prefetched(failing(), depth=2):
            got.append(x)
    assert got == list(range(5))

    closed = threading.Event()

    def endless():
        try:
            k = 0
            while True:
                yield k
                k += 1
        finally:
            closed.set()

    for x in prefetched(endless(), depth=2):
        if x == 3:
            break
    assert closed.wait(2.0)
    assert not any(t.name == "mst-frames" and t.is_alive() for t in threading.enumerate())


def test_track_reads_a_video_ahead_with_the_same_poses(shared_data, tmp_path, mst):
    """`mst track` of the real tea box reads its frames through the prefetching thread: the trajectory is the one
    the plain frame iterator gives (the session's steps are unchanged)."""
    from mst.pipeline import frames as F
    from mst.pipeline.tracking import run_track
    from mst.pipeline.tracking.config import read_tracker_xml

    t = shared_data / "visp-teabox"
    cfg = read_tracker_xml(t / "teabox.xml").replace(aid="off")
    p0 = tmp_path / "p0.txt"
    mst("init", "--model", t / "teabox.cao", "--camera", t / "teabox.xml", "--clicks", t / "teabox.clicks", "--points",
        t / "teabox.init", "-o", p0, "-q")
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    run_track(t / "teabox.mp4", t / "teabox.cao", t / "teabox.xml", p0, a, cfg, frames="0:12")
    orig = F.prefetched
    F.prefetched = lambda frames, depth=3: iter(frames)  # the plain iterator
    try:
        run_track(t / "teabox.mp4", t / "teabox.cao", t / "teabox.xml", p0, b, cfg, frames="0:12")
    finally:
        F.prefetched = orig
    assert a.read_bytes() == b.read_bytes() and len(a.read_text().splitlines()) >= 12
