"""Robust virtual visual servoing (ViSP ``vpMbEdgeTracker::computeVVS``): pose from edge matches.

Minimises, over the camera pose ``T_cam_model``, the robust sum of squared point-to-line distances
(pixels) between each moving-edge match and the projected model edge it belongs to, plus (optional)
KLT point reprojection errors (pixels):

* residual of edge sample i: ``r_i = n_i . (pi(T X_i) - m_i)`` with ``n_i`` the unit normal of the
  currently projected edge and ``m_i`` the chosen candidate; with several candidates per sample the
  one nearest the moving line is chosen at every iteration;
* Tukey M-estimator (c = 4.6851) on residuals scaled by the MAD (``1.4826 * median|r - med r|``,
  floored at ``min_mad_px``) like ``vpRobust``; iteratively re-weighted least squares;
* Levenberg-Marquardt damped Gauss-Newton steps.

Perturbation convention (shared with the SLAM aid): ``T_cam_model_new = se3_exp(xi) @ T_cam_model``
with ``xi = (v, w)``, v in metres and w in radians, in the camera frame. ``W = J^T diag(w) J``
(pixels^-2 per unit twist, i.e. the information matrix for 1 px residual noise) and the covariance
are returned in that order: the cluster-robust (CR2) covariance of :mod:`mst.pipeline.tracking.covariance`
(the samples' errors are correlated along an edge), floored by the classical ``sigma^2 W_e^-1``
(``sigma`` the weighted residual RMS, pixels; kept as ``VVSResult.cov_classical``).

The covariance is the edge samples' alone (``W_e``, :attr:`VVSResult.W_edges`), also where KLT points
took part in the fit: a KLT point's model coordinates come from the face plane under an earlier pose,
so all of them carry that pose's error and tell this frame's pose relative to the model no better than
that pose was known; in a steady view its error is this frame's own (the same edges, nearly the same
view). Counted as independent evidence they shrank the bound without making the pose better:
Rotterdam's 250 m UAV survey at 640x480 (issue 11), steady flight, KLT on / off on the 33 frames both
output 1.010 / 0.999 m, while the KLT lowered the 2-sigma bound of frames 3-12 from 0.9-1.2 % of the
distance (refused by the error budget) to 0.7-0.9 % (output), errors 0.5-1.0 %, one 1.035 % off
(2.4 sigma) and marked tracked (an AMD Zen 4 CPU, session 16). The KLT points still shape the pose.

The solver does not raise to mean "no pose": :attr:`VVSResult.status` (:class:`mst.errors.SolveStatus`)
says ``TOO_FEW`` (fewer than 6 residuals), ``DIVERGED`` (a non-finite pose or information matrix),
``DEGENERATE`` (a finite pose whose information matrix cannot be inverted: no covariance) or ``OK``.

Length: :func:`solve_pose` is one numeric pass over all samples, longer than 80 lines by design: it was moved, not
rewritten, when the tracking package was formed (issue #10), so that the order of its floating-point
operations, and the outputs, stay bit-identical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mst.core.poses import se3_exp as _se3_exp_batch
from mst.errors import SolveStatus
from mst.pipeline.tracking.compiled import kernels as _kc  # ahead of time or numba JIT


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Fast exact SE(3) exponential of one twist ``(v, w)`` (same as :func:`mst.core.poses.se3_exp`)."""
    v0, v1, v2, w0, w1, w2 = np.asarray(xi, float).tolist()
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-16:
        return _se3_exp_batch(np.asarray(xi, float))
    th = math.sqrt(th2)
    s, c = math.sin(th), math.cos(th)
    a = s / th
    b = (1.0 - c) / th2
    cc = (th - s) / (th2 * th)
    # R = I + a [w]x + b [w]x^2 ;  V = I + b [w]x + cc [w]x^2 ;  [w]x^2 = w w^T - th2 I
    x00, x11, x22 = w0 * w0 - th2, w1 * w1 - th2, w2 * w2 - th2
    x01, x02, x12 = w0 * w1, w0 * w2, w1 * w2
    r00, r11, r22 = 1.0 + b * x00, 1.0 + b * x11, 1.0 + b * x22
    V00, V11, V22 = 1.0 + cc * x00, 1.0 + cc * x11, 1.0 + cc * x22
    t0 = V00 * v0 + (cc * x01 - b * w2) * v1 + (cc * x02 + b * w1) * v2
    t1 = (cc * x01 + b * w2) * v0 + V11 * v1 + (cc * x12 - b * w0) * v2
    t2 = (cc * x02 - b * w1) * v0 + (cc * x12 + b * w0) * v1 + V22 * v2
    return np.array([[r00, b * x01 - a * w2, b * x02 + a * w1, t0],
                     [b * x01 + a * w2, r11, b * x12 - a * w0, t1],
                     [b * x02 - a * w1, b * x12 + a * w0, r22, t2],
                     [0.0, 0.0, 0.0, 1.0]])


TUKEY_C = 4.6851
SPREAD_K = 4.0  # heteroscedastic edge weight: w / (1 + SPREAD_K * var_edge / sigma^2)
#: the step test (a step below ``stop_px``) ends the iterations only once the Levenberg-Marquardt damping
#: has relaxed to this x the diagonal, or once a step was undone (the damping then rose at a minimum: on
#: real video it never relaxed again and every solve ran its 30 iterations, teabox edges 1.9 -> 2.6 ms) (two accepted steps from the default ``lm_mu`` 0.01). A damped step
#: is short along the pose's weakly observed direction (depth at survey range: the 1 % damping cut the
#: step of a pose 0.8 m off at 150 m below 0.1 px, and the solve stopped there), so stopping on it left
#: each frame near its start: the 120 m survey's return after the turn held 0.55-1.0 m off for 20 frames
STOP_MU = 1e-4


@dataclass
class VVSResult:
    """T_cam_model (4,4); W (6,6) J^T W J; cov_classical (6,6) ``rms^2 W_edges^-1``; weights (N,) edge weights;
    residual (N,) px; inlier (N,) bool; sigma_px robust scale; rms_px weighted RMS; iters; klt_inlier
    (M,) bool or None; status (see the module docstring; without a pose ``T_cam_model`` is the start);
    :attr:`cov` the twist covariance (cluster-robust, computed when first read: a frame reads only its
    last solve's, ~0.4 ms for 400 samples and 60 KLT points)."""

    T_cam_model: np.ndarray
    W: np.ndarray
    cov_classical: np.ndarray  #: ``rms^2 W_edges^-1`` (i.i.d. residuals); inf without one
    weights: np.ndarray
    residual: np.ndarray
    inlier: np.ndarray
    sigma_px: float
    rms_px: float
    iters: int
    klt_inlier: np.ndarray | None = None
    status: SolveStatus = SolveStatus.OK
    #: the cluster covariance's inputs (T, K, X, e, A, B, w, r: the edge samples): a gauge-fixed one is computed
    #: from them (:meth:`mst.pipeline.tracking.render_edges.RenderEdgeProvider.gauge_cov`)
    jk_inputs: tuple | None = None
    #: the edge samples' part of ``W`` (``W`` without the KLT block: ``W`` itself in a fit without KLT
    #: points): the information of the pose's own evidence, which the covariances are computed from
    #: (module docstring)
    W_edges: np.ndarray | None = None
    _cov: np.ndarray | None = field(default=None, repr=False)

    @property
    def cov(self) -> np.ndarray:
        """The twist covariance (6, 6) of the pose's own evidence, its edge samples (module docstring): the
        cluster-robust one of :mod:`mst.pipeline.tracking.covariance` floored by :attr:`cov_classical` where it has one (a finite pose, >= ``MIN_CLUSTERS`` clusters),
        else :attr:`cov_classical`."""
        if self._cov is None:
            self._cov = self.cov_classical
            if self.jk_inputs is not None and self.status is SolveStatus.OK:
                from mst.pipeline.tracking.covariance import edge_cluster_cov, psd_max

                C = edge_cluster_cov(*self.jk_inputs)[0]
                if C is not None:
                    self._cov = psd_max(self.cov_classical, C)
        return self._cov

    @property
    def has_pose(self) -> bool:
        """A finite pose and information matrix (``OK`` or ``DEGENERATE``)."""
        return self.status in (SolveStatus.OK, SolveStatus.DEGENERATE)


def _no_pose(T0: np.ndarray, n: int, status: SolveStatus, min_mad_px: float) -> VVSResult:
    """The result of a solve that found no pose: the start pose, no information, no inliers."""
    return VVSResult(T0.copy(), np.zeros((6, 6)), np.full((6, 6), np.inf), np.zeros(n), np.full(n, np.nan),
                     np.zeros(n, bool), min_mad_px, float("nan"), 0, None, status, W_edges=np.zeros((6, 6)))


def _median(a: np.ndarray) -> float:
    n = len(a)
    h = n // 2
    p = np.partition(a, [h - 1, h] if n % 2 == 0 and n > 1 else h)
    return float(0.5 * (p[h - 1] + p[h])) if n % 2 == 0 and n > 1 else float(p[h])


def tukey_weights(r: np.ndarray, min_scale: float, c: float = TUKEY_C) -> tuple[np.ndarray, float]:
    """Tukey biweight weights of residuals ``r`` with a MAD scale (floored at ``min_scale``)."""
    if len(r) == 0:
        return np.zeros(0), min_scale
    med = _median(r)
    sigma = max(1.4826 * _median(np.abs(r - med)), min_scale)
    u = r / (c * sigma)
    w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    return w, sigma


def _project(T: np.ndarray, X: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    iz = 1.0 / np.where(np.abs(z) < 1e-9, 1e-9, z)
    x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
    return fx * x + cx, fy * y + cy, x, y, iz


def _point_jacobian(x, y, iz, fx, fy):
    """(N,2,6) d(u,v)/d(xi) for the left perturbation, xi = (v, w)."""
    J = np.empty((len(x), 2, 6))
    J[:, 0, 0] = fx * iz
    J[:, 0, 1] = 0.0
    J[:, 0, 2] = -fx * x * iz
    J[:, 0, 3] = -fx * x * y
    J[:, 0, 4] = fx * (1.0 + x * x)
    J[:, 0, 5] = -fx * y
    J[:, 1, 0] = 0.0
    J[:, 1, 1] = fy * iz
    J[:, 1, 2] = -fy * y * iz
    J[:, 1, 3] = -fy * (1.0 + y * y)
    J[:, 1, 4] = fy * x * y
    J[:, 1, 5] = fy * x
    return J


def _line_jacobian(nx, ny, x, y, iz, fx, fy) -> np.ndarray:
    """(N,6) d(n . (u, v))/d(xi) for image normals ``(nx, ny)`` (left perturbation, xi = (v, w))."""
    a = nx * fx
    b = ny * fy
    return np.column_stack([a * iz, b * iz, -(a * x + b * y) * iz, -a * x * y - b * (1.0 + y * y),
                            a * (1.0 + x * x) + b * x * y, b * x - a * y])


def klt_info_scale(H_edges: np.ndarray, H_klt: np.ndarray, cap: float | None) -> float:
    """The factor on the KLT points' weights that caps their information at ``cap`` x the edge
    samples': ``rho = tr(H_e^-1 H_k) / 6`` (the KLT block's information in units of the edges', the
    mean generalised eigenvalue; invariant to the units of translation and rotation); the factor is
    ``min(1, cap / rho)``, 1 without a cap or when ``H_e`` is singular (the edges alone do not fix the
    pose: the KLT points must).

    Why a cap: a KLT point's model coordinates come from the face plane under the pose at its
    detection, so every point carries that pose's error, shared by all of them; it does not average
    down with the number of points as independent pixel noise would. The points constrain the pose
    relative to the detection pose, so they know the pose at most as well as the edges that found
    it (cap 1). Uncapped, 200 points outweighed the edges 5x (median rho 5.0 on teabox.mp4) and the
    pose followed the KLT tracks' drift: 0.2 px farther from ViSP's hybrid tracker after 20 frames."""
    if cap is None or cap <= 0:
        return 1.0
    try:
        rho = float(np.trace(np.linalg.solve(H_edges, H_klt))) / 6.0
    except np.linalg.LinAlgError:
        return 1.0
    return cap / rho if rho > cap else 1.0


def _vvs_result(T, H, He, w, r, w_tukey, wk, nk: int, klt_weight: float, has, n_samples: int, sigma: float,
                it: int, jk: tuple | None = None) -> VVSResult:
    """The solve's result from its last linearisation (``H`` its information, ``He`` the edge samples'
    part): weights, residuals (px) and the Tukey inlier mask back on all ``n_samples`` (NaN residual /
    zero weight where a sample had no candidate), the classical covariance ``rms^2 He^-1`` (inf where
    the edges alone do not pin the pose) and the status (degenerate H, non-finite pose); ``jk`` the
    inputs of the cluster-robust :attr:`VVSResult.cov`."""
    sw = float(w.sum())
    ssr = float(np.sum(w * r * r))
    klt_in = None
    if nk:
        klt_in = (wk[:nk] > 0.5 * klt_weight) & (wk[nk:] > 0.5 * klt_weight)
    rms = float(np.sqrt(ssr / max(sw, 1e-9)))
    status = SolveStatus.OK
    from mst.pipeline.tracking.exact import inverse

    try:
        cov = rms**2 * inverse(H)  # not LAPACK's inverse, which rounds per CPU (the cov is an output)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
        status = SolveStatus.DEGENERATE
    if nk and status is SolveStatus.OK:
        try:
            cov = rms**2 * inverse(He)
        except np.linalg.LinAlgError:  # the KLT points pin what the edges do not: a pose, no bound
            cov = np.full((6, 6), np.inf)
    if not np.isfinite(T).all() or not np.isfinite(H).all():
        status = SolveStatus.DIVERGED
    W_full = np.zeros(n_samples)
    W_full[has] = w
    Wt_full = np.zeros(n_samples)
    Wt_full[has] = w_tukey
    R_full = np.full(n_samples, np.nan)
    R_full[has] = r
    if not np.isfinite(T).all():
        jk = None
    return VVSResult(T, H, cov, W_full, R_full, Wt_full > 0.5, sigma, rms, it, klt_in, status, jk, He)


def solve_pose(T0: np.ndarray, K: np.ndarray, X_model: np.ndarray, edge: np.ndarray, A_model: np.ndarray,
               B_model: np.ndarray, cand_uv: np.ndarray, *, iters: int = 30, lm_mu: float = 0.01,
               min_mad_px: float = 1.0, tukey_c: float = TUKEY_C, klt_X_model: np.ndarray | None = None,
               klt_uv: np.ndarray | None = None, klt_weight: float = 1.0, stop_px: float = 0.1,
               edge_spread_weight: bool = True, klt_info_cap: float | None = None,
               fine_mad_px: float | None = None) -> VVSResult:
    """Robust VVS from ``T0``. ``cand_uv`` (N, C, 2) candidate pixels per sample (NaN = none).

    ``fine_mad_px`` (below ``min_mad_px``): a fine stage where the floor binds (the solve's robust
    scale at or below ``min_mad_px``, a finite pose): a second solve from the converged pose with the
    same matches and the floor ``fine_mad_px``, whose result is returned when it has a pose (else the
    first solve's). The same results as two calls (the tracker's edge pass made them), with the
    inputs prepared once and the first solve's result built only when it is returned (issue #14).

    Each iteration: residuals at the current pose, candidate choice, Tukey weights, a damped
    Gauss-Newton step; a step that raises the weighted cost (evaluated at the next iteration
    with the previous weights) is undone and the damping raised. Iterations stop when a step
    moves image points by less than ``stop_px`` pixels once the damping has relaxed to :data:`STOP_MU`. Samples without any candidate are
    ignored (weight 0). Fewer than 6 residuals: status ``TOO_FEW`` (no pose), see :class:`VVSResult`.

    The whole loop runs in one numba kernel (:func:`mst.pipeline.tracking.kernels.vvs_solve`, issue
    #14: per frame ~6 iterations of ~20 numpy calls each were most of the solve's time), every sum
    and product in a fixed order without BLAS: the pose of :func:`solve_pose_numpy` within rounding
    (~1e-15 relative; tests/test_tracking_kernels.py), and the same on every CPU and BLAS kernel.
    """
    vvs_inputs, vvs_solve = _kc.vvs_inputs, _kc.vvs_solve

    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    # the samples with a candidate and their candidates, non-finite coordinates at 1e9 (one kernel)
    has, X, e, cu, cv = vvs_inputs(np.ascontiguousarray(X_model, np.float64), np.ascontiguousarray(edge, np.int64),
                                   np.ascontiguousarray(cand_uv, np.float64))
    nk = 0 if klt_X_model is None else len(klt_X_model)
    if len(X) + 2 * nk < 6:
        return _no_pose(T0, len(X_model), SolveStatus.TOO_FEW, min_mad_px)
    AB = np.ascontiguousarray(np.concatenate([A_model, B_model]), np.float64)
    n = len(X)
    Xk = np.ascontiguousarray(klt_X_model, np.float64) if nk else np.zeros((0, 3))
    uk = np.ascontiguousarray(klt_uv, np.float64) if nk else np.zeros((0, 2))

    def run(T_start, mad):
        T, H, He = np.empty((4, 4)), np.empty((6, 6)), np.empty((6, 6))
        w, r, w_tukey, wk = np.empty(n), np.empty(n), np.empty(n), np.empty(2 * nk)
        it, sigma, status = vvs_solve(X, e, AB, len(A_model), cu, cv, Xk, uk, np.ascontiguousarray(T_start, np.float64),
                                      fx, fy, cx, cy, int(iters), float(lm_mu), float(mad), float(tukey_c),
                                      float(klt_weight), float(stop_px), STOP_MU, bool(edge_spread_weight), SPREAD_K,
                                      T, H, He, w, r, w_tukey, wk, float(klt_info_cap or 0.0))
        return T, H, He, w, r, w_tukey, wk, int(it), float(sigma), int(status)

    def result(raw, T_start, mad):
        T, H, He, w, r, w_tukey, wk, it, sigma, status = raw
        if status == 1:  # the damped retry of an accepted step could not be solved
            return _no_pose(T_start, len(X_model), SolveStatus.DIVERGED, mad)
        jk = (T, K, X, e, A_model, B_model, w, r)  # the edge samples: the pose's evidence
        return _vvs_result(T, H, He, w, r, w_tukey, wk, nk, klt_weight, has, len(X_model), sigma, it, jk)

    raw = run(T0, min_mad_px)
    if fine_mad_px is not None and fine_mad_px < min_mad_px:
        T1, sigma1 = (T0, min_mad_px) if raw[9] == 1 else (raw[0], raw[8])  # the first solve's pose and scale
        if sigma1 <= min_mad_px and np.isfinite(T1).all():
            fine = run(T1, fine_mad_px)
            # a pose (status OK or DEGENERATE): the kernel solved every step, finite pose and information
            if fine[9] != 1 and np.isfinite(fine[0]).all() and np.isfinite(fine[1]).all():
                return result(fine, T1, fine_mad_px)
    return result(raw, T0, min_mad_px)


def solve_pose_numpy(T0: np.ndarray, K: np.ndarray, X_model: np.ndarray, edge: np.ndarray, A_model: np.ndarray,
               B_model: np.ndarray, cand_uv: np.ndarray, *, iters: int = 30, lm_mu: float = 0.01,
               min_mad_px: float = 1.0, tukey_c: float = TUKEY_C, klt_X_model: np.ndarray | None = None,
               klt_uv: np.ndarray | None = None, klt_weight: float = 1.0, stop_px: float = 0.1,
               edge_spread_weight: bool = True, klt_info_cap: float | None = None) -> VVSResult:
    """The numpy formulation of :func:`solve_pose` (the reference of the kernels' tests). Robust VVS from ``T0``. ``cand_uv`` (N, C, 2) candidate pixels per sample (NaN = none).

    Each iteration: residuals at the current pose, candidate choice, Tukey weights, a damped
    Gauss-Newton step; a step that raises the weighted cost (evaluated at the next iteration
    with the previous weights) is undone and the damping raised. Iterations stop when a step
    moves image points by less than ``stop_px`` pixels once the damping has relaxed to :data:`STOP_MU`. Samples without any candidate are
    ignored (weight 0). Fewer than 6 residuals: status ``TOO_FEW`` (no pose), see :class:`VVSResult`.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    has = np.isfinite(cand_uv[..., 0]).any(axis=1)
    X = X_model[has]
    e = edge[has]
    cand = np.where(np.isfinite(cand_uv[has]), cand_uv[has], 1e9)
    cu, cv = cand[..., 0], cand[..., 1]
    nk = 0 if klt_X_model is None else len(klt_X_model)
    if len(X) + 2 * nk < 6:
        return _no_pose(T0, len(X_model), SolveStatus.TOO_FEW, min_mad_px)
    AB = np.concatenate([A_model, B_model])
    nE = len(A_model)
    T = T0.copy()
    mu = lm_mu
    raised = False  # a step was undone (see STOP_MU)
    rows = np.arange(len(X))
    fmax = max(fx, fy)
    Xc0 = X @ T[:3, :3].T + T[:3, 3]
    iz_max = float(1.0 / max(Xc0[:, 2].min(), 1e-9)) if len(X) else 1.0
    xy_max = float(np.abs(Xc0[:, :2] / np.maximum(Xc0[:, 2:3], 1e-9)).max()) if len(X) else 1.0

    def evaluate(Tc):
        R, t = Tc[:3, :3], Tc[:3, 3]
        Xc = X @ R.T + t
        iz = 1.0 / Xc[:, 2]
        x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
        u, v = fx * x + cx, fy * y + cy
        P = AB @ R.T + t
        pu = fx * P[:, 0] / P[:, 2]
        pv = fy * P[:, 1] / P[:, 2]
        du, dv = pu[nE:] - pu[:nE], pv[nE:] - pv[:nE]
        ln = np.sqrt(du * du + dv * dv) + 1e-12
        nx, ny = (-dv / ln)[e], (du / ln)[e]
        r_all = (u[:, None] - cu) * nx[:, None] + (v[:, None] - cv) * ny[:, None]
        return r_all, nx, ny, x, y, iz

    def evaluate_klt(Tc):
        Xc = klt_X_model @ Tc[:3, :3].T + Tc[:3, 3]
        iz = 1.0 / Xc[:, 2]
        x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
        rk = np.concatenate([fx * x + cx - klt_uv[:, 0], fy * y + cy - klt_uv[:, 1]])
        Jp = _point_jacobian(x, y, iz, fx, fy)
        return rk, np.concatenate([Jp[:, 0], Jp[:, 1]])

    prev = None  # (T, cost, ch, w, wk, H, g) of the last accepted linearisation
    it = 0
    w = np.zeros(len(X))
    w_tukey = w
    wk = np.zeros(2 * nk)
    sigma = min_mad_px
    H = np.zeros((6, 6))
    He = H
    r = np.zeros(len(X))
    rk = np.zeros(0)
    wk_out = wk
    for it in range(1, iters + 1):  # noqa: B007 (returned)
        r_all, nx, ny, x, y, iz = evaluate(T)
        if nk:
            rk, Jk = evaluate_klt(T)
        if prev is not None:
            r_old = r_all[rows, prev[2]]
            cost_new = float(np.sum(prev[3] * r_old * r_old))
            if nk:
                cost_new += float(np.sum(prev[4] * rk * rk))
            if cost_new > prev[1] * (1 + 1e-9) and mu < 1e8:
                # undo: retry from the previous linearisation with more damping
                mu *= 10.0
                raised = True
                T_prev, _, _, _, _, Hp, gp = prev
                try:
                    xi = -np.linalg.solve(Hp + mu * np.diag(np.diag(Hp) + 1e-9), gp)
                except np.linalg.LinAlgError:  # the damped system of an accepted step: not finite
                    return _no_pose(T0, len(X_model), SolveStatus.DIVERGED, min_mad_px)
                T = se3_exp(xi) @ T_prev
                continue
            mu = max(mu / 10.0, 1e-7)
        ch = np.argmin(np.abs(r_all), axis=1)
        r = r_all[rows, ch]
        w, sigma = tukey_weights(r, min_mad_px, tukey_c)
        w_tukey = w
        if edge_spread_weight and len(r):
            # heteroscedastic edge weights: an edge whose inlier residuals scatter (clutter next to
            # it, a bad model edge) counts less than an edge whose samples agree
            sw_e = np.bincount(e, weights=w, minlength=nE) + 1e-9
            m_e = np.bincount(e, weights=w * r, minlength=nE) / sw_e
            v_e = np.bincount(e, weights=w * (r - m_e[e]) ** 2, minlength=nE) / sw_e
            w = w / (1.0 + SPREAD_K * v_e[e] / (sigma * sigma))
        J = _line_jacobian(nx, ny, x, y, iz, fx, fy)
        wJ = w[:, None] * J
        H = J.T @ wJ
        He = H
        g = wJ.T @ r
        cost = float(np.sum(w * r * r))
        if nk:
            wk, _ = tukey_weights(rk, min_mad_px, tukey_c)
            wk = wk * klt_weight
            Hk = Jk.T @ (wk[:, None] * Jk)
            sc = klt_info_scale(H, Hk, klt_info_cap)
            wk_out = wk
            wk = sc * wk
            H = H + sc * Hk
            g = g + Jk.T @ (wk * rk)
            cost += float(np.sum(wk * rk * rk))
        try:
            xi = -np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-9), g)
        except np.linalg.LinAlgError:
            break
        prev = (T, cost, ch, w, wk, H, g)
        step_px = fmax * (np.abs(xi[:3]).max() * iz_max + np.abs(xi[3:]).max() * (1.0 + xy_max))
        T = se3_exp(xi) @ T
        if step_px < stop_px and (mu <= STOP_MU or raised):
            break
    else:
        # iteration budget spent: keep the last accepted pose
        if prev is not None:
            r_all, *_ = evaluate(T)
            r_old = r_all[rows, prev[2]]
            if float(np.sum(prev[3] * r_old * r_old)) > prev[1] * (1 + 1e-9):
                T = prev[0]
    jk = (T, K, X, e, A_model, B_model, w, r)  # the edge samples: the pose's evidence
    return _vvs_result(T, H, He, w, r, w_tukey, wk_out, nk, klt_weight, has, len(X_model), sigma, it, jk)
