"""Survey scale (issue 11): a UAV flyover of a real city model tracks out of the box, and a pose
that cannot be tracked says why.

Distance bands: one shared set (the real Rotterdam CityJSON subset), a 6-frame `mst synth flyover`
per band at 40, 120 and 250 m above the roofs, tracked with the defaults (mono SLAM aid, no far
plane) and with `--slam off`. Messages: a box model and blank frames (no rendering needed).
"""

from __future__ import annotations

import csv

import numpy as np
import pytest

from mst import InputError


def _cli(*args) -> None:
    from mst.cli.main import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    assert e.value.code == 0, args


def _ate(traj, gt):
    from mst.core.trajectory import read_tum

    tg, Tg = read_tum(gt)
    te, Te = read_tum(traj)
    idx = np.searchsorted(np.round(tg, 6), np.round(te, 6))
    return float(np.sqrt(np.mean(np.sum((Te[:, :3, 3] - Tg[idx, :3, 3]) ** 2, axis=1)))), Tg


@pytest.fixture(scope="module", params=[40, 120, 250], ids=["40m", "120m", "250m"])
def flyover(request, shared_data, tmp_path_factory):
    """A 6-frame flyover at the band's height, converted model, clicked first pose, and both runs."""
    h = request.param
    d = tmp_path_factory.mktemp(f"fly{h}")
    seq = d / "seq"
    # 320x240 is enough at 40 m; at 120/250 m the buildings need 640x480 to give edges of a few samples
    w, hgt = (320, 240) if h <= 40 else (640, 480)
    # 10 frames at 250 m: that pass starts where hidden edges leaking past tiny far buildings once
    # locked frame 0 24 m off (a z-buffer without conservative coverage)
    n = 10 if h >= 250 else 6
    _cli("synth", "flyover", "--model", shared_data / "cityjson/rotterdam_subset.json", "-o", seq, "--frames", n,
         "--distance", h, "--width", w, "--height", hgt, "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    _cli("convert-model", seq / "model.obj", "-o", d / "m.wrl", "-q")
    _cli("init", "--model", d / "m.wrl", "--camera", seq / "camera.json", "--clicks", seq / "clicks.txt",
         "-o", d / "p0.txt", "-q")
    from mst.pipeline.tracking import TrackConfig, run_track

    runs = {}
    for slam in ("auto", "off"):  # the default mode (edges + KLT, mono aid on standby) and edges only
        out = d / f"traj_{slam}.txt"
        s = run_track(seq / "rgb", d / "m.wrl", seq / "camera.json", d / "p0.txt", out, TrackConfig(aid=slam), fps=30)
        ate, Tg = _ate(out, seq / "gt.txt")
        cov = list(csv.DictReader(open(out.with_suffix(".cov.csv"))))
        sig = np.array([[float(r[f"std_{a}_m"]) for a in "xyz"] for r in cov if r["status"] == "model"])
        runs[slam] = (s, ate, sig)
    from mst.meshtools.formats import load_model

    V = np.asarray(load_model(d / "m.wrl").vertices)
    dist = float(np.median(np.linalg.norm(Tg[:, :3, 3] - V.mean(axis=0), axis=1)))  # camera to the block centre
    return h, dist, runs


#: session 6 (issue #12, the cluster-robust edge covariance): at 250 m edges only outputs 5 of 10 frames:
#: frame 5 is 0.87 % off with 2 sigma = 1.15 % of the distance (classical 0.77 %; err / sigma over the
#: run 1.21, classical 1.50), so the error budget refuses it, and frames 6-9 (0.19-0.56 % off, 2 sigma
#: 0.71-1.01 %) stay refused by its hysteresis (0.5 x the budget after a refusal; with 1.0 frames 6-9
#: return but the demo UAV pass outputs a pose 1.03 % off). The default mode (edges + KLT) tracks all 10
_FLY250_OFF = pytest.mark.xfail(strict=True, reason="edges only at 250 m: frame 5 (0.87 % off, 2 sigma 1.15 %) and "
                                                    "6-9 (hysteresis) refused by the error budget")


def test_flyover_band_default_mode_tracks_every_frame_as_well_as_edges_only(flyover, request):
    h, dist, runs = flyover
    if h >= 250:
        request.applymarker(_FLY250_OFF)
    (s_def, ate_def, _), (s_off, ate_off, sig_off) = runs["auto"], runs["off"]
    # the ViSP 100 m far plane stopped the 211 m flyover at frame 0: no far plane by default
    assert s_def["tracked"] == s_def["frames"] == s_off["tracked"] == s_off["frames"]
    # error budget: the edge pose's own covariance (the .cov.csv side output: 0.3-0.5 px residual
    # over ~600 samples). It treats the samples as independent, while neighbouring samples of one
    # edge share that edge's error (observed errors were 0.8-2.6 sigma on 6-10 frame runs at
    # 40-250 m): the ATE is within 5 sigma (RMS over the frames) of what the tracker reports
    budget = 5.0 * float(np.sqrt(np.mean(np.sum(sig_off**2, axis=1))))
    print(f"band {h} m: distance {dist:.0f} m, ATE default {ate_def:.3f} m ({100 * ate_def / dist:.2f} %), "
          f"edges only {ate_off:.3f} m, 5-sigma budget {budget:.3f} m, ms {s_def['median_ms']:.1f}/{s_off['median_ms']:.1f}")
    assert ate_off <= budget, (ate_off, budget)
    # the default mode (its SLAM aid) must never cost accuracy: as accurate as edges only, within the 6-frame
    # noise of the comparison (1 sigma of each run: 0.2 x the 5-sigma budget)
    assert ate_def <= ate_off + 0.2 * budget, (ate_def, ate_off, budget)
    # sanity against the distance: the target is 0.1 %, the edge covariance today allows
    # 0.1-0.5 % per frame (1 sigma), so 1.5 % is its 3-to-10-sigma bound, not a fit to one run
    assert ate_def <= 0.015 * dist, (ate_def, dist)


# ---------------------------------------------------------------------------- messages
def _box_scene(tmp_path, z_m: float, size_m: float = 10.0, frames: int = 2, far: float | None = None):
    """A cube of ``size_m`` at ``z_m`` on the optical axis, blank gray frames, a camera, a pose."""
    import cv2

    s = size_m / 2
    V = np.array([[x, y, zz] for x in (-s, s) for y in (-s, s) for zz in (-s, s)])
    F = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    obj = tmp_path / "box.obj"
    obj.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in V) + "".join(
        "f " + " ".join(str(i + 1) for i in f) + "\n" for f in F))
    cam = tmp_path / "cam.json"
    cam.write_text('{"model": "pinhole", "width": 320, "height": 240, "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}')
    fr = tmp_path / "frames"
    fr.mkdir()
    for i in range(frames):
        cv2.imwrite(str(fr / f"{i:06d}.png"), np.full((240, 320, 3), 128, np.uint8))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.3, 0.4, 0.0]))[0]  # three faces toward the camera
    T[2, 3] = z_m
    pose = tmp_path / "pose.txt"
    pose.write_text("\n".join(" ".join(f"{x:.12g}" for x in r) for r in T) + "\n")
    settings = None
    if far is not None:
        settings = tmp_path / "settings.xml"
        settings.write_text(f"<conf><face><far_clipping>{far}</far_clipping></face></conf>")
    return fr, obj, cam, pose, settings


def _track_error(tmp_path, fr, obj, cam, pose, settings=None) -> str:
    from mst.pipeline.tracking import TrackConfig, run_track
    from mst.pipeline.tracking.config import read_tracker_xml

    cfg = (read_tracker_xml(settings) if settings else TrackConfig()).replace(aid="off")
    out = tmp_path / "traj.txt"
    with pytest.raises(InputError) as e:
        run_track(fr, obj, cam, pose, out, cfg)
    assert not out.exists() and not out.with_suffix(".csv").exists()
    return str(e.value)


def test_message_beyond_far_plane_names_the_setting(tmp_path, capsys):
    from mst.cli.main import main
    from mst.errors import ConfigError

    fr, obj, cam, pose, settings = _box_scene(tmp_path, 200.0, far=100.0)
    # the library blames the field ...
    with pytest.raises(ConfigError) as e:
        _track_error(tmp_path, fr, obj, cam, pose, settings)
    assert e.value.field == "edges.far_clip_m" and "beyond the far clipping plane" in e.value.problem
    # ... and the command the settings file and its ViSP tag
    out = tmp_path / "traj.txt"
    with pytest.raises(SystemExit) as ex:
        main(["track", str(fr), "--model", str(obj), "--camera", str(cam), "--init", str(pose), "-o", str(out),
              "--settings", str(settings), "--slam", "off", "-q"])
    assert ex.value.code == 1 and not out.exists()
    msg = capsys.readouterr().err.strip()
    assert msg.startswith(f"mst track: error: {settings}: ") and "beyond the far clipping plane" in msg
    assert "far plane 100 m" in msg and "<far_clipping>" in msg


def test_no_far_plane_by_default(tmp_path):
    # the same box at 200 m with the defaults: its edges are sampled (no far plane); on blank frames
    # the moving edges find nothing, so the real cause is the pose solver's
    msg = _track_error(tmp_path, *_box_scene(tmp_path, 200.0))
    assert "far clipping" not in msg and "pose solver failed" in msg and "moving edge" in msg


def test_message_too_small_in_the_image(tmp_path):
    # a 1 m box at 2 km: 0.13 px across, below the level-of-detail thresholds
    msg = _track_error(tmp_path, *_box_scene(tmp_path, 2000.0, size_m=1.0))
    assert "too small in the image" in msg and msg.startswith(str(tmp_path / "pose.txt"))


def test_message_model_behind_the_camera(tmp_path):
    msg = _track_error(tmp_path, *_box_scene(tmp_path, -50.0))
    assert "behind the camera" in msg and msg.startswith(str(tmp_path / "pose.txt"))


def test_reason_behind_the_camera_at_a_later_pose(tmp_path):
    """A tracker whose predicted pose puts the model behind the camera says so (not "too few samples")."""
    import cv2

    from mst.core.camera import read_camera
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.tracking import EdgeTracker, TrackConfig

    fr, obj, cam, pose, _ = _box_scene(tmp_path, 50.0)
    tr = EdgeTracker(load_tracking_model(obj), read_camera(cam), TrackConfig())
    gray = cv2.imread(str(fr / "000000.png"), cv2.IMREAD_GRAYSCALE)
    T = np.loadtxt(pose)
    tr.near(T)  # near plane fixed at the first pose
    T_behind = T.copy()
    T_behind[2, 3] = -50.0
    r = tr.track(gray, T_behind, first=True)
    assert not r.healthy and "behind the camera" in r.reason


def test_message_pose_solver_failure(tmp_path):
    msg = _track_error(tmp_path, *_box_scene(tmp_path, 30.0))
    assert "pose solver failed" in msg and "moving edge" in msg


def test_mono_aid_without_landmarks_predicts_nothing(tmp_path):
    """Without a PnP pose the mono aid returns no prediction (the tracker starts from its last pose,
    as with --slam off): its constant-velocity guess from noisy edge poses, returned as the
    prediction, doubled the weakly observed depth error every frame of a 211 m flyover."""
    import cv2

    from mst.core.camera import read_camera
    from mst.pipeline.slam import make_aid

    fr, obj, cam, pose, _ = _box_scene(tmp_path, 30.0, frames=0)
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (240, 340)).astype(np.uint8), (0, 0), 2)
    aid = make_aid("mono", read_camera(cam))
    T = np.loadtxt(pose)
    gray = np.ascontiguousarray(tex[:, :320])
    for k in range(4):  # a still view: corners tracked, no parallax, no landmark
        pred = aid.predict(k, gray, T)
        assert pred is None, k
        T = T.copy()
        T[0, 3] -= 0.002  # a moving camera (constant velocity would predict a pose), too little parallax
        aid.update(k, gray, T, np.eye(6) * 1e6, True)
    assert len(aid.pts) > 50 and not aid.lm
