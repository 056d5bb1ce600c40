"""Trajectory comparison of ``mst eval traj``: association, alignment, ATE, RPE, the UAV table.

The metrics of :func:`compare_trajectories` (arrays in, a typed :class:`TrajResult` out) and the
file form :func:`evaluate_trajectories`; trajectory files are read by :mod:`mst.core.trajectory`.

Conventions: poses are ``T_model_cam`` 4x4 float64 (camera pose in the model/world frame, what TUM
files hold); positions in metres, angles in degrees. The computations follow evo (Grupp 2017)
exactly, so the numbers equal ``evo_ape`` / ``evo_rpe`` on the same files:

* association: evo's ``associate_trajectories`` (nearest timestamp within ``t_max_diff_s`` seconds,
  each pose of the trajectory with fewer poses matched into the longer one);
* alignment of the estimate onto the reference: ``none``; ``se3`` / ``sim3`` (Umeyama on the
  associated positions, without / with scale); ``first`` (the estimate's first associated pose
  mapped onto the reference's: ``T = T_ref[0] @ inv(T_est[0])``);
* ATE: ``|t_est - t_ref|`` per associated pose; rotation error: angle of ``R_est^T R_ref``;
* RPE (consecutive pairs chosen on the aligned estimate like evo): ``E = inv(inv(Q_i) Q_j) inv(P_i) P_j``,
  translation norm and rotation angle, for ``delta_frames`` frames and for ``delta_m`` metres of path;
* statistics: rmse, mean, median, std (population), min, max.

UAV table (mean and std of dX dY dZ and d-yaw): differences estimate - reference of the aligned
positions along the model axes (metres), and of the yaw (degrees, wrapped to (-180, 180], after
removing the constant camera-mount offset ``yaw_offset_deg``). **Yaw of a camera pose**: the heading
of the camera's optical axis (its +z axis) projected on the model XY plane, ``atan2(R[1,2], R[0,2])``
in degrees (0 = +X, 90 = +Y). When the optical axis is within 10 degrees of vertical (nadir camera)
the image-up direction (-y axis of the camera) is projected instead.

Gaps: reference poses that have no estimate within ``t_max_diff_s`` (tracking lost), counted and listed
as ranges of consecutive reference indices with their times.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.config import Config, param
from mst.core.poses import inv_T, make_T, rotation_angle_deg
from mst.core.trajectory import TRAJECTORY_FORMATS, parse_csv_columns, read_trajectory
from mst.errors import ConfigError

NADIR_LIMIT_DEG = 10.0
_INF = math.inf


@dataclass
class TrajConfig(Config):
    """Settings of the trajectory comparison (``mst eval traj``)."""

    align: str = param("se3", choices=("none", "se3", "sim3", "first"),
                       help="alignment of the estimate onto the reference: Umeyama without/with scale, first pose, none")
    t_max_diff_s: float = param(0.01, min=0, max=_INF, max_open=True,
                                help="association tolerance (evo's default): poses match within this, s")
    t_offset_s: float = param(0.0, min=-_INF, min_open=True, max=_INF, max_open=True,
                              help="added to the estimate's timestamps, s")
    delta_frames: int = param(1, min=1, help="RPE step in frames")
    delta_m: float = param(1.0, min=0, min_open=True, max=_INF, max_open=True, help="RPE step in metres of path")
    yaw_offset_deg: float = param(0.0, min=-_INF, min_open=True, max=_INF, max_open=True,
                                  help="constant camera-mount yaw offset removed from d-yaw, deg")
    format: str = param("auto", choices=TRAJECTORY_FORMATS,
                        help="trajectory file format (auto: .csv -> csv, 12 numbers per line -> kitti, else tum)")
    csv_columns: str | None = param(None, help="CSV columns as key=column pairs, e.g. t=time,x=e,y=n,z=h "
                                               "(keys t x y z qx qy qz qw; unnamed keys: the column of that name)")
    fps: float | None = param(None, min=0, min_open=True, max=_INF, max_open=True,
                              help="KITTI files: timestamps are line index / fps (null: the index)")

    def check(self) -> None:
        parse_csv_columns(self.csv_columns)  # a bad spec is a ConfigError of csv_columns


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


@dataclass(frozen=True)
class RelativeError:
    """RPE over pairs ``step`` apart (frames or metres of path): translation (m), rotation (deg)."""

    step_key: str          # "delta" (frames) or "delta_m" (metres)
    step: float
    translation: ErrorStats
    rotation_deg: ErrorStats | None

    def to_json(self) -> dict:
        return {self.step_key: self.step, "translation": self.translation.to_json(),
                "rotation_deg": self.rotation_deg.to_json() if self.rotation_deg is not None else None}


@dataclass(frozen=True)
class TrajSeries:
    """Per-pose arrays for plots (not part of the JSON)."""

    t: np.ndarray
    xyz_ref: np.ndarray
    xyz_est: np.ndarray
    dxyz: np.ndarray
    dyaw: np.ndarray | None
    t_ref_all: np.ndarray
    xyz_ref_all: np.ndarray


@dataclass(frozen=True)
class TrajResult:
    """Result of :func:`evaluate_trajectories`; :meth:`to_json` is the ``mst eval traj --json`` summary.

    ``ate`` metres, ``rotation_error_deg``, ``rpe_frames`` / ``rpe_metres``, ``uav_table`` (mean/std of
    dX dY dZ metres and d-yaw degrees, JSON-ready), ``gaps`` (reference poses without an estimate:
    counts and ranges), ``alignment`` (``T_ref_est`` 4x4 and ``scale``), ``notes`` (e.g. dropped
    duplicate poses), ``series`` for plots.
    """

    estimate: str
    reference: str
    notes: list[str]
    poses_estimate: int
    poses_reference: int
    associated: int
    t_max_diff_s: float
    align: str
    T_ref_est: np.ndarray
    scale: float
    ate: ErrorStats
    rotation_error_deg: ErrorStats | None
    rpe_frames: RelativeError
    rpe_metres: RelativeError
    uav_table: dict
    gaps: dict
    config: TrajConfig
    series: TrajSeries = field(repr=False)

    def to_json(self) -> dict:
        return {
            "estimate": self.estimate, "reference": self.reference, "notes": list(self.notes),
            "poses_estimate": self.poses_estimate, "poses_reference": self.poses_reference,
            "associated": self.associated, "t_max_diff_s": self.t_max_diff_s, "align": self.align,
            "alignment": {"T_ref_est": self.T_ref_est.tolist(), "scale": self.scale},
            "ate": self.ate.to_json(),
            "rotation_error_deg": self.rotation_error_deg.to_json() if self.rotation_error_deg is not None else None,
            "rpe_frames": self.rpe_frames.to_json(), "rpe_metres": self.rpe_metres.to_json(),
            "uav_table": self.uav_table, "gaps": self.gaps, "config": self.config.to_dict(),
        }


def evaluate_trajectories(est_path: str | os.PathLike, ref_path: str | os.PathLike,
                          config: TrajConfig | None = None) -> TrajResult:
    """Compare an estimated trajectory file with a reference file (see the module docstring)."""
    cfg = config or TrajConfig()
    est = read_trajectory(est_path, cfg.format, cfg.csv_columns, cfg.fps)
    ref = read_trajectory(ref_path, cfg.format, cfg.csv_columns, cfg.fps)
    notes = [f"{Path(p)}: {tr.duplicates_dropped} identical duplicate pose(s) dropped"
             for p, tr in ((est_path, est), (ref_path, ref)) if tr.duplicates_dropped]
    return compare_trajectories(est.t, est.T_model_cam, ref.t, ref.T_model_cam, cfg,
                                has_rotation=est.has_rotation and ref.has_rotation, names=(est_path, ref_path),
                                rotation_known=(est.has_rotation, ref.has_rotation), notes=notes)


def compare_trajectories(t_est: np.ndarray, T_est: np.ndarray, t_ref: np.ndarray, T_ref: np.ndarray,
                         cfg: TrajConfig | None = None, *, has_rotation: bool = True,
                         names: tuple = ("estimate", "reference"), rotation_known: tuple[bool, bool] | None = None,
                         notes: list[str] | None = None) -> TrajResult:
    """The core: compare the poses ``T_est`` (times ``t_est``) with ``T_ref`` (``T_model_cam``, sorted
    times, seconds). ``names`` label the two in the result and in errors."""
    cfg = cfg or TrajConfig()
    est_path, ref_path = names
    rot_e, rot_r = rotation_known if rotation_known is not None else (has_rotation, has_rotation)
    ie, ir = associate(t_est, t_ref, cfg.t_max_diff_s, cfg.t_offset_s)
    if len(ie) == 0:
        raise InputError(est_path, f"no timestamps match the reference within {cfg.t_max_diff_s} s "
                         f"(estimate {t_est[0]:.3f}..{t_est[-1]:.3f} s, reference {t_ref[0]:.3f}..{t_ref[-1]:.3f} s)")
    has_rot = has_rotation
    Te, Tr = T_est[ie], T_ref[ir]
    if cfg.align == "first" and not has_rot:
        raise InputError(ref_path if rot_e else est_path, "alignment first needs orientations (no quaternion columns)")
    if cfg.align in ("se3", "sim3") and len(ie) >= 3:
        _check_spread(cfg.align, ((est_path, Te), (ref_path, Tr)))
    Ta, T_align, scale = align_estimate(Te, Tr, cfg.align)
    dxyz = Ta[:, :3, 3] - Tr[:, :3, 3]
    ate = np.linalg.norm(dxyz, axis=1)
    rot_err = (error_stats(rotation_angle_deg(np.swapaxes(Ta[:, :3, :3], -1, -2) @ Tr[:, :3, :3]))
               if has_rot else None)
    pf = rpe_pairs_frames(len(Ta), max(1, int(cfg.delta_frames)))
    pm = rpe_pairs_metres(Ta[:, :3, 3], cfg.delta_m)
    et, er = rpe(Tr, Ta, pf)
    mt, mr = rpe(Tr, Ta, pm)
    rpe_f = RelativeError("delta", int(cfg.delta_frames), error_stats(et), error_stats(er) if has_rot else None)
    rpe_m = RelativeError("delta_m", cfg.delta_m, error_stats(mt), error_stats(mr) if has_rot else None)
    dyaw = wrap_deg(camera_yaw_deg(Ta) - camera_yaw_deg(Tr) - cfg.yaw_offset_deg) if has_rot else None
    table = {}
    for k, name in enumerate(("dX", "dY", "dZ")):
        table[name] = {"mean": float(dxyz[:, k].mean()), "std": float(dxyz[:, k].std()), "unit": "m"}
    table["dyaw"] = ({"mean": float(dyaw.mean()), "std": float(dyaw.std()), "unit": "deg",
                      "yaw_offset_deg": cfg.yaw_offset_deg} if dyaw is not None else None)
    series = TrajSeries(t=t_ref[ir], xyz_ref=Tr[:, :3, 3], xyz_est=Ta[:, :3, 3], dxyz=dxyz, dyaw=dyaw,
                        t_ref_all=t_ref, xyz_ref_all=T_ref[:, :3, 3])
    return TrajResult(estimate=str(est_path), reference=str(ref_path), notes=list(notes or []),
                      poses_estimate=int(len(t_est)), poses_reference=int(len(t_ref)), associated=int(len(ie)),
                      t_max_diff_s=cfg.t_max_diff_s, align=cfg.align, T_ref_est=T_align, scale=scale,
                      ate=error_stats(ate), rotation_error_deg=rot_err, rpe_frames=rpe_f, rpe_metres=rpe_m,
                      uav_table=table, gaps=_gaps(t_est, t_ref, cfg), config=cfg, series=series)


def _check_spread(align: str, trajectories) -> None:
    """Umeyama needs positions spread in 2 dimensions: name the trajectory that is degenerate."""
    for path, T in trajectories:
        sv = np.linalg.svd(T[:, :3, 3] - T[:, :3, 3].mean(0), compute_uv=False)
        if sv[1] <= 1e-9 * max(1.0, float(np.abs(T[:, :3, 3]).max())) * np.sqrt(len(T)):
            raise InputError(path, f"the {len(T)} associated positions are identical or on one line: "
                                   f"alignment {align} is not determined (use alignment first or none)")


def _gaps(t_est: np.ndarray, t_ref: np.ndarray, cfg: TrajConfig) -> dict:
    """Reference poses without an estimate within the tolerance (whatever the association side)."""
    te = t_est + cfg.t_offset_s
    k = np.clip(np.searchsorted(te, t_ref), 1, max(len(te) - 1, 1))
    near = np.minimum(np.abs(te[k] - t_ref), np.abs(te[k - 1] - t_ref)) if len(te) > 1 else np.abs(te[0] - t_ref)
    missing = near > cfg.t_max_diff_s
    gaps = gap_ranges(missing, t_ref)
    return {"missing_reference_poses": int(missing.sum()), "count": len(gaps), "ranges": gaps}


def report_rows(s: dict) -> list[list[str]]:
    """The main numbers as (metric, value) rows for the console table."""
    def f(v, nd=4):
        return "-" if v is None else f"{v:.{nd}f}"

    rows = [["associated poses", f"{s['associated']} (est {s['poses_estimate']}, ref {s['poses_reference']})"],
            ["alignment", f"{s['align']}" + (f" (scale {s['alignment']['scale']:.6f})" if s["align"] == "sim3" else "")]]
    a = s["ate"]
    rows.append(["ATE [m] rmse / mean / median / std / min / max",
                 " / ".join(f(a[k]) for k in ("rmse", "mean", "median", "std", "min", "max"))])
    if s["rotation_error_deg"]:
        r = s["rotation_error_deg"]
        rows.append(["rotation error [deg] rmse / mean / max", " / ".join(f(r[k], 3) for k in ("rmse", "mean", "max"))])
    for key, lab in (("rpe_frames", f"RPE {s['rpe_frames']['delta']} frame(s)"),
                     ("rpe_metres", f"RPE {s['rpe_metres']['delta_m']:g} m")):
        tr = s[key]["translation"]
        rr = s[key]["rotation_deg"]
        rows.append([f"{lab} [m] rmse / mean", f"{f(tr['rmse'])} / {f(tr['mean'])} ({tr['count']} pairs)"])
        if rr:
            rows.append([f"{lab} [deg] rmse / mean", f"{f(rr['rmse'], 3)} / {f(rr['mean'], 3)}"])
    g = s["gaps"]
    rows.append(["gaps (reference poses without estimate)",
                 f"{g['missing_reference_poses']} poses in {g['count']} range(s)"])
    return rows


def uav_rows(s: dict) -> list[list[str]]:
    """UAV-paper table rows: quantity, mean, std."""
    rows = []
    for k, lab in (("dX", "dX [m]"), ("dY", "dY [m]"), ("dZ", "dZ [m]"), ("dyaw", "d-yaw [deg]")):
        v = s["uav_table"][k]
        rows.append([lab, "-" if v is None else f"{v['mean']:.4f}", "-" if v is None else f"{v['std']:.4f}"])
    return rows
