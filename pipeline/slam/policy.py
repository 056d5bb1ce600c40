"""The aid policy: how the edge tracker's pose and the SLAM pose are combined, frame by frame.

A small Kalman filter on the pose (the SLAM pose's anchoring covariance ``P`` grown by a random-walk
drift; the edge pose's ``sigma_e^2 W^-1``), a chi-square gate against wrong edge matches, a
consensus of recent rejected edge poses that re-anchors a drifted map, the static-world check (the
object moving in the map's world), the output bound (no map pose against the image's evidence),
and the rigid re-anchoring of the map onto a model pose. The module docstring of
:mod:`mst.pipeline.slam` tells the whole story; :meth:`AidPolicy._judge` and
:meth:`AidPolicy._output` are the two halves of :meth:`ModelAidedSlam.update`.

:class:`AidPolicy` is one part of :class:`mst.pipeline.slam.aid.ModelAidedSlam` (a mixin on the
aid's filter state ``P``, ``info_ref``, ``n_rejects``, the streaks and ``moving_hold``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mst.core.poses import inv_T, se3_exp, se3_log
from mst.pipeline.slam.geometry import regularised_6x6
from mst.pipeline.slam.state import STATUS_LOST, STATUS_MODEL, STATUS_SLAM, FrameState


@dataclass
class Verdict:
    """What the policy decided about one frame's edge pose (see :meth:`AidPolicy._judge`)."""

    edge_ok: bool                 #: the edge pose is output (status ``model``)
    reset: bool = False           #: the whole map is re-anchored onto it (consensus or moving world)
    moving: bool = False          #: the object moves in the map's world: no fusion with the map
    contradicted: bool = False    #: the image supports another pose than the map beyond the output bound
    over_budget: bool = False     #: the map pose is beyond its drift budget: it does not judge the edge pose


class AidPolicy:
    """Gate, consensus, static-world check, fusion and re-anchoring of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`."""

    def _judge(self, k: int, T_edges: np.ndarray | None, W: np.ndarray | None, st: FrameState,
               edge_ok: bool, slam_ok: bool, over_budget: bool = False) -> Verdict:
        """The gate, consensus and static-world decisions on frame ``k``'s healthy edge pose.

        ``over_budget``: the map pose of this frame is beyond its drift budget (:mod:`.drift`): a map
        that could not be output cannot refuse a healthy edge pose either (as weak, by the gate, as
        contradicting it): where it would, the edge pose is output and the map re-anchored onto it;
        a strong edge pose that it agrees with is gated and fused as usual."""
        v = Verdict(edge_ok)
        if (edge_ok and slam_ok and over_budget and not self.moving_hold
                and not (self._strong_enough(W) and self._consistent(T_edges, W, st))):
            # after an occluder the map (its landmarks tracked on the occluder) had drifted 100-270 %
            # beyond its budget and refused 27 healthy edge poses as weak (trace(W) 0.4 x its
            # running mean, its KLT points seeded at the map's pose); on the demo's UAV pass a map
            # re-observing its stale landmarks of the turn gated a right edge pose, lost to the end.
            # Only a map that would refuse it: one that agrees with a strong edge pose is fused as
            # usual (a mono map's bound, far above its error, is beyond the budget on nearly every
            # frame; re-anchored unfused onto each edge pose, the explicit mono map of the 640x480
            # corridor was 0.05 m off at frame 30 against 0.005 m fused, 0.9 m at the return)
            v.over_budget = True
            self._disagree_streak = 0
            self.n_rejects = 0
            self.stats["budget_overrides"] += 1
            return v
        if edge_ok and slam_ok and self.moving_hold:
            # the object moves in the map's world: no gate, the map follows the model pose; leave this
            # state after static_world_frames frames in a row in which the map agrees again
            agree_now = self._consistent(T_edges, W, st, fresh=True)
            self._agree_streak = self._agree_streak + 1 if agree_now else 0
            if self._agree_streak >= self.cfg.static_world_frames:
                self.moving_hold = False
            else:
                v.reset = v.moving = True
        elif edge_ok and slam_ok:
            strong = self._strong_enough(W)
            passed = strong and self._gate(T_edges, W, st)
            # a weak (partial-view, ill-conditioned) edge pose never votes for a consensus reset
            agree = self._consensus(np.asarray(T_edges, float), st.T, rejected=not passed) if strong else 0
            if not passed:
                v.edge_ok = False
                if agree >= self.cfg.consensus_min:
                    # several recent edge poses agree with this one on the SLAM's offset: the SLAM
                    # (anchored on an early wrong edge pose, or drifted) is the one that is off
                    v.edge_ok = v.reset = True
                    self.P = None
                    self._recent_offsets.clear()
                    self.stats["consensus_resets"] += 1
                elif strong and agree > 0:
                    self._disagree_streak = 0  # the same offset again: a wrong match or drift, not motion
                    v.contradicted = self._beyond_bound(T_edges, st.T)
                elif strong:
                    self._disagree_streak += 1
                    v.contradicted = self._beyond_bound(T_edges, st.T)
                    if self._disagree_streak >= self.cfg.static_world_frames:
                        # static-world check: healthy, strong edge poses keep disagreeing with the
                        # map, each by a different offset (no consensus): the object moves in the
                        # map's world (carried, turntable). Stop bridging with the map, follow the
                        # model, re-anchor the map to it every frame until they agree again
                        v.edge_ok = v.reset = v.moving = True
                        self.moving_hold = True
                        self._agree_streak = 0
                        self.static_world_fired.append(int(k))
                        self.stats["static_world_breaks"] += 1
            else:
                self._disagree_streak = 0
        return v

    def _output(self, k: int, gray: np.ndarray, T_edges: np.ndarray | None, W: np.ndarray | None,
                st: FrameState, slam_ok: bool, v: Verdict) -> tuple[np.ndarray | None, str]:
        """The output pose and status of frame ``k`` after :meth:`_judge` (fusion, re-anchoring,
        SLAM pose, lost, relocalisation); updates the filter's bookkeeping."""
        if v.edge_ok:
            T_out, status = np.asarray(T_edges, float).copy(), STATUS_MODEL
            if W is not None:
                T_fused = self._fuse(T_out, W, st if slam_ok and not (v.moving or v.over_budget) else FrameState(k))
                if self.cfg.fuse_output if self.cfg.fuse_output is not None else self.mode == "rgbd":
                    T_out = T_fused
            if slam_ok and (self.frames_since_fix > 0 or v.reset or v.over_budget):
                self._reanchor(T_out, st.T, everything=v.reset)  # reset the map to the model
            if v.moving:
                self.P = None
                self._recent_offsets.clear()
                self.n_rejects = 0
            self.frames_since_fix = 0
            if W is not None:
                tr = float(np.trace(W))
                self.info_ref = tr if self.info_ref is None else 0.9 * self.info_ref + 0.1 * tr
        elif slam_ok and not self.moving_hold and not v.contradicted and self._disagree_streak == 0:
            T_out, status = st.T, STATUS_SLAM
            self.frames_since_fix += 1
        elif v.contradicted or (slam_ok and self._disagree_streak > 0):
            # the image supports another pose than the map by more than the output accuracy (a wrong
            # edge match, or the object moving in the map's world): which is right is not known
            # yet, so neither is output; the map is kept (not dragged) until the check decides
            T_out, status = None, STATUS_LOST
            self.frames_since_fix += 1
            self.stats["contradictions"] += 1
        elif self.moving_hold:
            # the map's world moves against the object: a map pose is no model pose
            T_out, status = None, STATUS_LOST
            self.frames_since_fix += 1
        else:
            self._reloc_sig = None
            T_out = self._relocalise(gray, k)
            status = STATUS_SLAM if T_out is not None else STATUS_LOST
            st.sig = self._reloc_sig
            self.frames_since_fix += 1
        return T_out, status

    def follow_model(self) -> None:
        """Stop bridging with the map: follow the model poses, re-anchor the map onto them, output no
        map pose until they agree for ``static_world_frames`` frames in a row (the state the
        static-world check enters). Also after a relocalisation: its pose passed the health test on
        its own image after a loss, the map of the lost stretch (the object may have been moved
        meanwhile) does not gate it."""
        self.moving_hold = True
        self._agree_streak = 0

    def refute_map_pose(self, k: int) -> bool:
        """The image refutes the map pose of frame ``k`` (output as ``slam``), while the model lies in
        the view at that pose: its edges and appearance are not there (the tracking session's check,
        :meth:`mst.pipeline.tracking.policy.TrackingPolicy.map_pose_refuted`). The map and the object
        disagree: the object moved in the map's world (carried, turned) or the map drifted. Either
        way this map pose is no model pose: the frame is not output (the session marks it lost).
        Once refuted, the map keeps predicting (its pose is still the best start for the edge
        search: on the UAV demo a refuted pose 4 m off led the edges back onto the block on the next
        frame); refuted ``static_world_frames`` frames in a row, the map's world has moved against
        the object: :meth:`follow_model`. Returns True while the map still bridges."""
        streak = self._refute_streak + 1 if self.map_refuted and self.map_refuted[-1] == k - 1 else 1
        self.map_refuted.append(int(k))
        self.stats["image_refutations"] += 1
        self._refute_streak = streak
        if streak >= self.cfg.static_world_frames:
            self.follow_model()
            self.T_hist.clear()
            return False
        return True

    def _process_noise(self) -> np.ndarray:
        """Per-frame random-walk covariance (v, w) of the SLAM pose against the model frame."""
        cfg = self.cfg
        rate = cfg.drift_rel_per_frame if cfg.drift_rel_per_frame is not None else (
            0.001 if self.mode == "rgbd" else 0.005)
        deg = cfg.drift_deg_per_frame if cfg.drift_deg_per_frame is not None else (
            0.05 if self.mode == "rgbd" else 0.2)
        return np.diag(np.r_[np.full(3, (rate * self.scene_depth) ** 2), np.full(3, np.radians(deg) ** 2)])

    def _slam_cov(self, st: FrameState) -> np.ndarray:
        """6x6 covariance (v, w) of the SLAM pose of this frame in the model frame: the filter's
        anchoring covariance ``P`` (grown by the process noise) plus the PnP noise."""
        P = self.P if self.P is not None else np.diag(np.r_[np.full(3, self.scene_depth**2), np.full(3, 1.0)])
        return P + self.cfg.slam_sigma_px**2 * np.linalg.inv(regularised_6x6(st.W))

    def _fuse(self, T_edges: np.ndarray, W_edges: np.ndarray | None, st: FrameState) -> np.ndarray:
        """Kalman update of the SLAM pose with the edge pose (left perturbation of the SLAM pose);
        updates the anchoring covariance ``P``."""
        Se = self.cfg.edge_sigma_px**2 * np.linalg.inv(regularised_6x6(np.asarray(W_edges, float)))
        if st.W is None:
            self.P = Se
            return np.asarray(T_edges, float).copy()
        S = self._slam_cov(st)
        K = S @ np.linalg.inv(regularised_6x6(S + Se))
        delta = se3_log(np.asarray(T_edges, float) @ inv_T(st.T))
        I6 = np.eye(6)
        self.P = regularised_6x6((I6 - K) @ S @ (I6 - K).T + K @ Se @ K.T)  # Joseph form
        return se3_exp(K @ delta) @ st.T

    def _consensus(self, T_edges: np.ndarray, T_slam: np.ndarray, rejected: bool) -> int:
        """How many of the recent healthy but rejected edge poses saw the same SLAM offset
        ``C = T_e^-1 T_slam`` (model frame) as this one; records this offset."""
        cfg = self.cfg
        C = inv_T(T_edges) @ T_slam
        n = 0
        for C_i, rej in self._recent_offsets:
            if not rej:
                continue
            D = inv_T(C_i) @ C
            if (np.linalg.norm(D[:3, 3]) < cfg.consensus_rel * self.scene_depth
                    and np.degrees(np.linalg.norm(se3_log(D)[3:])) < cfg.consensus_deg):
                n += 1
        self._recent_offsets.append((C, rejected))
        return n

    def _beyond_bound(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        """The two poses differ by more than ``disagree_rel`` x scene depth or ``disagree_deg``."""
        D = np.asarray(T_a, float) @ inv_T(T_b)
        ang = math.degrees(np.linalg.norm(se3_log(D)[3:]))
        dpos = np.linalg.norm(inv_T(T_a)[:3, 3] - inv_T(T_b)[:3, 3])
        return dpos > self.cfg.disagree_rel * self.scene_depth or ang > self.cfg.disagree_deg

    def _consistent(self, T_edges: np.ndarray, W_edges: np.ndarray | None, st: FrameState, fresh: bool = False) -> bool:
        """The chi-square test of :meth:`_gate` without its bookkeeping (True: edges and map agree).

        ``fresh``: the map was re-anchored onto the previous frame's edge pose, so its anchoring
        covariance is that pose's (about this frame's edge covariance), not the filter's ``P``."""
        if W_edges is None or st.W is None or (st.n_inliers < self.cfg.gate_min_inliers and not fresh):
            return not fresh
        delta = se3_log(np.asarray(T_edges, float) @ inv_T(st.T))
        Se = self.cfg.edge_sigma_px**2 * np.linalg.inv(regularised_6x6(np.asarray(W_edges, float)))
        if fresh:
            cov = 2.0 * Se + self.cfg.slam_sigma_px**2 * np.linalg.inv(regularised_6x6(st.W))
        else:
            cov = self._slam_cov(st) + Se
        return float(delta @ np.linalg.solve(cov, delta)) <= self.cfg.gate_chi2

    def _strong_enough(self, W: np.ndarray | None) -> bool:
        """Edge information (trace of W) against its running mean over accepted frames: a model
        half out of the view (entering or leaving) gives biased poses; the SLAM carries instead."""
        if W is None or self.info_ref is None:
            return True
        return float(np.trace(W)) >= self.cfg.min_info_ratio * self.info_ref

    def _gate(self, T_edges: np.ndarray, W_edges: np.ndarray | None, st: FrameState) -> bool:
        """True when the edge pose is consistent with the SLAM pose (or the SLAM is not confident)."""
        cfg = self.cfg
        if st.n_inliers < cfg.gate_min_inliers or W_edges is None or st.W is None:
            self.n_rejects = 0
            return True
        if self.n_rejects >= cfg.gate_max_rejects:  # the edges insist: the SLAM is probably the one off
            self.n_rejects = 0
            return True
        delta = se3_log(np.asarray(T_edges, float) @ inv_T(st.T))
        cov = self._slam_cov(st) + cfg.edge_sigma_px**2 * np.linalg.inv(regularised_6x6(np.asarray(W_edges, float)))
        d2 = float(delta @ np.linalg.solve(cov, delta))
        if d2 <= cfg.gate_chi2:
            self.n_rejects = 0
            return True
        self.n_rejects += 1
        self.stats["gate_rejects"] += 1
        return False

    def _reanchor(self, T_model_fix: np.ndarray, T_slam: np.ndarray, everything: bool = False) -> None:
        """Move the map built since the last model fix rigidly so that the current SLAM pose
        becomes the model pose: ``X' = C X`` with ``C = T_fix^-1 T_slam`` for landmarks not anchored
        under a model pose, ``T' = T C^-1`` for keyframes without a model prior and for the tracks'
        first views. The next local BA (with the priors) refines the rest. ``everything``: move all
        landmarks and keyframes and forget the keyframes' model priors (a consensus reset)."""
        C = inv_T(T_model_fix) @ T_slam
        Ci = inv_T(C)
        for t, x in self.lm.items():
            if everything or not self.lm_model.get(t, False):
                self.lm[t] = C[:3, :3] @ x + C[:3, 3]
        for kf in self.kfs:
            if everything:
                kf.prior_W = kf.prior_T_cam_model = None
            if kf.prior_W is None:
                kf.T_cam_model = kf.T_cam_model @ Ci
        if len(self.first_P):
            self.first_P = self.first_P @ Ci
        self.stats["reanchors"] += 1
