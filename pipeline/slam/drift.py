"""The drift budget of the SLAM aid: how far a map (``slam``) pose may be off, propagated from the
last model-verified poses through the landmarks (no threshold fitted to a run).

Every landmark carries four 1-sigma uncertainties (model frame) and the camera centre ``c`` it was
made from:

* ``corr`` (m): the error it inherits from the poses it was made under: each view's own error at
  the point (``J C J^T`` with ``J = [I, -[X]x]``, so the correlation of a pose's translation and
  rotation counts) and the view's inherited map error, independent of each other, so added in
  quadrature (root-sum-square), the larger of the two views. It is common to the landmarks of one
  stretch, so it does **not** average out in a PnP pose.
* ``scale`` (m, mono): the two views' *relative* error over the sine of the parallax,
  ``(sigma_centre + z sigma_rot) / sin(parallax)``, a depth error along the rays of ``c`` common to
  every landmark of that baseline (the mono scale drift), plus the relative scale error inherited
  from the pose it was made under (x its depth).
* ``ind`` (m): its own measurement noise, independent between landmarks: two-view triangulation
  ``z (sigma_px / f) sqrt(2) / sin(parallax)`` or the depth sensor's (rgbd).
* ``rot`` (rad): the rotation error of the views it was made under.

A map pose found by PnP on ``n`` landmarks at the camera centre ``c'`` inherits
``sm = hypot(mean(corr), sqrt(mean(ind^2) / n)) + mean(scale min(|c' - c| / z, 1))`` (the landmarks' own
noise, averaged by the fit, is independent of the error they inherited; a mono landmark's depth error
along the rays of the view ``c`` it was triangulated from, at distance ``z``, moves no camera at ``c``)
and ``sr = mean(rot)``, and adds its fit's covariance ``rms^2 (J^T J)^-1`` (``rms`` its reprojection RMS:
the inlier count and their spread in the image count); a model pose anchors with the edge tracker's
covariance (its residual RMS^2 x W^-1), no map part. New landmarks made under a pose take its
uncertainty: it grows with every generation of landmarks away from the last model anchor (distance
and rotation travelled into unmapped space, the parallax of each generation) and stays put while the
camera re-observes the same landmarks. The bound of a map pose is ``drift_sigmas`` x (camera centre
``sm + sqrt(tr C_vv)``; rotation ``sr + sqrt(tr C_ww) + (sm - scale part) / scene_depth``); it is output only while
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


#: columns of a landmark's uncertainty record (``lm_sig`` values, a keyframe's ``sig_desc`` rows):
#: ``(corr m, ind m, rot rad, scale, cx, cy, cz)`` (:class:`DriftBudget`)
LM_SIG_COLS = 7
_INF_LM = (math.inf,) * LM_SIG_COLS


def camera_centre(T_cam_model: np.ndarray) -> np.ndarray:
    """(3,) camera centre (model frame, m) of the pose ``T_cam_model``."""
    T = np.asarray(T_cam_model, float)
    return -T[:3, :3].T @ T[:3, 3]


class DriftBudget:
    """Landmark and pose uncertainty bookkeeping of :class:`~mst.pipeline.slam.aid.ModelAidedSlam`.

    A pose's uncertainty is ``(sm, sr, C, ss, sm_scale)``: ``sm`` (m) and ``sr`` (rad) the error it
    inherits from the map landmarks it was found on (0 for a model pose), ``C`` the 6x6 covariance of
    its own fit (edges or PnP), twist (v, w), ``ss`` the relative depth (scale) error of the mono map
    it was found on and ``sm_scale`` the part of ``sm`` that scale explains (a common scale error
    moves the camera but does not turn it). A landmark's record is ``(corr, ind, rot, scale, c)``:
    its common error (m), its own
    noise along its ray (m, depth or triangulation), the rotation (rad) of the views it was made
    under, the depth error (m) common to its triangulation baseline (mono scale drift) and the
    camera centre ``c`` (model frame) it was made from. A depth error along the ray of ``c`` moves
    a camera at ``c`` not at all (the rays are the same) and one at ``c'`` by the error times
    ``min(|c' - c| / z, 1)`` (``z`` the landmark's distance from ``c``): a common one scales that
    stretch of the map about ``c``."""

    def _landmark_sigs(self, tids: np.ndarray, model_only: bool = False) -> np.ndarray:
        """(N, :data:`LM_SIG_COLS`) uncertainty records of the landmarks ``tids`` (inf where a track has
        none; with ``model_only`` also where its landmark was anchored under a map pose)."""
        lm_sig, lm_model = self.lm_sig, self.lm_model
        return np.array([lm_sig.get(int(t), _INF_LM) if not model_only or lm_model.get(int(t), False) else _INF_LM
                         for t in tids], float).reshape(-1, LM_SIG_COLS)

    def _model_pose_sig(self, W: np.ndarray | None) -> tuple:
        """``(0, 0, C, 0, 0)`` of an edge pose with information ``W``: ``C = edge_sigma_px^2 W^-1`` (0 without W)."""
        if W is None:
            return 0.0, 0.0, np.zeros((6, 6)), 0.0, 0.0
        return 0.0, 0.0, self.cfg.edge_sigma_px**2 * np.linalg.inv(regularised_6x6(np.asarray(W, float))), 0.0, 0.0

    def _pnp_sig(self, tids: np.ndarray, W_pnp: np.ndarray, rms_px: float | None = None,
                 T: np.ndarray | None = None) -> tuple:
        """``(sm, sr, C, ss, sm_scale)`` of a PnP pose ``T`` on the landmarks ``tids``: the map part (their mean
        common error, plus their scale error times the camera's distance from the view they were
        triangulated from, plus their own noise averaged over them; their mean rotation) moves the
        camera with the landmarks; ``C`` is the fit's ``sigma^2 (J^T J)^-1`` with ``sigma`` its
        reprojection RMS ``rms_px`` (at least :data:`KLT_FLOOR_PX`; ``slam_sigma_px`` when not
        given); ``sm_scale`` is the scale part of ``sm``. The common errors are correlated (one
        stretch of the map): their mean, not an average that shrinks with n."""
        n = len(tids)
        if n == 0:
            return math.inf, math.inf, np.full((6, 6), np.inf), math.inf, math.inf
        s = self._landmark_sigs(tids)
        scl, ind = s[:, 3], s[:, 1]
        if T is None:
            reach = np.full(n, np.inf)
        else:
            # a depth error along the ray of the view a landmark was made from moves a camera at the
            # lever arm d from that view by (error / z) min(d, z): none at the view itself
            X = np.array([self.lm.get(int(t), (np.nan,) * 3) for t in tids], float).reshape(-1, 3)
            with np.errstate(invalid="ignore"):
                z = np.linalg.norm(X - s[:, 4:7], axis=1)
                lever = np.linalg.norm(s[:, 4:7] - camera_centre(T), axis=1)
                reach = np.where(np.isfinite(lever) & np.isfinite(z), np.minimum(lever / np.maximum(z, 1e-9), 1.0), 1.0)
        with np.errstate(invalid="ignore"):
            e_scale = np.where(scl > 0, scl * np.where(np.isfinite(reach), reach, 1.0), 0.0)
        sm_scale = float(e_scale.mean())
        # the landmarks' own noise averages over them and is not scaled by the reach: on the 40 m UAV
        # pass the first map poses were 0.8 % off while the anchors' claimed sigma, the fit's and a
        # reach-scaled noise came to 0.24 % (the edge tracker's covariance is 3.8x optimistic there,
        # RMS against the truth; 0.5-2x elsewhere): the full noise term is what covers it
        e_ind = ind
        # the inherited common error and the fit's share of the landmarks' own noise are independent:
        # root-sum-square (their linear sum, the bound of fully correlated errors, accumulated over every
        # generation of landmarks: the rgbd corridor's bound was 5-15x its measured error, session 19)
        sm = float(math.hypot(s[:, 0].mean(), math.sqrt(float(np.mean(e_ind**2)) / n)) + sm_scale)
        sig = self.cfg.slam_sigma_px if rms_px is None else max(float(rms_px), KLT_FLOOR_PX)
        if T is None:
            ss = math.inf if np.any(scl > 0) else 0.0
        else:
            with np.errstate(invalid="ignore", divide="ignore"):
                ss = float(np.mean(np.where(scl > 0, scl / np.where(np.isfinite(z), np.maximum(z, 1e-9), np.nan), 0.0)))
            ss = math.inf if not math.isfinite(ss) else ss
        return sm, float(s[:, 2].mean()), sig**2 * np.linalg.inv(regularised_6x6(W_pnp)), ss, sm_scale

    def _landmark_sig(self, X_first: np.ndarray, X_cur: np.ndarray, first_sig: np.ndarray, first_C: np.ndarray,
                      parallax_deg: np.ndarray) -> np.ndarray:
        """(M, 7) records of landmarks triangulated from their first view (camera points ``X_first``,
        inherited ``first_sig`` (M, 2) = (sm, sr), fit ``first_C`` (M, 6, 6)) and the current pose
        (``self._pose_sig`` at ``self._pose_c``, camera points ``X_cur``) with the given parallax.

        Besides each view's own error, the two views' relative error (their fit parts: the common
        map part cancels) misplaces every landmark triangulated between them in depth alike,
        ``(sigma_centre + z sigma_rot) / sin(parallax)``: the scale drift of a mono map, kept apart
        from the common error (m, plus the relative scale the current pose inherits, x z) as a depth
        error along the current view's rays: a camera there inherits none of it."""
        sm, sr, C, ss = self._pose_sig[:4]
        z = np.abs(X_cur[:, 2])
        ang = np.radians(np.clip(parallax_deg, 1e-6, 90.0))
        c1 = np.einsum("nii->n", first_C[:, :3, :3])
        r1 = np.einsum("nii->n", first_C[:, 3:, 3:])
        c2, r2 = float(np.trace(C[:3, :3])), float(np.trace(C[3:, 3:]))
        base = (np.sqrt(np.maximum(c1 + c2, 0.0)) + z * np.sqrt(np.maximum(r1 + r2, 0.0))) / np.sin(ang)
        corr = np.maximum(np.hypot(first_sig[:, 0], point_sigmas(X_first, first_C)), np.hypot(sm, point_sigmas(X_cur, C)))
        rot = np.maximum(first_sig[:, 1] + np.sqrt(np.maximum(r1, 0.0)), sr + math.sqrt(max(r2, 0.0)))
        ind = z * (self.cfg.slam_sigma_px / self.K[0, 0]) * math.sqrt(2.0) / np.sin(ang)
        scale = ss * z + base
        return np.c_[corr, ind, rot, scale, np.broadcast_to(self._pose_c, (len(z), 3))]

    def _depth_landmark_sig(self, X_cam: np.ndarray) -> np.ndarray:
        """(M, 7) records of landmarks lifted from depth under the current pose (camera points ``X_cam``)."""
        sm, sr, C, ss = self._pose_sig[:4]
        X = np.asarray(X_cam, float).reshape(-1, 3)
        n = len(X)
        rot = sr + math.sqrt(max(float(np.trace(C[3:, 3:])), 0.0))
        return np.c_[np.hypot(sm, point_sigmas(X, C)), np.abs(X[:, 2]) * RGBD_DEPTH_SIGMA_REL, np.full(n, rot),
                     ss * np.linalg.norm(X, axis=1), np.broadcast_to(self._pose_c, (n, 3))]

    def _anchor_sig(self, cov_edges: np.ndarray) -> tuple[float, float, np.ndarray]:
        """``(0, 0, C)`` of an edge pose with the tracker's covariance ``cov_edges`` (its residual
        RMS^2 x W^-1) x ``anchor_sigma_scale``^2: the uncertainty it is judged by against the drift
        budget when it competes with a map pose beyond it."""
        return 0.0, 0.0, self.cfg.anchor_sigma_scale**2 * np.asarray(cov_edges, float)

    def map_pose_cov(self) -> np.ndarray | None:
        """(6, 6) twist covariance of the last output map pose (None when the last output was no map
        pose, or its uncertainty is not finite): :meth:`sig_cov` of its uncertainty."""
        return None if self._out_sig is None else self.sig_cov(self._out_sig)

    def sig_cov(self, sig: tuple) -> np.ndarray | None:
        """(6, 6) covariance of the left twist ``(v, w)`` (m, rad; camera frame, the tracker's
        ``traj.cov.csv`` convention) of a pose with the uncertainty ``sig`` (``(sm, sr, C, ...)``, see
        :meth:`_pnp_sig`), consistent with its bound (:meth:`_bound_of`): the fit's covariance ``C``
        plus an isotropic map part, sized so that ``sqrt(trace)`` of the centre block is the bound's
        linear sum ``sm + sigma_centre(C)`` and that of the rotation block ``sr_map + sigma_rot(C)``
        (``sr_map = sr + rigid part of sm / scene depth``). The map error moves every landmark of the
        stretch alike, in no known direction, and a centre error ``dc`` (model frame) is the twist
        ``v = -R dc``: isotropic in the model frame is isotropic in the camera's. None when not finite."""
        sm, sr, sc, sr_fit, sr_depth = self._sig_parts(sig)
        C = np.asarray(sig[2], float)
        if not (math.isfinite(sm) and math.isfinite(sr) and math.isfinite(sr_depth) and np.isfinite(C).all()):
            return None
        sr_map = sr + max(sr_depth, 0.0)
        out = 0.5 * (C + C.T)
        out[:3, :3] += np.eye(3) * (sm * sm + 2.0 * sm * sc) / 3.0
        out[3:, 3:] += np.eye(3) * (sr_map * sr_map + 2.0 * sr_map * sr_fit) / 3.0
        return out

    def drift_bound(self) -> tuple[float, float] | None:
        """The bound of the last map pose: ``drift_sigmas`` x (camera-centre sigma m, rotation sigma
        deg); None when the last output was no map pose."""
        return None if self._out_sig is None else self._bound_of(self._out_sig)

    def sig_within_budget(self, sig: tuple, distance_m: float) -> bool:
        """Whether a pose with the uncertainty ``sig`` (``(sm, sr, C, ...)``, see :meth:`_pnp_sig`) is
        within the drift budget at ``distance_m`` from the model."""
        b = self._bound_of(sig)
        return b[0] <= self.cfg.drift_budget_rel * distance_m and b[1] <= self.cfg.drift_budget_deg

    def _sig_parts(self, sig: tuple) -> tuple[float, float, float, float, float]:
        """``(sm, sr, sc, sr_fit, sr_depth)`` of a pose uncertainty ``sig``: its map parts, its fit's
        centre and rotation sigmas (:func:`pose_sigmas`) and the rigid part of ``sm`` (without the
        common scale error, which moves the camera but does not turn it) over the scene depth (rad)."""
        sm, sr, C = sig[:3]
        sm_rigid = sm - (sig[4] if len(sig) > 4 else 0.0)
        sc, sr_fit = pose_sigmas(C)
        return sm, sr, sc, sr_fit, sm_rigid / max(self.scene_depth, 1e-9)

    def _bound_of(self, sig: tuple) -> tuple[float, float]:
        """``drift_sigmas`` x (camera-centre sigma m, rotation sigma deg) of a pose uncertainty ``sig``."""
        sm, sr, sc, sr_fit, sr_depth = self._sig_parts(sig)
        k = self.cfg.drift_sigmas
        # rotation: the views' rotation passed on, the fit's, and the landmarks' common error seen
        # across the scene depth (errors that differ over the image turn the camera: on the 40 m
        # UAV pass the map poses were 0.2 deg off with an anchor rotation sigma of 0.05 deg); a
        # common scale error moves the camera but does not turn it (mono corridor: the bound had
        # been 30-250x the measured rotation error)
        return k * (sm + sc), k * math.degrees(sr + sr_fit + sr_depth)

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
