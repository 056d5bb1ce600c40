"""``mst synth turntable|carried|leave|occluder|blackout`` (pipeline/synth/dynamic.py) and ``mst track`` on them.

The issue's bounds (#12), asserted at 640x480: no frame with status ``model``/``slam``/``relocalised``
whose pose is off by more than 1 % of the distance or 2 deg, and the object re-acquired within 10
frames of being fully visible and at rest again. Error budget at 640x480: the edge tracker's
still-frame error on this textured object is 0.06-0.11 % of the distance and 0.04-0.08 deg
(measured; checked below to be under half the bound, else the bound would say nothing), so 1 %
leaves a 10x margin for the frames where something happens, while a wrong pose (a SLAM map of the
still room given as the moving object's, a pose locked onto the background) is 2-25 % off. One test
per scenario runs in the default suite on short sequences (30-45 frames: the events are faster per
frame, which makes re-acquisition harder, not easier); the full-length ones are ``slow``.

At 320x240 the tracker's own still-frame error is 1.2-1.7 % (the checker texture pulls the moving
edges by ~2-3 px at that size), above the issue's bound: the 320x240 tests (``slow``) use twice
the still-frame error (plus 2 deg for rotations) as "right", and the same 10-frame re-acquisition.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest

from mst.eval.bench.slam import SAMPLE_MODEL


def _synth(tmp_path_factory, scenario, frames, width=320, height=240):
    from mst.pipeline.synth import SynthConfig, synthesize

    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    out = tmp_path_factory.mktemp("dyn") / scenario
    s = synthesize(scenario, SAMPLE_MODEL, out, SynthConfig(width=width, height=height, frames=frames))
    assert s["frames"] == frames and (out / "frames.csv").exists() and (out / "gt.txt").exists()
    return out


def _track(seq, mode, out):
    from mst.core.poses import pose_error
    from mst.core.trajectory import read_tum
    from mst.pipeline.tracking import TrackConfig, run_track

    s = run_track(seq / "rgb", seq / "model.obj", seq / "camera.json", seq / "cMo" / "000000.txt", out, TrackConfig(aid=mode), fps=30.0)
    st = np.array([r["status"] for r in csv.DictReader(open(out.with_suffix(".csv")))])
    tg, Pg = read_tum(seq / "gt.txt")
    t, P = read_tum(out)
    idx = np.rint(t * 30).astype(int)
    from mst.meshtools.formats import load_triangles

    V = np.asarray(load_triangles(seq / "model.obj")[0])
    c = 0.5 * (V.min(0) + V.max(0))
    dt, dr = pose_error(P, Pg[idx])
    rel = np.full(len(st), np.nan)
    deg = np.full(len(st), np.nan)
    rel[idx] = dt / np.linalg.norm(Pg[idx][:, :3, 3] - c, axis=1)
    deg[idx] = dr
    truth = list(csv.DictReader(open(seq / "frames.csv")))
    return s, st, rel, deg, truth


def test_dynamic_scenarios_write_their_truth(tmp_path_factory):
    """Small and fast (default suite): the scenarios render, with frames.csv flags."""
    for sc, key in (("turntable", "object_moving"), ("carried", "object_moving"), ("leave", "in_view"),
                    ("occluder", "occluded_fraction"), ("blackout", "black")):
        out = _synth(tmp_path_factory, sc, 5, 160, 120)
        rows = list(csv.DictReader(open(out / "frames.csv")))
        assert len(rows) == 5 and len(list((out / "rgb").glob("*.png"))) == 5
        assert float(rows[0]["in_view"]) == 1.0 and float(rows[0]["object_moving"]) == 0  # starts fully in view, at rest
        if key == "in_view":  # the object leaves the view entirely
            assert any(float(r[key]) == 0 for r in rows)
        else:
            assert any(float(r[key]) > 0 for r in rows)  # the event happens inside 5 frames too


def _reacquired_within(st, truth, frames=10):
    """Frames from the object being fully visible and at rest again (after its motion) to the first
    model/relocalised frame (None: never)."""
    moving = np.array([r["object_moving"] == "1" for r in truth])
    view = np.array([float(r["in_view"]) == 1.0 for r in truth])
    last = int(np.flatnonzero(moving)[-1])
    rest = np.flatnonzero(view & ~moving & (np.arange(len(st)) > last))
    assert len(rest) > frames  # the sequence gives the tracker the time
    ok = np.flatnonzero(np.isin(st[rest[0]:], ["model", "relocalised"]))
    return int(ok[0]) if len(ok) else None


def _settled(truth) -> np.ndarray:
    """(N,) bool: the object fully visible and at rest, nothing in the way (no occluder, black or
    blurred frame)."""
    return np.array([r["object_moving"] == "0" and float(r["in_view"]) == 1.0 and float(r["occluded_fraction"]) == 0.0
                     and r["black"] == "0" and r["blur"] == "0" for r in truth])


def _reacquired_after_event(st, truth, frames=10):
    """Frames from the first settled frame after the scenario's last event (motion, leaving the
    view, occluder, black or blurred frames) to the first model/relocalised frame (None: never)."""
    ok = _settled(truth)
    last = int(np.flatnonzero(~ok)[-1])
    assert len(st) - (last + 1) > frames  # the sequence gives the tracker the time
    hit = np.flatnonzero(np.isin(st[last + 1:], ["model", "relocalised"]))
    return int(hit[0]) if len(hit) else None


#: frames of the default-suite 640x480 sequences (short; blackout: 11 frames after the blur burst).
#: Faster still (turntable 30, carried 32 frames: 12 deg and more per frame) is not met yet: the
#: turntable is not re-acquired, one relocalised pose of the carried object is 1.07 % off
SHORT_640 = {"turntable": 40, "carried": 40, "leave": 45, "occluder": 30, "blackout": 42}


@pytest.fixture(scope="session")
def seq640(tmp_path_factory):
    cache = {}

    def get(scenario, frames):
        if (scenario, frames) not in cache:
            cache[scenario, frames] = _synth(tmp_path_factory, scenario, frames, 640, 480)
        return cache[scenario, frames]
    return get


def _check_issue_bounds(seq, tmp_path):
    """The issue's bounds on one sequence in the default mode (module docstring)."""
    s, st, rel, deg, truth = _track(seq, "auto", tmp_path / "t.txt")
    ok = _settled(truth)
    a0 = int(np.flatnonzero(~ok)[0])
    assert (st[:a0] == "model").all()
    assert np.nanmax(rel[:a0]) < 0.005 and np.nanmax(deg[:a0]) < 1.0  # the premise: still error << the bound
    out = np.isin(st, ["model", "slam", "relocalised"])
    assert np.isfinite(rel[out]).all()
    wrong = np.flatnonzero(out & ((rel > 0.01) | (deg > 2.0)))
    assert not len(wrong), [(int(k), st[k], round(100 * rel[k], 2), round(deg[k], 2)) for k in wrong]
    k = _reacquired_after_event(st, truth)
    assert k is not None and k <= 10, k
    return s, st, truth


def _scenario_checks(scenario, st, truth):
    moving = np.array([r["object_moving"] == "1" for r in truth])
    if scenario in ("turntable", "carried"):
        assert not (st[moving] == "slam").any()  # no map pose of the still room given as the moving object's
    if scenario == "leave":
        gone = np.array([float(r["in_view"]) == 0.0 for r in truth])
        assert gone.any() and (st[gone] == "lost").all()  # nothing of it in the view: no pose
    if scenario == "blackout":
        black = np.array([r["black"] == "1" for r in truth])
        assert (st[black] == "lost").all()  # nothing to see: nothing output


#: the default suite keeps leave and occluder (re-acquisition after leaving and after an occluder, the
#: issue's two hardest); the others run with -m slow (suite time: 3 min)
SLOW_SHORT = ("turntable", "carried", "blackout")


@pytest.mark.parametrize("scenario", [pytest.param(sc, marks=pytest.mark.slow) if sc in SLOW_SHORT else sc
                                      for sc in SHORT_640])
def test_issue_bounds_640_short(seq640, tmp_path, scenario):
    """Default suite: every dynamic scenario, short, at 640x480: the issue's 1 % / 2 deg bound on
    every output pose and re-acquisition within 10 frames."""
    s, st, truth = _check_issue_bounds(seq640(scenario, SHORT_640[scenario]), tmp_path)
    _scenario_checks(scenario, st, truth)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", list(SHORT_640))
def test_issue_bounds_640_full_length(seq640, tmp_path, scenario):
    """The full-length sequences (``DEFAULT_FRAMES_DYNAMIC``) at 640x480, same bounds."""
    from mst.pipeline.synth.dynamic import DEFAULT_FRAMES_DYNAMIC

    s, st, truth = _check_issue_bounds(seq640(scenario, DEFAULT_FRAMES_DYNAMIC[scenario]), tmp_path)
    _scenario_checks(scenario, st, truth)


@pytest.fixture(scope="module")
def turntable(tmp_path_factory):
    return _synth(tmp_path_factory, "turntable", 80)


_BUDGET_320 = pytest.mark.xfail(strict=True, reason=(
    "sessions 5-6: at 320x240 the error budget refuses still-object poses as 'pose uncertain' (2 sigma "
    "~1.7 % of the nearest-vertex distance, median) and it is right to: measured against the truth (turntable, "
    "still frames 0-23) the poses are 0.89 % off (median), 1.99 % (max), the covariance is not "
    "pessimistic (err / sigma 1.35 with the cluster-robust covariance, 1.66 classical); these tests ask "
    "every still frame to be output, which the issue's 1 % bound does not allow at this resolution "
    "(640x480: 0.08 % off, the default-suite variants pass). Open: the moving edges' accuracy at 320x240"))


@_BUDGET_320
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["auto", "mono"])
def test_turntable_no_map_pose_while_the_object_turns(turntable, tmp_path, mode):
    s, st, rel, deg, truth = _track(turntable, mode, tmp_path / "t.txt")
    moving = np.array([r["object_moving"] == "1" for r in truth])
    a0 = int(np.flatnonzero(moving)[0])
    bound = 2.0 * np.nanmax(rel[:a0])  # the tracker's own error on the still object, x2
    out = st != "lost"
    assert (st[:a0] == "model").all()
    # every output pose is right: no map (SLAM) pose of the still room given as the turning object's
    assert np.nanmax(rel[out]) <= bound and np.nanmax(deg[out]) < 2.0
    assert not (st[moving] == "slam").any()
    # the object at rest again in full view (its side turned 90 deg): re-acquired within 10 frames
    # (the default: from keypoints of views rendered with the learned texture, turned by 30-90 deg)
    k = _reacquired_within(st, truth)
    assert k is not None and k <= 10


@_BUDGET_320
@pytest.mark.slow
def test_occluder_no_wrong_pose_and_back_within_10_frames(tmp_path_factory, tmp_path):
    seq = _synth(tmp_path_factory, "occluder", 60)
    s, st, rel, deg, truth = _track(seq, "auto", tmp_path / "t.txt")
    occ = np.array([float(r["occluded_fraction"]) > 0.02 for r in truth])
    a0 = int(np.flatnonzero(occ)[0])
    out = st != "lost"
    assert (st[:a0] == "model").all()
    assert np.nanmax(rel[out]) <= 2.0 * np.nanmax(rel[:a0]) and np.nanmax(deg[out]) < 2.0
    # after the occluder has passed, the model pose is back within 10 frames
    after = np.flatnonzero(occ)[-1] + 1
    assert (st[after:after + 10] == "model").any()


@pytest.mark.slow
def test_blackout_relocalised_and_blur_bridged(tmp_path_factory, tmp_path):
    from mst.pipeline.tracking.relocalise import RelocConfig

    seq = _synth(tmp_path_factory, "blackout", 60)
    s, st, rel, deg, truth = _track(seq, "auto", tmp_path / "t.txt")
    black = np.array([r["black"] == "1" for r in truth])
    a0 = int(np.flatnonzero(black)[0])
    out = st != "lost"
    assert (st[black] == "lost").all()  # nothing to see: nothing output
    back = int(np.flatnonzero(black)[-1]) + 1
    assert "relocalised" in st[back:back + RelocConfig().every + 1]
    assert np.nanmax(rel[out]) <= 2.0 * np.nanmax(rel[:a0]) and np.nanmax(deg[out]) < 2.0


@_BUDGET_320
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["auto", "mono"])
def test_carried_no_map_pose_of_the_still_room(tmp_path_factory, tmp_path, mode):
    """The object carried along a path while the room (the SLAM map) stays: before the image check
    of map poses the default output 20 `slam` poses of the room up to 25 % / 18 deg off."""
    seq = _synth(tmp_path_factory, "carried", 80)
    s, st, rel, deg, truth = _track(seq, mode, tmp_path / "t.txt")
    moving = np.array([r["object_moving"] == "1" for r in truth])
    a0 = int(np.flatnonzero(moving)[0])
    out = st != "lost"
    assert (st[:a0] == "model").all()
    assert np.nanmax(rel[out]) <= 2.0 * np.nanmax(rel[:a0]) and np.nanmax(deg[out]) < 2.0
    assert not (st[moving] == "slam").any()
    k = _reacquired_within(st, truth)
    assert k is not None and k <= 10


@pytest.fixture(scope="module")
def leave(tmp_path_factory):
    return _synth(tmp_path_factory, "leave", 90)


@_BUDGET_320
@pytest.mark.slow
def test_leave_moved_and_back_no_wrong_pose(leave, tmp_path):
    """The object slides out of the view, is turned 30 deg and moved unseen, and slides back in:
    the default outputs no pose while it is gone and only right poses after it is back.
    (``--slam off`` re-acquires sooner, 0 frames after it is at rest, but outputs relocalised
    poses up to 3.5 % off: beyond 2x its still-frame error.)"""
    s, st, rel, deg, truth = _track(leave, "auto", tmp_path / "t.txt")
    moving = np.array([r["object_moving"] == "1" for r in truth])
    gone = np.array([float(r["in_view"]) == 0.0 for r in truth])
    a0 = int(np.flatnonzero(moving)[0])
    out = st != "lost"
    assert (st[:a0] == "model").all()
    assert (st[gone] == "lost").all()  # nothing of it in the view: no pose (a map pose of the room is none)
    assert np.nanmax(rel[out]) <= 2.0 * np.nanmax(rel[:a0]) and np.nanmax(deg[out]) < 2.0
    k = _reacquired_within(st, truth)
    assert k is not None and k <= 10  # was 18 frames before the rendered views and the widened refinement
