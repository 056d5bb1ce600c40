"""The core of ``mst eval traj``: :func:`compare_trajectories` (two pose series in, a typed
:class:`TrajResult` out) and its file form :func:`evaluate_trajectories` (files read by
:mod:`mst.core.trajectory`)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.poses import rotation_angle_deg
from mst.core.trajectory import read_trajectory
from mst.eval.traj.config import TrajConfig
from mst.eval.traj.metrics import (
    ErrorStats,
    align_estimate,
    associate,
    camera_yaw_deg,
    error_stats,
    gap_ranges,
    rpe,
    rpe_pairs_frames,
    rpe_pairs_metres,
    wrap_deg,
)


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
    return compare_trajectories(est.t, est.T_model_cam, ref.t, ref.T_model_cam, cfg, names=(est_path, ref_path),
                                rotation_known=(est.has_rotation, ref.has_rotation), notes=notes)


def compare_trajectories(t_est: np.ndarray, T_est: np.ndarray, t_ref: np.ndarray, T_ref: np.ndarray,
                         cfg: TrajConfig | None = None, *, names: tuple = ("estimate", "reference"),
                         rotation_known: tuple[bool, bool] = (True, True), notes: list[str] | None = None
                         ) -> TrajResult:
    """The core: compare the poses ``T_est`` (times ``t_est``) with ``T_ref`` (``T_model_cam``, sorted
    times, seconds). ``names`` label the two in the result and in errors; ``rotation_known``: whether
    each holds orientations (a positions-only CSV does not: no rotation errors, no d-yaw)."""
    cfg = cfg or TrajConfig()
    est_path, ref_path = names
    rot_e, rot_r = rotation_known
    ie, ir = associate(t_est, t_ref, cfg.t_max_diff_s, cfg.t_offset_s)
    if len(ie) == 0:
        raise InputError(est_path, f"no timestamps match the reference within {cfg.t_max_diff_s} s "
                         f"(estimate {t_est[0]:.3f}..{t_est[-1]:.3f} s, reference {t_ref[0]:.3f}..{t_ref[-1]:.3f} s)")
    has_rot = rot_e and rot_r
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
