"""Issue 11: tracking the UAV scenarios of ``mst synth`` in the default mode (edges + KLT, mono aid on
standby) against ``--slam off``.

* The FPV facade pass over a procedural city block (default suite, 320x240): every frame tracked,
  the yaw error against the issue's 0.1 deg, the ATE against the pose's own covariance and stated
  against the 0.1 %-of-distance target.
* The survey pass (``mst synth uav``: pitched 45 deg down, hovering while it turns 135 deg away from
  the block and back) over the real Rotterdam CityJSON set at 40, 120 and 250 m above the ground
  (slow, 640x480, 240 frames = 8 s): no pose is marked tracked while no building is in view, the
  steady flight before the turn is tracked in every frame as accurately as edges only, and the
  block is tracked again after the turn. Numbers are printed (``-s``) per band.
"""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

from mst.eval.traj.metrics import view_distance_m


def _cli(*args) -> None:
    from mst.cli.main import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    assert e.value.code == 0, args


def _prepare(seq, d, model=None):
    """Converted model (or ``model`` as given), the first pose from the clicks."""
    m = model
    if m is None:
        m = d / "m.wrl"
        _cli("convert-model", seq / "model.obj", "-o", m, "-q")
    _cli("init", "--model", m, "--camera", seq / "camera.json", "--clicks", seq / "clicks.txt", "-o", d / "p0.txt", "-q")
    return m


def _run(seq, d, m, slam: str, fps: float):
    from mst.core.trajectory import read_tum
    from mst.pipeline.tracking import TrackConfig, run_track

    out = d / f"traj_{slam}.txt"
    s = run_track(seq / "rgb", m, seq / "camera.json", d / "p0.txt", out, TrackConfig(aid=slam), fps=fps)
    tg, Tg = read_tum(seq / "gt.txt")
    te, Te = read_tum(out)
    idx = np.searchsorted(np.round(tg, 6), np.round(te, 6))
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    status = {int(r["frame"]): r["status"] for r in rows}
    reason = {int(r["frame"]): r["reason"] for r in rows}
    cov = {int(r["frame"]): np.array([float(r[f"std_{a}_m"]) for a in "xyz"])
           for r in csv.DictReader(open(out.with_suffix(".cov.csv"))) if r["status"] == "model"}
    err = np.linalg.norm(Te[:, :3, 3] - Tg[idx, :3, 3], axis=1)
    fg, fe = Tg[idx, :3, 2], Te[:, :3, 2]  # optical axes in the model frame (z up): heading = yaw
    dyaw = (np.degrees(np.arctan2(fe[:, 1], fe[:, 0]) - np.arctan2(fg[:, 1], fg[:, 0])) + 180) % 360 - 180
    return {"summary": s, "idx": idx, "err": err, "dyaw": dyaw, "status": status, "reason": reason, "cov": cov, "Tg": Tg,
            "Te": Te}


def _model_px(seq) -> np.ndarray:
    return np.array([int(r["model_px"]) for r in csv.DictReader(open(seq / "frames.csv"))])


_view_distance = view_distance_m  # eval.traj.metrics: shared with the UAV bench


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


# ---------------------------------------------------------------------------- FPV facade pass
def test_fpv_facade_pass_default_tracks_every_frame(tmp_path):
    _fpv_facade_pass(tmp_path, 320, 240)


def test_fpv_facade_pass_default_tracks_every_frame_at_640x480(tmp_path):
    """The pass at 640x480: ViSP's 8 px range, and a frame that search loses is searched again with a
    half-resolution pass first (config.retry_pyramid_levels: 2 from 640 px wide); without the retry
    19 of 30 frames were tracked (session 11). Edges only tracks every frame too: a frame that the
    retry loses is fitted from the constant-velocity pose of the last two model frames
    (TrackingSession._edge_pose); without that 5 of 30."""
    off = _fpv_facade_pass(tmp_path, 640, 480)
    assert off["summary"]["tracked"] == 30 and set(off["status"].values()) == {"model"}


@pytest.mark.slow
def test_fpv_facade_pass_default_tracks_every_frame_at_1080p(tmp_path):
    """The same pass filmed at 1920x1080: the default search range scales with the width (24 px), and a
    frame that search loses is searched again with a half-resolution pass first
    (config.retry_pyramid_levels); with 24 px and one level 2 of 30 frames were tracked (1 m and
    ~2 deg a frame moves the facades further than the range)."""
    _fpv_facade_pass(tmp_path, 1920, 1080)


def _fpv_facade_pass(tmp_path, width: int, height: int) -> dict:
    """The FPV pass over the 36-building block at ``width`` x ``height``, 30 frames at 10 frames/s, tracked in
    the default mode and edges only, with the issue's checks on the default; returns the edges-only run."""
    from mst.meshtools.formats import load_model, save_model
    from mst.meshtools.generate import city_block_model

    city = tmp_path / "city.wrl"
    save_model(city, city_block_model(36, seed=0))
    seq = tmp_path / "seq"
    # 3 s at 10 frames/s: 1 m and up to ~2 deg of yaw between frames, the S-turn and banking
    _cli("synth", "fpv", "--model", city, "-o", seq, "--frames", 30, "--fps", 10, "--width", width, "--height", height,
         "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, tmp_path, model=city)
    d = _run(seq, tmp_path, m, "auto", 10.0)
    off = _run(seq, tmp_path, m, "off", 10.0)
    s = d["summary"]
    assert s["tracked"] == s["frames"] == 30 and set(d["status"].values()) == {"model"}
    cam = json.loads((seq / "camera.json").read_text())
    dist = _view_distance(d["Tg"], load_model(city).vertices, cam, range(30), q=0.0)  # the nearest facade corner: the strict reading
    sig = np.array(list(d["cov"].values()))
    # error budget: the edge pose's own covariance, 5 sigma RMS over the frames (neighbouring samples of
    # one edge share its error, so the covariance is optimistic by 1-3x: test_track_survey)
    budget = 5.0 * float(np.sqrt(np.mean(np.sum(sig**2, axis=1))))
    ate, yaw = _rms(d["err"]), _rms(d["dyaw"])
    print(f"fpv: nearest-building distance {dist:.1f} m, ATE default {ate:.3f} m ({100 * ate / dist:.3f} %, target 0.1 %), "
          f"budget {budget:.3f} m, yaw RMS {yaw:.4f} max {np.abs(d['dyaw']).max():.4f} deg (target 0.1); "
          f"edges only {off['summary']['tracked']}/30 frames, ATE {_rms(off['err']):.3f} m")
    assert ate <= budget, (ate, budget)
    # the issue's accuracy target itself, against the nearest facade corner (the strict reading of "the
    # camera-building distance"; 0.076 % measured in session 7, byte-identical across CPUs)
    assert ate <= 0.001 * dist, (ate, dist)
    # the issue's yaw target: 0.1 deg (the covariance's rotation sigma here is ~0.01-0.02 deg)
    assert yaw <= 0.1, yaw
    # the default is never worse than edges only: as many frames, as accurate on the frames both output
    assert s["tracked"] >= off["summary"]["tracked"]
    common = np.intersect1d(d["idx"], off["idx"])
    e_d = d["err"][np.isin(d["idx"], common)]
    e_o = off["err"][np.isin(off["idx"], common)]
    assert _rms(e_d) <= _rms(e_o) + 0.2 * budget, (_rms(e_d), _rms(e_o))
    return off


# ---------------------------------------------------------------------------- survey bands
# the 250 m band (session 8): after the turn the edge poses' honest 2 sigma bound stays at 0.6-1.0 %
# of the distance (err / sigma 0.99 at the true poses, 1.16 over the pass: the image of one small
# block gives no more; more samples, LOD off or a 2 px step, left it at 0.76-0.87 %); before the
# error budget's steady return (budget.RETURN_STEADY_FRAMES) one frame at 1.0 % refused the
# following 27 (output waited for 0.5 %) and only 20 of the last 48 frames were model (needs 24);
# now 39 of 48, 126 model poses (main: 100), worst model pose 0.86 % of the nearest-vertex distance,
# whole-run ATE 1.10 m (0.36 % of 307 m: the issue's 0.1 % is below what the image pins per frame;
# edges only 0.91 m on 84 poses; measured after the merge of the VVS step test)
def _survey_runs(h: float, shared_data, d, size: tuple = ()):
    """The survey pass over Rotterdam at ``h`` m (240 frames; ``size`` = (width, height), else the
    scenario's 640x480) in ``d``, tracked in both modes: ``(h, seq, model vertices, runs)``."""
    from mst.meshtools.formats import load_model

    seq = d / "seq"
    wh = ["--width", size[0], "--height", size[1]] if size else []
    _cli("synth", "uav", "--model", shared_data / "cityjson/rotterdam_subset.json", "-o", seq, "--frames", 240,
         "--distance", h, *wh, "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, d)
    runs = {slam: _run(seq, d, m, slam, 30.0) for slam in ("auto", "off")}
    return h, seq, load_model(m).vertices, runs


@pytest.fixture(scope="module", params=[40, 120, 250], ids=["40m", "120m", "250m"])
def survey(request, shared_data, tmp_path_factory):
    return _survey_runs(request.param, shared_data, tmp_path_factory.mktemp(f"uav{request.param}"))


@pytest.mark.slow
def test_uav_survey_band_default_mode(survey):
    from mst.pipeline.synth.scenarios_uav import GAP_PHASES

    h, seq, V, runs = survey
    n = 240
    px = _model_px(seq)
    steady = np.arange(n) < 0.2 * n  # before the hover and the turn: straight flight, the block in view
    assert (px[steady] > 0).all()
    cam = json.loads((seq / "camera.json").read_text())
    dist = _view_distance(runs["auto"]["Tg"], V, cam, np.flatnonzero(steady))
    line = [f"band {h} m: camera-building distance {dist:.0f} m"]
    for slam, r in runs.items():
        st = r["status"]
        # honest: no pose is marked tracked by the model (model / relocalised) without a building in view
        assert not [k for k, s in st.items() if px[k] == 0 and s in ("model", "relocalised")], slam
        sel = steady[r["idx"]]
        r["ate_steady"] = _rms(r["err"][sel])
        sig = np.array([r["cov"][k] for k in r["idx"][sel] if k in r["cov"]])
        r["budget"] = 5.0 * float(np.sqrt(np.mean(np.sum(sig**2, axis=1))))
        after = r["idx"] > GAP_PHASES[3] * n
        line.append(f"{slam}: {r['summary']['tracked']}/{n} output ({dict(r['summary']['status_counts'])}), "
                    f"steady ATE {r['ate_steady']:.3f} m ({100 * r['ate_steady'] / dist:.3f} %, target 0.1 %), "
                    f"5-sigma budget {r['budget']:.3f} m, whole-run ATE {_rms(r['err']):.3f} m, "
                    f"max {r['err'].max():.2f} m, after the turn {np.count_nonzero(after)} frames "
                    f"ATE {_rms(r['err'][after]) if after.any() else float('nan'):.3f} m")
    print("; ".join(line))
    d, o = runs["auto"], runs["off"]
    # the steady flight: every frame tracked by the model in the default mode, where the edges' evidence
    # pins it (edges only outputs every steady frame); in a pixel-limited band (250 m at 640x480: the
    # edges' 2 sigma 0.8-1.2 % of the distance, frame to frame) every steady frame is output or refused
    # by the error budget, never lost otherwise
    limited = not all(o["status"].get(k) == "model" for k in np.flatnonzero(steady))
    _assert_output_or_uncertain(d, np.flatnonzero(steady), ("model",), strict=not limited)
    # error budget: the edge covariance (5 sigma RMS, see the FPV test)
    assert d["ate_steady"] <= d["budget"], (d["ate_steady"], d["budget"])
    # the SLAM aid costs no accuracy there: within the comparison's noise (1 sigma = 0.2 x the budget)
    assert d["ate_steady"] <= o["ate_steady"] + 0.2 * o["budget"], (d["ate_steady"], o["ate_steady"])
    # and it never costs frames: the default outputs at least as many poses as edges only
    assert d["summary"]["tracked"] >= o["summary"]["tracked"]
    # the block is tracked again after the turn (the model / relocalised in the last 20 %); in the
    # pixel-limited band every frame there is tracked again or refused by the error budget, and at least
    # as many are output as by edges only (session 16: 11 / 8 of 48, the rest 2 sigma 0.7-1.6 %; with the
    # KLT points counted as evidence 39 were output, one steady pose 1.035 % off, test_klt_points_are_no_evidence)
    tail = [d["status"].get(k) for k in range(int(0.8 * n), n)]
    if not limited:
        assert tail.count("model") + tail.count("relocalised") >= 0.5 * len(tail), tail
    else:
        _assert_output_or_uncertain(d, range(int(0.8 * n), n), ("model", "relocalised"), strict=False)
        tail_o = [o["status"].get(k) for k in range(int(0.8 * n), n)]
        assert sum(s in ("model", "relocalised") for s in tail) >= sum(s in ("model", "relocalised") for s in tail_o)
    # the drift budget (issue 12): no `slam` pose off by more than 1 % of its distance to the model
    # (the nearest vertex, the budget's own distance) or 2 deg; before it, 3-5 map poses at the ends
    # of the turn were 0.8-1.4 % (40 m) up to 3-5 m off; and where both output a pose, the default is
    # within the comparison's noise of edges only
    _assert_slam_within_budget(d, V)
    # and no model (or relocalised) pose beyond 1 % / 2 deg in either mode, over the whole pass (before
    # the error budget, test_track_budget.py: the turn frame at 40 m 1.4 %, at 120 m 2.1 % off)
    for r in runs.values():
        _assert_within_budget(r, V, ("model", "relocalised"))
    both = np.isin(d["idx"], o["idx"])
    e_d, e_o = d["err"][both], o["err"][np.isin(o["idx"], d["idx"])]
    assert _rms(e_d) <= _rms(e_o) + 0.2 * o["budget"], (_rms(e_d), _rms(e_o))
    # "at least as accurate as edges only" when the default outputs more frames (README, UAV survey):
    # the frames both output are compared (above); each extra frame (a turn frame edges only gave
    # up) is held to the per-pose output bound (1 % / 2 deg, above); and the extra frames may not
    # make the whole pass worse than the issue's ATE target (0.1 % of the camera-building
    # distance) or, where edges only misses that target too (the pixel-limited bands), than edges
    # only's own whole-pass ATE (within the comparison's noise, 0.2 x its budget). Measured
    # (session 8, after the VVS step test waits for the damping to relax, vvs.STOP_MU): 40 m 158
    # frames 0.036 m (0.06 %; edges only 134, 0.022 m), 120 m 157 frames 0.254 m (edges only 142,
    # 0.205 m, + 0.131 m noise; target 0.15 m). Before it the 120 m return after the turn held
    # 0.55-1.0 m off for 20 frames (143 frames, 0.375 m: a strict xfail of sessions 6-7)
    ate_d, ate_o = _rms(d["err"]), _rms(o["err"])
    assert ate_d <= max(0.001 * dist, ate_o + 0.2 * o["budget"]), (ate_d, ate_o, dist)


@pytest.mark.slow
def test_uav_survey_of_the_procedural_block_comes_back_after_the_turn(tmp_path):
    """The 40 m survey pass (640x480, 240 frames) over the procedural 36-building block (no shared data
    needed), default mode: after the hover and the 135 deg turn the block is tracked again (model or
    relocalised in at least half of the last 20 % of the frames, as on Rotterdam), no pose is marked
    tracked by the model without a building in view, and none beyond 1 % / 2 deg. Before the map's
    relocalisation gate (slam.reloc_gate_rel) the map relocalised 60 m away after the turn (the ground
    texture repeats) and the session started every later frame from there: 87 of 240 frames output,
    none after frame 86, 92 frames with the block in view not output; with it 173 output, 6 not."""
    from mst.meshtools.formats import load_model, save_model
    from mst.meshtools.generate import city_block_model

    n = 240
    city = tmp_path / "city.wrl"
    save_model(city, city_block_model(36, seed=0))
    seq = tmp_path / "seq"
    _cli("synth", "uav", "--model", city, "-o", seq, "--frames", n, "--distance", 40, "--no-depth", "--aa", 4,
         "--texture-size", 512, "-q")
    _prepare(seq, tmp_path, model=city)
    r = _run(seq, tmp_path, city, "auto", 30.0)
    px = _model_px(seq)
    st = r["status"]
    assert not [k for k, s in st.items() if px[k] == 0 and s in ("model", "relocalised")]
    _assert_within_budget(r, load_model(city).vertices, ("model", "relocalised", "slam"))
    tail = [st.get(k) for k in range(int(0.8 * n), n)]
    assert tail.count("model") + tail.count("relocalised") >= 0.5 * len(tail), tail
    # the summary says what the gate did (the map relocalised, and refused the teleports)
    assert r["summary"]["map_relocalisations"]["gated"] >= 1, r["summary"]["map_relocalisations"]


@pytest.fixture(scope="module", params=[40, 120, 250], ids=["40m", "120m", "250m"])
def survey_1080(request, shared_data, tmp_path_factory):
    """The survey pass of :func:`survey` filmed at 1920x1080 (the camera's focal length scaled with
    the width: the same field of view), both modes."""
    return _survey_runs(request.param, shared_data, tmp_path_factory.mktemp(f"uav1080_{request.param}"), (1920, 1080))


@pytest.mark.slow
def test_uav_survey_band_at_1080p_meets_the_issue_target(survey_1080):
    """Issue 11's target where the image resolves it: at 1920x1080 every band's whole-run ATE of the
    default mode within 0.1 % of the camera-building distance, or, where a few frames of the block's
    return after the turn decide it, no worse than edges only's within the comparison's noise (the rule
    of :func:`test_uav_survey_band_default_mode`): at 250 m two frames as the block re-enters the view
    are 1.9 / 2.2 m off (0.6-0.7 %, inside the 1 % per-pose budget) and the whole run 0.323 m = 0.106 %
    on an AMD Zen 4 CPU (edges only 0.271 m; the other frames 0.072 %), under 0.1 % on Intel Sapphire
    Rapids (sessions 9-15: the run diverges in rounding from frame to frame); no pose marked tracked without a
    building in view or beyond 1 % / 2 deg; the default at least as accurate as edges only on the
    frames both output (within the comparison's noise, 0.2 x edges only's 5-sigma budget, as in
    :func:`test_uav_survey_band_default_mode`). The default search range scales with the width
    (8 px at 640 -> 24 px here): with ViSP's fixed 8 px the 250 m band was 0.23-0.26 % (h1, session 9)."""
    h, seq, V, runs = survey_1080
    n = 240
    px = _model_px(seq)
    steady = np.arange(n) < 0.2 * n
    cam = json.loads((seq / "camera.json").read_text())
    dist = _view_distance(runs["auto"]["Tg"], V, cam, np.flatnonzero(steady))
    for slam, r in runs.items():
        assert not [k for k, s in r["status"].items() if px[k] == 0 and s in ("model", "relocalised")], slam
        _assert_within_budget(r, V, ("model", "relocalised", "slam"))
        sig = np.array([r["cov"][k] for k in r["idx"][steady[r["idx"]]] if k in r["cov"]])
        r["budget"] = 5.0 * float(np.sqrt(np.mean(np.sum(sig**2, axis=1))))
        print(f"1080p band {h} m ({dist:.0f} m): {slam} {r['summary']['tracked']}/{n} output, whole-run ATE "
              f"{_rms(r['err']):.3f} m ({100 * _rms(r['err']) / dist:.3f} %)")
    d, o = runs["auto"], runs["off"]
    assert all(d["status"].get(k) == "model" for k in np.flatnonzero(steady))
    ate_d, ate_o = _rms(d["err"]), _rms(o["err"])
    assert ate_d <= max(0.001 * dist, ate_o + 0.2 * o["budget"]), (ate_d, ate_o, dist)
    both = np.isin(d["idx"], o["idx"])
    e_d, e_o = d["err"][both], o["err"][np.isin(o["idx"], d["idx"])]
    assert _rms(e_d) <= _rms(e_o) + 0.2 * o["budget"], (_rms(e_d), _rms(e_o))
    assert d["summary"]["tracked"] >= o["summary"]["tracked"]


def _assert_output_or_uncertain(run, frames, statuses, strict: bool) -> None:
    """Every frame of ``frames`` output with one of ``statuses`` (``strict``), or else refused by the
    error budget (``pose uncertain``: its own evidence does not pin it), never lost otherwise."""
    from mst.pipeline.tracking.budget import REASON_UNCERTAIN

    bad = {k: (run["status"].get(k), run["reason"].get(k)) for k in frames if run["status"].get(k) not in statuses
           and (strict or not str(run["reason"].get(k, "")).startswith(REASON_UNCERTAIN))}
    assert not bad, bad


def _assert_slam_within_budget(run, V) -> None:
    """Every `slam` pose of ``run`` within 1 % of its camera's distance to the nearest model vertex and 2 deg."""
    _assert_within_budget(run, V, ("slam",))


def _assert_within_budget(run, V, statuses) -> None:
    """Every pose of ``run`` with one of ``statuses`` within 1 % of its camera's distance to the
    nearest model vertex and 2 deg."""
    from mst.core.poses import pose_error

    sl = np.array([run["status"].get(int(k)) in statuses for k in run["idx"]], bool)
    if not sl.any():
        return
    Tg = run["Tg"][run["idx"][sl]]
    dist = np.linalg.norm(Tg[:, None, :3, 3] - V[None], axis=2).min(1)
    assert np.all(run["err"][sl] <= 0.01 * dist), (run["err"][sl], dist)
    _, deg = pose_error(run["Te"][sl], Tg)
    assert np.all(deg <= 2.0), deg


@pytest.fixture(scope="module")
def fpv_rotterdam(shared_data, tmp_path_factory):
    """The FPV facade pass over Rotterdam (640x480, 150 frames, 30 m from the facade), default mode."""
    d = tmp_path_factory.mktemp("fpvR")
    seq = d / "seq"
    _cli("synth", "fpv", "--model", shared_data / "cityjson/rotterdam_subset.json", "-o", seq, "--distance", 30,
         "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, d)
    from mst.meshtools.formats import load_model

    return _run(seq, d, m, "auto", 30.0), load_model(m).vertices


@pytest.mark.slow
def test_fpv_rotterdam_no_slam_pose_beyond_the_budget(fpv_rotterdam):
    """Issue 11/12: the edges lose the facade after a few frames; the default's map then output
    `slam` poses 25 m and 18 deg off. With the drift budget no map pose beyond 1 % / 2 deg is output."""
    run, V = fpv_rotterdam
    _assert_slam_within_budget(run, V)


@pytest.mark.slow
def test_fpv_rotterdam_first_frames_from_an_exact_pose_within_the_budget(fpv_rotterdam):
    """Frames 0-4 from the (exact) clicked pose: the first frame's tolerant search had moved it 20 px
    (0.73 m, 2.4 %, 21 sigma of its own covariance) and frames 1-4 followed at 1.5-4.8 %; with the plain
    fit kept they are 0.06-0.23 m. Bound: the issue's 1 % of the distance (nearest vertex) and 2 deg."""
    from mst.core.poses import pose_error

    run, V = fpv_rotterdam
    first = run["idx"] < 5
    assert first.sum() == 5 and all(run["status"][k] == "model" for k in range(5))
    Tg = run["Tg"][run["idx"][first]]
    dist = np.linalg.norm(Tg[:, None, :3, 3] - V[None], axis=2).min(1)
    assert np.all(run["err"][first] <= 0.01 * dist), run["err"][first] / dist
    assert np.all(pose_error(run["Te"][first], Tg)[1] <= 2.0)


@pytest.mark.slow
def test_fpv_rotterdam_no_wrong_output_pose(fpv_rotterdam):
    """Frames 5-6 were `model` 2.1 / 2.9 % off (~10 sigma of their own covariance, health score 0.42 /
    0.65). Frame 5 lies 2.6 % of the distance from the constant-velocity prediction, and the refit from
    the prediction converges 1.7 % away; frame 6 (after the refused frame 5) refits 1.7-2.1 % away from
    +-3 sigma along its weakest direction: two fits of one image beyond the 1 % budget apart, so both
    frames are `lost` ("ambiguous", --json ambiguous_frames). Bound: every output pose within 1 % of
    the distance (nearest vertex)."""
    run, V = fpv_rotterdam
    Tg = run["Tg"][run["idx"]]
    dist = np.linalg.norm(Tg[:, None, :3, 3] - V[None], axis=2).min(1)
    assert np.all(run["err"] <= 0.01 * dist), run["err"] / dist
    amb = run["summary"]["ambiguous_frames"]
    assert amb and all(run["status"][k] == "lost" for k in amb)


# ---------------------------------------------------------------------------- policy
def test_relocalisation_is_tried_while_the_aid_carries_with_the_model_in_view():
    """A SLAM stretch with the model projecting into the image (edge samples) gets relocalisation
    attempts like a lost stretch (the 40 m survey: the aid's 11 m-off map poses became a
    relocalised frame); without samples (the model out of view) or with the aid on standby, none."""
    from mst.core.poses import se3_exp
    from mst.pipeline.tracking.edge_tracker import FrameResult
    from mst.pipeline.tracking.session import TrackingPolicy

    T = se3_exp(np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0]))
    bad = FrameResult(T, False, 100, 20, 0.3, 40.0, np.eye(6), np.eye(6), reason="inliers 20%", support=0.3)
    unseen = FrameResult(T, False, 0, 0, float("nan"), float("nan"), np.eye(6), np.eye(6), reason="outside")
    p = TrackingPolicy(T, search_range_px=8)
    p.accepted(T)
    p.frame_done(bad)
    assert not p.should_relocalise(bad, every=2)  # edges only / standby: not lost yet, no attempt
    tries = []
    for _ in range(4):  # the aid carries: slam frames (accepted, lost_streak stays 0)
        tries.append(p.should_relocalise(bad, every=2, aid_on=True))
        p.slam_streak += 1
        p.accepted(T)
    assert tries == [True, False, True, False] and p.lost_streak == 0
    assert not p.should_relocalise(unseen, every=2, aid_on=True)  # the model out of view: no attempt


def test_t_junction_joint_between_coplanar_facades_is_not_tracked():
    """Two buildings' facades in one plane, split unevenly (a T-junction: the low facade's joint edge
    lies on the tall one's longer edge): the joint shows no image edge and is dropped; the tall
    facade's edge above the low one is a real outline and stays; facades turned 10 deg keep both."""
    from mst.meshtools.model import PolygonModel
    from mst.pipeline.tracking.visibility import ModelGeometry

    def edges(turn_deg: float):
        a = np.radians(turn_deg)
        V = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1],  # low facade, normal -y
                      [1, 0, 0], [1 + np.cos(a), np.sin(a), 0], [1 + np.cos(a), np.sin(a), 2], [1, 0, 2]], float)
        g = ModelGeometry.from_model(PolygonModel(V, [[0, 1, 2, 3], [4, 5, 6, 7]]))
        return {tuple(sorted(map(tuple, np.round(g.vertices[e], 6).tolist()))) for e in g.edges}

    joint = ((1.0, 0.0, 0.0), (1.0, 0.0, 1.0))
    tall = ((1.0, 0.0, 0.0), (1.0, 0.0, 2.0))
    flat = edges(0.0)
    assert joint not in flat and tall in flat and len(flat) == 7
    turned = edges(10.0)
    assert joint in turned and tall in turned and len(turned) == 8


def test_first_frame_is_judged_by_the_error_budget(shared_data, tmp_path):
    """Issue 12's worst failure on the first frame: at 250 m over Delft at 640x480 the image pins the
    pose to ~2 % of the distance (2 sigma) and the first fit was output as `model` 8 % off. The
    first frame is judged by the error budget as every other: no output `model` pose beyond 1 % of
    its distance or 2 deg, and where no frame can be output the run fails naming the budget's
    cause (one line, nothing written) instead of starting from a pose its image does not pin."""
    from mst import InputError

    seq = tmp_path / "seq"
    _cli("synth", "uav", "--model", shared_data / "cityjson/delft_1b.json", "-o", seq, "--frames", 10,
         "--distance", 250, "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, tmp_path)
    from mst.meshtools.formats import load_model

    try:
        run = _run(seq, tmp_path, m, "auto", 30.0)
    except InputError as e:
        assert "frame 0: pose uncertain" in str(e) and "error budget" in str(e), e
        # with the evidence the first fit had (issue 11: the message names the real cause)
        assert re.search(r"\(\d+ of \d+ model edge samples matched\)", str(e)), e
        assert not list(tmp_path.glob("traj_auto*")), "a refused run left output behind"
        return
    _assert_within_budget(run, load_model(m).vertices, ("model", "slam"))
