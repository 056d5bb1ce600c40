"""Model-aided SLAM beside the edge tracker (``mst track --slam mono|rgbd``).

The edge tracker gives a drift-free but fragile pose (it needs the model in view and a good edge
match); the SLAM gives a high-rate pose that drifts. This module fuses them like GPS/INS:

* **front end** (a few ms per frame): KLT (pyramidal Lucas-Kanade with a forward-backward check)
  tracks up to ``max_points`` corners frame to frame, replenished per grid cell with
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

Conventions: ``T_cam_model`` maps model points to the camera frame (ViSP's cMo); twists and ``W``
are in the order ``(v, w)`` (translation then rotation) as :func:`mst.core.poses.se3_exp`;
pose perturbations are on the left (camera frame): ``T = exp(delta) @ T0``. Pixels, metres, degrees.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.camera import Camera
from mst.core.poses import inv_T, pnp_ransac, se3_exp, se3_log

STATUS_MODEL, STATUS_SLAM, STATUS_LOST = "model", "slam", "lost"


@dataclass
class SlamConfig:
    """Settings of the model-aided SLAM (pixels, metres, degrees)."""

    max_points: int = 400            #: tracked corners kept per frame
    grid: tuple[int, int] = (8, 6)   #: replenishing grid (columns, rows)
    min_distance_px: float = 10.0    #: minimum distance between corners
    corner_quality: float = 0.005    #: goodFeaturesToTrack quality level
    replenish_ratio: float = 0.8     #: detect new corners when fewer than this x max_points are tracked
    klt_win: int = 11                #: KLT window (pixels)
    klt_levels: int = 3              #: KLT pyramid levels above the base
    fb_max_px: float = 1.0           #: forward-backward error bound (pixels)
    pnp_reproj_px: float = 3.0       #: RANSAC inlier bound (pixels)
    pnp_min_inliers: int = 12        #: fewer inliers: no SLAM pose
    tri_min_angle_deg: float = 1.0   #: mono: parallax needed to triangulate
    tri_max_reproj_px: float = 2.0   #: mono: reprojection bound of a new landmark
    tri_refine_deg: float = 8.0      #: mono: re-triangulate a landmark while its parallax grows, up to this
    depth_min_m: float = 0.05
    depth_max_m: float = 50.0
    depth_edge_rel: float = 0.03     #: rgbd: reject pixels whose 3x3 depth spread exceeds this x depth
    kf_min_frames: int = 3           #: frames between keyframes, at least
    kf_max_frames: int = 15          #: a keyframe at least every this many frames
    kf_angle_deg: float = 4.0        #: keyframe when the view rotated this much since the last one
    kf_translation_rel: float = 0.1  #: ... or moved this fraction of the median scene depth
    kf_track_ratio: float = 0.6      #: ... or fewer than this fraction of its landmarks are still tracked
    ba: bool | None = None           #: local bundle adjustment at keyframes (None: mono only)
    rgbd_reset_on_model: bool = True #: rgbd: re-lift all landmarks from depth under each model pose
    #: model frames output the information-weighted fusion of edge and SLAM poses (True) or the edge
    #: pose itself (False); None = by mode: fused for rgbd (metric depth landmarks are precise), the
    #: edge pose for mono (triangulated landmarks are noisier than the model fix; measured on the
    #: synthetic orbit: fusing raised the mono error from 0.07 % to 0.1 % of the distance)
    fuse_output: bool | None = None
    min_info_ratio: float = 0.5      #: with a working SLAM, an edge pose needs trace(W) >= this x its running mean
    ba_window: int = 6               #: keyframes in the local BA
    ba_max_points: int = 250         #: landmarks in one local BA (most observed first)
    ba_iterations: int = 10          #: Levenberg-Marquardt iterations per BA solve
    ba_min_observations: int = 20    #: a keyframe with fewer landmarks in the BA keeps its pose
    ba_guard_ratio: float = 1.1      #: Lhuillier bound: constrained RMSE <= ratio * e0 + px
    ba_guard_px: float = 0.1
    ba_loss_px: float = 2.0          #: Cauchy loss scale of the reprojection terms
    ba_max_error_px: float = 4.0     #: landmarks with a larger mean error after BA are dropped
    edge_sigma_px: float = 1.0       #: noise of the edge residuals: cov(edge pose) = sigma^2 W^-1
    slam_sigma_px: float = 1.0       #: noise of the KLT points: cov(PnP pose) = sigma^2 (J^T J)^-1
    #: random-walk drift of the SLAM pose per frame (x median scene depth), the filter's process
    #: noise; None: 0.001 for rgbd, 0.005 for mono (corridor runs: 1.2 % after 77 frames rgbd)
    drift_rel_per_frame: float | None = None
    drift_deg_per_frame: float | None = None  #: None: 0.05 rgbd, 0.2 mono
    gate_chi2: float = 22.46         #: chi-square (6 dof, 99.9 %) bound of the edge/SLAM disagreement
    gate_min_inliers: int = 40       #: the SLAM pose gates the edges only with this many PnP inliers
    gate_max_rejects: int = 10       #: after this many rejected healthy edge poses in a row, trust edges
    consensus_window: int = 8        #: recent healthy edge poses compared on the SLAM's offset
    consensus_min: int = 4           #: rejected edges are accepted when this many recent ones agree
    consensus_rel: float = 0.003     #: agreement: offsets within this x scene depth ...
    consensus_deg: float = 0.5       #: ... and this many degrees
    #: static-world check: this many healthy, strong edge poses in a row rejected by the gate without
    #: a consensus (each off by a different offset) = the object moves in the map's world; the same
    #: count of agreeing frames ends it
    static_world_frames: int = 3
    #: a healthy strong edge pose rejected by the gate that differs from the map pose by more than
    #: this x scene depth or these degrees (the accuracy promised for output poses) leaves the frame
    #: lost: no map pose is output against its image's evidence
    disagree_rel: float = 0.01
    disagree_deg: float = 2.0
    reloc_keyframes: int = 40        #: keyframes kept for relocalisation
    reloc_min_inliers: int = 20
    reloc_features: int = 800        #: ORB features on a frame being relocalised
    max_export_points: int = 200_000 #: cap of the exported landmark map

    @classmethod
    def from_dict(cls, d: dict | SlamConfig | None) -> SlamConfig:
        """Build from a mapping; unknown keys are ignored (the tracker may pass its whole config)."""
        if isinstance(d, SlamConfig):
            return d
        names = {f.name for f in fields(cls)}
        d = dict(d or {})
        if isinstance(d.get("slam"), dict):  # a nested "slam" section overrides
            d.update(d.pop("slam"))
        kw = {k: v for k, v in d.items() if k in names}
        if "grid" in kw:
            kw["grid"] = tuple(int(x) for x in kw["grid"])
        return cls(**kw)


@dataclass
class Keyframe:
    """A keyframe: pose, 2D observations, model constraint (pose + 6x6 W), relocalisation data."""

    k: int
    T_cam_model: np.ndarray                       # 4x4
    tids: np.ndarray                              # (M,) landmark ids observed
    uv: np.ndarray                                # (M, 2) float32 pixels
    prior_T_cam_model: np.ndarray | None = None   # model pose (edge tracker) or None
    prior_W: np.ndarray | None = None             # its 6x6 J^T J, twist order (v, w)
    desc: np.ndarray | None = None                # (R, 32) uint8 ORB descriptors (relocalisation)
    X_desc: np.ndarray | None = None              # (R, 3) float32 model points of those descriptors


@dataclass
class _FrameState:
    """What predict() found for frame k, consumed by update()."""

    k: int
    T: np.ndarray | None = None
    W: np.ndarray | None = None
    n_inliers: int = 0


# ---------------------------------------------------------------------------- small vectorised helpers
def pose_information(K: np.ndarray, X_cam: np.ndarray) -> np.ndarray:
    """6x6 information ``J^T J`` (pixels^-2 units up to sigma^2) of a pose from points ``X_cam`` (N,3).

    ``J`` (2N x 6) is the derivative of the pixel projection with respect to a left perturbation
    ``exp(delta) @ T_cam_model``, ``delta = (v, w)``.
    """
    X = np.asarray(X_cam, float)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    iz = 1.0 / z
    fx, fy = K[0, 0], K[1, 1]
    o = np.zeros_like(z)
    # d(u)/d(X_cam) then d(X_cam)/d(delta) = [I, -[X]x]
    Ju = np.stack([fx * iz, o, -fx * x * iz**2, -fx * x * y * iz**2, fx * (1 + x * x * iz**2), -fx * y * iz], 1)
    Jv = np.stack([o, fy * iz, -fy * y * iz**2, -fy * (1 + y * y * iz**2), fy * x * y * iz**2, fy * x * iz], 1)
    return Ju.T @ Ju + Jv.T @ Jv


def _vw_to_wv(M: np.ndarray) -> np.ndarray:
    """Reorder a 6x6 matrix from twist order (v, w) to (w, v) (COLMAP's prior residual order)."""
    p = [3, 4, 5, 0, 1, 2]
    return M[np.ix_(p, p)]


def prior_covariance_wv(W: np.ndarray, sigma_px: float) -> np.ndarray:
    """Covariance in COLMAP's (rotation, translation) order from an information ``W`` in (v, w) order.

    ``cov = sigma^2 (W + eps I)^-1`` with a small relative regularisation so that a rank-deficient W
    (e.g. one planar face) gives a large but finite variance in the unobserved directions.
    """
    W = 0.5 * (np.asarray(W, float) + np.asarray(W, float).T)
    eps = 1e-9 * max(np.trace(W), 1e-12)
    cov = sigma_px**2 * np.linalg.inv(W + eps * np.eye(6))
    cov = 0.5 * (cov + cov.T)
    return _vw_to_wv(cov)


def triangulate_two_view(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of N points from two views.

    ``P1``/``P2``: (N, 3, 4) or (3, 4) normalised projection matrices ``[R | t]`` (model -> camera);
    ``x1``/``x2``: (N, 2) normalised image coordinates. Returns (N, 3) model points.
    """
    P1 = np.broadcast_to(P1, (len(x1), 3, 4))
    P2 = np.broadcast_to(P2, (len(x1), 3, 4))
    A = np.stack([x1[:, :1] * P1[:, 2] - P1[:, 0], x1[:, 1:2] * P1[:, 2] - P1[:, 1],
                  x2[:, :1] * P2[:, 2] - P2[:, 0], x2[:, 1:2] * P2[:, 2] - P2[:, 1]], axis=1)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:4]


def _reg(M: np.ndarray) -> np.ndarray:
    """A symmetric 6x6 matrix with a tiny relative ridge (safe to invert when rank-deficient)."""
    M = 0.5 * (M + M.T)
    return M + 1e-9 * max(float(np.trace(M)), 1e-12) * np.eye(6)


def _to_gray(img: np.ndarray) -> np.ndarray:
    import cv2

    a = np.asarray(img)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.dtype != np.uint8:
        a = np.clip(a, 0, 255).astype(np.uint8)
    return a


def _bilinear_depth(D: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Depth image ``D`` (H, W) in metres (0/NaN = none) at sub-pixel positions ``u, v`` (N,) (pixel
    centres at integers): bilinear over the 4 neighbours, NaN where one of them has no depth.

    The nearest pixel's depth applied to a sub-pixel ray is off by up to half a pixel of depth
    gradient: centimetres on a wall or floor seen at a grazing angle, and the rounding of ``x.5``
    made the lifted map (and the drift carried on it) depend on the last bits of the pose."""
    h, w = D.shape
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    a = np.clip(u - u0, 0.0, 1.0)
    b = np.clip(v - v0, 0.0, 1.0)
    d00, d01 = D[v0, u0].astype(float), D[v0, u0 + 1].astype(float)
    d10, d11 = D[v0 + 1, u0].astype(float), D[v0 + 1, u0 + 1].astype(float)
    d = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    ok = (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)   # False for NaN too
    return np.where(ok, d, np.nan)


def _list_depth(depth_dir: Path) -> list[Path]:
    try:  # FUSE's reader when present
        from mst.pipeline.depth_io import list_depth_frames

        return list(list_depth_frames(depth_dir))
    except ImportError:
        pass
    files = [p for p in sorted(depth_dir.iterdir()) if p.suffix.lower() in (".npy", ".png", ".exr", ".bin")]
    by_stem: dict[str, Path] = {}
    for p in files:  # one file per frame: prefer .npy (metres) over .png (mm)
        if p.stem not in by_stem or p.suffix.lower() == ".npy":
            by_stem[p.stem] = p
    return [by_stem[s] for s in sorted(by_stem)]


def _read_depth(path: Path) -> np.ndarray:
    try:
        from mst.pipeline.depth_io import read_depth

        return read_depth(path)
    except ImportError:
        pass
    if path.suffix.lower() == ".npy":
        d = np.load(path).astype(np.float32)
    else:
        import cv2

        raw = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
        if raw is None:
            raise InputError(path, "cannot read the depth image")
        d = raw.astype(np.float32) * (0.001 if raw.dtype == np.uint16 else 1.0)
    d[~np.isfinite(d)] = 0
    return d


# ---------------------------------------------------------------------------- the aid
class ModelAidedSlam:
    """The SLAM aid called by the tracking loop (see :func:`make_aid` for the arguments)."""

    def __init__(self, mode: str, camera: Camera, config: dict | SlamConfig | None = None,
                 depth_dir: Path | None = None, depth_camera: Camera | None = None,
                 T_depth_color: np.ndarray | None = None):
        import cv2

        if mode not in ("mono", "rgbd"):
            raise ValueError(f"SLAM mode must be 'mono' or 'rgbd', not {mode!r}")
        self.mode = mode
        self.cfg = SlamConfig.from_dict(config)
        # rgbd: the depth-lifted landmarks are metric and re-anchored under every model pose; a BA
        # refits them to the KLT drift (measured worse), so BA is a mono feature unless asked for
        self.use_ba = (mode == "mono") if self.cfg.ba is None else bool(self.cfg.ba)
        self.cam = camera
        self.K = camera.K
        self.dist = camera.dist if camera.has_distortion else None
        self._depth_files: list[Path] = []
        if mode == "rgbd":
            if depth_dir is None:
                raise InputError(None, "--slam rgbd needs a depth folder (--depth DIR)")
            depth_dir = Path(depth_dir)
            if not depth_dir.is_dir():
                raise InputError(depth_dir, "depth folder does not exist")
            self._depth_files = _list_depth(depth_dir)
            if not self._depth_files:
                raise InputError(depth_dir, "no depth frames (.npy/.png/.exr/.bin) in the folder")
        self.K_depth = (depth_camera or camera).K
        self._depth_camera_given = depth_camera is not None
        self.T_depth_color = np.eye(4) if T_depth_color is None else np.asarray(T_depth_color, float)
        self._orb = cv2.ORB_create(nfeatures=self.cfg.reloc_features)
        self._lk = dict(winSize=(self.cfg.klt_win, self.cfg.klt_win), maxLevel=self.cfg.klt_levels,
                        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.01))
        # tracks (current frame): pixels, landmark/track ids, first observation (mono)
        self.pts = np.zeros((0, 2), np.float32)
        self.tid = np.zeros(0, np.int64)
        self.first_xn = np.zeros((0, 2))          # normalised coordinates at the first observation
        self.tri_deg = np.zeros(0)                # mono: parallax (deg) of the track's triangulation, 0 = none
        self.first_P = np.zeros((0, 3, 4))        # [R|t] of that frame (model -> camera)
        self._next_tid = 0
        # landmarks: id -> model point, and whether it was anchored under a model (edge) pose
        self.lm: dict[int, np.ndarray] = {}
        self.lm_model: dict[int, bool] = {}
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
        self._cur: _FrameState | None = None
        self.stats = {"keyframes": 0, "ba_runs": 0, "ba_prior_accepted": 0, "ba_prior_downweighted": 0,
                      "ba_prior_dropped": 0, "gate_rejects": 0, "consensus_resets": 0, "relocalisations": 0, "reloc_attempts": 0}
        self.timing_ms = {"predict": 0.0, "update": 0.0, "ba": 0.0}
        self.moving_hold = False          # static-world check fired: the map does not bridge
        self._disagree_streak = 0
        self._agree_streak = 0
        self.static_world_fired: list[int] = []

    # ------------------------------------------------------------------ public interface
    def predict(self, k: int, gray: np.ndarray, T_cam_model_prev: np.ndarray | None) -> np.ndarray | None:
        """Track the corners into frame ``k`` and return the PnP pose ``T_cam_model`` (or None).

        Without a PnP pose (too few landmarks) it returns None: the tracker then starts from its
        last pose, as without the aid. (A constant-velocity guess from the previous output poses
        is still used to guide the KLT search; returned as the prediction, it doubled the edge
        poses' weakly observed depth error every frame on a 211 m flyover: 1.4 m at frame 24,
        24 m at 28, lost from 29 on, where the edges alone tracked every frame.)
        """
        import time

        t0 = time.perf_counter()
        gray = _to_gray(gray)
        st = _FrameState(k)
        T_cv = self._constant_velocity(T_cam_model_prev)
        if self.prev_gray is not None and len(self.pts):
            self._track(gray, T_cv)
            st.T, st.W, st.n_inliers = self._pnp(T_cv)
        self._cur = st
        self._cur_gray = gray
        self.timing_ms["predict"] += (time.perf_counter() - t0) * 1e3
        if self._disagree_streak > 0 or self.moving_hold:
            # the map is in doubt or its world moves: predict the object's motion from the last
            # output (edge) poses instead
            return None if T_cv is None else T_cv.copy()
        if st.T is not None:
            return st.T.copy()
        return None

    def update(self, k: int, gray: np.ndarray, T_cam_model_edges: np.ndarray | None,
               W: np.ndarray | None, healthy: bool, weak_edge_pose: np.ndarray | None = None
               ) -> tuple[np.ndarray | None, str]:
        """Fuse the edge tracker's pose for frame ``k``; return ``(T_cam_model_out or None, status)``.

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
        reset = False
        moving = False
        contradicted = False  # a healthy strong edge pose contradicts the map beyond the accuracy bound
        if edge_ok and slam_ok and self.moving_hold:
            # the object moves in the map's world: no gate, the map follows the model pose; leave this
            # state after static_world_frames frames in a row in which the map agrees again
            agree_now = self._consistent(T_cam_model_edges, W, st, fresh=True)
            self._agree_streak = self._agree_streak + 1 if agree_now else 0
            if self._agree_streak >= self.cfg.static_world_frames:
                self.moving_hold = False
            else:
                reset = moving = True
        elif edge_ok and slam_ok:
            strong = self._strong_enough(W)
            passed = strong and self._gate(T_cam_model_edges, W, st)
            # a weak (partial-view, ill-conditioned) edge pose never votes for a consensus reset
            agree = self._consensus(np.asarray(T_cam_model_edges, float), st.T, rejected=not passed) if strong else 0
            if not passed:
                edge_ok = False
                if agree >= self.cfg.consensus_min:
                    # several recent edge poses agree with this one on the SLAM's offset: the SLAM
                    # (anchored on an early wrong edge pose, or drifted) is the one that is off
                    edge_ok = reset = True
                    self.P = None
                    self._recent_offsets.clear()
                    self.stats["consensus_resets"] += 1
                elif strong and agree > 0:
                    self._disagree_streak = 0  # the same offset again: a wrong match or drift, not motion
                    contradicted = self._beyond_bound(T_cam_model_edges, st.T)
                elif strong:
                    self._disagree_streak += 1
                    contradicted = self._beyond_bound(T_cam_model_edges, st.T)
                    if self._disagree_streak >= self.cfg.static_world_frames:
                        # static-world check: healthy, strong edge poses keep disagreeing with the
                        # map, each by a different offset (no consensus): the object moves in the
                        # map's world (carried, turntable). Stop bridging with the map, follow the
                        # model, re-anchor the map to it every frame until they agree again
                        edge_ok = reset = moving = True
                        self.moving_hold = True
                        self._agree_streak = 0
                        self.static_world_fired.append(int(k))
                        self.stats["static_world_breaks"] = self.stats.get("static_world_breaks", 0) + 1
            else:
                self._disagree_streak = 0
        if (not healthy and slam_ok and not contradicted and weak_edge_pose is not None
                and np.isfinite(weak_edge_pose).all() and self._beyond_bound(weak_edge_pose, st.T)):
            contradicted = True
            self.stats["weak_contradictions"] = self.stats.get("weak_contradictions", 0) + 1
        if edge_ok:
            T_out, status = np.asarray(T_cam_model_edges, float).copy(), STATUS_MODEL
            if W is not None:
                T_fused = self._fuse(T_out, W, st if slam_ok and not moving else _FrameState(k))
                if self.cfg.fuse_output if self.cfg.fuse_output is not None else self.mode == "rgbd":
                    T_out = T_fused
            if slam_ok and (self.frames_since_fix > 0 or reset):
                self._reanchor(T_out, st.T, everything=reset)  # reset the map to the model
            if moving:
                self.P = None
                self._recent_offsets.clear()
                self.n_rejects = 0
            self.frames_since_fix = 0
            if W is not None:
                tr = float(np.trace(W))
                self.info_ref = tr if self.info_ref is None else 0.9 * self.info_ref + 0.1 * tr
        elif slam_ok and not self.moving_hold and not contradicted and self._disagree_streak == 0:
            T_out, status = st.T, STATUS_SLAM
            self.frames_since_fix += 1
        elif contradicted or (slam_ok and self._disagree_streak > 0):
            # the image supports another pose than the map by more than the output accuracy (a wrong
            # edge match, or the object moving in the map's world): which is right is not known
            # yet, so neither is output; the map is kept (not dragged) until the check decides
            T_out, status = None, STATUS_LOST
            self.frames_since_fix += 1
            self.stats["contradictions"] = self.stats.get("contradictions", 0) + 1
        elif self.moving_hold:
            # the map's world moves against the object: a map pose is no model pose
            T_out, status = None, STATUS_LOST
            self.frames_since_fix += 1
        else:
            T_out = self._relocalise(gray)
            status = STATUS_SLAM if T_out is not None else STATUS_LOST
            self.frames_since_fix += 1
        if T_out is not None:
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

    # ------------------------------------------------------------------ front end
    def _constant_velocity(self, T_prev: np.ndarray | None) -> np.ndarray | None:
        if len(self.T_hist) == 2:
            T1, T0 = self.T_hist[-1], self.T_hist[-2]
            return (T1 @ inv_T(T0)) @ T1
        if self.T_hist:
            return self.T_hist[-1].copy()
        return None if T_prev is None else np.asarray(T_prev, float)

    def _project(self, T_cam_model: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model points (N,3) -> pixels (N,2) and camera depth (N,)."""
        Xc = X @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
        z = Xc[:, 2]
        zs = np.where(z > 1e-9, z, 1e-9)
        if self.dist is None:
            uv = (Xc[:, :2] / zs[:, None]) * [self.K[0, 0], self.K[1, 1]] + [self.K[0, 2], self.K[1, 2]]
        else:
            uv = self.cam.project(np.c_[Xc[:, :2], zs])
        return uv, z

    def _normalised(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N,2) -> normalised image coordinates (N,2) (distortion removed)."""
        import cv2

        if len(uv) == 0:
            return np.zeros((0, 2))
        if self.dist is None:
            return (np.asarray(uv, float) - [self.K[0, 2], self.K[1, 2]]) / [self.K[0, 0], self.K[1, 1]]
        return cv2.undistortPoints(np.asarray(uv, np.float64).reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2)

    def _landmark_array(self, tids: np.ndarray) -> np.ndarray:
        nan = np.full(3, np.nan)
        lm = self.lm
        return np.array([lm.get(int(t), nan) for t in tids]).reshape(-1, 3)

    def _track(self, gray: np.ndarray, T_cv: np.ndarray | None) -> None:
        """KLT prev -> gray with a forward-backward check; drops lost tracks."""
        import cv2

        p0 = self.pts.reshape(-1, 1, 2)
        guess = p0.copy()
        flags = 0
        if T_cv is not None:
            X = self._landmark_array(self.tid)
            has = np.isfinite(X[:, 0])
            if has.sum() >= 6:
                uv, z = self._project(T_cv, X[has])
                ok = z > 0
                g = guess[has, 0]
                g[ok] = uv[ok]
                guess[has, 0] = g
                d = np.median((uv[ok] - self.pts[has][ok]), axis=0) if ok.any() else np.zeros(2)
                guess[~has, 0] += d
                flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        guess = guess.astype(np.float32)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self.prev_gray, gray, p0, guess, flags=flags, **self._lk)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self.prev_gray, p1, p0.copy(),
                                              flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk)
        h, w = gray.shape
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm(pb.reshape(-1, 2) - self.pts, axis=1)
        keep = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.cfg.fb_max_px)
        keep &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
        self._keep_tracks(keep)
        self.pts = p1[keep].astype(np.float32)

    def _keep_tracks(self, keep: np.ndarray) -> None:
        self.pts = self.pts[keep]
        self.tid = self.tid[keep]
        self.first_xn = self.first_xn[keep]
        self.tri_deg = self.tri_deg[keep]
        self.first_P = self.first_P[keep]

    def _pnp(self, T_guess: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None, int]:
        """PnP + RANSAC on tracks with landmarks; drops outlier tracks' landmarks."""
        import cv2

        X = self._landmark_array(self.tid)
        has = np.flatnonzero(np.isfinite(X[:, 0]))
        if len(has) < max(6, self.cfg.pnp_min_inliers):
            return None, None, 0
        Xh, uvh = X[has], self.pts[has].astype(np.float64)
        ok, rvec, tvec, inl = pnp_ransac(Xh, uvh, self.K, self.dist, 100, self.cfg.pnp_reproj_px, cv2.SOLVEPNP_SQPNP)
        if not ok or inl is None or len(inl) < 6:
            return None, None, 0
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(Xh[inl], uvh[inl], self.K, self.dist, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, tvec.ravel()
        uv, z = self._project(T, Xh)
        err = np.linalg.norm(uv - uvh, axis=1)
        good = (err < self.cfg.pnp_reproj_px) & (z > 0)
        # outliers: the landmark is wrong or the track slipped -> drop the track
        keep = np.ones(len(self.tid), bool)
        keep[has[~good]] = False
        for t in self.tid[has[~good]]:
            self.lm.pop(int(t), None)
        self._keep_tracks(keep)
        Xc = Xh[good] @ R.T + T[:3, 3]
        if len(Xc):
            self.scene_depth = float(np.median(Xc[:, 2]))
        return T, pose_information(self.K, Xc), int(good.sum())

    # ------------------------------------------------------------------ fusion gate
    def _process_noise(self) -> np.ndarray:
        """Per-frame random-walk covariance (v, w) of the SLAM pose against the model frame."""
        cfg = self.cfg
        rate = cfg.drift_rel_per_frame if cfg.drift_rel_per_frame is not None else (
            0.001 if self.mode == "rgbd" else 0.005)
        deg = cfg.drift_deg_per_frame if cfg.drift_deg_per_frame is not None else (
            0.05 if self.mode == "rgbd" else 0.2)
        return np.diag(np.r_[np.full(3, (rate * self.scene_depth) ** 2), np.full(3, np.radians(deg) ** 2)])

    def _slam_cov(self, st: _FrameState) -> np.ndarray:
        """6x6 covariance (v, w) of the SLAM pose of this frame in the model frame: the filter's
        anchoring covariance ``P`` (grown by the process noise) plus the PnP noise."""
        P = self.P if self.P is not None else np.diag(np.r_[np.full(3, self.scene_depth**2), np.full(3, 1.0)])
        return P + self.cfg.slam_sigma_px**2 * np.linalg.inv(_reg(st.W))

    def _fuse(self, T_edges: np.ndarray, W_edges: np.ndarray | None, st: _FrameState) -> np.ndarray:
        """Kalman update of the SLAM pose with the edge pose (left perturbation of the SLAM pose);
        updates the anchoring covariance ``P``."""
        Se = self.cfg.edge_sigma_px**2 * np.linalg.inv(_reg(np.asarray(W_edges, float)))
        if st.W is None:
            self.P = Se
            return np.asarray(T_edges, float).copy()
        S = self._slam_cov(st)
        K = S @ np.linalg.inv(_reg(S + Se))
        delta = se3_log(np.asarray(T_edges, float) @ inv_T(st.T))
        I6 = np.eye(6)
        self.P = _reg((I6 - K) @ S @ (I6 - K).T + K @ Se @ K.T)  # Joseph form
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

    def _consistent(self, T_edges: np.ndarray, W_edges: np.ndarray | None, st: _FrameState, fresh: bool = False) -> bool:
        """The chi-square test of :meth:`_gate` without its bookkeeping (True: edges and map agree).

        ``fresh``: the map was re-anchored onto the previous frame's edge pose, so its anchoring
        covariance is that pose's (about this frame's edge covariance), not the filter's ``P``."""
        if W_edges is None or st.W is None or (st.n_inliers < self.cfg.gate_min_inliers and not fresh):
            return not fresh
        delta = se3_log(np.asarray(T_edges, float) @ inv_T(st.T))
        Se = self.cfg.edge_sigma_px**2 * np.linalg.inv(_reg(np.asarray(W_edges, float)))
        if fresh:
            cov = 2.0 * Se + self.cfg.slam_sigma_px**2 * np.linalg.inv(_reg(st.W))
        else:
            cov = self._slam_cov(st) + Se
        return float(delta @ np.linalg.solve(cov, delta)) <= self.cfg.gate_chi2

    def _strong_enough(self, W: np.ndarray | None) -> bool:
        """Edge information (trace of W) against its running mean over accepted frames: a model
        half out of the view (entering or leaving) gives biased poses; the SLAM carries instead."""
        if W is None or self.info_ref is None:
            return True
        return float(np.trace(W)) >= self.cfg.min_info_ratio * self.info_ref

    def _gate(self, T_edges: np.ndarray, W_edges: np.ndarray | None, st: _FrameState) -> bool:
        """True when the edge pose is consistent with the SLAM pose (or the SLAM is not confident)."""
        cfg = self.cfg
        if st.n_inliers < cfg.gate_min_inliers or W_edges is None or st.W is None:
            self.n_rejects = 0
            return True
        if self.n_rejects >= cfg.gate_max_rejects:  # the edges insist: the SLAM is probably the one off
            self.n_rejects = 0
            return True
        delta = se3_log(np.asarray(T_edges, float) @ inv_T(st.T))
        cov = self._slam_cov(st) + cfg.edge_sigma_px**2 * np.linalg.inv(_reg(np.asarray(W_edges, float)))
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
        self.stats["reanchors"] = self.stats.get("reanchors", 0) + 1

    # ------------------------------------------------------------------ map maintenance
    def _maintain_map(self, k: int, gray: np.ndarray, T: np.ndarray, status: str,
                      T_prior: np.ndarray | None, W_prior: np.ndarray | None) -> np.ndarray:
        """New landmarks, new corners, keyframes and local BA for frame k with pose ``T``.

        Returns the (possibly BA-refined, for status 'slam') output pose.
        """
        if self.mode == "rgbd":
            self._lift_depth(k, T, status == STATUS_MODEL)
        else:
            self._triangulate(T, status == STATUS_MODEL)
        n_before = len(self.pts)
        self.frames_since_kf += 1
        need_kf = self._need_keyframe(T)
        if n_before < self.cfg.replenish_ratio * self.cfg.max_points or need_kf:
            self._replenish(gray, T)
            if self.mode == "rgbd" and len(self.pts) > n_before:
                self._lift_depth(k, T, status == STATUS_MODEL, only_new=n_before)
        if need_kf:
            T = self._add_keyframe(k, gray, T, status, T_prior, W_prior)
        return T

    def _need_keyframe(self, T: np.ndarray) -> bool:
        cfg = self.cfg
        if not self.kfs:
            return True
        if self.frames_since_kf < cfg.kf_min_frames:
            return False
        if self.frames_since_kf >= cfg.kf_max_frames:
            return True
        last = self.kfs[-1]
        dT = T @ inv_T(last.T_cam_model)
        ang = math.degrees(np.linalg.norm(se3_log(dT)[3:]))
        C1, C0 = inv_T(T)[:3, 3], inv_T(last.T_cam_model)[:3, 3]
        if ang > cfg.kf_angle_deg or np.linalg.norm(C1 - C0) > cfg.kf_translation_rel * self.scene_depth:
            return True
        alive = np.isin(last.tids, self.tid).sum()
        return alive < cfg.kf_track_ratio * max(len(last.tids), 1)

    def _replenish(self, gray: np.ndarray, T: np.ndarray) -> None:
        """Detect new corners away from the tracked ones, at most a fair share per grid cell."""
        import cv2

        cfg = self.cfg
        n_new = cfg.max_points - len(self.pts)
        if n_new <= 0:
            return
        h, w = gray.shape
        mask = np.full((h, w), 255, np.uint8)
        r = int(cfg.min_distance_px)
        for x, y in self.pts.astype(np.int32):  # one small disc per track (<= max_points)
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        c = cv2.goodFeaturesToTrack(gray, maxCorners=2 * n_new + 50, qualityLevel=cfg.corner_quality,
                                    minDistance=cfg.min_distance_px, mask=mask, blockSize=5)
        if c is None:
            return
        c = c.reshape(-1, 2)
        gx, gy = cfg.grid
        cell_new = (np.minimum((c[:, 1] * gy / h).astype(int), gy - 1) * gx
                    + np.minimum((c[:, 0] * gx / w).astype(int), gx - 1))
        cell_old = (np.minimum((self.pts[:, 1] * gy / h).astype(int), gy - 1) * gx
                    + np.minimum((self.pts[:, 0] * gx / w).astype(int), gx - 1))
        cap = int(math.ceil(cfg.max_points / (gx * gy)))
        room = np.maximum(cap - np.bincount(cell_old, minlength=gx * gy), 0)
        # corners come sorted by quality: rank within each cell, keep rank < room
        order = np.argsort(cell_new, kind="stable")
        cs = cell_new[order]
        start = np.searchsorted(cs, cs, side="left")
        rank = np.arange(len(cs)) - start
        sel = order[rank < room[cs]]
        if len(sel) < n_new:  # fill up with the best remaining corners anywhere
            rest = np.setdiff1d(np.arange(len(c)), sel)
            sel = np.r_[sel, rest[: n_new - len(sel)]]
        sel = np.sort(sel)[:n_new]
        new = c[sel].astype(np.float32)
        m = len(new)
        self.pts = np.r_[self.pts, new].astype(np.float32)
        self.tid = np.r_[self.tid, np.arange(self._next_tid, self._next_tid + m)]
        self._next_tid += m
        self.first_xn = np.r_[self.first_xn, self._normalised(new)]
        self.tri_deg = np.r_[self.tri_deg, np.zeros(m)]
        self.first_P = np.r_[self.first_P, np.broadcast_to(T[:3], (m, 3, 4))]

    def _lift_depth(self, k: int, T: np.ndarray, model_pose: bool, only_new: int | None = None) -> None:
        """rgbd: give tracks without a landmark (and, under a model pose, landmarks anchored under a
        SLAM pose) a model point from depth frame k."""
        if k >= len(self._depth_files):
            return
        if only_new is not None:
            idx = np.arange(only_new, len(self.tid))
        else:
            if model_pose and self.cfg.rgbd_reset_on_model:
                # the SLAM is reset to the model pose (RGB-D paper): re-lift every track, which also
                # cancels the slow drift of KLT tracks against their landmarks
                need = np.ones(len(self.tid), bool)
            else:
                need = ~np.isfinite(self._landmark_array(self.tid)[:, 0])
            idx = np.flatnonzero(need)
        if len(idx) == 0:
            return
        X_cam = self._depth_at(self._depth_frame(k), self.pts[idx])
        ok = np.isfinite(X_cam[:, 0])
        if not ok.any():
            return
        T_model_cam = inv_T(T)
        X_model = X_cam[ok] @ T_model_cam[:3, :3].T + T_model_cam[:3, 3]
        for t, x in zip(self.tid[idx[ok]], X_model):
            self.lm[int(t)] = x
            self.lm_model[int(t)] = model_pose

    def _depth_frame(self, k: int) -> np.ndarray | None:
        """Depth frame k (metres, 0 = none), cached; None past the end of the depth list."""
        if k >= len(self._depth_files):
            return None
        if getattr(self, "_depth_k", None) != k:
            self._depth = _read_depth(self._depth_files[k])
            self._depth_k = k
            h, w = self._depth.shape
            if not self._depth_camera_given and self.cam.width and w != self.cam.width:
                # registered depth at another resolution (e.g. colour frames resized by --scale)
                self.K_depth = self.cam.scaled(w / self.cam.width).K
        return self._depth

    def _depth_at(self, D: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Colour pixels (N,2) -> colour-camera points (N,3) (NaN where no valid depth).

        The depth image lives in the depth camera (``K_depth``, ``T_depth_color``); the depth along
        each colour ray is found by fixed-point iteration on the depth image (exact when registered).
        """
        cfg = self.cfg
        xn = self._normalised(uv)
        r_c = np.c_[xn, np.ones(len(xn))]                          # colour ray, z = 1
        R, t = self.T_depth_color[:3, :3], self.T_depth_color[:3, 3]
        Kd = self.K_depth
        h, w = D.shape
        Rr = r_c @ R.T                                             # ray direction in the depth frame
        z = np.full(len(xn), max(self.scene_depth, cfg.depth_min_m))
        valid = np.ones(len(xn), bool)
        for _ in range(3 if np.any(t != 0) or np.any(R != np.eye(3)) else 1):
            P_d = z[:, None] * Rr + t
            zd = np.where(P_d[:, 2] > 1e-6, P_d[:, 2], 1e-6)
            uf = Kd[0, 0] * P_d[:, 0] / zd + Kd[0, 2]
            vf = Kd[1, 1] * P_d[:, 1] / zd + Kd[1, 2]
            u, v = np.rint(uf).astype(int), np.rint(vf).astype(int)
            inside = (u >= 1) & (v >= 1) & (u < w - 1) & (v < h - 1)
            uc, vc = np.clip(u, 1, w - 2), np.clip(v, 1, h - 2)
            dm = _bilinear_depth(D, uf, vf)
            valid = inside & np.isfinite(dm) & (dm > cfg.depth_min_m) & (dm < cfg.depth_max_m)
            dz = np.where(np.abs(Rr[:, 2]) > 1e-9, Rr[:, 2], 1e-9)
            z = np.where(valid, (dm - t[2]) / dz, z)
        # depth discontinuity test on the 3x3 neighbourhood
        nb = np.stack([D[vc + dv, uc + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], 1).astype(float)
        nb_ok = np.all(np.isfinite(nb) & (nb > 0), axis=1)
        spread = np.where(nb_ok, nb.max(1) - nb.min(1), np.inf)
        valid &= spread < cfg.depth_edge_rel * np.maximum(dm, 1e-6)
        valid &= (z > cfg.depth_min_m) & (z < cfg.depth_max_m)
        X = z[:, None] * r_c
        X[~valid] = np.nan
        return X

    def _triangulate(self, T: np.ndarray, model_pose: bool) -> None:
        """mono: triangulate tracks from their first view and this one once the parallax is enough,
        and re-triangulate young landmarks while their parallax keeps growing (depth error ~ pose
        error / baseline: a landmark from a 1 deg baseline is refined at 1.5, 2.25, ... deg)."""
        cfg = self.cfg
        if not len(self.tid):
            return
        has = np.array([int(t) in self.lm for t in self.tid], bool)
        self.tri_deg[~has] = 0.0
        cand = np.flatnonzero(self.tri_deg < cfg.tri_refine_deg)
        if len(cand) == 0:
            return
        x1 = self.first_xn[cand]
        P1 = self.first_P[cand]
        x2 = self._normalised(self.pts[cand])
        # parallax: angle between the two bearing rays in the model frame
        r1 = np.einsum("nji,nj->ni", P1[:, :, :3], np.c_[x1, np.ones(len(x1))])
        r2 = np.c_[x2, np.ones(len(x2))] @ T[:3, :3]
        cosang = np.sum(r1 * r2, 1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
        ang = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
        ok = (ang > cfg.tri_min_angle_deg) & (ang > 1.5 * self.tri_deg[cand])
        if not ok.any():
            return
        cand, x1, P1, x2, ang = cand[ok], x1[ok], P1[ok], x2[ok], ang[ok]
        X = triangulate_two_view(P1, T[:3], x1, x2)
        # checks: finite, in front of both cameras, reprojection in both views
        X1c = np.einsum("nij,nj->ni", P1[:, :, :3], X) + P1[:, :, 3]
        X2c = X @ T[:3, :3].T + T[:3, 3]
        f = self.K[0, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            e1 = np.linalg.norm(X1c[:, :2] / X1c[:, 2:3] - x1, axis=1) * f
            e2 = np.linalg.norm(X2c[:, :2] / X2c[:, 2:3] - x2, axis=1) * f
        # no far bound: the parallax test above already bounds the depth error (depth_max_m is the
        # depth sensor's range; a 50 m cap rejected every landmark of a 200 m UAV flyover)
        good = (np.isfinite(X).all(1) & (X1c[:, 2] > cfg.depth_min_m) & (X2c[:, 2] > cfg.depth_min_m)
                & (e1 < cfg.tri_max_reproj_px) & (e2 < cfg.tri_max_reproj_px))
        self.tri_deg[cand[good]] = ang[good]
        for t, x in zip(self.tid[cand[good]], X[good]):
            self.lm[int(t)] = x
            self.lm_model[int(t)] = model_pose

    # ------------------------------------------------------------------ keyframes, BA, relocalisation
    def _add_keyframe(self, k: int, gray: np.ndarray, T: np.ndarray, status: str,
                      T_prior: np.ndarray | None, W_prior: np.ndarray | None) -> np.ndarray:

        self.frames_since_kf = 0
        X = self._landmark_array(self.tid)
        kf = Keyframe(k, T.copy(), self.tid.copy(), self.pts.copy(),
                      None if T_prior is None else np.asarray(T_prior, float).copy(),
                      None if W_prior is None else W_prior.copy())
        # relocalisation data: ORB features of the keyframe with model points (rgbd: lifted from
        # depth; mono: the landmark of a track within 3 px)
        kps, desc = self._orb.detectAndCompute(gray, None)
        if desc is not None and len(kps) >= self.cfg.reloc_min_inliers:
            uv = np.array([kp.pt for kp in kps], np.float64)
            D = self._depth_frame(k) if self.mode == "rgbd" else None
            if D is not None:
                Xc = self._depth_at(D, uv)
                Xk = Xc @ inv_T(T)[:3, :3].T + inv_T(T)[:3, 3]
            else:
                Xk = np.full((len(uv), 3), np.nan)
                has = np.flatnonzero(np.isfinite(X[:, 0]))
                if len(has):
                    q = self.pts[has].astype(np.float64)
                    d2 = (uv**2).sum(1)[:, None] + (q**2).sum(1)[None, :] - 2.0 * uv @ q.T
                    j = np.argmin(d2, axis=1)
                    near = d2[np.arange(len(uv)), j] < 9.0
                    Xk[near] = X[has[j[near]]]
            ok = np.isfinite(Xk[:, 0])
            if ok.sum() >= self.cfg.reloc_min_inliers:
                kf.desc, kf.X_desc = desc[ok], Xk[ok].astype(np.float32)
        evicted = self.kfs[0] if len(self.kfs) == self.kfs.maxlen else None
        self.kfs.append(kf)
        self.reloc_kfs.append(kf)
        self.stats["keyframes"] += 1
        if evicted is not None:
            # the evicted keyframe keeps only its relocalisation data (it stays in reloc_kfs)
            evicted.tids, evicted.uv = np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
            self._prune_landmarks()
        if self.use_ba and len(self.kfs) >= 3:
            T = self._local_ba(status)
        return T

    def _prune_landmarks(self) -> None:
        """Forget landmarks neither tracked nor observed in the BA window (export the mono ones)."""
        live = set(self.tid.tolist())
        for kf in self.kfs:
            live.update(kf.tids.tolist())
        dead = [t for t in self.lm if t not in live]
        if not dead:
            return
        pts = np.array([self.lm[t] for t in dead])
        for t in dead:
            del self.lm[t]
            self.lm_model.pop(t, None)
        room = self.cfg.max_export_points - self._n_export
        if room > 0:
            self._export.append(pts[:room])
            self._n_export += min(room, len(pts))

    def _local_ba(self, status: str) -> np.ndarray:
        """Guarded, model-constrained local BA over the keyframe window; returns the current pose."""
        import time

        t0 = time.perf_counter()
        try:
            return self._local_ba_impl(status)
        except (RuntimeError, ValueError, np.linalg.LinAlgError):  # a degenerate window: skip this BA
            self.stats["ba_errors"] = self.stats.get("ba_errors", 0) + 1
            return self.kfs[-1].T_cam_model.copy()
        finally:
            self.timing_ms["ba"] += (time.perf_counter() - t0) * 1e3
            self.stats["ba_runs"] += 1

    def _local_ba_impl(self, status: str) -> np.ndarray:
        import pyceres
        import pycolmap
        import pycolmap.cost_functions as cf

        cfg = self.cfg
        kfs = list(self.kfs)
        cur = kfs[-1]
        T_in = cur.T_cam_model.copy()   # this frame's output pose before the BA
        # landmarks seen by >= 2 window keyframes
        all_t = np.concatenate([kf.tids for kf in kfs])
        u, cnt = np.unique(all_t, return_counts=True)
        u = u[cnt >= 2]
        u = np.array([t for t in u if int(t) in self.lm], np.int64)
        if len(u) < 10:
            return cur.T_cam_model
        if len(u) > cfg.ba_max_points:
            c2 = cnt[np.isin(np.unique(all_t), u)]
            u = np.sort(u[np.argsort(-c2, kind="stable")[: cfg.ba_max_points]])
        if self.dist is None:
            cam = pycolmap.Camera(model="PINHOLE", width=self.cam.width or 640, height=self.cam.height or 480,
                                  params=[self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]], camera_id=1)
        else:
            d = np.zeros(4)
            d[: min(4, len(self.dist))] = self.dist[:4]
            cam = pycolmap.Camera(model="OPENCV", width=self.cam.width or 640, height=self.cam.height or 480,
                                  params=[self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *d], camera_id=1)

        def build():
            rec = pycolmap.Reconstruction()
            rec.add_camera_with_trivial_rig(cam)
            obs_idx = []
            for i, kf in enumerate(kfs):
                sel = np.flatnonzero(np.isin(kf.tids, u))
                obs_idx.append(sel)
                img = pycolmap.Image(name=f"{i}", points2D=pycolmap.Point2DList(
                    [pycolmap.Point2D(xy) for xy in kf.uv[sel].astype(np.float64)]), camera_id=1, image_id=i + 1)
                T = kf.T_cam_model
                rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy()))
            pid_of = {}
            for t in u:
                pid_of[int(t)] = rec.add_point3D(self.lm[int(t)], pycolmap.Track())
            for i, kf in enumerate(kfs):
                for j, t in enumerate(kf.tids[obs_idx[i]]):
                    pid = pid_of[int(t)]
                    rec.add_observation(pid, pycolmap.TrackElement(i + 1, j))
            return rec, pid_of

        def options():
            bo = pycolmap.BundleAdjustmentOptions()
            bo.refine_focal_length = False
            bo.refine_principal_point = False
            bo.refine_extra_params = False
            bo.print_summary = False
            bo.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
            bo.ceres.loss_function_scale = cfg.ba_loss_px
            bo.ceres.solver_options.max_num_iterations = cfg.ba_iterations
            bo.ceres.solver_options.num_threads = 1
            return bo

        def rmse(rec) -> float:
            rec.update_point_3d_errors()
            errs = np.array([p.error for p in rec.points3D.values()])
            # robust: ignore gross outliers (they are removed afterwards)
            errs = errs[errs < 4 * cfg.ba_max_error_px]
            return float(np.sqrt(np.mean(errs**2))) if len(errs) else np.inf

        def solve(rec, priors: list[tuple[int, np.ndarray, np.ndarray]], fixed: list[int]):
            bo = options()
            bc = pycolmap.BundleAdjustmentConfig()
            for i in range(len(kfs)):
                bc.add_image(i + 1)
            bc.set_constant_cam_intrinsics(1)
            for i in sorted(set(fixed) | weak):
                bc.set_constant_rig_from_world_pose(i + 1)
            ba = pycolmap.create_default_ceres_bundle_adjuster(bo, bc, rec)
            prob = ba.problem
            for i, cov, Tp in priors:
                prob.add_residual_block(cf.AbsolutePosePriorCost(cov, pycolmap.Rigid3d(
                    pycolmap.Rotation3d(Tp[:3, :3]), Tp[:3, 3].copy())), None, [rec.frame(i + 1).rig_from_world.params])
            summ = pyceres.SolverSummary()
            pyceres.solve(bo.ceres.create_solver_options(bc, prob), prob, summ)

        # keyframes with few observations in this BA are held (a free, weakly observed pose wanders)
        n_obs = [int(np.isin(kf.tids, u).sum()) for kf in kfs]
        weak = {i for i, n in enumerate(n_obs) if n < cfg.ba_min_observations}
        # 1) unconstrained BA, gauge fixed by the two oldest keyframes (scale too, for mono)
        rec_init, pid_of = build()
        rec0 = pycolmap.Reconstruction(rec_init)
        solve(rec0, [], [0, 1])
        e0 = rmse(rec0)
        # 2) constrained BA with the model priors
        priors = [(i, prior_covariance_wv(kf.prior_W, cfg.edge_sigma_px), kf.prior_T_cam_model)
                  for i, kf in enumerate(kfs) if kf.prior_W is not None and kf.prior_T_cam_model is not None]
        result = rec0
        if priors:
            # two or more 6-DoF priors fix the gauge (scale included); with one, the oldest
            # keyframe keeps the scale
            fixed = [] if len(priors) >= 2 else [0]
            bound = cfg.ba_guard_ratio * e0 + cfg.ba_guard_px
            for scale, key in ((1.0, "ba_prior_accepted"), (100.0, "ba_prior_downweighted")):
                rec1 = pycolmap.Reconstruction(rec_init)
                solve(rec1, [(i, c * scale, Tp) for i, c, Tp in priors], fixed)
                if rmse(rec1) <= bound:
                    result = rec1
                    self.stats[key] += 1
                    break
            else:
                self.stats["ba_prior_dropped"] += 1
        # write back: keyframe poses, landmarks; drop landmarks with large errors
        for i, kf in enumerate(kfs):
            kf.T_cam_model = np.eye(4)
            kf.T_cam_model[:3] = result.image(i + 1).cam_from_world().matrix()
        result.update_point_3d_errors()
        for t, pid in pid_of.items():
            p = result.point3D(pid)
            if p.error > cfg.ba_max_error_px or not np.isfinite(p.xyz).all():
                self.lm.pop(t, None)
            else:
                self.lm[t] = np.asarray(p.xyz, float).copy()
        if status != STATUS_SLAM:
            return T_in  # under a model pose the output stays the (fused) model pose
        return cur.T_cam_model.copy()

    def _relocalise(self, gray: np.ndarray) -> np.ndarray | None:
        """ORB matching against the stored keyframes (newest first) + PnP RANSAC."""
        import cv2

        cands = [kf for kf in reversed(self.reloc_kfs) if kf.desc is not None and len(kf.desc) >= self.cfg.reloc_min_inliers]
        if not cands:
            return None
        self.stats["reloc_attempts"] += 1
        kps, desc = self._orb.detectAndCompute(gray, None)
        if desc is None or len(kps) < self.cfg.reloc_min_inliers:
            return None
        uv_all = np.array([kp.pt for kp in kps], np.float64)
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        for kf in cands[:10]:
            m = bf.knnMatch(kf.desc, desc, k=2)
            good = [(a.queryIdx, a.trainIdx) for a, *b in m if b and a.distance < 0.8 * b[0].distance and a.distance < 64]
            if len(good) < self.cfg.reloc_min_inliers:
                continue
            qi, ti = np.array(good).T
            X, uv = kf.X_desc[qi].astype(np.float64), uv_all[ti]
            ok, rvec, tvec, inl = pnp_ransac(X, uv, self.K, self.dist, 200, self.cfg.pnp_reproj_px, cv2.SOLVEPNP_SQPNP)
            if not ok or inl is None or len(inl) < self.cfg.reloc_min_inliers:
                continue
            inl = inl.ravel()
            rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[inl], self.K, self.dist, rvec, tvec)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            # restart the tracks from the inlier matches (new landmark ids, positions from the keyframe)
            m_ = len(inl)
            new_t = np.arange(self._next_tid, self._next_tid + m_)
            self._next_tid += m_
            for t, x in zip(new_t, X[inl]):
                self.lm[int(t)] = x
                self.lm_model[int(t)] = False
            self.pts = np.r_[self.pts, uv[inl].astype(np.float32)].astype(np.float32)
            self.tid = np.r_[self.tid, new_t]
            self.first_xn = np.r_[self.first_xn, self._normalised(uv[inl])]
            self.tri_deg = np.r_[self.tri_deg, np.full(m_, 90.0)]
            self.first_P = np.r_[self.first_P, np.broadcast_to(T[:3], (m_, 3, 4))]
            self.stats["relocalisations"] += 1
            return T
        return None


class StandbyAid:
    """The default aid (``--slam auto`` without depth): the mono SLAM switched on only when needed.

    Measured on the real ``teabox.mp4`` (README, tracking section): with the model in view, the
    always-on mono aid does not make the edge poses better (forward-backward error 0.28 px against
    0.28 px edges only and 0.23 px edges + KLT) and costs 2-3x the time. So while the edge poses are
    healthy and strong (``trace(W)`` at least ``wake_info_ratio`` x its running mean) this aid only
    keeps the last ``buffer_frames`` frames with their model poses (references, no work). On the
    first weak or unhealthy edge pose (the model leaving the view, occluded, fast motion) it
    **wakes**: a :class:`ModelAidedSlam` ('mono') is built by replaying the buffered frames with
    their model poses (tracks, triangulated landmarks, keyframes), and from then on it predicts and
    bridges exactly as ``--slam mono``. After ``sleep_after`` strong model frames in a row it goes
    back to standby (its map points are kept for :meth:`landmarks`).

    ``standby`` is True while asleep; the tracking loop calls :meth:`needs_wake` after the edge
    pass and :meth:`wake` (which returns the SLAM prediction of the current frame) before
    :meth:`update`. Poses ``T_cam_model`` (4x4); ``W`` the 6x6 edge information (twist order v, w).
    """

    def __init__(self, camera: Camera, config: dict | SlamConfig | None = None, buffer_frames: int = 20,
                 wake_info_ratio: float = 0.7, sleep_after: int = 30):
        self.camera, self.config = camera, config
        self.buf: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = deque(maxlen=max(2, buffer_frames))
        self.wake_info_ratio, self.sleep_after = wake_info_ratio, sleep_after
        self.aid: ModelAidedSlam | None = None
        self.info_ref: float | None = None
        self.n_strong = 0
        self._retired: list[np.ndarray] = []
        self._fired: list[int] = []
        self.stats = {"wakes": 0, "sleeps": 0, "frames_active": 0, "wake_frames": []}
        self.timing_ms = {"wake": 0.0}

    @property
    def standby(self) -> bool:
        return self.aid is None

    @property
    def static_world_fired(self) -> list[int]:
        """Frames where the static-world check of the (current or an earlier) mono map fired."""
        return self._fired + (self.aid.static_world_fired if self.aid is not None else [])

    def _strong(self, W: np.ndarray | None) -> bool:
        if W is None or not np.isfinite(W).all():
            return False
        return self.info_ref is None or float(np.trace(W)) >= self.wake_info_ratio * self.info_ref

    def needs_wake(self, healthy: bool, W: np.ndarray | None) -> bool:
        """True when asleep and this frame's edge pose is unhealthy or weak."""
        return self.aid is None and not (healthy and self._strong(W))

    def wake(self, k: int, gray: np.ndarray, T_cam_model_prev: np.ndarray | None) -> np.ndarray | None:
        """Build the mono SLAM from the buffered frames; return its prediction for frame ``k``."""
        import time

        t0 = time.perf_counter()
        self.aid = ModelAidedSlam("mono", self.camera, self.config)
        for kb, gb, Tb, Wb in self.buf:
            self.aid.predict(kb, gb, Tb)
            self.aid.update(kb, gb, Tb, Wb, True)
        self.buf.clear()
        self.n_strong = 0
        self.stats["wakes"] += 1
        self.stats["wake_frames"].append(int(k))
        T = self.aid.predict(k, gray, T_cam_model_prev)
        self.timing_ms["wake"] += (time.perf_counter() - t0) * 1e3
        return T

    def predict(self, k: int, gray: np.ndarray, T_cam_model_prev: np.ndarray | None) -> np.ndarray | None:
        """Asleep: None (the tracker starts from its previous pose); awake: the mono prediction."""
        return None if self.aid is None else self.aid.predict(k, gray, T_cam_model_prev)

    def update(self, k: int, gray: np.ndarray, T_cam_model_edges: np.ndarray | None,
               W: np.ndarray | None, healthy: bool, weak_edge_pose: np.ndarray | None = None
               ) -> tuple[np.ndarray | None, str]:
        """As :meth:`ModelAidedSlam.update`; asleep, a healthy strong edge pose is output as is."""
        if self.aid is None and not self.needs_wake(healthy, W):
            self.buf.append((k, _to_gray(gray), np.asarray(T_cam_model_edges, float).copy(), np.asarray(W, float)))
            tr = float(np.trace(W))
            self.info_ref = tr if self.info_ref is None else 0.9 * self.info_ref + 0.1 * tr
            return np.asarray(T_cam_model_edges, float).copy(), STATUS_MODEL
        if self.aid is None:  # the loop did not call wake() (hook contract): wake now
            self.wake(k, gray, T_cam_model_edges)
        T_out, status = self.aid.update(k, gray, T_cam_model_edges, W, healthy, weak_edge_pose)
        self.stats["frames_active"] += 1
        self.n_strong = self.n_strong + 1 if (status == STATUS_MODEL and healthy and self._strong(W)) else 0
        if self.n_strong >= self.sleep_after:
            self._retired.append(self.aid.landmarks())
            self._fired += self.aid.static_world_fired
            self.aid.close()
            self.aid = None
            self.stats["sleeps"] += 1
        return T_out, status

    def landmarks(self) -> np.ndarray:
        """(N, 3) model-frame map points of every active stretch (empty when it never woke)."""
        parts = self._retired + ([self.aid.landmarks()] if self.aid is not None else [])
        parts = [p for p in parts if len(p)]
        return np.concatenate(parts, 0) if parts else np.zeros((0, 3))

    def close(self) -> None:
        if self.aid is not None:
            self._retired.append(self.aid.landmarks())
            self._fired += self.aid.static_world_fired
            self.aid.close()
            self.aid = None
        self.buf.clear()


def make_aid(mode: str, camera: Camera, config: dict | None = None, depth_dir: Path | None = None,
             depth_camera: Camera | None = None, T_depth_color: np.ndarray | None = None) -> ModelAidedSlam | StandbyAid:
    """Create the SLAM aid for the tracking loop.

    ``mode``: ``'mono'`` (landmarks triangulated with the known poses) or ``'rgbd'`` (landmarks lifted
    from the depth frames in ``depth_dir``, the k-th sorted file for frame k). ``depth_camera``: the
    depth camera's intrinsics when the depth is not registered to colour; ``T_depth_color`` (4x4) maps
    colour-camera points to the depth camera (identity when None). ``config``: :class:`SlamConfig`
    fields (unknown keys ignored). ``'standby'``: :class:`StandbyAid` (mono, switched on when needed).
    """
    if mode == "standby":
        return StandbyAid(camera, config)
    return ModelAidedSlam(mode, camera, config, depth_dir, depth_camera, T_depth_color)
