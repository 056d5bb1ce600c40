"""Rigid poses, quaternions, SE(3) exp/log, small number/transform files (trajectory and pose files:
:mod:`mst.core.trajectory`).

Conventions (used everywhere in mst):

* Poses are 4x4 float64 homogeneous matrices. ``T_a_b`` maps points from frame *b* to frame *a*:
  ``X_a = T_a_b @ X_b``. ``T_cam_model`` is ViSP's ``cMo``; ``T_model_cam`` is the camera pose in
  model coordinates (what TUM files hold).
* Camera frame: x right, y down, z forward (OpenCV/ViSP). Units: metres, radians internally.
* Twists ``xi = (v, w)``: translation part first, rotation part second (ViSP's velocity order).
* Quaternions in files are TUM order ``qx qy qz qw``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mst import InputError


def matmul_exact(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for small matrices (..., n, k) @ (..., k, m) (poses, rotations) without BLAS:
    ``sum_j A[..., :, j] B[..., j, :]`` with ``j`` ascending, one elementwise multiply and add each,
    so the same bits on every CPU (BLAS kernels round differently per CPU: with or without fused
    multiply-adds, other summation orders). Use it where a pose feeds the tracker's decisions."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    out = A[..., :, 0:1] * B[..., 0:1, :]
    for j in range(1, A.shape[-1]):
        out = out + A[..., :, j:j + 1] * B[..., j:j + 1, :]
    return out


# ---------------------------------------------------------------------------- rotations
def skew(w: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    w = np.asarray(w, dtype=np.float64)
    o = np.zeros(w.shape[:-1] + (3, 3))
    o[..., 0, 1], o[..., 0, 2] = -w[..., 2], w[..., 1]
    o[..., 1, 0], o[..., 1, 2] = w[..., 2], -w[..., 0]
    o[..., 2, 0], o[..., 2, 1] = -w[..., 1], w[..., 0]
    return o


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) in radians -> rotation matrices (..., 3, 3) (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * matmul_exact(K, K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3) in radians (robust near pi)."""
    return quat_to_rotvec(quat_from_R(R))


def quat_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (qx, qy, qz, qw), qw >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Shepperd's method, vectorised: pick the largest of (w, x, y, z) for stability
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((len(m), 4))
    for idx in range(4):
        s = k == idx
        if not s.any():
            continue
        r = m[s]
        if idx == 0:
            t = np.sqrt(1.0 + tr[s]) * 2
            q[s] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / t, (r[:, 0, 2] - r[:, 2, 0]) / t, (r[:, 1, 0] - r[:, 0, 1]) / t, 0.25 * t], 1)
        elif idx == 1:
            t = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2
            q[s] = np.stack([0.25 * t, (r[:, 0, 1] + r[:, 1, 0]) / t, (r[:, 0, 2] + r[:, 2, 0]) / t, (r[:, 2, 1] - r[:, 1, 2]) / t], 1)
        elif idx == 2:
            t = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2
            q[s] = np.stack([(r[:, 0, 1] + r[:, 1, 0]) / t, 0.25 * t, (r[:, 1, 2] + r[:, 2, 1]) / t, (r[:, 0, 2] - r[:, 2, 0]) / t], 1)
        else:
            t = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2
            q[s] = np.stack([(r[:, 0, 2] + r[:, 2, 0]) / t, (r[:, 1, 2] + r[:, 2, 1]) / t, 0.25 * t, (r[:, 1, 0] - r[:, 0, 1]) / t], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(R.shape[:-2] + (4,))


def R_from_quat(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) as (qx, qy, qz, qw) (normalised here) -> rotation matrices (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """(..., 4) (qx, qy, qz, qw) -> rotation vectors (..., 3), radians, angle in [0, pi]."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., 3:4] < 0, -q, q)
    s = np.linalg.norm(q[..., :3], axis=-1)
    ang = 2.0 * np.arctan2(s, q[..., 3])
    scale = np.where(s < 1e-12, 2.0, ang / np.where(s < 1e-12, 1.0, s))
    return q[..., :3] * scale[..., None]


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle (degrees) of rotation matrices (..., 3, 3)."""
    return np.degrees(np.linalg.norm(so3_log(R), axis=-1))


# ---------------------------------------------------------------------------- SE(3)
def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotation(s) (..., 3, 3) and translation(s) (..., 3) into (..., 4, 4)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make_T(Rt, -matmul_exact(Rt, T[..., :3, 3:4])[..., 0])


def transform_points(T: np.ndarray, X: np.ndarray, *, elementwise: bool = False) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points.

    ``elementwise=True`` sums ``x R[:, 0] + y R[:, 1] + z R[:, 2] + t`` column by column, with no
    BLAS call (BLAS threads stall when the cores are busy, and a 3x3 product gains nothing from
    them). Its last bits differ from the matrix product's, so a stage keeps the form its outputs
    were made with (fusion: elementwise).
    """
    X = np.asarray(X, dtype=np.float64)
    if elementwise:
        R, t = T[:3, :3], T[:3, 3]
        return X[:, 0:1] * R[:, 0] + X[:, 1:2] * R[:, 1] + X[:, 2:3] * R[:, 2] + t
    return X @ T[:3, :3].T + T[:3, 3]


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Twist(s) (..., 6) = (v, w) -> (..., 4, 4) via the exact SE(3) exponential."""
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[..., :3], xi[..., 3:]
    R = so3_exp(w)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    c = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ths - np.sin(ths)) / ths**3)
    V = np.eye(3) + b * K + c * matmul_exact(K, K)
    return make_T(R, matmul_exact(V, v[..., None])[..., 0])


def se3_log(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> twists (..., 6) = (v, w), inverse of :func:`se3_exp`."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[..., :3, :3])
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    half = ths / 2.0
    coef = np.where(small, 1.0 / 12.0, (1.0 - half * np.cos(half) / np.sin(np.where(small, 1.0, half))) / ths**2)
    Vinv = np.eye(3) - 0.5 * K + coef * matmul_exact(K, K)
    v = matmul_exact(Vinv, T[..., :3, 3:4])[..., 0]
    return np.concatenate([v, w], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0), roll_deg: float = 0.0) -> np.ndarray:
    """Camera pose ``T_world_cam`` (4x4) at ``eye`` looking at ``target`` (x right, y down, z forward).

    ``up`` is the world up direction; ``roll_deg`` rotates the camera about its optical axis.
    """
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    if roll_deg:
        a = np.radians(roll_deg)
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        R = R @ Rz
    return make_T(R, eye)


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation error (model units) and rotation error (degrees) between camera poses.

    Both arguments are ``T_model_cam`` (camera poses in model coordinates), shape (..., 4, 4).
    """
    dt = np.linalg.norm(T_est[..., :3, 3] - T_ref[..., :3, 3], axis=-1)
    dR = np.swapaxes(T_ref[..., :3, :3], -1, -2) @ T_est[..., :3, :3]
    return dt, rotation_angle_deg(dR)


# ---------------------------------------------------------------------------- files
#: largest accepted coordinate of a position in a pose or trajectory file, metres: 1e9 m is far beyond
#: any map (Earth-centred coordinates are ~6.4e6 m); larger values are corrupt and overflow later
MAX_POSITION_M = 1e9


def read_numbers(p: Path, what: str = "file") -> np.ndarray:
    """All numbers of a small text file; ``#`` comments, commas and brackets ignored.

    UTF-8 (byte-order mark accepted); NaN/inf and numbers beyond 1e12 are refused (no rigid
    transform or pose has them: a corrupt value).
    """
    from mst import read_text

    vals: list[float] = []
    for ln, line in enumerate(read_text(p, what).splitlines(), 1):
        s = line.split("#", 1)[0].replace(",", " ").replace("[", " ").replace("]", " ")
        try:
            vals.extend(float(x) for x in s.split())
        except ValueError:
            raise InputError(p, f"line {ln}: not a number in {line.strip()[:60]!r}") from None
    a = np.asarray(vals)
    if not np.isfinite(a).all():
        raise InputError(p, "NaN or infinite values")
    if len(a) and np.abs(a).max() > MAX_POSITION_M:
        raise InputError(p, f"value {a[np.argmax(np.abs(a))]:g} beyond {MAX_POSITION_M:g}: corrupt?")
    return a


def rigid_from_rows(a: np.ndarray, p: Path) -> np.ndarray:
    """12 or 16 row-major numbers -> 4x4 rigid transform, rotation re-orthonormalised (SVD); an
    :class:`mst.InputError` naming ``p`` when they are not one."""
    T = np.eye(4)
    T[: len(a) // 4] = a.reshape(-1, 4)
    R = T[:3, :3]
    if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
        raise InputError(p, "the 4x4 matrix is not a rigid transform (rotation part not orthonormal)")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise InputError(p, "last row must be 0 0 0 1")
    T[:3, :3] = orthonormalise(R)
    return T


def orthonormalise(R: np.ndarray, iterations: int = 30) -> np.ndarray:
    """The rotation nearest to a near-orthonormal (3, 3) ``R`` (the polar factor ``U V^T`` of its SVD) by
    Newton's iteration ``X <- (X + X^-T) / 2`` (quadratic convergence; ``X^-T`` = the cofactor rows
    ``(x1 x x2, x2 x x0, x0 x x1)`` over the determinant), in elementwise products and sums in a fixed order:
    the same bits on every CPU, where LAPACK's SVD does not give them (a ViSP ``cMo`` file read on two CPUs
    started the tracker from poses differing in their last bits, and tracking took another path)."""
    X = np.array(R, dtype=np.float64)
    for _ in range(iterations):
        C = np.stack([np.cross(X[1], X[2]), np.cross(X[2], X[0]), np.cross(X[0], X[1])])
        det = float((X[0, 0] * C[0, 0] + X[0, 1] * C[0, 1]) + X[0, 2] * C[0, 2])
        Y = 0.5 * (X + C / det)
        if (Y == X).all():
            break
        X = Y
    return X


def read_rigid_transform(path: str | os.PathLike, what: str = "transform file") -> np.ndarray:
    """Read a 4x4 (16 numbers) or 3x4 (12) rigid transform, row-major, e.g. ViSP's ``depth_M_color.txt``.

    ``#`` comments, commas and brackets are allowed. Raises :class:`mst.InputError` naming the file
    when it is missing, holds another count of numbers, or is not rigid.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, f"{what} does not exist")
    a = read_numbers(p, what)
    if len(a) not in (12, 16):
        raise InputError(p, f"{len(a)} numbers: expected a 4x4 (16) or 3x4 (12) matrix")
    return rigid_from_rows(a, p)


def pnp_ransac(X_model: np.ndarray, uv_px: np.ndarray, K: np.ndarray, dist, iterations: int, reproj_px: float,
               flags: int):
    """``cv2.solvePnPRansac`` of model points ``X_model (N, 3)`` m and pixels ``uv_px (N, 2)``.

    Returns ``(ok, rvec, tvec, inliers)``; ``ok`` is False (no pose) where OpenCV refuses the data
    instead of solving it: SQPnP asserts on point sets of too little spread (repeated points, e.g.
    several keypoints matched to one landmark), which is no pose rather than a crash."""
    import cv2

    try:
        return cv2.solvePnPRansac(X_model, uv_px, K, dist, iterationsCount=iterations, reprojectionError=reproj_px,
                                  confidence=0.999, flags=flags)
    except cv2.error:
        return False, None, None, None


def refine_pnp(X_model: np.ndarray, uv_px: np.ndarray, K: np.ndarray, dist, rvec: np.ndarray,
               tvec: np.ndarray) -> np.ndarray:
    """``T_cam_model`` (4x4) of a PnP pose ``(rvec, tvec)`` refined by ``cv2.solvePnPRefineLM`` on
    model points ``X_model (N, 3)`` m and pixels ``uv_px (N, 2)`` (e.g. the inliers of :func:`pnp_ransac`)."""
    import cv2

    rvec, tvec = cv2.solvePnPRefineLM(X_model, uv_px, K, dist, rvec, tvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return T
