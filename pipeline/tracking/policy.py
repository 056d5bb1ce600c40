"""The sequence-level tracking decisions and their state: :class:`TrackingPolicy` (frame results in,
decisions out; no images), used by :class:`mst.pipeline.tracking.session.TrackingSession`.

Frames: ``T_cam_model`` (ViSP cMo). Pixels.
"""

from __future__ import annotations

import numpy as np

from mst.core.poses import inv_T, matmul_exact
from mst.pipeline.tracking.budget import PoseBudget, Refusals
from mst.pipeline.tracking.budget import beyond_budget as budget_exceeded
from mst.pipeline.tracking.edge_tracker import FrameResult
from mst.pipeline.tracking.health import HealthMonitor

#: on re-acquisition (the model back after a SLAM-only stretch) an edge pose is healthy only when its
#: gradient support is at least this fraction of its running mean over the model frames (measured
#: on the synthetic corridor at 640x480: correct poses 0.90-0.96 against a usual 0.93, poses locked
#: onto floor/texture edges 0.52-0.66; the real teabox: 0.66-0.73)
REACQUIRE_SUPPORT_RATIO = 0.8

#: after a loss an edge pose is healthy only with a robust inlier ratio of at least this (ViSP-era
#: rule of thumb), or, in a sequence whose model frames usually have fewer inliers, at least
#: :data:`REACQUIRE_SUPPORT_RATIO` x their running mean (the gradient support's rule): the procedural
#: block at 40 m (model edges against textured ground, correct poses at 41-66 %) lost its last 36
#: frames to a fixed 50 % (recovery fits 0.003-0.03 m off at 48-49 %)
RECOVER_INLIER_RATIO = 0.5

#: a map (``slam``) pose is checked against the image only where the model lies mostly in the view
#: at that pose: at least this fraction of the usual number of visible edge samples of the accepted
#: model frames (fewer: the model is leaving or out of the view, where the map must bridge and the
#: health score's binomial floors are wide)
MAP_CHECK_MIN_VIEW = 0.5


class TrackingPolicy:
    """The sequence-level tracking decisions and their state (no images: frame results in, decisions out).

    State: the last output pose ``T_prev`` (and the one before, ``T_prev2``, for the constant-velocity
    prediction), ``lost_streak`` (frames lost in a row), ``first`` (no frame done yet),
    ``prev_status``, ``support_ref`` (running mean of the gradient support of model frames),
    ``T_hint`` (a healthy edge pose the aid refused: where the next frame starts), the health
    monitor (``monitor``, None without the health score) and its reject count.
    """

    def __init__(self, T0: np.ndarray, search_range_px: float, constant_velocity: bool = False,
                 monitor: HealthMonitor | None = None, budget: PoseBudget | None = None):
        self.T_prev = T0
        self.T_prev2: np.ndarray | None = None
        self.T_hint: np.ndarray | None = None
        self.lost_streak = 0
        self.slam_streak = 0  # frames in a row output by the SLAM aid alone
        self.first = True
        self.first_reason = ""
        self.prev_status = "model"
        self.support_ref: float | None = None
        self.inlier_ref: float | None = None  #: running mean of the robust inlier ratio of model frames
        self.search_range_px = search_range_px
        self.constant_velocity = constant_velocity
        self.monitor = monitor
        self.n_score_rejects = 0
        self.n_ref: float | None = None  #: running mean of the visible edge samples of model frames
        self.budget = budget  #: the error budget of an output pose (None: not checked)
        self.distance_m = None  #: ``distance_m(T_cam_model) -> m`` to the model (set by the session)
        self.refusals = Refusals()  #: the error budget's state: refused frames, the model-pose pair

    # -------------------------------------------------------------- before the edge tracker
    def start_pose(self, T_pred: np.ndarray | None, aided: bool, shift_px) -> np.ndarray:
        """The pose a frame starts from: the aid's prediction ``T_pred``, else constant velocity (when
        on), else a hint, else the last pose. ``shift_px(T)``: the image motion (px) from ``T_prev`` to T."""
        if T_pred is None and self.constant_velocity and self.T_prev2 is not None and self.lost_streak == 0:
            T_pred = matmul_exact(matmul_exact(self.T_prev, inv_T(self.T_prev2)), self.T_prev)  # constant velocity (camera-frame motion)
        T_start = T_pred if T_pred is not None else (self.T_hint if self.T_hint is not None else self.T_prev)
        self.T_hint = None
        if (aided and T_pred is not None and self.prev_status == "model" and self.lost_streak == 0
                and not self.first and shift_px(T_pred) < 0.5 * self.search_range_px):
            # slow motion: the edges' own last pose is inside the search range already; the
            # SLAM pose (its map triangulated from earlier edge poses) would only pass its
            # error on along the edges' weakly observed direction (250 m flyover: 2.5-3.9 m
            # predictions, the edges followed). The aid predicts where the motion is large
            T_start = self.T_prev
        return T_start

    def reacquiring(self, aided: bool) -> bool:
        """Re-acquisition: the model comes back after a SLAM-only stretch. The SLAM prediction has
        drifted (mono: ~1 deg = several pixels), the previous image holds no model edges to take
        contrasts from: a widened coarse-to-fine search too, and the pose must look like a full fit
        (gradient support near its usual value), since a pose locked onto floor/texture edges
        passes the absolute tests."""
        return aided and self.prev_status == "slam" and self.lost_streak == 0 and not self.first

    @property
    def recover(self) -> bool:
        """The edge tracker's recovery mode (widened, coarse-to-fine search): after a loss."""
        return self.lost_streak > 0

    def should_relocalise(self, fr: FrameResult, every: int, aid_on: bool = False) -> bool:
        """Lost, or (``aid_on``: an active SLAM aid will carry the frame) the model projects into the
        image (edge samples), and this frame's edge pose unhealthy: a relocalisation attempt every
        ``every`` frames of the stretch. (A drifted aid keeps the model's edges outside their
        search range after a stretch without the model: on the 40 m UAV survey its map poses
        reached 11 m off while the relocaliser could find the block.)"""
        n = self.lost_streak if self.lost_streak > 0 else (self.slam_streak + 1 if aid_on and fr.n_samples > 0 else 0)
        return n > 0 and not fr.healthy and (n - 1) % every == 0

    # -------------------------------------------------------------- judging an edge pose
    def judge(self, fr: FrameResult, first_frame: bool, count: bool = True) -> FrameResult:
        """The calibrated health score on top of the tracker's absolute tests (``fr`` updated).
        ``count``: a health-score reject is counted."""
        if self.monitor is not None and fr.evidence is not None:
            fr.features = self.monitor.features(fr.evidence, fr.klt_agree, fr.n_klt)
            fr.score, worst = self.monitor.score(fr.features)
            if fr.healthy and not first_frame and fr.score <= 0:
                fr.healthy = False
                fr.reason = f"health score {fr.score:.2f} ({worst})"
                self.n_score_rejects += int(count)
        return fr

    def beyond_budget(self, fr: FrameResult) -> str:
        """Why an edge pose's own uncertainty exceeds the error budget ('' when it does not, or
        without a budget or a model distance): :func:`mst.pipeline.tracking.budget.beyond_budget`, after
        an uncertain frame with the return rule of :meth:`~mst.pipeline.tracking.budget.Refusals.judge`."""
        if self.budget is None or self.distance_m is None:
            return ""
        return self.refusals.judge(self.budget, fr, self.distance_m)

    def uncertain(self, fr: FrameResult) -> bool:
        """Whether the edge pose ``fr``'s own uncertainty exceeds the error budget, without the return rule
        after a refusal and without touching its state (:func:`mst.pipeline.tracking.budget.beyond_budget`):
        for choosing between two fits of one frame before :meth:`beyond_budget` judges the one kept."""
        if self.budget is None or self.distance_m is None or fr.T_cam_model is None:
            return False
        return bool(budget_exceeded(self.budget, fr.cov, fr.T_cam_model, self.distance_m))

    def map_pose_refuted(self, ev) -> str:
        """Why the image refutes a map (``slam``) pose, from its evidence ``ev`` at that pose ('' when
        it does not, or cannot judge: no health score, or the model mostly out of the view there).

        The same calibrated score as for an edge pose (:meth:`judge`), without KLT: with the model
        in the view at the map's pose, its edges of the learned polarity and its learned
        appearance must be there. A map of a still room while the object is carried, or a drifted
        mono map on the model's return, puts the model where the image shows none of it."""
        if self.monitor is None or ev is None or self.n_ref is None or ev.n < MAP_CHECK_MIN_VIEW * self.n_ref:
            return ""
        score, worst = self.monitor.score(self.monitor.features(ev, None, 0))
        return f"map pose refuted by the image: score {score:.2f} ({worst})" if score <= 0 else ""

    def gate_recovery(self, fr: FrameResult, reacq: bool) -> bool:
        """Whether the frame's edge pose counts as healthy. After a re-acquisition or a loss (edges
        only, or the aid lost too), a pose found by the widened search on its first frame back has
        too little history for the health score (few edges in view: wide binomial floors) and can
        lock onto texture edges: its gradient support must be near its usual value."""
        healthy = fr.healthy
        recovering = reacq or self.lost_streak > 0
        if healthy and recovering and self.support_ref is not None and fr.support < REACQUIRE_SUPPORT_RATIO * self.support_ref:
            healthy = False
            fr.reason = f"gradient support {fr.support:.0%} (usual {self.support_ref:.0%})"
        return healthy

    @property
    def recover_inlier_ratio(self) -> float:
        """The robust inlier ratio a fit of the edge tracker's recovery mode (after a loss) needs:
        :data:`RECOVER_INLIER_RATIO`, or :data:`REACQUIRE_SUPPORT_RATIO` x the running mean over this
        sequence's model frames where that is lower (set on the tracker by the session each frame)."""
        if self.inlier_ref is None:
            return RECOVER_INLIER_RATIO
        return min(RECOVER_INLIER_RATIO, REACQUIRE_SUPPORT_RATIO * self.inlier_ref)

    # -------------------------------------------------------------- after the output decision
    def update_support(self, status: str, recovering: bool, support: float, inliers: float | None = None) -> None:
        """The running means of the gradient support and of the robust inlier ratio (``inliers``) over
        model frames (not recovering ones)."""
        if status == "model" and not recovering:
            self.support_ref = support if self.support_ref is None else 0.9 * self.support_ref + 0.1 * support
            if inliers is not None:
                self.inlier_ref = inliers if self.inlier_ref is None else 0.9 * self.inlier_ref + 0.1 * inliers

    def learn(self, fr: FrameResult, status: str, healthy: bool) -> None:
        """An accepted model frame teaches the health monitor."""
        if self.monitor is not None and status in ("model", "relocalised") and healthy and fr.evidence is not None:
            self.monitor.learn(fr.evidence, fr.features)
            n = float(fr.evidence.n)
            self.n_ref = n if self.n_ref is None else 0.9 * self.n_ref + 0.1 * n

    def should_learn_appearance(self, fr: FrameResult, status: str, healthy: bool, min_score: float = 0.5) -> bool:
        """A model (or relocalised) frame confident enough to teach the relocaliser (the first, or a
        health score >= ``min_score``: :attr:`RelocConfig.learn_min_score`)."""
        return status in ("model", "relocalised") and healthy and (self.first or fr.score >= min_score)

    def accepted(self, T_out: np.ndarray) -> None:
        """An output pose: the next frame starts from it."""
        self.T_prev2 = self.T_prev if self.lost_streak == 0 and not self.first else None
        self.T_prev = T_out
        self.lost_streak = 0

    def lost(self, fr: FrameResult) -> None:
        """No output pose; a healthy edge pose the aid refused (it contradicts the map) is not output,
        but it says where the object is: the next frame starts there."""
        self.lost_streak += 1
        if fr.healthy and fr.T_cam_model is not None:
            self.T_hint = fr.T_cam_model

    def frame_done(self, fr: FrameResult) -> None:
        if self.first:
            self.first_reason = fr.reason
        self.first = False
        self.refusals.seen(fr)
