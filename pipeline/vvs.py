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
``sigma^2 W^-1`` with ``sigma`` the weighted residual RMS (pixels) are returned in that order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mst.pipeline.poses import se3_exp

TUKEY_C = 4.6851


@dataclass
class VVSResult:
    """T_cam_model (4,4); W (6,6) J^T W J; cov (6,6) twist covariance; weights (N,) edge weights;
    residual (N,) px; inlier (N,) bool; sigma_px robust scale; rms_px weighted RMS; iters."""

    T_cam_model: np.ndarray
    W: np.ndarray
    cov: np.ndarray
    weights: np.ndarray
    residual: np.ndarray
    inlier: np.ndarray
    sigma_px: float
    rms_px: float
    iters: int
    klt_inlier: np.ndarray | None = None


def tukey_weights(r: np.ndarray, min_scale: float, c: float = TUKEY_C) -> tuple[np.ndarray, float]:
    """Tukey biweight weights of residuals ``r`` with a MAD scale (floored at ``min_scale``)."""
    if len(r) == 0:
        return np.zeros(0), min_scale
    med = np.median(r)
    sigma = max(1.4826 * float(np.median(np.abs(r - med))), min_scale)
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


def solve_pose(T0: np.ndarray, K: np.ndarray, X_model: np.ndarray, edge: np.ndarray, A_model: np.ndarray,
               B_model: np.ndarray, cand_uv: np.ndarray, *, iters: int = 30, lm_mu: float = 0.01,
               min_mad_px: float = 1.0, tukey_c: float = TUKEY_C, klt_X_model: np.ndarray | None = None,
               klt_uv: np.ndarray | None = None, klt_weight: float = 1.0) -> VVSResult:
    """Robust VVS from ``T0``. ``cand_uv`` (N, C, 2) candidate pixels per sample (NaN = none).

    Samples without any candidate are ignored (weight 0). Raises ``ValueError`` when fewer than
    6 residuals are available.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    has = np.isfinite(cand_uv[..., 0]).any(axis=1)
    X = X_model[has]
    e = edge[has]
    cand = np.where(np.isfinite(cand_uv[has]), cand_uv[has], 1e9)
    nk = 0 if klt_X_model is None else len(klt_X_model)
    if len(X) + 2 * nk < 6:
        raise ValueError("fewer than 6 residuals")
    T = T0.copy()
    mu = lm_mu
    rows = np.arange(len(X))

    def residuals(Tc):
        u, v, x, y, iz = _project(Tc, X, fx, fy, cx, cy)
        ua, va, *_ = _project(Tc, A_model, fx, fy, cx, cy)
        ub, vb, *_ = _project(Tc, B_model, fx, fy, cx, cy)
        d = np.stack([ub - ua, vb - va], 1)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        n = np.stack([-d[:, 1], d[:, 0]], 1)[e]
        r_all = (u[:, None] - cand[..., 0]) * n[:, None, 0] + (v[:, None] - cand[..., 1]) * n[:, None, 1]
        return r_all, n, (u, v, x, y, iz)

    def klt_res(Tc):
        u, v, x, y, iz = _project(Tc, klt_X_model, fx, fy, cx, cy)
        return np.concatenate([u - klt_uv[:, 0], v - klt_uv[:, 1]]), (x, y, iz)

    it = 0
    w = np.ones(len(X))
    wk = np.ones(2 * nk)
    sigma = min_mad_px
    for it in range(1, iters + 1):  # noqa: B007 (returned)
        r_all, n, (u, v, x, y, iz) = residuals(T)
        ch = np.argmin(np.abs(r_all), axis=1)
        r = r_all[rows, ch]
        w, sigma = tukey_weights(r, min_mad_px, tukey_c)
        Jp = _point_jacobian(x, y, iz, fx, fy)
        J = n[:, 0, None] * Jp[:, 0] + n[:, 1, None] * Jp[:, 1]
        H = J.T @ (w[:, None] * J)
        g = J.T @ (w * r)
        cost = float(np.sum(w * r * r))
        if nk:
            rk, (xk, yk, izk) = klt_res(T)
            wk, _ = tukey_weights(rk, min_mad_px, tukey_c)
            wk = wk * klt_weight
            Jk = _point_jacobian(xk, yk, izk, fx, fy)
            Jk = np.concatenate([Jk[:, 0], Jk[:, 1]])
            H += Jk.T @ (wk[:, None] * Jk)
            g += Jk.T @ (wk * rk)
            cost += float(np.sum(wk * rk * rk))
        for _ in range(8):
            A = H + mu * np.diag(np.diag(H) + 1e-9)
            try:
                xi = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                xi = -np.linalg.lstsq(A, g, rcond=None)[0]
            Tn = se3_exp(xi) @ T
            r_all_n, _, _ = residuals(Tn)
            rn = r_all_n[rows, ch]
            cost_n = float(np.sum(w * rn * rn))
            if nk:
                rkn, _ = klt_res(Tn)
                cost_n += float(np.sum(wk * rkn * rkn))
            if cost_n <= cost * (1 + 1e-12):
                mu = max(mu / 10.0, 1e-7)
                break
            mu *= 10.0
        else:
            break
        T = Tn
        if np.abs(xi[:3]).max() < 1e-8 * max(1.0, abs(T[2, 3])) and np.abs(xi[3:]).max() < 1e-9:
            break
    # final statistics at the solution
    r_all, n, (u, v, x, y, iz) = residuals(T)
    ch = np.argmin(np.abs(r_all), axis=1)
    r = r_all[rows, ch]
    w, sigma = tukey_weights(r, min_mad_px, tukey_c)
    Jp = _point_jacobian(x, y, iz, fx, fy)
    J = n[:, 0, None] * Jp[:, 0] + n[:, 1, None] * Jp[:, 1]
    H = J.T @ (w[:, None] * J)
    sw = float(w.sum())
    ssr = float(np.sum(w * r * r))
    klt_in = None
    if nk:
        rk, (xk, yk, izk) = klt_res(T)
        wk, _ = tukey_weights(rk, min_mad_px, tukey_c)
        Jk = _point_jacobian(xk, yk, izk, fx, fy)
        Jk = np.concatenate([Jk[:, 0], Jk[:, 1]])
        H += Jk.T @ ((wk * klt_weight)[:, None] * Jk)
        klt_in = (wk[:nk] > 0.5) & (wk[nk:] > 0.5)
    rms = float(np.sqrt(ssr / max(sw, 1e-9)))
    try:
        cov = rms**2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    W_full = np.zeros(len(X_model))
    W_full[has] = w
    R_full = np.full(len(X_model), np.nan)
    R_full[has] = r
    return VVSResult(T, H, cov, W_full, R_full, W_full > 0.5, sigma, rms, it, klt_in)
