"""Issues 11/12: an edge pose is output as `model` only where its image pins it to the error budget
(:class:`mst.pipeline.tracking.session.PoseBudget`: the drift budget's 2 sigma within 1 % of the
model distance and 2 deg).

* uncertain: the pose's own covariance bound beyond the budget (Delft at 250 m, 640x480; slow test
  in test_track_gates.py);
* ambiguous: two healthy fits of one image beyond the budget apart, one from the motion prediction
  (checked when the pose lies far from it: Rotterdam FPV frame 5, the 40 m survey's turn frame) or,
  after a refused frame, from +-3 sigma along the fit's weakest direction (FPV frame 6);
* a refused pose is `lost` (reason, ``pose_budget_frames`` / ``ambiguous_frames``), and the next
  frame starts from it.

Unit tests with a stand-in tracker (no images): a camera 100 m from a model vertex, moving 0.1 m a
frame along x.
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import inv_T, se3_exp
from mst.pipeline.tracking.budget import REASON_AMBIGUOUS, REASON_UNCERTAIN, ModelDistance, PoseBudget
from mst.pipeline.tracking.edge_tracker import FrameResult
from mst.pipeline.tracking.session import TrackingPolicy, TrackingSession

D = 100.0  # m, camera to the model vertex


def _T(x: float) -> np.ndarray:
    """T_cam_model of a camera at (x, 0, -D) looking along +z at the vertex (0, 0, 0)."""
    return inv_T(se3_exp(np.array([x, 0.0, -D, 0.0, 0.0, 0.0])))


def _cx(T: np.ndarray) -> float:
    return float((-T[:3, :3].T @ T[:3, 3])[0])


def _fr(T, sigma_m=0.05, sigma_deg=0.01) -> FrameResult:
    cov = np.diag([sigma_m**2 / 3] * 3 + [np.radians(sigma_deg) ** 2] * 3)
    return FrameResult(T, True, 200, 180, 0.2, 5.0, np.linalg.inv(cov), cov)


def test_pose_uncertain_beyond_the_budget_is_refused():
    p = TrackingPolicy(_T(0.0), search_range_px=8, budget=PoseBudget())
    p.distance_m = lambda T: D
    # 2 sigma of the camera centre against 1 % of 100 m = 1 m; of the rotation against 2 deg
    assert p.beyond_budget(_fr(_T(0.0), sigma_m=0.45)) == ""
    assert p.beyond_budget(_fr(_T(0.0), sigma_m=0.55)).startswith(REASON_UNCERTAIN)
    assert p.beyond_budget(_fr(_T(0.0), sigma_deg=0.9)) == ""
    assert p.beyond_budget(_fr(_T(0.0), sigma_deg=1.1)).startswith(REASON_UNCERTAIN)
    assert TrackingPolicy(_T(0.0), search_range_px=8).beyond_budget(_fr(_T(0.0), sigma_m=5.0)) == ""  # no budget


def test_indefinite_covariance_is_refused_however_small_its_trace():
    """A fit whose covariance is not positive definite pins no direction it leaves out: refused, even
    where its trace is tiny (the pose had been output as `model` with no covariance written)."""
    p = TrackingPolicy(_T(0.0), search_range_px=8, budget=PoseBudget())
    p.distance_m = lambda T: D
    fr = _fr(_T(0.0), sigma_m=0.01)
    assert p.beyond_budget(fr) == ""
    v = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]) / np.sqrt(2.0)
    fr.cov = fr.cov - 1.5 * float(v @ fr.cov @ v) * np.outer(v, v)  # one negative eigenvalue, trace smaller
    assert np.linalg.eigvalsh(fr.cov).min() < 0 and np.trace(fr.cov) < np.trace(_fr(_T(0.0), sigma_m=0.01).cov)
    assert p.beyond_budget(fr).startswith(REASON_UNCERTAIN)
    fr.cov = np.diag([1e-6] * 5 + [0.0])  # singular: a zero variance
    assert p.beyond_budget(fr).startswith(REASON_UNCERTAIN)


def test_model_distance_is_a_lower_bound_within_5_percent():
    V = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    md = ModelDistance(V)
    assert np.isclose(md(_T(0.0)), D)
    for x in np.linspace(0.0, 30.0, 61):
        exact = float(np.linalg.norm(V - [x, 0.0, -D], axis=1).min())
        got = md(_T(x))
        assert exact * 0.9 <= got <= exact + 1e-9, (x, got, exact)


class _Tracker:
    """Stand-in edge tracker: the fit of frame ``k`` is the truth ``truth(k)``, except on the
    ``trap`` frames, where a start at the last accepted pose (within 5 cm) converges to ``trap[k]``
    instead (a second minimum of that image)."""

    def __init__(self, truth, trap=None):
        self.truth, self.trap = truth, trap or {}
        self.geom = type("G", (), {"vertices": np.zeros((1, 3))})()
        self.K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
        self.k, self.starts, self.T_acc = 0, [], _T(0.0)

    def track(self, gray, T_init, recover=False, first=False, klt=True):
        self.starts.append((self.k, T_init.copy()))
        T = self.truth(self.k)
        if self.k in self.trap and abs(_cx(T_init) - _cx(self.T_acc)) < 0.05:
            T = self.trap[self.k]
        return _fr(T)

    def accept(self, gray, T, anchor=True):
        self.T_acc = T

    def discard_klt_matches(self):
        pass


class _Scored(_Tracker):
    """:class:`_Tracker` whose fits carry a health score: ``score_wrong`` on a trap pose, else ``score_right``."""

    def __init__(self, truth, trap, score_wrong, score_right):
        super().__init__(truth, trap)
        self.score_wrong, self.score_right = score_wrong, score_right

    def track(self, gray, T_init, recover=False, first=False, klt=True):
        fr = super().track(gray, T_init, recover, first)
        on_trap = any(np.allclose(fr.T_cam_model, T) for T in self.trap.values())
        fr.score = self.score_wrong if on_trap else self.score_right
        return fr


def _run(tracker, n):
    s = TrackingSession(tracker, TrackingPolicy(_T(0.0), search_range_px=8, budget=PoseBudget()))
    recs = []
    for k in range(n):
        tracker.k = k
        recs.append(s.step(k, k / 30.0, np.zeros((4, 4), np.uint8)))
    return s, recs


def test_second_minimum_far_from_the_prediction_is_refused_and_the_sequence_goes_on_from_it():
    truth = lambda k: _T(0.1 * k)  # noqa: E731
    wrong = _T(0.1 * 5 + 2.0)  # frame 5 from the last pose: 2 m (2 %) off the truth, 1.9 m from the prediction
    tr = _Tracker(truth, {5: wrong})
    s, recs = _run(tr, 9)
    st = [r.status for r in recs]
    assert st == ["model"] * 5 + ["lost"] + ["model"] * 3, st
    assert recs[5].reason.startswith(REASON_AMBIGUOUS) and "motion prediction" in recs[5].reason
    assert s.policy.refusals.ambiguous_frames == [5] and s.policy.refusals.budget_frames == []
    # frame 6 starts from the refused pose (the image's estimate), then is fitted +-3 sigma along its
    # weakest direction (after a refusal): the truth again each time, so it is output
    starts6 = [T for k, T in tr.starts if k == 6]
    assert np.allclose(starts6[0], wrong) and len(starts6) == 3
    for r in recs[6:]:
        assert np.allclose(r.T_cam_model, truth(r.index))


def test_real_acceleration_refits_to_the_same_pose_and_is_output():
    # the object pushed: 3 % of the distance off the constant-velocity prediction in one frame, the
    # image unambiguous (every start converges to the same pose)
    truth = lambda k: _T(0.1 * k + (3.0 if k >= 5 else 0.0))  # noqa: E731
    tr = _Tracker(truth)
    s, recs = _run(tr, 8)
    assert [r.status for r in recs] == ["model"] * 8
    assert s.policy.refusals.ambiguous_frames == []
    assert len([k for k, _ in tr.starts if k == 5]) == 2  # the fit, and the refit from the prediction


def test_no_prediction_check_close_to_the_prediction():
    truth = lambda k: _T(0.1 * k)  # noqa: E731
    tr = _Tracker(truth)
    _run(tr, 6)
    # one fit a frame after the first (its tolerant and plain fits): every pose within half the
    # budget of its prediction
    assert [k for k, _ in tr.starts if k > 0] == [1, 2, 3, 4, 5]


def test_refit_with_clearly_better_evidence_replaces_the_pose():
    # frame 5's first fit lands in the image's worse minimum (health score 0.5); the refit from the
    # prediction is the truth with a typical score (0.95 > 0.5 + SCORE_MARGIN): the frame takes it
    from mst.pipeline.tracking.budget import SCORE_MARGIN

    truth = lambda k: _T(0.1 * k)  # noqa: E731
    wrong = _T(0.1 * 5 + 2.0)
    assert 0.95 > 0.5 + SCORE_MARGIN
    s, recs = _run(_Scored(truth, {5: wrong}, score_wrong=0.5, score_right=0.95), 8)
    assert [r.status for r in recs] == ["model"] * 8
    assert np.allclose(recs[5].T_cam_model, truth(5))
    assert s.policy.refusals.ambiguous_frames == []


def test_refit_with_similar_evidence_stays_ambiguous():
    # the same two minima with scores 0.8 and 0.9 (within SCORE_MARGIN): the image cannot choose
    truth = lambda k: _T(0.1 * k)  # noqa: E731
    wrong = _T(0.1 * 5 + 2.0)
    s, recs = _run(_Scored(truth, {5: wrong}, score_wrong=0.8, score_right=0.9), 8)
    assert recs[5].status == "lost" and recs[5].reason.startswith(REASON_AMBIGUOUS)


def test_after_an_uncertain_frame_output_resumes_within_half_the_budget():
    # 1-sigma schedule (m, camera 100 m away: the budget is 2 sigma <= 1 m): frame 3 beyond it, frame 4
    # back just under it (the least trustworthy: refused by the hysteresis), frame 5 within half of it
    from mst.pipeline.tracking.budget import RETURN_FRACTION

    sig = {3: 0.6, 4: 0.45}
    assert 2 * 0.45 > RETURN_FRACTION * 1.0 and 2 * 0.2 <= RETURN_FRACTION * 1.0

    class Sigmas(_Tracker):
        def track(self, gray, T_init, recover=False, first=False, klt=True):
            return _fr(self.truth(self.k), sigma_m=sig.get(self.k, 0.2))

    s, recs = _run(Sigmas(lambda k: _T(0.1 * k)), 7)
    assert [r.status for r in recs] == ["model"] * 3 + ["lost", "lost"] + ["model"] * 2
    assert recs[3].reason.startswith(REASON_UNCERTAIN) and "after a refusal" in recs[4].reason
    assert s.policy.refusals.budget_frames == [3, 4]


def test_after_an_uncertain_frame_output_resumes_after_a_steady_stretch_within_the_budget():
    # a bound that stays between half and all of the budget (2 sigma 0.8 m of the 1 m budget): the
    # first RETURN_STEADY_FRAMES - 1 frames after the refusal are refused by the hysteresis, then the
    # stretch is output; a frame beyond the budget inside the stretch starts the count again (the
    # Rotterdam 250 m survey band: 2 sigma 0.6-1.0 % for 27 frames after one at 1.0 %, all refused
    # while output waited for 0.5 %)
    from mst.pipeline.tracking.budget import RETURN_FRACTION, RETURN_STEADY_FRAMES

    assert RETURN_STEADY_FRAMES == 3 and RETURN_FRACTION * 1.0 < 2 * 0.4 <= 1.0 < 2 * 0.6
    sig = {2: 0.6, 3: 0.4, 4: 0.4, 5: 0.4, 6: 0.4, 7: 0.6, 8: 0.4, 9: 0.4, 10: 0.4}

    class Sigmas(_Tracker):
        def track(self, gray, T_init, recover=False, first=False, klt=True):
            return _fr(self.truth(self.k), sigma_m=sig.get(self.k, 0.2))

    s, recs = _run(Sigmas(lambda k: _T(0.1 * k)), 11)
    st = [r.status for r in recs]
    assert st == ["model"] * 2 + ["lost"] * 3 + ["model"] * 2 + ["lost"] * 3 + ["model"], st
    assert all("after a refusal" in recs[k].reason for k in (3, 4, 8, 9))
    assert s.policy.refusals.budget_frames == [2, 3, 4, 7, 8, 9]


def test_no_steady_return_while_the_model_enters_the_view():
    # the same bounds, the visible samples growing 10 % a frame after the refusal (the model coming
    # back into the view, where the bound is optimistic: the demo's UAV return): refused until the
    # view holds still for RETURN_STEADY_FRAMES frames
    from mst.pipeline.tracking.budget import RETURN_STEADY_VIEW

    n = {k: int(200 * 1.1 ** max(0, min(k, 6) - 2)) for k in range(12)}  # grows from frame 3 to 6, then holds
    assert all(abs(n[k] - n[k - 1]) > RETURN_STEADY_VIEW * n[k - 1] for k in range(3, 7))
    sig = {2: 0.6}

    class Growing(_Tracker):
        def track(self, gray, T_init, recover=False, first=False, klt=True):
            fr = _fr(self.truth(self.k), sigma_m=sig.get(self.k, 0.4))
            fr.n_samples = n[self.k]
            return fr

    s, recs = _run(Growing(lambda k: _T(0.1 * k)), 12)
    st = [r.status for r in recs]
    # frames 3-6 grow (refused), 7-8 hold (refused, counted), 9 the third steady frame: output
    assert st == ["model"] * 2 + ["lost"] * 7 + ["model"] * 3, st


class _LossThenTrap(_Tracker):
    """:class:`_Tracker` that loses frame ``lost`` (no healthy fit) and whose fits are weakest along the
    camera's x axis (1 sigma 0.2 m: +-3 sigma starts land 0.6 m away, outside the trap's 5 cm)."""

    def __init__(self, truth, trap, lost):
        super().__init__(truth, trap)
        self.lost = lost

    def track(self, gray, T_init, recover=False, first=False, klt=True):
        fr = super().track(gray, T_init, recover, first)
        cov = np.diag([0.2**2, 0.01**2, 0.01**2] + [np.radians(0.01) ** 2] * 3)
        fr.cov, fr.W = cov, np.linalg.inv(cov)
        if self.k == self.lost:
            fr.healthy, fr.reason = False, "too few visible edge samples"
        return fr


def test_without_a_prediction_after_a_loss_a_second_minimum_is_refused():
    """After a lost frame the motion prediction needs two model frames again; until then a fit is also
    tried from +-3 sigma along its weakest direction (as after a refusal). Frame 6, the second
    after the loss, converges from the last pose to a second minimum 2 m (2 %) off: refused as
    ambiguous, not output as `model` (Rotterdam 120 m at 640x480, edges only, session 11: the frame
    after a relocalised one, 1.4 % off, had been output)."""
    truth = lambda k: _T(0.1 * k)  # noqa: E731
    wrong = _T(0.1 * 6 + 2.0)
    tr = _LossThenTrap(truth, {6: wrong}, lost=4)
    s, recs = _run(tr, 9)
    st = [r.status for r in recs]
    assert st == ["model"] * 4 + ["lost", "model", "lost", "model", "model"], st
    assert recs[6].reason.startswith(REASON_AMBIGUOUS) and "3 sigma" in recs[6].reason
    assert not any(np.allclose(r.T_cam_model, wrong) for r in recs if r.status == "model")
    # no loss before frame 4: frames 1-3 are fitted once each (no +-3 sigma refits without a reason)
    assert [k for k, _ in tr.starts if 0 < k < 4] == [1, 2, 3]


class _Outrun(_Tracker):
    """Stand-in tracker whose fit converges to the truth only from a start within ``reach`` m of it (along
    x), else it is lost; ``dead`` frames are lost from any start. Records whether KLT was on per fit (the
    tracker's ``use_klt`` and the fit's ``klt`` argument)."""

    def __init__(self, truth, reach=0.15, dead=()):
        super().__init__(truth)
        self.reach, self.dead, self.use_klt, self.klt_on = reach, set(dead), True, []

    def track(self, gray, T_init, recover=False, first=False, klt=True):
        fr = super().track(gray, T_init, recover, first)
        self.klt_on.append((self.k, self.use_klt and klt))
        if self.k in self.dead or abs(_cx(T_init) - _cx(self.truth(self.k))) >= self.reach:
            fr.healthy, fr.reason = False, "inliers 20%"
        return fr


def _speeding(k: int) -> float:
    """Camera x (m): 0.1 m a frame up to frame 2, then 0.2 m a frame (beyond the stand-in's 0.15 m reach)."""
    return 0.1 * k if k <= 2 else 0.2 + 0.2 * (k - 2)


def test_a_lost_fit_is_fitted_again_from_the_constant_velocity_pose_without_klt():
    """A camera that speeds up outruns the search from the last pose (frame 3: 0.2 m away, reach 0.15);
    the constant-velocity pose of the last two model frames (0.1 m away, then exact) keeps every
    frame, fitted with the KLT points left out (TrackingSession._edge_pose)."""
    truth = lambda k: _T(_speeding(k))  # noqa: E731
    tr = _Outrun(truth)
    s, recs = _run(tr, 7)
    assert [r.status for r in recs] == ["model"] * 7, [(r.status, r.reason) for r in recs]
    for r in recs:
        assert np.allclose(r.T_cam_model, truth(r.index))
    # frame 3: the plain fit (KLT on), then the rescue (KLT off, the fit's own argument), and KLT on again after it
    assert [on for k, on in tr.klt_on if k == 3][:2] == [True, False] and tr.use_klt


def test_no_constant_velocity_fit_after_a_frame_without_a_model_pose():
    """After a lost frame there is no motion of two model poses to repeat: the frame after it is not
    fitted from a constant-velocity pose (repeating a motion through refused or withheld poses led the
    Rotterdam FPV pass into a wrong basin, 17 % off, session 11)."""
    truth = lambda k: _T(_speeding(k))  # noqa: E731
    tr = _Outrun(truth, dead={3})
    s, recs = _run(tr, 5)
    assert recs[3].status == "lost" and recs[4].status == "lost"
    # frame 3 was tried from the last pose and from the constant-velocity one (0.2, 0.3 m); frame 4 only
    # from the last output pose (frame 2's, in the recovery search)
    assert [round(_cx(T), 9) for k, T in tr.starts if k == 3] == [0.2, 0.3]
    assert [round(_cx(T), 9) for k, T in tr.starts if k == 4] == [0.2]
