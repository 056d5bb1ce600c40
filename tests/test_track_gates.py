"""Issues 11/12: wrong `model` poses from the first frame's search, and Delft at long range.

* the first frame's two fits (:data:`FIRST_FRAME_AGREE_SIGMA`): the tolerant multi-pass search
  from the user's pose is replaced by the plain fit from it when they disagree by many sigma (a
  multi-modal image around the user's pose; unit test here, the FPV pass in test_track_uav.py);
* Delft at 250 m above the ground, 640x480 (slow), where one building ~60 px wide (46-79 edge
  samples) gave frame 0 29 m (10 %) off from an exact initial pose: now within 1 %. The later
  frames drifted 1-3 % as `model`; their own 2-sigma bound is 1.3-2.8 % of the distance, so the
  error budget (test_track_budget.py) refuses them: `lost`, "pose uncertain".
"""

from __future__ import annotations

import numpy as np
import pytest

from mst.core.poses import se3_exp
from mst.pipeline.tracking.edge_tracker import FrameResult
from mst.pipeline.tracking.session import FIRST_FRAME_AGREE_SIGMA, TrackingPolicy


def _fr(sigma_m: float, T=None) -> FrameResult:
    """A healthy edge pose with an isotropic position covariance of ``sigma_m`` over the 3 axes (the
    classical one: information ``W`` = rms^2 cov^-1 for its 0.1 px residual RMS)."""
    cov = np.diag([sigma_m**2 / 3] * 3 + [1e-8] * 3)
    T = T if T is not None else se3_exp(np.array([0.0, 0.0, 100.0, 0.0, 0.0, 0.0]))
    return FrameResult(T, True, 50, 45, 0.1, 3.0, 0.1**2 * np.linalg.inv(cov), cov)


def test_first_frame_keeps_the_plain_fit_when_the_tolerant_one_moved_many_sigma():
    """The session's first frame: the tolerant fit is replaced by the plain fit from the initial pose
    when they disagree by more than FIRST_FRAME_AGREE_SIGMA under the tolerant fit's classical covariance."""
    from mst.pipeline.tracking.session import TrackingSession

    T0 = se3_exp(np.array([0.0, 0.0, 100.0, 0.0, 0.0, 0.0]))
    sig = 0.1  # m, per axis

    class Tracker:
        def __init__(self, dx):
            self.dx = dx

        def track(self, gray, T_init, recover=False, first=False, klt=True):
            return _fr(sig * np.sqrt(3), T=T_init.copy())  # the plain fit: at the initial pose

    for dx_sigma, kept_plain in ((0.5 * FIRST_FRAME_AGREE_SIGMA, False), (2.0 * FIRST_FRAME_AGREE_SIGMA, True)):
        s = TrackingSession(Tracker(dx_sigma), TrackingPolicy(T0, search_range_px=8))
        T_far = se3_exp(np.array([dx_sigma * sig, 0, 0, 0, 0, 0])) @ T0
        tolerant = _fr(sig * np.sqrt(3), T=T_far)
        out = s._first_frame_mode(np.zeros((4, 4), np.uint8), T0, tolerant)
        assert (out is not tolerant) == kept_plain
        assert np.allclose(out.T_cam_model, T0 if kept_plain else T_far)


@pytest.fixture(scope="module")
def delft250(shared_data, tmp_path_factory):
    from test_track_uav import _cli, _prepare

    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import load_model

    d = tmp_path_factory.mktemp("delft250")
    seq = d / "seq"
    _cli("synth", "uav", "--model", shared_data / "cityjson/delft_1b.json", "-o", seq, "--frames", 240,
         "--distance", 250, "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, d)
    return seq, d, m, load_model(m).vertices, read_tum(seq / "gt.txt")


def _track_delft(delft250, slam: str, frames: str):
    """Relative position error (of the nearest-vertex distance) and rotation error (deg) per output pose."""
    from mst.core.poses import pose_error
    from mst.core.trajectory import read_tum
    from mst.pipeline.tracking import TrackConfig, run_track

    seq, d, m, V, (tg, Tg) = delft250
    out = d / f"traj_{slam}_{frames.replace(':', '_')}.txt"
    from mst import InputError

    try:
        s = run_track(seq / "rgb", m, seq / "camera.json", d / "p0.txt", out, TrackConfig(aid=slam), fps=30, frames=frames)
    except InputError as e:
        # no frame output: every one refused (frame 0 included: the first frame is judged by the
        # error budget too); the run names the cause and writes nothing
        assert "frame 0: pose uncertain" in str(e) and not out.exists(), e
        return None, np.zeros(0), np.zeros(0)
    te, Te = read_tum(out)
    idx = np.searchsorted(np.round(tg, 6), np.round(te, 6))
    err = np.linalg.norm(Te[:, :3, 3] - Tg[idx, :3, 3], axis=1)
    dist = np.linalg.norm(Tg[idx][:, None, :3, 3] - V[None], axis=2).min(1)
    return s, err / dist, pose_error(Te, Tg[idx])[1]


@pytest.mark.slow
@pytest.mark.parametrize("slam", ["auto", "off"])
def test_delft_250m_first_frame_stays_near_an_exact_initial_pose(delft250, slam):
    """Frame 0 from the (exact) clicked pose: the tolerant search moved it 29 m (10 %, 27 sigma of its
    own covariance) in both modes; the plain fit is 0.74 m (0.25 %). Bound: the issue's 1 % / 2 deg.
    Since the first frame is judged by the error budget (its 2 sigma here 1.2 % of the distance) the
    run may also refuse it, with that cause (``_track_delft``); an output frame 0 is within the bound."""
    s, rel, deg = _track_delft(delft250, slam, "0:1")
    if s is not None:
        assert s["status_counts"]["model"] == 1
        assert rel[0] <= 0.01 and deg[0] <= 2.0, (rel, deg)


@pytest.mark.slow
def test_delft_250m_no_model_pose_beyond_one_percent(delft250):
    """26 of the 60 frames were `model` 1-3 % off (both modes), up to 5.6 sigma of their own
    covariance, whose 1-sigma is itself 0.6-1.4 % of the distance here: the image (one ~60 px
    building, 46-79 edge samples) does not pin the pose to the issue's 1 %. With the error budget
    (PoseBudget: 2 sigma within 1 % of the model distance, 2 deg) those frames are `lost` with their
    cause and counted in --json; every pose still output is within the bound."""
    import csv

    for slam in ("auto", "off"):
        s, rel, deg = _track_delft(delft250, slam, "0:60")
        if s is None:  # every frame refused by the budget, frame 0 included (its 2 sigma 1.2 %)
            continue
        assert np.all(rel <= 0.01) and np.all(deg <= 2.0), (slam, rel.max(), deg.max())
        rows = {int(r["frame"]): r for r in csv.DictReader(open(s["csv"]))}
        refused = s["pose_budget_frames"]
        # the building stays in view: every lost frame is the budget's, each with its cause in the CSV
        assert sorted(refused) == sorted(k for k, r in rows.items() if r["status"] == "lost"), slam
        assert refused and all(rows[k]["reason"].startswith("pose uncertain") for k in refused)
        assert s["model"] >= 1  # a run that outputs nothing fails instead (above)
