"""The lever arm (camera position in the body frame) from the GPS fixes, where the attitude makes it
observable (``mst nav fuse --estimate-lever-arm``).

Model (world frame, the mount ``R_bc`` of the calibration held): ``g_i = Rz(d) R_wm (p_i - R_i R_bcᵀ l)
+ t + noise``, ``p_i``/``R_i`` the vision camera position and rotation at the fix (model frame), ``d``
a correction of the calibration's model-to-world yaw. Gauss-Newton in ``(t, d, l)``, weighted by the
calibration's Huber weights of the fixes. A constant attitude makes ``l`` and ``t`` the same
unknown, and on an orbit facing its centre the lever's tangential part turns with the orbit like a
yaw of the model: the reported std is the marginal one of ``l`` (``t`` and ``d`` free), so it says
how much of ``l`` this log's attitude changes tell apart from the calibration.
"""

from __future__ import annotations

import numpy as np


def estimate_lever_arm(p_model: np.ndarray, R_model_cam: np.ndarray, g_world: np.ndarray, w: np.ndarray,
                       R_wm: np.ndarray, R_bc: np.ndarray, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lever arm (3,) m and its std (3,) m from fixes ``g_world`` (N, 3) with weights ``w`` (N,), the
    vision ``p_model`` (N, 3) / ``R_model_cam`` (N, 3, 3) at the fixes, GPS sigma ``sig`` (3,)."""
    Wi = np.diag(1.0 / sig**2)
    n = len(p_model)
    B = np.einsum("njk,kl->njl", R_model_cam, R_bc.T)            # model-frame antenna offset per unit lever
    x = np.zeros(7)                                              # (t, d, l)
    ez = np.array([0.0, 0.0, 1.0])
    H = np.eye(7)
    for _ in range(3):
        c, s_ = np.cos(x[3]), np.sin(x[3])
        Rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        R = Rz @ R_wm
        a = p_model - np.einsum("nij,j->ni", B, x[4:])           # antenna, model frame
        r = g_world - (a @ R.T + x[:3])
        J = np.zeros((n, 3, 7))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3] = np.cross(ez, a @ R.T)
        J[:, :, 4:] = -np.einsum("ij,njk->nik", R, B)
        H = np.einsum("n,nji,jk,nkl->il", w, J, Wi, J)
        b = np.einsum("n,nji,jk,nk->i", w, J, Wi, r)
        x = x + np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(7), b)
    cov = np.linalg.pinv(H)
    return x[4:], np.sqrt(np.maximum(np.diag(cov)[4:], 0.0))
