"""``make bench``'s tracking rows (mst.eval.bench.track): the ViSP comparison judged on runs taken in turn."""

from __future__ import annotations

import numpy as np


def test_interleaved_judgement_takes_each_frames_fastest_run_of_both_trackers():
    """The judged ratio is mst's per-frame fastest run over ViSP's (medians over frames), so a run slowed by
    load on some frames (here the second mst run, 10x on frames 0-1) does not move it; the wall medians of all
    runs are reported beside it."""
    from mst.eval.bench.track import _frame_min_median, _judge_interleaved

    mst = [np.array([1.0, 2.0, 3.0]), np.array([10.0, 20.0, 2.0])]
    visp = [np.array([2.0, 2.0, 2.0]), np.array([4.0, 4.0, 4.0])]
    row = {"frame_min_median_ms": _frame_min_median(visp)}
    _judge_interleaved(row, mst, visp, "target")
    assert row["mst_frame_min_median_ms"] == 2.0  # frame minima 1, 2, 2
    assert row["ratio_vs_visp_frame_min"] == 1.0 and row["ok"]
    assert row["mst_median_ms"] == 2.5 and row["ratio_vs_visp"] == round(2.5 / 3.0, 3)
    assert row["interleaved_runs"] == 2
    slow = {"frame_min_median_ms": 1.9}
    _judge_interleaved(slow, mst, visp, "target")
    assert not slow["ok"]
    shown = {"frame_min_median_ms": 1.0}
    _judge_interleaved(shown, mst, visp, None)  # a configuration shown, not judged
    assert "ok" not in shown and "target" not in shown


def test_one_run_times_every_frame_but_the_first(shared_data):
    """:func:`_mst_runner` (one :func:`_one_run` a call) on the real tea box: one time per frame after the
    first, positive and finite."""
    import cv2

    from mst.core.camera import read_camera
    from mst.eval.bench.track import _mst_runner
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import init_from_clicks, read_clicks
    from mst.pipeline.tracking.config import read_tracker_xml

    tb = shared_data / "visp-teabox"
    cam = read_camera(tb / "teabox.xml").with_size(640, 480)
    X, uv = read_clicks(tb / "teabox.clicks", tb / "teabox.init")
    cap = cv2.VideoCapture(str(tb / "teabox.mp4"))
    grays = []
    while len(grays) < 6:
        ok, img = cap.read()
        assert ok
        grays.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    run = _mst_runner(load_tracking_model(tb / "teabox.cao"), cam, read_tracker_xml(tb / "teabox.xml"), grays,
                      init_from_clicks(X, uv, cam.K).T_cam_model)
    for mode in ("edge", "hybrid"):
        ms = run(mode)
        assert ms.shape == (5,) and np.isfinite(ms).all() and (ms > 0).all()
