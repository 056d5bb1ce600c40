"""A tracking session over a sequence: :class:`TrackingSession` ``step(index, time_s, gray) -> FrameRecord``.

The session holds the one-frame tracker (:class:`~mst.pipeline.tracking.edge_tracker.EdgeTracker`),
the optional SLAM aid (:mod:`mst.pipeline.slam`) and relocaliser, and a :class:`~mst.pipeline.tracking.policy.TrackingPolicy`: the
sequence-level decisions and their state (where a frame starts, re-acquisition after a SLAM-only
stretch or a loss, the running gradient-support mean, the calibrated health score, when to
relocalise, what the next frame starts from). The policy is testable on its own: it takes frame
results and statuses, never touches images.

Frames: ``T_cam_model`` (ViSP cMo). Pixels, milliseconds.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from mst.core.poses import inv_T, matmul_exact
from mst.pipeline.tracking.budget import (
    ModelDistance,
    ambiguity,
    is_refusal,
)
from mst.pipeline.tracking.edge_tracker import EdgeTracker, FrameResult
from mst.pipeline.tracking.exact import centre, quad_form, rigid
from mst.pipeline.tracking.policy import MAP_CHECK_MIN_VIEW, REACQUIRE_SUPPORT_RATIO, TrackingPolicy  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

#: the first frame: the tolerant multi-pass search from the user's pose and a plain search from it
#: (one pass, the usual range and robust scale) must agree within this many sigma (Mahalanobis
#: distance of the twist between them, under the tolerant fit's i.i.d. covariance ``rms^2 W^-1``:
#: the jackknife covariance of the output, which also counts the edges' correlated errors, put
#: the Rotterdam FPV search's 20 px move within 10 sigma); beyond it the image
#: is multi-modal around the user's pose and the solution nearer to it (the plain one) is kept.
#: Measured from the initial pose: real teabox (clicks a few px off) 5.0 sigma (1.3 px); exact
#: initial poses, Rotterdam FPV 30 m 21 sigma (the tolerant search moved 20 px, 0.73 m, 2.4 %; the
#: plain one 0.17 m) and Delft 250 m 27 sigma (29 m; the plain one 0.74 m)
FIRST_FRAME_AGREE_SIGMA = 10.0

#: statuses of a frame's output pose
OUTPUT_STATUSES = ("model", "slam", "relocalised", "lost")


#: the shared empty per-sample arrays of a kept record (:meth:`FrameRecord.kept`), read-only
_NO_UV, _NO_FLAGS, _NO_EDGES = np.zeros((0, 2)), np.zeros(0, bool), np.zeros((0, 2, 2))
for _a in (_NO_UV, _NO_FLAGS, _NO_EDGES):
    _a.setflags(write=False)


@dataclass
class FrameRecord:
    """What a session made of one frame.

    ``status``: ``model`` (the edge pose), ``slam`` (the aid's pose), ``relocalised``, ``lost``;
    ``T_cam_model``: the output pose (None when lost); ``result``: the edge tracker's result that
    was used (its pose, samples, health); ``aid_state``: ``''`` (no aid), ``standby``, ``on`` or
    ``static-world-broken``; ``ms``: the frame's tracking time; ``cov``: the (6, 6) covariance of the
    output pose's left twist ``(v, w)`` (m, rad, camera frame): the edge fit's for ``model`` and
    ``relocalised``, the propagated drift covariance of a ``slam`` map pose
    (:meth:`mst.pipeline.slam.drift.DriftBudget.map_pose_cov`); None when lost or not known.
    """

    index: int
    time_s: float
    status: str
    T_cam_model: np.ndarray | None
    result: FrameResult
    aid_state: str
    ms: float
    cov: np.ndarray | None = None

    @property
    def reason(self) -> str:
        """Why the edge pose was not used (empty when it was)."""
        return "" if self.status in ("model", "relocalised") else (self.result.reason or "edge pose not used")

    def kept(self) -> FrameRecord:
        """This record as a run keeps it once the frame's overlay is drawn: the edge result without its
        per-sample arrays (samples, inliers, edges, KLT points, evidence), its scalars, pose, covariance
        and information kept (the outputs, the summary and the messages read only those). A run keeps
        its frames in a :class:`mst.pipeline.tracking.runlog.RunLog` and this record of its first frame
        only (whole records grew a run's RSS by ~24 KB a frame, kept ones by ~3.4 KB)."""
        slim = dataclasses.replace(self.result, uv=_NO_UV, inlier=_NO_FLAGS, edge_uv=_NO_EDGES, klt_uv=_NO_UV,
                                   evidence=None)
        return dataclasses.replace(self, result=slim)

    def csv_row(self) -> list:
        """The ``traj.csv`` row (see :data:`mst.pipeline.tracking.runner.CSV_HEADER`)."""
        fr = self.result
        return [self.index, f"{self.time_s:.6f}", self.status, fr.n_samples, fr.n_inliers,
                f"{fr.residual_px:.4f}" if np.isfinite(fr.residual_px) else "nan",
                f"{fr.proj_error_deg:.3f}", f"{self.ms:.3f}",
                f"{fr.score:.3f}" if np.isfinite(fr.score) else "nan", self.aid_state, self.reason]

    def to_json(self) -> dict:
        fr = self.result
        return {"frame": self.index, "time_s": self.time_s, "status": self.status, "samples": fr.n_samples,
                "inliers": fr.n_inliers, "residual_px": fr.residual_px, "health_deg": fr.proj_error_deg,
                "score": fr.score, "aid": self.aid_state, "reason": self.reason, "ms": self.ms,
                "T_cam_model": None if self.T_cam_model is None else self.T_cam_model.tolist()}


def _shift_px(tracker: EdgeTracker, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Largest image displacement (px) between two poses of up to ~200 model vertices in front of
    both cameras (all of them when fewer)."""
    V = tracker.geom.vertices
    V = V[:: max(1, len(V) // 200)]
    K = tracker.K
    uv = []
    for T in (T_a, T_b):
        Xc = rigid(V, T[:3, :3], T[:3, 3])
        uv.append(Xc)
    ok = (uv[0][:, 2] > 0) & (uv[1][:, 2] > 0)
    if not ok.any():
        return float("inf")
    p = [X[ok, :2] / X[ok, 2:3] * [K[0, 0], K[1, 1]] for X in uv]
    return float(np.linalg.norm(p[0] - p[1], axis=1).max())


def model_distance(tracker: EdgeTracker, T_cam_model: np.ndarray) -> float:
    """Distance (m) from the camera centre of ``T_cam_model`` to the nearest model vertex: the
    distance that the drift budget of a map pose is relative to."""
    c = centre(T_cam_model)
    V = np.asarray(tracker.geom.vertices, float)
    return float(np.sqrt(((V - c) ** 2).sum(1).min())) if len(V) else float("inf")


def _standby(aid) -> bool | None:
    """The default aid's standby flag (None: an always-on aid, which has none)."""
    return getattr(aid, "standby", None)


class TrackingSession:
    """Tracks a sequence frame by frame: ``step(index, time_s, gray) -> FrameRecord``.

    ``tracker``: the one-frame :class:`EdgeTracker` (its model, camera, edges and KLT settings);
    ``aid``: a SLAM aid from :func:`mst.pipeline.slam.make_aid` or None; ``reloc``: a
    :class:`~mst.pipeline.tracking.relocalise.Relocaliser` or None; ``policy``: the
    :class:`TrackingPolicy` (its state starts at the initial pose).
    """

    def __init__(self, tracker: EdgeTracker, policy: TrackingPolicy, aid=None, reloc=None):
        self.tracker, self.policy, self.aid, self.reloc = tracker, policy, aid, reloc
        if policy.budget is not None and policy.distance_m is None and hasattr(tracker, "geom"):
            policy.distance_m = ModelDistance(tracker.geom.vertices)

    def _edge_pose(self, idx: int, gray: np.ndarray, T_start: np.ndarray, reacq: bool) -> tuple[FrameResult, bool]:
        """The frame's edge pose from ``T_start``, then the rescues: the standby aid's prediction,
        the widened search on re-acquisition, relocalisation while lost. ``(result, relocalised)``."""
        tr, p, aid, reloc = self.tracker, self.policy, self.aid, self.reloc
        fr = p.judge(tr.track(gray, T_start, recover=p.recover, first=p.first), p.first)
        if p.first and fr.healthy:
            fr = self._first_frame_mode(gray, T_start, fr)
        if aid is not None and _standby(aid) and not p.first and aid.needs_wake(fr.healthy, fr.W):
            # the default aid wakes on a weak or unhealthy edge pose: its prediction may
            # rescue this frame (fast motion), else the edge pose goes to its gate as usual
            T_wake = aid.wake(idx, gray, p.T_prev)
            if T_wake is not None and not fr.healthy:
                fr_s = p.judge(tr.track(gray, T_wake, recover=p.recover), False)
                if fr_s.healthy:
                    fr = fr_s
        if (aid is not None and not p.first and not reacq and p.lost_streak == 0 and p.prev_status == "model"
                and T_start is not p.T_prev and (not fr.healthy or p.uncertain(fr))):
            # the other way round: the aid's prediction may be the one off (a map triangulated from
            # edge poses that could not see a turn about a body of revolution's axis: the vase's
            # `fast` orbit, frame 11, 3.2 deg off where the last edge pose was 2.3 deg off and
            # edges alone converge from it); the edges' own last pose is the second start. Also
            # for a healthy fit beyond the error budget (the same orbit, frame 12: from a prediction
            # 10.9 deg off, 2 sigma 4.7 % of the distance, refused, and frames 13-14 by the return
            # rule; from the last pose, 2.1 deg off, edges alone fit it 0.3 % off): the second fit is
            # taken when it is healthy and, where the first was healthy, within the budget
            fr_p = p.judge(tr.track(gray, p.T_prev, recover=p.recover), False)
            if fr_p.healthy and (not fr.healthy or not p.uncertain(fr_p)):
                fr = fr_p
        T_cv = None if (fr.healthy or p.first or reacq or p.constant_velocity) else p.refusals.predicted()
        if T_cv is not None:
            # the last motion repeated (the last two frames output as model poses; the start itself
            # when edges.constant_velocity is on), fitted on the edges alone: a fast, steady camera
            # outruns the search from the last pose. Measured (session 11): the FPV pass at 640x480,
            # 10 frames/s (1 m and ~2 deg a frame), edges only 5 -> 30 of 30 frames; Rotterdam
            # 40 m survey at 1080p, the default 146 -> 156 frames (the model leaving the view: the
            # other fits, with the 5-7 KLT tracks on its last sliver, lost frames 72-80), ATE
            # 0.006 -> 0.007 m. Only for a lost fit after two output model poses: refits of a pose
            # refused by the error budget came back within it but less accurate (Rotterdam 120 m at
            # 640x480, after the turn: 0.195 -> 0.451 m), and after withheld poses the motion led
            # the Rotterdam FPV pass into a wrong basin (5.7 m, 17 % off, output as model)
            fr_v = p.judge(tr.track(gray, T_cv, recover=p.recover, klt=False), False)
            if fr_v.healthy:
                fr = fr_v
                tr.discard_klt_matches()  # this fit used none: the next frame re-detects them
        if reacq:
            # also the widened search; keep the better fit (healthy, then gradient support)
            fr_w = p.judge(tr.track(gray, T_start, recover=True), False)
            if (fr_w.healthy, fr_w.support) > (fr.healthy, fr.support):
                fr = fr_w
                tr.discard_klt_matches()  # the KLT inliers were those of the discarded fit
        relocalised = False
        if reloc is not None and p.should_relocalise(fr, reloc.cfg.every, aid_on=aid is not None and not _standby(aid)):
            # lost: search the learned keypoints, refine with the edges, accept only if healthy
            for T_r in reloc.candidates(gray):  # most PnP inliers first; the first healthy one is taken
                # no contrast reference, no coarse pass (the widened coarse-to-fine search from a
                # rough PnP pose was tried: at 320x240 on `leave` it let poses 2.1 deg off through)
                fr_r = p.judge(tr.track(gray, T_r, first=True), False)
                if fr_r.healthy:
                    fr, relocalised = fr_r, True
                    tr.discard_klt_matches()
                    break
        return fr, relocalised

    def _ambiguous(self, gray: np.ndarray, fr: FrameResult) -> FrameResult:
        """Refuse ``fr`` (``healthy`` False, reason ``ambiguous``) when a second healthy fit of the image
        lies beyond the budget from it (:func:`mst.pipeline.tracking.budget.ambiguity`): from the
        motion prediction of the last two model frames, and from +-3 sigma after a refused frame
        (or, without a prediction, after any frame that was not a model pose); poses compared
        modulo the model's axis of revolution (:meth:`_modulo_symmetry`). A refit
        with clearly better evidence (:data:`mst.pipeline.tracking.budget.SCORE_MARGIN`) is returned
        in its place: the first fit settled in the image's worse minimum."""
        p, tr = self.policy, self.tracker
        if p.budget is None or p.distance_m is None or fr.T_cam_model is None:
            return fr
        klt = getattr(tr, "_klt_next", None)  # the KLT inliers of the kept fit (the refits' are not kept)

        def refit(T_start):
            return p.judge(tr.track(gray, T_start, recover=p.recover), False, count=False)

        # no motion prediction since a frame that was not a model pose (the two frames after a loss,
        # the one after a relocalised frame): also from +-3 sigma, as after a refusal. Rotterdam
        # 120 m at 640x480, edges only: frame 177, after a relocalised one, had been output 1.4 % off
        T_cv, ref = p.refusals.predicted(), p.refusals
        why, better = ambiguity(p.budget, fr, p.distance_m(fr.T_cam_model), T_cv, ref.after or (T_cv is None and ref.broken),
                                refit, align=self._modulo_symmetry)
        if better is not None:
            tr.discard_klt_matches()  # the KLT inliers were those of the discarded fit
            why = p.beyond_budget(better)
            if why:
                better.healthy, better.reason = False, why
            return better
        if hasattr(tr, "_klt_next"):
            tr._klt_next = klt
        if why:
            fr.healthy, fr.reason = False, why
        return fr

    def _modulo_symmetry(self, T_ref: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``T`` turned about the model's axis of revolution onto ``T_ref`` (render-based edges of a body of
        revolution: the turn is no difference of the image, :meth:`RenderEdgeProvider.align_to`); else ``T``."""
        align = getattr(getattr(self.tracker, "sample_provider", None), "align_to", None)
        return T if align is None else align(T_ref, T)

    def _first_frame_mode(self, gray: np.ndarray, T_init: np.ndarray, fr: FrameResult) -> FrameResult:
        """The first frame's tolerant fit ``fr`` against a plain fit from the user's pose ``T_init``:
        the plain one when both are healthy and they disagree by more than
        ``FIRST_FRAME_AGREE_SIGMA`` (see there)."""
        from mst.core.poses import se3_log

        if fr.cov is None or not np.isfinite(fr.cov).all():
            return fr
        fr_p = self.policy.judge(self.tracker.track(gray, T_init), True)
        if not fr_p.healthy or fr_p.T_cam_model is None:
            return fr
        dx = se3_log(matmul_exact(self._modulo_symmetry(fr.T_cam_model, fr_p.T_cam_model), inv_T(fr.T_cam_model)))
        if fr.W is None or not np.isfinite(fr.W).all() or not fr.residual_px > 0:
            return fr
        # in the metric of the fit's information and residual noise (i.i.d.: how far apart the image puts
        # the two fits), not of its covariance, which also counts the edges' correlated errors
        d = float(np.sqrt(max(quad_form(dx, fr.W), 0.0))) / float(fr.residual_px)
        if d <= FIRST_FRAME_AGREE_SIGMA:
            return fr
        log.info(f"first frame: the tolerant search moved {d:.0f} sigma away from the plain fit from the initial pose "
                 "(a multi-modal image around it): the plain fit is kept")
        return fr_p

    def step(self, idx: int, time_s: float, gray: np.ndarray) -> FrameRecord:
        """Track one 8-bit gray frame (H, W); the frame's record (its output pose and status)."""
        t0 = time.perf_counter()
        tr, p, aid, reloc = self.tracker, self.policy, self.aid, self.reloc
        tr.recover_min_inlier_ratio = p.recover_inlier_ratio
        T_pred = aid.predict(idx, gray, p.T_prev) if aid is not None else None
        T_start = p.start_pose(T_pred, aid is not None, lambda T: _shift_px(tr, T, p.T_prev))
        reacq = p.reacquiring(aid is not None)
        fr, relocalised = self._edge_pose(idx, gray, T_start, reacq)
        healthy = p.gate_recovery(fr, reacq)
        if healthy:
            # the error budget judges the pose that the rescues and gates above settled on, and only
            # a pose that passed them all (inside the rescues a refusal set off other fits: the demo's
            # UAV pass lost its return after the turn; before the recovery gate, a pose that it
            # refuses was withheld and followed: the 40 m pass, 2.5-3.3 % off after its return)
            why = p.beyond_budget(fr)
            if why:
                fr.healthy, fr.reason = False, why
            elif not relocalised and not p.first:
                fr = self._ambiguous(gray, fr)
            healthy = fr.healthy
        recovering = reacq or p.lost_streak > 0
        # an edge pose refused by the error budget (uncertain, ambiguous) is not output, but it is the
        # image's best estimate: the sequence goes on from it as from a model frame (see _withhold_edge)
        withheld = not healthy and fr.T_cam_model is not None and is_refusal(fr.reason)
        if aid is not None and relocalised:
            # a relocalised pose passed the health test on its own image after a loss: the map of
            # the lost stretch (the object may have been moved meanwhile) does not gate it
            if _standby(aid) is False:
                aid.close()  # the default's map belongs to the lost stretch: back to standby
            elif _standby(aid) is None:
                aid.follow_model()
        if aid is not None and T_pred is not None and fr.T_cam_model is not None:
            # a body of revolution's turn about its axis is no difference of the image: the edge pose
            # is the one of its equivalents nearest the map's prediction (the map sees that turn,
            # the edges cannot), so that the aid's gates compare what the image determines
            fr.T_cam_model = self._modulo_symmetry(T_pred, fr.T_cam_model)
        if aid is not None:
            # an edge pose refused only by the health score still says where the image
            # puts the object: the aid outputs no map pose that contradicts it
            weak = (fr.T_cam_model if not healthy and fr.T_cam_model is not None
                    and (fr.reason or "").startswith("health score") else None)
            # the edge covariance anchors the drift budget of the aids that keep one, and with the
            # distance to the model lets a healthy edge pose override a map pose beyond the budget
            # (an aid of the plain hook contract takes the first six arguments only)
            kw = {"cov_edges": fr.cov, "distance_fn": lambda T: model_distance(tr, T)} if hasattr(aid, "within_budget") else {}
            T_out, status = aid.update(idx, gray, fr.T_cam_model, fr.W, healthy or withheld, weak_edge_pose=weak, **kw)
            if withheld and status != "slam":
                return self._withhold_edge(idx, time_s, gray, fr, t0)
            if status == "slam" and T_out is not None and hasattr(aid, "within_budget"):
                # a map pose is output only while its propagated uncertainty is within the drift
                # budget at its distance to the model (mst.pipeline.slam.drift); beyond it the
                # map keeps running, so that the model can re-anchor it
                if not aid.within_budget(idx, model_distance(tr, T_out)):
                    rel, deg = aid.drift_log[idx]
                    fr.reason = (f"drift budget: map pose uncertain to {rel:.1%} of the model distance, "
                                 f"{deg:.2f} deg")
                    return self._withhold(idx, time_s, gray, T_out, fr, recovering, t0)
            if status == "slam" and T_out is not None and p.monitor is not None:
                # a map pose is output only while the image does not refute it (the model in view)
                why = p.map_pose_refuted(tr.evidence(gray, T_out))
                if why:
                    fr.reason = why
                    if aid.refute_map_pose(idx):
                        # not output, but the map still bridges: the next frame goes on from its
                        # pose as from a slam frame (only the output is withheld)
                        return self._withhold(idx, time_s, gray, T_out, fr, recovering, t0)
                    T_out, status = None, "lost"
        elif withheld:
            return self._withhold_edge(idx, time_s, gray, fr, t0)
        else:
            T_out, status = (fr.T_cam_model, "model") if healthy else (None, "lost")
        p.update_support(status, recovering, fr.support, fr.n_inliers / max(fr.n_samples, 1))
        if relocalised and status == "model":
            status = "relocalised"
        p.prev_status = status
        p.slam_streak = p.slam_streak + 1 if status == "slam" else 0
        p.learn(fr, status, healthy)
        if (reloc is not None and p.should_learn_appearance(fr, status, healthy, reloc.cfg.learn_min_score)
                and reloc.should_learn(idx, fr.T_cam_model)):
            reloc.learn(idx, gray, fr.T_cam_model)
        if T_out is not None and status != "lost":
            tr.accept(gray, T_out, anchor=status in ("model", "relocalised"))
            p.accepted(T_out)
        else:
            p.lost(fr)
            T_out, status = None, "lost"
        p.frame_done(fr)
        p.refusals.output(status, T_out)
        ms = (time.perf_counter() - t0) * 1000.0
        # a map pose's propagated drift covariance (the aid's state is this frame's until its next update)
        cov = None if status == "lost" else getattr(aid, "map_pose_cov", lambda: None)() if status == "slam" else fr.cov
        return FrameRecord(idx, time_s, status, T_out, fr, self._aid_state(idx), ms, cov)

    def _withhold_edge(self, idx: int, time_s: float, gray: np.ndarray, fr: FrameResult, t0: float) -> FrameRecord:
        """An edge pose refused by the error budget: ``lost`` (its reason in the CSV, the frame in
        ``pose_budget_frames`` / ``ambiguous_frames``), while the next frame starts from it and takes
        its contrast reference from it, as after a model frame (the aid was updated with it as one).
        Nothing learns from it (health statistics, polarities, keyframes), and the next frame's edge
        pose is checked for ambiguity (:meth:`_ambiguous`). Going on from the lost frame's map pose
        or last output pose instead lost the demo's UAV pass from the turn on (79 frames)."""
        tr, p = self.tracker, self.policy
        tr.accept(gray, fr.T_cam_model, anchor=False)
        p.accepted(fr.T_cam_model)
        p.prev_status = "model"
        p.slam_streak = 0
        p.frame_done(fr)
        p.refusals.refused(idx, fr.reason)
        ms = (time.perf_counter() - t0) * 1000.0
        return FrameRecord(idx, time_s, "lost", None, fr, self._aid_state(idx), ms)

    def _withhold(self, idx: int, time_s: float, gray: np.ndarray, T_map: np.ndarray, fr: FrameResult,
                  recovering: bool, t0: float) -> FrameRecord:
        """A map pose that is not output (``lost``) while the map still bridges: the next frame goes
        on from it as from a slam frame (edge search start, re-acquisition, relocalisation attempts)."""
        tr, p = self.tracker, self.policy
        tr.accept(gray, T_map, anchor=False)
        p.accepted(T_map)
        p.update_support("slam", recovering, fr.support)
        p.prev_status = "slam"
        p.slam_streak += 1
        p.frame_done(fr)
        p.refusals.output("lost", None)
        ms = (time.perf_counter() - t0) * 1000.0
        return FrameRecord(idx, time_s, "lost", None, fr, self._aid_state(idx), ms)

    def _aid_state(self, idx: int) -> str:
        aid = self.aid
        if aid is None:
            return ""
        state = "standby" if _standby(aid) else "on"
        fired = getattr(aid, "static_world_fired", None)
        refuted = getattr(aid, "map_refuted", None)
        beyond = getattr(aid, "drift_budget_frames", None)
        if beyond and beyond[-1] == idx:
            state = "drift-budget"  # the map pose's uncertainty exceeded the drift budget: not output
        elif fired and fired[-1] == idx:
            state = "static-world-broken"  # the map's world moved against the object here
        elif refuted and refuted[-1] == idx:
            state = "map-refuted"  # the image refuted the map pose here: the map stops bridging
        return state
