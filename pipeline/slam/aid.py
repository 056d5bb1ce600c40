"""The model-aided SLAM beside the edge tracker (``mst track --slam mono|rgbd``): :class:`ModelAidedSlam`.

The edge tracker gives a drift-free but fragile pose (it needs the model in view and a good edge
match); the SLAM gives a high-rate pose that drifts. This module fuses them like GPS/INS:

* **front end** (a few ms per frame): KLT (pyramidal Lucas-Kanade with a forward-backward check)
  tracks up to ``klt.max_features`` corners frame to frame, replenished per grid cell with
  ``goodFeaturesToTrack``. Landmarks live in **model coordinates**: lifted from depth (``rgbd``,
  honouring the depth camera intrinsics and ``T_depth_color``) or triangulated from two views with
  known poses (``mono``, parallax and reprojection checks). The camera pose of frame k is found by
  PnP + RANSAC on the 2D-3D tracks (:meth:`ModelAidedSlam.predict`), which tells the edge tracker
  where to project the model.
* **fusion** (:meth:`ModelAidedSlam.update`), a small Kalman filter on the pose: the SLAM pose
  carries a 6x6 anchoring covariance ``P`` (grown each frame by a random-walk drift of
  ``drift_rel_per_frame`` x scene depth), plus its PnP noise ``sigma_s^2 (J^T J)^-1``; the edge pose
  has ``sigma_e^2 W^-1``. A healthy edge pose is accepted (status ``model``, output = the fused
  pose, ``P`` updated) unless (a) its information ``trace(W)`` fell below ``min_info_ratio`` x its
  running mean (model half out of the view: biased) or (b) it disagrees with the SLAM pose beyond a
  chi-square bound on the Mahalanobis distance (a wrong edge match must not drag the SLAM). A
  rejected edge pose is accepted anyway when ``consensus_min`` recent rejected edge poses saw the
  same SLAM offset (the SLAM, not the edges, is off: the whole map is re-anchored). Otherwise the
  SLAM pose is output (``slam``); ``lost`` only when neither works and relocalisation against the
  stored keyframes fails. When the model comes back after a SLAM-only stretch, the map built
  meanwhile is moved rigidly onto the fused pose; rgbd landmarks are re-lifted from depth under
  every model pose (the RGB-D paper's reset), mono landmarks are corrected by the local BA.
  Mono landmarks are re-triangulated while their parallax grows (up to ``tri_refine_deg``).
* **keyframes and local BA**: a keyframe stores its pose, its 2D observations and, as the model
  constraint, only the model pose and the 6x6 ``W = J^T J`` of its edge optimisation (constant size).
  At each keyframe a local bundle adjustment over the last ``ba_window`` keyframes runs in pycolmap:
  first unconstrained (reference reprojection RMSE ``e0``), then with ``AbsolutePosePriorCost``
  priors (covariance ``sigma_e^2 W^-1``); the constrained result is accepted only when its RMSE stays
  below ``ba_guard_ratio * e0 + ba_guard_px`` (Lhuillier's scheme), else the priors are down-weighted
  and, failing that, dropped.
* **relocalisation**: ORB descriptors of each keyframe's landmark observations (with a copy of the
  3D points) are kept for the last ``reloc_keyframes`` keyframes; when everything is lost, the
  current frame is matched against them and the pose found by PnP + RANSAC.

Memory is bounded: a sliding window of keyframes with observations, a bounded ring of relocalisation
keyframes, and landmarks pruned to those still tracked or observed in the window. Only the exported
map (:meth:`ModelAidedSlam.landmarks`, bounded by ``max_export_points``) grows with the explored area.

The aid's parts live in the package's modules, each a mixin on the state set up in
:meth:`ModelAidedSlam.__init__`: :mod:`.frontend` (KLT, PnP, corners), :mod:`.landmarks` (rgbd
lifting, mono triangulation), :mod:`.policy` (gate, consensus, static world, fusion, re-anchoring),
:mod:`.keyframes` (keyframes, pruning, relocalisation), :mod:`.ba` (local BA); pure helpers in
:mod:`.geometry`, records in :mod:`.state`, settings in :mod:`.config`.

Conventions: ``T_cam_model`` maps model points to the camera frame (ViSP's cMo); twists and ``W``
are in the order ``(v, w)`` (translation then rotation) as :func:`mst.core.poses.se3_exp`;
pose perturbations are on the left (camera frame): ``T = exp(delta) @ T0``. Pixels, metres, degrees.
"""

from __future__ import annotations

import math
from collections import deque
from pathlib import Path

import numpy as np

from mst.core.camera import Camera
from mst.core.klt import to_gray
from mst.pipeline.depth_io import DepthConfig, list_depth_frames
from mst.pipeline.slam.ba import LocalBA
from mst.pipeline.slam.config import SlamConfig, slam_depth_config
from mst.pipeline.slam.drift import DriftBudget, camera_centre
from mst.pipeline.slam.frontend import FrontEnd
from mst.pipeline.slam.keyframes import KeyframeMap
from mst.pipeline.slam.landmarks import Landmarks
from mst.pipeline.slam.policy import AidPolicy
from mst.pipeline.slam.state import STATUS_MODEL, FrameState, Keyframe


class ModelAidedSlam(FrontEnd, Landmarks, AidPolicy, KeyframeMap, LocalBA, DriftBudget):
    """The SLAM aid called by the tracking loop (see :func:`mst.pipeline.slam.make_aid` for the arguments).

    State shared by its parts: the tracks of the current frame (``pts`` (N, 2) float32 pixels,
    ``tid`` landmark/track ids, mono ``first_xn``/``first_P``/``tri_deg`` of the first view), the
    landmarks ``lm`` (id -> model point) with ``lm_model`` (anchored under a model pose), the
    keyframe windows ``kfs`` (BA) and ``reloc_kfs``, the filter (``P``, ``info_ref``,
    ``n_rejects``, the consensus offsets, the static-world streaks, ``moving_hold``), the median
    ``scene_depth``, ``stats`` and ``timing_ms``.
    """

    def __init__(self, mode: str, camera: Camera, config: SlamConfig | dict | None = None,
                 depth_dir: Path | None = None, depth_camera: Camera | None = None,
                 T_depth_color: np.ndarray | None = None, depth: DepthConfig | None = None):
        import cv2

        if mode not in ("mono", "rgbd"):
            raise ValueError(f"SLAM mode must be 'mono' or 'rgbd', not {mode!r}")
        self.mode = mode
        self.cfg = SlamConfig.from_dict(config)
        self.depth = slam_depth_config() if depth is None else depth
        # rgbd: the depth-lifted landmarks are metric and re-anchored under every model pose; a BA
        # refits them to the KLT drift (measured worse), so BA is a mono feature unless asked for
        self.use_ba = (mode == "mono") if self.cfg.ba is None else bool(self.cfg.ba)
        self.cam = camera
        self.K = camera.K
        self.dist = camera.dist if camera.has_distortion else None
        self._depth_files: list[Path] = []
        if mode == "rgbd":
            if depth_dir is None:
                raise ValueError("the rgbd aid needs depth_dir, a folder of depth frames")
            self._depth_files = list(list_depth_frames(depth_dir))  # InputError: missing, empty
        self._depth: np.ndarray | None = None
        self._depth_k: int | None = None
        self.K_depth = (depth_camera or camera).K
        self._depth_camera_given = depth_camera is not None
        self.T_depth_color = np.eye(4) if T_depth_color is None else np.asarray(T_depth_color, float)
        self._orb = cv2.ORB_create(nfeatures=self.cfg.reloc_features)
        # tracks (current frame): pixels, landmark/track ids, first observation (mono)
        self.pts = np.zeros((0, 2), np.float32)
        self.tid = np.zeros(0, np.int64)
        self.first_xn = np.zeros((0, 2))          # normalised coordinates at the first observation
        self.tri_deg = np.zeros(0)                # mono: parallax (deg) of the track's triangulation, 0 = none
        self.first_P = np.zeros((0, 3, 4))        # [R|t] of that frame (model -> camera)
        self.first_sig = np.zeros((0, 2))         # that frame's pose uncertainty: map part (m, rad) ...
        self.first_C = np.zeros((0, 6, 6))        # ... and its fit's twist covariance (:mod:`.drift`)
        self._next_tid = 0
        self._last_pnp_sig: tuple | None = None
        # landmarks: id -> model point, and whether it was anchored under a model (edge) pose
        self.lm: dict[int, np.ndarray] = {}
        self.lm_model: dict[int, bool] = {}
        self.lm_sig: dict[int, tuple] = {}  #: (corr m, ind m, rot rad, scale, triangulation view centre xyz m) (:mod:`.drift`)
        self._pose_sig = (0.0, 0.0, np.zeros((6, 6)), 0.0, 0.0)  # sigmas of the pose the map is being extended under
        self._pose_c = np.zeros(3)  # ... and its camera centre (model frame, m)
        #: the frame of the last output pose (its centre: ``_pose_c``), the relocalisation gate's
        #: reference, and the camera's steps (m per frame) between output poses, its speed (:meth:`reloc_gate_m`)
        self._last_out_k: int | None = None
        self._steps: deque[float] = deque(maxlen=300)
        self._out_sig: tuple | None = None  # sigmas of the last output map pose
        self._reloc_sig: tuple | None = None
        self.drift_log: dict[int, tuple[float, float]] = {}  #: frame -> (bound / distance, bound deg)
        self.drift_budget_frames: list[int] = []  #: map poses beyond the drift budget (not output)
        self._export: list[np.ndarray] = []
        self._n_export = 0
        self.kfs: deque[Keyframe] = deque(maxlen=max(2, self.cfg.ba_window))
        self.reloc_kfs: deque[Keyframe] = deque(maxlen=max(1, self.cfg.reloc_keyframes))
        self.prev_gray: np.ndarray | None = None
        self.T_hist: deque[np.ndarray] = deque(maxlen=2)   # last output poses, for constant velocity
        self.frames_since_fix = 0
        self.frames_since_kf = 0
        self.n_rejects = 0
        self.info_ref: float | None = None
        self.P: np.ndarray | None = None       # 6x6 anchoring covariance (v, w) of the SLAM pose
        self._recent_offsets: deque[tuple[np.ndarray, bool]] = deque(maxlen=max(1, self.cfg.consensus_window))
        self.scene_depth = 1.0
        self._cur: FrameState | None = None
        self._cur_gray: np.ndarray | None = None
        #: event counts (each key from the start: no key appears later)
        self.stats = {"keyframes": 0, "ba_runs": 0, "ba_prior_accepted": 0, "ba_prior_downweighted": 0,
                      "ba_prior_dropped": 0, "ba_errors": 0, "gate_rejects": 0, "consensus_resets": 0,
                      "relocalisations": 0, "reloc_attempts": 0, "reloc_gated": 0, "reanchors": 0, "contradictions": 0,
                      "weak_contradictions": 0, "static_world_breaks": 0, "image_refutations": 0,
                      "budget_overrides": 0}
        self.timing_ms = {"predict": 0.0, "update": 0.0, "ba": 0.0}
        self.moving_hold = False          # static-world check fired: the map does not bridge
        self._disagree_streak = 0
        self._agree_streak = 0
        self.static_world_fired: list[int] = []
        self.map_refuted: list[int] = []  #: frames whose map pose the image refuted (:meth:`refute_map_pose`)
        self._refute_streak = 0

    # ------------------------------------------------------------------ public interface
    def predict(self, k: int, gray: np.ndarray, T_cam_model_prev: np.ndarray | None) -> np.ndarray | None:
        """Track the corners into frame ``k`` and return the PnP pose ``T_cam_model`` (or None).

        Without a PnP pose (too few landmarks) it returns None: the tracker then starts from its
        last pose, as without the aid. So it does for a PnP pose with fewer than ``pnp_min_inliers``
        inliers, the bar :meth:`update` sets for trusting it (session 22: on the 8 deg/frame vase
        ``fast`` orbit the poses of 6-10 inliers started the edge fit 16-97 mm / 2.5-4.4 deg off, where
        the last pose was 3-28 mm / 0.6-2.3 deg off; those of 16-19 inliers were as good as or better
        than the last pose). (A constant-velocity guess from the previous output poses
        is still used to guide the KLT search; returned as the prediction, it doubled the edge
        poses' weakly observed depth error every frame on a 211 m flyover: 1.4 m at frame 24,
        24 m at 28, lost from 29 on, where the edges alone tracked every frame.)
        """
        import time

        t0 = time.perf_counter()
        gray = to_gray(gray)
        st = FrameState(k)
        T_cv = self._constant_velocity(T_cam_model_prev)
        if self.prev_gray is not None and len(self.pts):
            self._track(gray, T_cv)
            st.T, st.W, st.n_inliers = self._pnp(T_cv)
            st.sig = self._last_pnp_sig
        self._cur = st
        self._cur_gray = gray
        self.timing_ms["predict"] += (time.perf_counter() - t0) * 1e3
        if self._disagree_streak > 0 or self.moving_hold:
            # the map is in doubt or its world moves: predict the object's motion from the last
            # output (edge) poses instead
            return None if T_cv is None else T_cv.copy()
        if st.T is not None and st.n_inliers >= self.cfg.pnp_min_inliers:
            return st.T.copy()
        return None

    def update(self, k: int, gray: np.ndarray, T_cam_model_edges: np.ndarray | None,
               W: np.ndarray | None, healthy: bool, weak_edge_pose: np.ndarray | None = None,
               cov_edges: np.ndarray | None = None, distance_fn=None) -> tuple[np.ndarray | None, str]:
        """Fuse the edge tracker's pose for frame ``k``; return ``(T_cam_model_out or None, status)``.

        ``distance_fn``: ``T_cam_model -> metres`` to the model (the drift budget's distance): a map
        pose beyond its budget there does not judge a healthy edge pose that is within it by its
        own covariance (:meth:`AidPolicy._judge`).

        ``cov_edges``: the edge pose's 6x6 twist covariance (its residual RMS^2 x W^-1, the tracker's
        ``FrameResult.cov``): the uncertainty that model-anchored landmarks inherit (drift budget,
        :mod:`.drift`); None: ``edge_sigma_px^2 W^-1``.

        ``weak_edge_pose``: an edge pose that passed the tracker's absolute tests but not its
        calibrated health score (too weak to be output or to move the map). When the map pose lies
        beyond the output bound from it, the image supports another pose than the map (the object
        moving in the map's world, or the map gone wrong): neither is output (``lost``)."""
        import time

        if self._cur is None or self._cur.k != k:
            self.predict(k, gray, self.T_hist[-1] if self.T_hist else T_cam_model_edges)
        t0 = time.perf_counter()
        gray = self._cur_gray
        st = self._cur
        slam_ok = st.T is not None and st.n_inliers >= self.cfg.pnp_min_inliers
        edge_ok = bool(healthy) and T_cam_model_edges is not None and np.isfinite(T_cam_model_edges).all()
        W_ok = W is not None and np.isfinite(W).all()
        W = np.asarray(W, float) if W_ok else None
        if self.P is not None:
            self.P = self.P + self._process_noise()
        over = False
        if edge_ok and slam_ok and distance_fn is not None and st.sig is not None and cov_edges is not None:
            d = distance_fn(T_cam_model_edges)
            over = not self.sig_within_budget(st.sig, d) and self.sig_within_budget(self._anchor_sig(cov_edges), d)
        v = self._judge(k, T_cam_model_edges, W, st, edge_ok, slam_ok, over_budget=over)
        if (not healthy and slam_ok and not v.contradicted and weak_edge_pose is not None
                and np.isfinite(weak_edge_pose).all() and self._beyond_bound(weak_edge_pose, st.T)):
            v.contradicted = True
            self.stats["weak_contradictions"] += 1
        T_out, status = self._output(k, gray, T_cam_model_edges, W, st, slam_ok, v)
        self._out_sig = None
        if T_out is not None:
            if status == STATUS_MODEL:
                ok_cov = cov_edges is not None and np.isfinite(cov_edges).all()
                self._pose_sig = (0.0, 0.0, np.asarray(cov_edges, float).copy(), 0.0, 0.0) if ok_cov else self._model_pose_sig(W)
            else:
                self._pose_sig = self._out_sig = st.sig if st.sig is not None else (
                    math.inf, math.inf, np.full((6, 6), np.inf), math.inf, math.inf)
            self._note_output(k, camera_centre(T_out))
            W_prior = W if status == STATUS_MODEL else None
            T_out = self._maintain_map(k, gray, T_out, status, T_cam_model_edges if W_prior is not None else None,
                                       W_prior)
            self.T_hist.append(T_out.copy())
        else:
            self.T_hist.clear()
        self.prev_gray = gray
        self._cur = None
        self.timing_ms["update"] += (time.perf_counter() - t0) * 1e3
        return (None if T_out is None else T_out.copy()), status

    def _note_output(self, k: int, centre: np.ndarray) -> None:
        """Frame ``k``'s output pose has its camera centre at ``centre`` (m, model frame): the centre the
        map is extended from (``_pose_c``), and its step per frame from the last output pose (the
        relocalisation gate, :meth:`reloc_gate_m`)."""
        if self._last_out_k is not None and k > self._last_out_k:
            self._steps.append(float(np.linalg.norm(centre - self._pose_c)) / (k - self._last_out_k))
        self._pose_c = np.asarray(centre, float).copy()
        self._last_out_k = int(k)

    def landmarks(self) -> np.ndarray:
        """(N, 3) float64 model-frame map points: retired landmarks plus the current ones."""
        cur = [v for v in self.lm.values()]
        parts = self._export + ([np.asarray(cur)] if cur else [])
        return np.concatenate(parts, 0).astype(np.float64) if parts else np.zeros((0, 3))

    def close(self) -> None:
        """Release the map (the object stays usable for :meth:`landmarks`)."""
        self.prev_gray = None
        self.kfs.clear()
        self.reloc_kfs.clear()
