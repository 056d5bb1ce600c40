"""The drift budget of the SLAM aid: how far a map (``slam``) pose may be off, propagated from the
last model-verified poses through the landmarks (no threshold fitted to a run).

Every landmark carries three 1-sigma uncertainties (model frame):

* ``corr`` (m): the error it inherits from the poses it was made under: each view's own error at
  the point (``J C J^T`` with ``J = [I, -[X]x]``, so the correlation of a pose's translation and
  rotation counts) plus the view's inherited map error, the larger of the two views; for a mono
  triangulation also the two views' *relative* error over the sine of the parallax,
  ``(sigma_centre + z sigma_rot) / sin(parallax)``, which scales every landmark of that baseline
  alike (the mono scale drift). It is common to the landmarks of one stretch, so it does **not**
  average out in a PnP pose.
* ``ind`` (m): its own measurement noise, independent between landmarks: two-view triangulation
  ``z (sigma_px / f) sqrt(2) / sin(parallax)`` or the depth sensor's (rgbd).
* ``rot`` (rad): the rotation error of the views it was made under.

A map pose found by PnP on ``n`` landmarks inherits ``sm = mean(corr) + sqrt(mean(ind^2) / n)`` and
``sr = mean(rot)``, and adds its fit's covariance ``rms^2 (J^T J)^-1`` (``rms`` its reprojection RMS:
the inlier count and their spread in the image count); a model pose anchors with the edge tracker's
covariance (its residual RMS^2 x W^-1), no map part. New landmarks made under a pose take its
uncertainty: it grows with every generation of landmarks away from the last model anchor (distance
and rotation travelled into unmapped space, the parallax of each generation) and stays put while the
camera re-observes the same landmarks. The bound of a map pose is ``drift_sigmas`` x (camera centre
``sm + sqrt(tr C_vv)``; rotation ``sr + sqrt(tr C_ww) + sm / scene_depth``); it is output only while
the bound is within ``drift_budget_rel`` x its distance to the model and ``drift_budget_deg``
(:meth:`DriftBudget.within_budget`, called by the tracking session).
"""

from __future__ import annotations

import math

import numpy as np

from mst.pipeline.slam.geometry import regularised_6x6

#: relative 1-sigma depth noise of a depth-sensor landmark (rgbd), x depth: Kinect-like structured
#: light at 1-3 m (the synthetic ``--depth-noise kinect`` model's order); independent per landmark
RGBD_DEPTH_SIGMA_REL = 0.005

#: the floor of a PnP fit's pixel noise: KLT's sub-pixel accuracy on real images is ~0.1 px (the
#: iterations stop at 0.01 px; image noise, blur and interpolation leave about ten times that)
KLT_FLOOR_PX = 0.1


def pose_sigmas(cov6: np.ndarray) -> tuple[float, float]:
    """1-sigma camera-centre (m) and rotation (rad) uncertainty of a pose with the 6x6 covariance
    ``cov6`` of its left twist ``(v, w)``: with ``T' = exp(d) T`` the centre moves by ``-R^T v``, so
    its sigma is ``sqrt(trace(C_vv))``; the rotation's ``sqrt(trace(C_ww))``."""
    c = np.asarray(cov6, float)
    return (math.sqrt(max(float(np.trace(c[:3, :3])), 0.0)), math.sqrt(max(float(np.trace(c[3:, 3:])), 0.0)))


def point_sigmas(X_cam: np.ndarray, cov6: np.ndarray) -> np.ndarray:
    """(N,) 1-sigma error (m) of model points recovered from the camera points ``X_cam`` (N, 3) under a
    pose with the twist covariance ``cov6`` ((6, 6), or (N, 6, 6) one per point): with
    ``T' = exp(v, w) T`` a point moves by ``-R^T (v + w x X)``, so its covariance is
    ``J C J^T`` with ``J = [I, -[X]x]``. The correlation of v and w counts: a pose uncertain along
    the orbit about the object (v and w together) moves points at the object's depth little."""
    X = np.asarray(X_cam, float).reshape(-1, 3)
    n = len(X)
    J = np.zeros((n, 3, 6))
    J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    # -[X]x
    J[:, 0, 4], J[:, 0, 5] = z, -y
    J[:, 1, 3], J[:, 1, 5] = -z, x
    J[:, 2, 3], J[:, 2, 4] = y, -x
    C = np.asarray(cov6, float)
    tr = np.einsum("nij,...jk,nik->n", J, C, J) if C.ndim == 2 else np.einsum("nij,njk,nik->n", J, C, J)
    return np.sqrt(np.maximum(tr, 0.0))


class DriftBudget:
    """Landmark and pose uncertainty bookkeeping of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`.

    A pose's uncertainty is ``(sm, sr, C)``: ``sm`` (m) and ``sr`` (rad) the error it inherits from the
    map landmarks it was found on (0 for a model pose) and ``C`` the 6x6 covariance of its own fit
    (edges or PnP), twist (v, w). A landmark's is ``(corr, ind, rot)``: its common error (m), its own
    noise (m) and the rotation (rad) of the views it was made under."""

    def _model_pose_sig(self, W: np.ndarray | None) -> tuple[float, float, np.ndarray]:
        """``(0, 0, C)`` of an edge pose with information ``W``: ``C = edge_sigma_px^2 W^-1`` (0 without W)."""
        if W is None:
            return 0.0, 0.0, np.zeros((6, 6))
        return 0.0, 0.0, self.cfg.edge_sigma_px**2 * np.linalg.inv(regularised_6x6(np.asarray(W, float)))

    def _pnp_sig(self, tids: np.ndarray, W_pnp: np.ndarray, rms_px: float | None = None) -> tuple[float, float, np.ndarray]:
        """``(sm, sr, C)`` of a PnP pose on the landmarks ``tids``: the map part (their mean common
        error plus their own noise averaged over them; their mean rotation) moves the camera with the
        landmarks; ``C`` is the fit's ``sigma^2 (J^T J)^-1`` with ``sigma`` its reprojection RMS
        ``rms_px`` (at least :data:`KLT_FLOOR_PX`; ``slam_sigma_px`` when not given)."""
        n = len(tids)
        if n == 0:
            return math.inf, math.inf, np.full((6, 6), np.inf)
        s = np.array([self.lm_sig.get(int(t), (math.inf,) * 3) for t in tids], float).reshape(-1, 3)
        sm = float(s[:, 0].mean() + math.sqrt(float(np.mean(s[:, 1] ** 2)) / n))
        sig = self.cfg.slam_sigma_px if rms_px is None else max(float(rms_px), KLT_FLOOR_PX)
        return sm, float(s[:, 2].mean()), sig**2 * np.linalg.inv(regularised_6x6(W_pnp))

    def _landmark_sig(self, X_first: np.ndarray, X_cur: np.ndarray, first_sig: np.ndarray, first_C: np.ndarray,
                      parallax_deg: np.ndarray) -> np.ndarray:
        """(M, 3) ``(corr, ind, rot)`` sigmas of landmarks triangulated from their first view (camera
        points ``X_first``, inherited ``first_sig`` (M, 2) = (sm, sr), fit ``first_C`` (M, 6, 6)) and
        the current pose (``self._pose_sig``, camera points ``X_cur``) with the given parallax.

        Besides each view's own error, the two views' relative error (their fit parts: the common
        map part cancels) scales the depth of every landmark triangulated between them alike,
        ``(sigma_centre + z sigma_rot) / sin(parallax)``: the scale drift of a mono map."""
        sm, sr, C = self._pose_sig
        z = np.abs(X_cur[:, 2])
        ang = np.radians(np.clip(parallax_deg, 1e-6, 90.0))
        c1 = np.einsum("nii->n", first_C[:, :3, :3])
        r1 = np.einsum("nii->n", first_C[:, 3:, 3:])
        c2, r2 = float(np.trace(C[:3, :3])), float(np.trace(C[3:, 3:]))
        base = (np.sqrt(np.maximum(c1 + c2, 0.0)) + z * np.sqrt(np.maximum(r1 + r2, 0.0))) / np.sin(ang)
        corr = np.maximum(first_sig[:, 0] + point_sigmas(X_first, first_C), sm + point_sigmas(X_cur, C)) + base
        rot = np.maximum(first_sig[:, 1] + np.sqrt(np.maximum(r1, 0.0)), sr + math.sqrt(max(r2, 0.0)))
        ind = z * (self.cfg.slam_sigma_px / self.K[0, 0]) * math.sqrt(2.0) / np.sin(ang)
        return np.c_[corr, ind, rot]

    def _depth_landmark_sig(self, X_cam: np.ndarray) -> np.ndarray:
        """(M, 3) sigmas of landmarks lifted from depth under the current pose (camera points ``X_cam``)."""
        sm, sr, C = self._pose_sig
        X = np.asarray(X_cam, float).reshape(-1, 3)
        rot = sr + math.sqrt(max(float(np.trace(C[3:, 3:])), 0.0))
        return np.c_[sm + point_sigmas(X, C), np.abs(X[:, 2]) * RGBD_DEPTH_SIGMA_REL, np.full(len(X), rot)]

    def _anchor_sig(self, cov_edges: np.ndarray) -> tuple[float, float, np.ndarray]:
        """``(0, 0, C)`` of an edge pose with the tracker's covariance ``cov_edges`` (its residual
        RMS^2 x W^-1) x ``anchor_sigma_scale``^2: the uncertainty it is judged by against the drift
        budget when it competes with a map pose beyond it."""
        return 0.0, 0.0, self.cfg.anchor_sigma_scale**2 * np.asarray(cov_edges, float)

    def drift_bound(self) -> tuple[float, float] | None:
        """The bound of the last map pose: ``drift_sigmas`` x (camera-centre sigma m, rotation sigma
        deg); None when the last output was no map pose."""
        return None if self._out_sig is None else self._bound_of(self._out_sig)

    def sig_within_budget(self, sig: tuple, distance_m: float) -> bool:
        """Whether a pose with the uncertainty ``sig`` (``(sm, sr, C)``, see :meth:`_pnp_sig`) is
        within the drift budget at ``distance_m`` from the model."""
        b = self._bound_of(sig)
        return b[0] <= self.cfg.drift_budget_rel * distance_m and b[1] <= self.cfg.drift_budget_deg

    def _bound_of(self, sig: tuple) -> tuple[float, float]:
        """``drift_sigmas`` x (camera-centre sigma m, rotation sigma deg) of a pose uncertainty ``sig``."""
        sm, sr, C = sig
        sc, sr_fit = pose_sigmas(C)
        k = self.cfg.drift_sigmas
        # rotation: the views' rotation passed on, the fit's, and the landmarks' common error seen
        # across the scene depth (errors that differ over the image turn the camera: on the 40 m
        # UAV pass the map poses were 0.2 deg off with an anchor rotation sigma of 0.05 deg)
        return k * (sm + sc), k * math.degrees(sr + sr_fit + sm / max(self.scene_depth, 1e-9))

    def within_budget(self, k: int, distance_m: float) -> bool:
        """Whether the map pose of frame ``k`` (the last output) is within the drift budget at
        ``distance_m`` from the model; a pose beyond it is recorded (``drift_budget_frames``) and
        not output by the session, while the map keeps running (the model can re-anchor it)."""
        b = self.drift_bound()
        if b is None:
            return True
        self.drift_log[int(k)] = (b[0] / max(distance_m, 1e-12), b[1])
        ok = self.sig_within_budget(self._out_sig, distance_m)
        if not ok:
            self.drift_budget_frames.append(int(k))
        return ok
