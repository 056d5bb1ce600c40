"""The keyframe pose graph of ``mst refine``: ICP priors and tracked relative motions, solved by
sparse robust least squares (scipy).

Poses are ``T_model_cam`` (camera -> model frame). Unknowns: a left increment ``xi_i`` (v, w) per
keyframe, ``X_i = exp(xi_i) @ T_i``. Factors:

* prior (keyframes whose depth found the model): ``L_iᵀ log(X_i P_i⁻¹)``, ``P_i`` the keyframe's
  ICP pose and ``L_i Lᵀ_i`` its information;
* between (consecutive keyframes): ``W log(Z_ij⁻¹ X_i⁻¹ X_j)``, ``Z_ij = T_i⁻¹ T_j`` of the tracked
  trajectory (its relative motion is kept where no prior says otherwise), ``W`` = diag(1/sigma_t,
  1/sigma_r) in the keyframe's camera frame;
* a weak pull of every keyframe to where it is (1e-3 of the between weight): fixes the gauge of a
  stretch without any prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from mst.core.poses import inv_T, se3_exp, se3_log


@dataclass
class Prior:
    index: int              #: keyframe index
    T_model_cam: np.ndarray  #: (4, 4) the ICP pose
    info: np.ndarray         #: (6, 6) information of a left increment (v, w)


def _sqrt_info(info: np.ndarray) -> np.ndarray:
    """Upper factor U with UᵀU = info (eigen-decomposition: a rank-deficient info stays so)."""
    w, Q = np.linalg.eigh(0.5 * (info + info.T))
    return (Q * np.sqrt(np.clip(w, 0, None))).T


def solve_pose_graph(T_kf: np.ndarray, Z: np.ndarray, priors: list[Prior], sigma_t_m: float, sigma_r_rad: float,
                     max_nfev: int = 50) -> np.ndarray:
    """Refined keyframe poses (n, 4, 4) from current ``T_kf`` (n, 4, 4), tracked relative motions
    ``Z`` (n-1, 4, 4) between consecutive keyframes, and ICP ``priors``."""
    n = len(T_kf)
    W = np.concatenate([np.full(3, 1 / sigma_t_m), np.full(3, 1 / sigma_r_rad)])
    damp = 1e-3 * W
    pi = np.array([p.index for p in priors], dtype=np.int64)
    P_inv = inv_T(np.array([p.T_model_cam for p in priors])) if priors else np.zeros((0, 4, 4))
    U = np.array([_sqrt_info(p.info) for p in priors]) if priors else np.zeros((0, 6, 6))
    Z_inv = inv_T(Z) if n > 1 else np.zeros((0, 4, 4))

    def residuals(x: np.ndarray) -> np.ndarray:
        xi = x.reshape(n, 6)
        X = se3_exp(xi) @ T_kf
        out = [(damp * xi).ravel()]
        if n > 1:
            e = se3_log(Z_inv @ inv_T(X[:-1]) @ X[1:])
            out.append((W * e).ravel())
        if len(pi):
            e = se3_log(X[pi] @ P_inv)
            out.append(np.einsum("kij,kj->ki", U, e).ravel())
        return np.concatenate(out)

    m = 6 * n + 6 * max(n - 1, 0) + 6 * len(pi)
    S = lil_matrix((m, 6 * n), dtype=np.int8)
    for i in range(n):
        S[6 * i:6 * i + 6, 6 * i:6 * i + 6] = 1
    r0 = 6 * n
    for i in range(n - 1):
        S[r0 + 6 * i:r0 + 6 * i + 6, 6 * i:6 * i + 12] = 1
    r0 += 6 * max(n - 1, 0)
    for k, i in enumerate(pi):
        S[r0 + 6 * k:r0 + 6 * k + 6, 6 * i:6 * i + 6] = 1
    sol = least_squares(residuals, np.zeros(6 * n), jac_sparsity=S.tocsr(), method="trf", loss="linear",
                        max_nfev=max_nfev, x_scale="jac")
    return se3_exp(sol.x.reshape(n, 6)) @ T_kf


def interpolate_corrections(k_kf: np.ndarray, T_before: np.ndarray, T_after: np.ndarray, k_all: np.ndarray,
                            T_all: np.ndarray) -> np.ndarray:
    """Apply keyframe corrections ``C_i = T_after_i T_before_i⁻¹`` (model frame, left) to every
    pose: linear in the twist between the neighbouring keyframes, the nearest one's outside."""
    xi = se3_log(T_after @ inv_T(T_before))
    k_kf = np.asarray(k_kf, dtype=np.float64)
    out = np.empty((len(k_all), 6))
    for j in range(6):  # six np.interp calls, vectorised over all frames
        out[:, j] = np.interp(np.asarray(k_all, np.float64), k_kf, xi[:, j])
    return se3_exp(out) @ T_all
