"""The aid's records: frame statuses, keyframes (pose, observations, model prior, relocalisation
descriptors) and what :meth:`ModelAidedSlam.predict` found for a frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATUS_MODEL, STATUS_SLAM, STATUS_LOST = "model", "slam", "lost"


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
    sig_desc: np.ndarray | None = None            # (R, 7) their uncertainty records (:mod:`.drift`)


@dataclass
class FrameState:
    """What predict() found for frame k, consumed by update()."""

    k: int
    T: np.ndarray | None = None
    W: np.ndarray | None = None
    n_inliers: int = 0
    sig: tuple | None = None  #: uncertainty (map part m, map rotation rad, 6x6 fit covariance) of T (:mod:`.drift`)
