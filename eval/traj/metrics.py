"""Trajectory metrics, as evo computes them: association by timestamp, Umeyama / first-pose
alignment, error statistics, RPE pairs, camera yaw and gap ranges (arrays in, arrays or
:class:`ErrorStats` out)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mst import InputError
from mst.core.poses import inv_T, make_T, rotation_angle_deg
from mst.errors import ConfigError

NADIR_LIMIT_DEG = 10.0


# ----------------------------------------------------------------------------------- association
def associate(t_est: np.ndarray, t_ref: np.ndarray, max_diff: float = 0.01, offset_est: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i_est, i_ref)`` of associated poses, evo's ``associate_trajectories`` rule.

    The trajectory with fewer poses is matched into the longer one (ties: the reference is the
    shorter), each of its stamps to the nearest stamp within ``max_diff`` seconds (the upper
    neighbour wins only when strictly closer). ``offset_est`` is added to the estimate's stamps.
    """
    te = np.asarray(t_est, np.float64) + offset_est
    tr = np.asarray(t_ref, np.float64)
    est_longer = len(te) > len(tr)
    s1, s2 = (tr, te) if est_longer else (te, tr)
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    inrange = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
    i2 = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    ub = s2[i2] - s1
    lb = np.where(i2 > 0, s1 - s2[np.maximum(i2 - 1, 0)], np.inf)
    best = np.where((ub <= max_diff) & (ub < lb), i2, np.where((lb <= max_diff) & (lb <= ub), i2 - 1, -1))
    ok = inrange & (best >= 0)
    i1 = np.nonzero(ok)[0]
    j = best[ok].astype(np.int64)
    return (j, i1) if est_longer else (i1, j)


# ------------------------------------------------------------------------------------ alignment
def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``y ~ s R x + t`` for (N, 3) point sets (Umeyama 1991, evo's formulation)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n = len(x)
    mx, my = x.mean(0), y.mean(0)
    sigma_x = np.linalg.norm(x - mx) ** 2 / n
    cov = (y - my).T @ (x - mx) / n
    u, d, v = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise InputError(None, "degenerate trajectory (positions collinear or identical): cannot align se3/sim3")
    S = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(v) < 0.0:
        S[2, 2] = -1
    R = u @ S @ v
    s = float(np.trace(np.diag(d) @ S) / sigma_x) if with_scale else 1.0
    t = my - s * (R @ mx)
    return R, t, s


def align_estimate(T_est: np.ndarray, T_ref: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Align associated estimate poses onto the reference: ``(T_est_aligned, T_ref_est (4x4), scale)``.

    The aligned pose is ``T_ref_est @ T_est`` with the translation scaled by ``scale`` first (sim3).
    """
    T_est = np.asarray(T_est, np.float64)
    if mode == "none":
        return T_est.copy(), np.eye(4), 1.0
    if mode == "first":
        T = T_ref[0] @ inv_T(T_est[0])
        return T @ T_est, T, 1.0
    if mode in ("se3", "sim3"):
        if len(T_est) < 3:
            raise InputError(None, f"alignment {mode} needs at least 3 associated poses, got {len(T_est)}")
        R, t, s = umeyama(T_est[:, :3, 3], T_ref[:, :3, 3], mode == "sim3")
        Ts = T_est.copy()
        Ts[:, :3, 3] *= s
        T = make_T(R, t)
        return T @ Ts, T, s
    raise ConfigError("align", f"unknown alignment {mode!r} (none, se3, sim3, first)")


# ------------------------------------------------------------------------------------- metrics
@dataclass(frozen=True)
class ErrorStats:
    """rmse, mean, median, std (population), min, max and count of an error array (evo's definitions);
    every statistic None when the array is empty."""

    count: int
    rmse: float | None = None
    mean: float | None = None
    median: float | None = None
    std: float | None = None
    min: float | None = None
    max: float | None = None

    def to_json(self) -> dict:
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "std": self.std, "min": self.min,
                "max": self.max, "count": self.count}


def error_stats(e: np.ndarray) -> ErrorStats:
    """rmse, mean, median, std (population), min, max of an error array (evo's definitions)."""
    e = np.asarray(e, np.float64)
    if len(e) == 0:
        return ErrorStats(count=0)
    return ErrorStats(rmse=float(np.sqrt(np.mean(e**2))), mean=float(np.mean(e)), median=float(np.median(e)),
                      std=float(np.std(e)), min=float(np.min(e)), max=float(np.max(e)), count=int(len(e)))


def rpe_pairs_frames(n: int, delta: int) -> np.ndarray:
    """Consecutive index pairs ``(i, i + delta)`` with ``i`` a multiple of ``delta`` (evo)."""
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def rpe_pairs_metres(positions: np.ndarray, delta_m: float) -> np.ndarray:
    """Consecutive pairs whose path length reaches ``delta_m`` metres (evo's path filter)."""
    step = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    ids = [0]
    acc = 0.0
    for i, s in enumerate(step, start=1):  # running sum that resets: sequential by nature (N poses)
        acc += float(s)
        if acc >= delta_m:
            ids.append(i)
            acc = 0.0
    ids = np.asarray(ids)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def rpe(T_ref: np.ndarray, T_est: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose errors for index pairs: ``(translation (metres), rotation angle (degrees))``."""
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    Q = inv_T(T_ref[i]) @ T_ref[j]
    P = inv_T(T_est[i]) @ T_est[j]
    E = inv_T(Q) @ P
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle_deg(E[:, :3, :3])


def camera_yaw_deg(T_model_cam: np.ndarray) -> np.ndarray:
    """Yaw (degrees, (-180, 180]) of camera poses: heading of the optical axis on the model XY plane.

    ``atan2(z_y, z_x)`` of the camera's +z axis in the model frame; when it is within 10 degrees of
    vertical, the heading of the image-up direction (camera -y axis) is used instead.
    """
    R = np.asarray(T_model_cam, np.float64)[..., :3, :3]
    z = R[..., :, 2]
    up = -R[..., :, 1]
    nadir = np.abs(z[..., 2]) > np.cos(np.radians(NADIR_LIMIT_DEG))
    v = np.where(nadir[..., None], up, z)
    return np.degrees(np.arctan2(v[..., 1], v[..., 0]))


def view_distance_m(T_model_cam: np.ndarray, V_model: np.ndarray, cam: dict, frames, q: float = 50.0) -> float:
    """Median over ``frames`` of the ``q``-th percentile distance (m) from the camera to the model
    vertices in its view: the camera-building distance that issue 11's "0.1 % of the distance" is
    relative to (q = 50: the buildings in view; q = 0: the nearest corner, the strict reading).

    ``T_model_cam`` (N, 4, 4) camera poses in the model frame, ``V_model`` (M, 3), ``cam`` the camera
    dict (fx fy cx cy width height); NaN when no vertex is in view in any of ``frames``."""
    out = []
    for k in frames:
        T = inv_T(T_model_cam[k])
        X = V_model @ T[:3, :3].T + T[:3, 3]
        ok = X[:, 2] > 0
        u = cam["fx"] * X[ok, 0] / X[ok, 2] + cam["cx"]
        v = cam["fy"] * X[ok, 1] / X[ok, 2] + cam["cy"]
        inside = (u >= 0) & (u < cam["width"]) & (v >= 0) & (v < cam["height"])
        if inside.any():
            out.append(np.percentile(np.linalg.norm(X[ok][inside], axis=1), q))
    return float(np.median(out)) if out else float("nan")


def wrap_deg(a: np.ndarray) -> np.ndarray:
    """Wrap angles (degrees) to (-180, 180]."""
    return -((-np.asarray(a, np.float64) + 180.0) % 360.0 - 180.0)


def gap_ranges(missing: np.ndarray, t_ref: np.ndarray) -> list[dict]:
    """Runs of consecutive missing reference indices as dicts (first, last, frames, t_start, t_end)."""
    idx = np.nonzero(missing)[0]
    if len(idx) == 0:
        return []
    brk = np.nonzero(np.diff(idx) > 1)[0]
    starts = np.r_[idx[0], idx[brk + 1]]
    ends = np.r_[idx[brk], idx[-1]]
    return [{"first": int(a), "last": int(b), "frames": int(b - a + 1), "t_start": float(t_ref[a]),
             "t_end": float(t_ref[b])} for a, b in zip(starts, ends)]
