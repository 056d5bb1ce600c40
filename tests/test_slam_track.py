"""``mst track --slam rgbd|mono`` end to end on ``mst synth`` sequences (320x240 to stay fast).

The same checks at 640x480 with the issue's bounds (error < 0.2 % within 5 frames of the model's
return, fast x8/x10 mean <= 1 %) are in ``eval/bench/slam.py``: at 320x240 the edge tracker's own
noise is ~0.3-0.5 % of the distance, so the bounds here are looser.
"""

from __future__ import annotations

import numpy as np
import pytest
from drift_helpers import budget_errors, budget_track, calibrated_share

from mst.eval.bench.slam import SAMPLE_MODEL, out_of_view, recovery_frames, trajectory_errors


def _synth(tmp_path_factory, name, scenario, **kw):
    from mst.pipeline.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("slam_track") / name
    synthesize(scenario, SAMPLE_MODEL, out, SynthConfig(width=320, height=240, **kw))
    return out


#: (sequence folder, mode) -> (summary, trajectory file) of the default-settings runs: several tests
#: check different properties of one run (the corridor in rgbd and mono, the x10 orbit in rgbd), so
#: each run is made once per module (suite time) and its files are read by each test
_RUNS: dict = {}


def _run(seq, mode, out_dir):
    """``mst track`` of ``seq`` in ``mode`` with the default settings (``--json`` written too)."""
    from mst.pipeline.tracking import TrackConfig, run_track

    key = (str(seq), mode)
    if key not in _RUNS:
        out = out_dir / f"{seq.name}-{mode}.txt"
        s = run_track(seq / "rgb", seq / "model.obj", seq / "camera.json", seq / "cMo" / "000000.txt", out,
                      TrackConfig(aid=mode), depth_dir=seq / "depth" if mode == "rgbd" else None, fps=30.0,
                      write_json=True)
        _RUNS[key] = (s, out)
    return _RUNS[key]


@pytest.fixture(scope="module")
def runs_dir(tmp_path_factory):
    yield tmp_path_factory.mktemp("slam_track_runs")
    _RUNS.clear()


def _track(seq, mode, out_dir):
    s, out = _run(seq, mode, out_dir)
    return s, trajectory_errors(seq, out)


def _track_budget(seq, mode, out_dir, budget: bool = True):
    """:func:`drift_helpers.budget_track`; the budget-on run is the shared default-settings run."""
    if not budget:
        key = (str(seq), mode, "nobudget")
        if key not in _RUNS:
            _RUNS[key] = budget_track(seq, mode, out_dir / f"{seq.name}-{mode}-nobudget.txt", budget=False)
        return _RUNS[key]
    s, out = _run(seq, mode, out_dir)
    return s, budget_errors(seq, out)


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    return _synth(tmp_path_factory, "corridor", "corridor", frames=90)


@pytest.fixture(scope="module")
def fast(tmp_path_factory):
    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    return {d: _synth(tmp_path_factory, f"fast{d}", "fast", base="orbit", drop=d, frames=30) for d in (8, 10)}


def test_corridor_rgbd_carries_the_pose_while_the_model_is_away(corridor, runs_dir):
    hidden = out_of_view(corridor)
    assert hidden.sum() >= 30
    summ, e = _track(corridor, "rgbd", runs_dir)
    _, e_off = _track(corridor, "off", runs_dir)
    st = e["status"]
    assert summ["aid"] == "rgbd"
    # while the model is away the map runs, but its poses are output only within the drift budget
    # (1 % / 2 deg at a 2-sigma bound): at 320x240 the edge poses that anchor it are uncertain to
    # 0.3-0.5 % (1 sigma), so the bound is near the budget (until session 18 most of the stretch was
    # withheld, `lost` with aid `drift-budget`; since session 19's root-sum-square of the independent
    # parts it is output, 0.1-0.8 % off, the bound 1.2-4x the error). The frames not output are the budgets', no others:
    # the map's drift budget, or the edge pose's own (uncertain / ambiguous: the corridor's last
    # frames see 40-47 samples, 2 sigma = 2 % of the distance)
    refused = summ["drift_budget_frames"] + summ["pose_budget_frames"] + summ["ambiguous_frames"]
    assert ((st == "lost") == np.isin(e["frame"], refused)).all()
    assert ((st[hidden] == "slam") | (st[hidden] == "lost")).all()
    # the model pose takes over again after the return; no re-initialisation was needed
    ret = np.flatnonzero(hidden)[-1] + 1
    # (or refused by the edge pose's own budget: the corridor's last frames see 40-47 samples and their
    # fits claim 2 sigma = 2 % of the distance; at 320x240 that covariance is ~2x pessimistic, a
    # cost of the honest rule, measured in the closing note of session 5)
    after = st[ret + 5:]
    own = np.isin(e["frame"][ret + 5:], summ["pose_budget_frames"] + summ["ambiguous_frames"])
    assert (after[~own] == "model").mean() > 0.8 and own.mean() < 0.5
    assert np.nanmax(e["rel"][hidden]) < 0.01          # drift while away: < 1 % of the distance
    assert np.nanmax(e["rel"][ret + 5:]) < 0.008       # 320x240 edge-tracker noise level
    assert recovery_frames(e["rel"], hidden, bound=0.008) <= 5
    # the edge tracker alone does far worse on the same frames: it loses them, and (health score)
    # it reports them lost instead of outputting poses locked onto the floor/wall texture
    assert (e_off["status"] == "lost").sum() + np.nansum(e_off["rel"] > 0.05) > 10
    assert np.nanmax(e_off["rel"]) < 0.01 and np.nanmax(e_off["deg"]) < 2.0  # the bound: 1 % or 2 deg
    # where both give a pose, the aid costs no accuracy: the paired difference is within two of its
    # standard errors (over all frames the aid's mean also counts its drift while the model is away,
    # where the edge tracker has no pose at all)
    both = np.isfinite(e["rel"]) & np.isfinite(e_off["rel"])
    d = e["rel"][both] - e_off["rel"][both]
    assert both.sum() >= 10 and d.mean() <= 2.0 * d.std(ddof=1) / np.sqrt(len(d))


@pytest.mark.parametrize("mode", ["mono", "auto"])
def test_corridor_mono_rejects_wrong_edge_poses_on_the_return(corridor, runs_dir, mode):
    """Mono on the same corridor: the model comes back into a drifted SLAM prediction.

    Starting from it, the edge tracker converges onto floor/wall-texture edges for several frames
    (poses 35-46 % of the distance off that pass the absolute health tests); those must not be output
    as ``model`` nor reset the map. At 320x240 the mono map's scale drifts while the model is away (the
    SLAM pose is ~25 % off at the return), so here the pose stays the SLAM's; the 640x480 bench row
    ``corridor mono`` measures the actual re-acquisition (back under 0.2 % within a few frames).
    """
    import csv

    hidden = out_of_view(corridor)
    summ, e = _track(corridor, mode, runs_dir)
    st = e["status"]
    assert summ["aid"] == {"mono": "mono", "auto": "mono-standby"}[mode]
    if mode == "auto":  # the default: the mono aid woke before the model left the view
        assert summ["aid_wakes"] >= 1 and min(summ["aid_wake_frames"]) < np.flatnonzero(hidden)[0]
    # while the model is away the map runs, but its poses (the scale drifting to ~50 % of the
    # distance here) are far beyond the drift budget: withheld, `lost` with aid `drift-budget`
    # (test_slam_drift.py: the bound covers the measured error)
    rows = list(csv.DictReader(open(_run(corridor, mode, runs_dir)[1].with_suffix(".csv"))))
    aid = np.array([r["aid"] for r in rows])
    assert not (st[hidden] == "model").any() and (aid[hidden] == "drift-budget").mean() > 0.9
    assert np.isin(np.flatnonzero(aid == "drift-budget"), summ["drift_budget_frames"]).all()
    ret = np.flatnonzero(hidden)[-1] + 1
    # ... and every pose output as a model pose after the return is a correct one (320x240 edge noise)
    after = np.arange(len(st)) >= ret
    assert np.all(e["rel"][after & (st == "model")] < 0.01)
    # ... and no map pose either, before or after the return: the drifted map (its pose 45-63 % of
    # the distance off at the return) is beyond its budget and contradicted by the image
    assert np.all(e["rel"][st != "lost"] < 0.01)


def test_the_summary_names_the_lost_frames_that_the_budgets_withheld(corridor, runs_dir):
    """``mst track``'s summary says why the lost frames were lost where a pose existed but was withheld:
    the mono corridor's map poses beyond the drift budget (every one of them a lost frame)."""
    from mst.cli.track import withheld_line

    s, e = _track(corridor, "mono", runs_dir)
    lost = e["frame"][e["status"] == "lost"]
    drift = s["drift_budget_frames"]
    assert len(drift) > 0 and np.isin(drift, lost).all()
    line = withheld_line(s.optional, len(lost), 0.01, 2.0)
    assert line.startswith(f"of the {len(lost)} lost frames, withheld: {len(set(drift))} map poses beyond the drift "
                           "budget (2 sigma over 1 % of the distance or 2 deg"), line
    assert withheld_line({}, len(lost), 0.01, 2.0) == "" and withheld_line(s.optional, 0, 0.01, 2.0) == ""


# ---------------------------------------------------------------------------- drift budget (320x240)
@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_corridor_predicted_bound_covers_the_measured_error(corridor, runs_dir, mode):
    """With the budget lifted every map pose is output with its predicted bound: the bound (2 sigma)
    must cover the measured error on >= 95 % of them (a 2-sigma bound of an honest Gaussian error
    covers 95 %), the rgbd aid's map (0.1-0.6 % off) and the mono map whose scale drifts to ~50 %
    of the distance alike."""
    _, e = _track_budget(corridor, mode, runs_dir, budget=False)
    assert calibrated_share(e) >= 0.95


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_corridor_map_poses_carry_their_drift_covariance(corridor, runs_dir, mode):
    """``traj.cov.csv`` holds each map pose's propagated drift covariance (issue #15: ``slam`` frames
    with their growing uncertainty, for ``mst nav fuse`` and ``mst refine`` to weigh): every ``slam``
    row has one; its rotation 2 sigma is the drift budget's own bound (the JSON's ``slam_uncertainty``,
    the same number), its camera-position 2 sigma covers the measured error on >= 95 % of them (an
    honest Gaussian's 2 sigma covers 95 %), and the stretch's last map pose is more uncertain than its
    first (the uncertainty grows away from the model anchor). The budget lifted: every map pose output."""
    import csv

    from mst.core.trajectory import read_tum
    from mst.pipeline.slam.config import SlamConfig

    _, e = _track_budget(corridor, mode, runs_dir, budget=False)
    out = runs_dir / f"{corridor.name}-{mode}-nobudget.txt"
    rows = {int(r["frame"]): r for r in csv.DictReader(open(out.with_suffix(".cov.csv")))}
    t, T = read_tum(out)
    _, Tg = read_tum(corridor / "gt.txt")
    at = {int(k): i for i, k in enumerate(np.rint(t * 30.0).astype(int))}
    sl = np.flatnonzero(e["status"] == "slam")
    assert len(sl) >= 10
    k2 = SlamConfig().drift_sigmas
    sig_m, err_m = [], []
    for i in sl:
        f = int(e["frame"][i])
        r = rows[f]
        assert r["status"] == "slam" and r["c00"], f
        C = np.array([float(r[f"c{a}{b}"]) for a in range(6) for b in range(6)]).reshape(6, 6)
        assert np.linalg.eigvalsh(C).min() > 0, f
        np.testing.assert_allclose(k2 * np.degrees(np.sqrt(np.trace(C[3:, 3:]))), e["pred"][i, 1], rtol=1e-4)
        sig_m.append(np.sqrt(sum(float(r[f"std_{a}_m"]) ** 2 for a in "xyz")))
        err_m.append(np.linalg.norm(T[at[f], :3, 3] - Tg[f, :3, 3]))
    sig_m, err_m = np.array(sig_m), np.array(err_m)
    assert np.mean(err_m <= k2 * sig_m) >= 0.95, (err_m / sig_m).max()
    assert sig_m[-1] > sig_m[0], sig_m


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_corridor_no_map_pose_beyond_the_budget(corridor, runs_dir, mode):
    """Budget on (the default): no output pose off by more than 1 % of the distance or 2 deg; the map
    poses withheld are marked ``drift-budget``, counted in --json, and the model frames before the
    stretch are unchanged. At 320x240 the edge poses themselves are uncertain to ~0.3-0.5 % (1 sigma,
    their covariance, which matches their measured error), so a 2-sigma bound of a map anchored on
    them is near 1 % already: the mono stretch is withheld here, the rgbd map (0.1-0.8 % off) is
    output where its own bound is within the budget (640x480: the slow test below)."""
    s, e = _track_budget(corridor, mode, runs_dir)
    hidden = out_of_view(corridor)
    out = e["status"] != "lost"
    assert np.all(e["rel"][out] <= 0.01) and np.all(e["deg"][out] <= 2.0)
    budget = e["aid"] == "drift-budget"
    assert (e["status"][budget] == "lost").all()
    assert s["drift_budget_frames"] == [int(f) for f in e["frame"][budget]]
    # the rule itself: a map pose is output exactly where its predicted bound is within the budget
    from mst.pipeline.tracking import TrackConfig

    cfg = TrackConfig().slam
    slam = e["status"] == "slam"
    within = (e["pred"][:, 0] <= cfg.drift_budget_rel) & (e["pred"][:, 1] <= cfg.drift_budget_deg)
    assert (budget | slam)[hidden].mean() > 0.9 and within[slam].all() and not within[budget].any()
    if mode == "mono":  # the mono map's scale drifts to ~25 % of the distance here: beyond the budget
        assert budget[hidden].mean() > 0.9
    assert (e["status"][: np.flatnonzero(hidden)[0] - 3] == "model").all()


#: session 6 (issue #12, the cluster-robust edge covariance): on the x10 orbit in the default mode frame 22
#: was 0.81 % off, its 2 sigma 1.32 % of the distance, so the error budget (2 sigma within 1 %) refused it
#: (a strict xfail here until session 19). Session 19: the awake aid's map, beyond its (conservative)
#: drift budget on nearly every frame, had been re-anchored unfused onto each edge pose instead of
#: gated and fused with it (mst.pipeline.slam.policy.AidPolicy._judge); fused, its prediction starts
#: frame 22 where the fit lands 0.51 % off (the sequence's worst), within its budget: 30 of 30 frames


@pytest.mark.parametrize("drop", [8, 10])
@pytest.mark.parametrize("mode", ["rgbd", "mono", "auto"])
def test_fast_orbit_every_frame_tracked(fast, runs_dir, drop, mode):
    seq = fast[drop]
    summ, e = _track(seq, mode, runs_dir)
    assert summ["lost"] == 0 and summ["tracked"] == summ["frames"] == 30
    assert np.nanmean(e["rel"]) <= 0.01
    assert np.nanmax(e["rel"]) <= 0.02


def test_fast_orbit_edge_only_is_worse(fast, runs_dir):
    """Reference: the edge tracker alone on the x10 sequence (reported, and worse than with SLAM)."""
    _, e_off = _track(fast[10], "off", runs_dir)
    _, e_slam = _track(fast[10], "rgbd", runs_dir)
    bad_off = (e_off["status"] == "lost").sum() + np.nansum(e_off["rel"] > 0.01)
    bad_slam = (e_slam["status"] == "lost").sum() + np.nansum(e_slam["rel"] > 0.01)
    assert bad_slam < bad_off


def test_mono_landmarks_written_and_lie_on_the_scene(fast, tmp_path):
    """``--landmarks``: the mono SLAM map is written as PLY in model coordinates, on the scene surfaces."""
    import open3d as o3d

    from mst.meshtools.formats import load_triangles
    from mst.pipeline.fusion import read_ply_points
    from mst.pipeline.tracking import TrackConfig, run_track

    seq = fast[8]
    lm = tmp_path / "map.ply"
    s = run_track(seq / "rgb", seq / "model.obj", seq / "camera.json", seq / "cMo" / "000000.txt", tmp_path / "t.txt",
                  TrackConfig(aid="mono"), fps=30.0, landmarks_path=lm)
    X, _ = read_ply_points(lm)
    assert s["landmarks"] == len(X) >= 50
    V, F = load_triangles(seq / "scene.ply")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(V.astype(np.float32), F.astype(np.uint32))
    d = scene.compute_distance(X.astype(np.float32)).numpy()
    dist_cam = np.linalg.norm(X - X.mean(0), axis=1).mean()
    # triangulated points: most within 2 % of the scene scale of a real surface
    assert np.median(d) < 0.02 * dist_cam
    assert (d < 0.05 * dist_cam).mean() > 0.8
