"""Issues 11/12: the gates that keep a wrong edge pose from being output as ``model``.

* the conditioning gate (:data:`MAX_POSITION_SIGMA_REL`): a pose whose own camera-centre sigma is
  more than 0.5 % of the distance to the model is not output, and the reason names the cause;
* the stale-start gate (:data:`STALE_HELD_POSE_S`): after 1 s without an output pose only a
  relocalised pose re-acquires;
* the first frame's two fits (:data:`FIRST_FRAME_AGREE_SIGMA`);
* the real case behind them (slow): Delft at 250 m above the ground, 640x480, where one building
  ~60 px wide gave `model` frames 1-10 % off (29 m at frame 0 from an exact initial pose, the
  reported sigma 1.1-1.7 m a coordinate): now no pose is output beyond 1 % and the run says why.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest

from mst.core.poses import se3_exp
from mst.pipeline.tracking.edge_tracker import FrameResult
from mst.pipeline.tracking.session import (
    FIRST_FRAME_AGREE_SIGMA,
    MAX_POSITION_SIGMA_REL,
    STALE_HELD_POSE_S,
    TrackingPolicy,
)


def _fr(sigma_m: float, T=None) -> FrameResult:
    """A healthy edge pose with an isotropic position covariance of ``sigma_m`` over the 3 axes."""
    cov = np.diag([sigma_m**2 / 3] * 3 + [1e-8] * 3)
    T = T if T is not None else se3_exp(np.array([0.0, 0.0, 100.0, 0.0, 0.0, 0.0]))
    return FrameResult(T, True, 50, 45, 0.1, 3.0, np.linalg.inv(cov), cov)


def test_conditioning_gate_refuses_a_pose_weaker_than_half_the_budget():
    p = TrackingPolicy(np.eye(4), search_range_px=8)
    dist = 300.0
    ok = _fr(0.9 * MAX_POSITION_SIGMA_REL * dist)
    assert p.gate_conditioning(ok, True, lambda T, enough: dist) and ok.reason == "" and ok.healthy
    weak = _fr(1.1 * MAX_POSITION_SIGMA_REL * dist)
    assert not p.gate_conditioning(weak, True, lambda T, enough: dist)
    assert not weak.healthy and "weakly constrained" in weak.reason and "too small in the image" in weak.reason
    assert p.n_weak == 1
    # an unhealthy pose stays unhealthy, its reason untouched; a pose without covariance is not judged
    bad = _fr(10.0)
    bad.reason = "inliers 20%"
    assert not p.gate_conditioning(bad, False, lambda T, enough: dist) and bad.reason == "inliers 20%"
    nocov = _fr(10.0)
    nocov.cov = None
    assert p.gate_conditioning(nocov, True, lambda T, enough: dist)


def test_conditioning_distance_lower_bound_is_the_bounding_box():
    """The distance is the nearest model vertex; the bounding box stands in only where it already
    suffices (a lower bound), so that a 50k-polygon city costs no pass over its vertices."""
    from types import SimpleNamespace

    from mst.pipeline.tracking.session import _model_distance_at_least, model_distance

    V = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 5]], float)
    tr = SimpleNamespace(geom=SimpleNamespace(vertices=V))
    T = se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    T[:3, 3] = -np.array([5.0, 5.0, 105.0])  # camera centre (5, 5, 105), R = I
    exact = model_distance(tr, T)
    assert exact == pytest.approx(np.linalg.norm([5, 5, 100]))
    assert _model_distance_at_least(tr, T, 1.0) == pytest.approx(100.0)  # the box's distance: >= 1 m, <= exact
    assert _model_distance_at_least(tr, T, 101.0) == pytest.approx(exact)  # not enough: the exact one


def test_stale_start_gate_after_one_second_without_output():
    p = TrackingPolicy(np.eye(4), search_range_px=8)
    p.frame_done(_fr(0.1), 0.0, output=True)
    fresh = _fr(0.1)
    assert p.gate_stale(fresh, True, False, STALE_HELD_POSE_S - 0.01)
    stale = _fr(0.1)
    assert not p.gate_stale(stale, True, False, STALE_HELD_POSE_S + 0.5)
    assert not stale.healthy and "stale start" in stale.reason and "relocaliser" in stale.reason
    # a relocalised pose (verified on its own image) re-acquires however long the loss
    assert p.gate_stale(_fr(0.1), True, True, 10.0)
    # a lost frame does not refresh the clock; an output one does
    p.frame_done(_fr(0.1), 5.0, output=False)
    assert p.t_output == 0.0
    p.frame_done(_fr(0.1), 5.0, output=True)
    assert p.gate_stale(_fr(0.1), True, False, 5.5)


def test_first_frame_keeps_the_plain_fit_when_the_tolerant_one_moved_many_sigma():
    """The session's first frame: the tolerant fit is replaced by the plain fit from the initial pose
    when they disagree by more than FIRST_FRAME_AGREE_SIGMA under the tolerant fit's covariance."""
    from mst.pipeline.tracking.session import TrackingSession

    T0 = se3_exp(np.array([0.0, 0.0, 100.0, 0.0, 0.0, 0.0]))
    sig = 0.1  # m, per axis

    class Tracker:
        def __init__(self, dx):
            self.dx = dx

        def track(self, gray, T_init, recover=False, first=False):
            return _fr(sig * np.sqrt(3), T=T_init.copy())  # the plain fit: at the initial pose

    for dx_sigma, kept_plain in ((0.5 * FIRST_FRAME_AGREE_SIGMA, False), (2.0 * FIRST_FRAME_AGREE_SIGMA, True)):
        s = TrackingSession(Tracker(dx_sigma), TrackingPolicy(T0, search_range_px=8))
        T_far = se3_exp(np.array([dx_sigma * sig, 0, 0, 0, 0, 0])) @ T0
        tolerant = _fr(sig * np.sqrt(3), T=T_far)
        out = s._first_frame_mode(np.zeros((4, 4), np.uint8), T0, tolerant)
        assert (out is not tolerant) == kept_plain
        assert np.allclose(out.T_cam_model, T0 if kept_plain else T_far)


@pytest.mark.slow
def test_delft_250m_no_model_pose_beyond_one_percent(shared_data, tmp_path):
    """Delft at 250 m, 640x480, 60 frames of the straight flight, default and edges only: every output
    pose within 1 % of its distance to the model (nearest vertex) and 2 deg, or no pose at all with
    the cause named. Before the gates: 23 (default) / 26 (edges only) of 60 `model` frames 1-10 % off."""
    from test_track_uav import _cli, _prepare

    from mst import InputError
    from mst.core.poses import pose_error
    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import load_model
    from mst.pipeline.tracking import TrackConfig, run_track

    seq = tmp_path / "seq"
    _cli("synth", "uav", "--model", shared_data / "cityjson/delft_1b.json", "-o", seq, "--frames", 240,
         "--distance", 250, "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, tmp_path)
    V = load_model(m).vertices
    tg, Tg = read_tum(seq / "gt.txt")
    for slam in ("auto", "off"):
        out = tmp_path / f"traj_{slam}.txt"
        try:
            run_track(seq / "rgb", m, seq / "camera.json", tmp_path / "p0.txt", out, TrackConfig(aid=slam), fps=30,
                      frames="0:60")
        except InputError as e:  # nothing output: the message names the cause, not the pose
            assert "weakly constrained" in str(e) and "too small" in str(e), str(e)
            continue
        te, Te = read_tum(out)
        idx = np.searchsorted(np.round(tg, 6), np.round(te, 6))
        err = np.linalg.norm(Te[:, :3, 3] - Tg[idx, :3, 3], axis=1)
        dist = np.linalg.norm(Tg[idx][:, None, :3, 3] - V[None], axis=2).min(1)
        assert np.all(err <= 0.01 * dist), (slam, err / dist)
        assert np.all(pose_error(Te, Tg[idx])[1] <= 2.0)
        rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
        assert any("weakly constrained" in r["reason"] for r in rows if r["status"] == "lost")
