"""The UAV paper's table against navigation logs: dX dY dZ d-yaw (mean, std) for vision, GPS/AHRS and fused.

Every column is a camera trajectory ``T_model_cam`` compared with one reference (``mst eval traj
EST REF --nav nav.csv``): poses associated by nearest timestamp within ``t_max_diff_s`` seconds, no
alignment (all are in the model frame: the GPS/AHRS log is mapped into it with the calibration of
``mst nav fuse --json``). dX dY dZ: estimate - reference along the model axes [m]; d-yaw: heading of
the optical axis (:func:`mst.eval.traj.metrics.camera_yaw_deg`), estimate - reference - the column's yaw
offset, wrapped [deg]. The GPS/AHRS column is the platform attitude turned by the estimated mount;
without a calibration file the model frame is taken as the world frame, the lever arm as zero and
the mount as unknown: then the column's constant yaw offset (the mount yaw) is removed as the
circular mean of its d-yaw and reported, as in the paper.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.trajectory import read_tum
from mst.eval.traj.metrics import camera_yaw_deg, wrap_deg
from mst.pipeline.nav.log import R_MOUNT_CAM, NavLog, interpolate_poses, read_navlog


@dataclass(frozen=True)
class MeanStd:
    """Mean and (population) standard deviation of one difference (m or deg)."""

    mean: float
    std: float

    def to_json(self) -> dict:
        return {"mean": self.mean, "std": self.std}


@dataclass(frozen=True)
class NavColumn:
    """One column of the table: dX dY dZ (m) and d-yaw (deg) of an estimate against the reference,
    the yaw offset removed (deg), the ATE rmse (m), matched poses and gaps (reference poses without one)."""

    dX: MeanStd
    dY: MeanStd
    dZ: MeanStd
    dyaw: MeanStd
    yaw_offset_deg: float
    ate_rmse_m: float
    matched: int
    gaps: int
    #: the matched series (not in the JSON): reference times (s), estimate positions (m), d-yaw (deg)
    t_s: np.ndarray | None = field(default=None, repr=False, compare=False)
    xyz_m: np.ndarray | None = field(default=None, repr=False, compare=False)
    dyaw_deg: np.ndarray | None = field(default=None, repr=False, compare=False)

    def to_json(self) -> dict:
        return {"dX": self.dX.to_json(), "dY": self.dY.to_json(), "dZ": self.dZ.to_json(),
                "dyaw": self.dyaw.to_json(), "yaw_offset_deg": self.yaw_offset_deg, "ate_rmse_m": self.ate_rmse_m,
                "matched": self.matched, "gaps": self.gaps}


@dataclass
class NavTable:
    """The columns (name -> :class:`NavColumn`, in insertion order) against one reference; the
    reference's own series and the log's dropouts for :func:`nav_figure`."""

    reference: str
    columns: dict[str, NavColumn] = field(default_factory=dict)
    ref_t_s: np.ndarray | None = field(default=None, repr=False)
    ref_xyz_m: np.ndarray | None = field(default=None, repr=False)
    dropouts_s: list = field(default_factory=list, repr=False)  #: (start, end) of the log's GPS dropouts

    def to_json(self) -> dict:
        return {"reference": self.reference, "columns": {k: c.to_json() for k, c in self.columns.items()}}

    def rows(self) -> list[list[str]]:
        """Table rows: quantity, then 'mean +- std' per column."""
        out = []
        cols = list(self.columns.values())
        for key, lab in (("dX", "dX [m]"), ("dY", "dY [m]"), ("dZ", "dZ [m]"), ("dyaw", "d-yaw [deg]")):
            out.append([lab] + [f"{getattr(c, key).mean:+.3f} ± {getattr(c, key).std:.3f}" for c in cols])
        out.append(["yaw offset removed [deg]"] + [f"{c.yaw_offset_deg:.2f}" for c in cols])
        out.append(["ATE rmse [m]"] + [f"{c.ate_rmse_m:.3f}" for c in cols])
        out.append(["matched / gaps"] + [f"{c.matched} / {c.gaps}" for c in cols])
        return out


def nav_camera_poses(nav: NavLog, T_world_model: np.ndarray | None = None, R_body_cam: np.ndarray | None = None,
                     lever_arm_m=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, bool]:
    """Camera poses ``T_model_cam`` (M, 4, 4) of the GPS fixes (fix rows only) of a log. Without
    ``R_body_cam`` the camera is taken to look along the body's x axis (mount 0: its yaw offset is
    then the mount yaw). Returns (t (M,), T (M, 4, 4), mount_known)."""
    T_wm = np.eye(4) if T_world_model is None else np.asarray(T_world_model, float)
    R_bc = R_MOUNT_CAM if R_body_cam is None else np.asarray(R_body_cam, float)
    R_wb = nav.R_world_body()[nav.fix]
    R_mc = T_wm[:3, :3].T[None] @ R_wb @ R_bc[None]
    p_w = nav.p_world[nav.fix] + np.einsum("nij,j->ni", R_wb, np.asarray(lever_arm_m, float))
    T = np.tile(np.eye(4), (len(R_mc), 1, 1))
    T[:, :3, :3] = R_mc
    T[:, :3, 3] = (p_w - T_wm[:3, 3]) @ T_wm[:3, :3]
    return nav.t[nav.fix], T, R_body_cam is not None


def column_stats(t_ref: np.ndarray, T_ref: np.ndarray, t_est: np.ndarray, T_est: np.ndarray, t_max_diff: float,
                 remove_yaw_offset: bool = False, yaw_offset_deg: float = 0.0) -> NavColumn:
    """dX dY dZ d-yaw statistics of one estimate against the reference (module docstring)."""

    j = np.clip(np.searchsorted(t_est, t_ref), 1, len(t_est) - 1) if len(t_est) > 1 else np.zeros(len(t_ref), int)
    if len(t_est) > 1:
        j = np.where(np.abs(t_est[j - 1] - t_ref) <= np.abs(t_est[j] - t_ref), j - 1, j)
    ok = np.abs(t_est[j] - t_ref) <= t_max_diff
    if not ok.any():
        raise InputError(None, f"no poses within t_max_diff_s ({t_max_diff:g} s) of the reference's timestamps")
    Te, Tr = T_est[j[ok]], T_ref[ok]
    d = Te[:, :3, 3] - Tr[:, :3, 3]
    dyaw = wrap_deg(camera_yaw_deg(Te) - camera_yaw_deg(Tr))
    off = yaw_offset_deg
    if remove_yaw_offset:
        off = float(np.degrees(np.arctan2(np.sin(np.radians(dyaw)).mean(), np.cos(np.radians(dyaw)).mean())))
    dyaw = wrap_deg(dyaw - off)
    ms = [MeanStd(float(d[:, i].mean()), float(d[:, i].std())) for i in range(3)]
    return NavColumn(dX=ms[0], dY=ms[1], dZ=ms[2], dyaw=MeanStd(float(dyaw.mean()), float(dyaw.std())),
                     yaw_offset_deg=off, ate_rmse_m=float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
                     matched=int(ok.sum()), gaps=int((~ok).sum()), t_s=t_ref[ok], xyz_m=Te[:, :3, 3], dyaw_deg=dyaw)


def nav_table(t_ref, T_ref, columns: list[tuple[str, np.ndarray, np.ndarray, bool]], t_max_diff: float = 0.01,
              reference: str = "reference") -> NavTable:
    """Table for ``columns`` = [(name, t, T_model_cam, remove_yaw_offset), ...] against the reference."""
    tab = NavTable(reference=reference)
    for name, t, T, rm in columns:
        tab.columns[name] = column_stats(np.asarray(t_ref), np.asarray(T_ref), np.asarray(t), np.asarray(T), t_max_diff, rm)
    return tab


def nav_table_from_files(estimate: str | os.PathLike, reference: str | os.PathLike, nav_path: str | os.PathLike,
                         calib_path: str | os.PathLike | None = None, vision_path: str | os.PathLike | None = None,
                         t_max_diff: float = 0.01) -> NavTable:
    """Columns: vision (``vision_path``, a TUM file, if given), GPS/AHRS (``nav_path`` with the
    calibration JSON of ``mst nav fuse --json``: keys T_world_model, R_body_cam, lever_arm_m,
    nav_offset_enh), and the estimate (named by its file stem) against ``reference`` (TUM)."""
    t_ref, T_ref = read_tum(reference)
    T_wm = R_bc = None
    lever = (0.0, 0.0, 0.0)
    offset = None
    if calib_path is not None:
        p = Path(calib_path)
        if not p.is_file():
            raise InputError(p, "calibration file does not exist")
        try:
            c = json.loads(p.read_text())
            T_wm, R_bc = np.array(c["T_world_model"], float), np.array(c["R_body_cam"], float)
            lever = tuple(c.get("lever_arm_m", lever))
            offset = c.get("nav_offset_enh")
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(p, f"not a calibration of `mst nav fuse --json` ({type(e).__name__}: {e})") from None
        if T_wm.shape != (4, 4) or R_bc.shape != (3, 3):
            raise InputError(p, "T_world_model must be 4x4 and R_body_cam 3x3")
    nav = read_navlog(nav_path, offset=offset if offset is not None and any(offset) else None)
    cols: list[tuple[str, np.ndarray, np.ndarray, bool]] = []
    if vision_path is not None:
        cols.append(("vision", *read_tum(vision_path), False))
    t_n, T_n, known = nav_camera_poses(nav, T_wm, R_bc, lever)
    tab = nav_table(t_ref, T_ref, [], t_max_diff, reference=str(reference))
    for name, t, T, rm in cols:
        tab.columns[name] = column_stats(t_ref, T_ref, t, T, t_max_diff, rm)
    # the log's rows rarely fall on frame times: the reference is interpolated to the fix times
    # (inside its time range); "gaps" then counts fixes outside it
    inside = (t_n >= t_ref[0]) & (t_n <= t_ref[-1])
    if not inside.any():
        raise InputError(nav_path, "no GPS fix inside the reference's time range")
    T_ri = interpolate_poses(t_ref, T_ref, t_n[inside])
    st = column_stats(t_n[inside], T_ri, t_n[inside], T_n[inside], 1e-9, remove_yaw_offset=not known)
    tab.columns["GPS/AHRS"] = dataclasses.replace(st, gaps=int((~inside).sum()))
    tab.columns[Path(estimate).stem] = column_stats(t_ref, T_ref, *read_tum(estimate), t_max_diff)
    tab.ref_t_s, tab.ref_xyz_m = t_ref, T_ref[:, :3, 3]
    tab.dropouts_s = _runs(nav.t, ~nav.fix)
    return tab


def _runs(t: np.ndarray, flag: np.ndarray) -> list[tuple[float, float]]:
    """(start, end) times of the runs of ``flag``."""
    f = np.concatenate([[False], np.asarray(flag, bool), [False]])
    d = np.diff(f.astype(np.int8))
    return [(float(t[a]), float(t[b - 1])) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]


def _gaps(t: np.ndarray) -> list[tuple[float, float]]:
    """Stretches (s) where the times ``t`` jump by more than 1.5 x their median step (tracking lost)."""
    if len(t) < 3:
        return []
    step = np.median(np.diff(t))
    k = np.flatnonzero(np.diff(t) > 1.5 * step)
    return [(float(t[i]), float(t[i + 1])) for i in k]


def nav_figure(path: str | os.PathLike, tab: NavTable, title: str = "") -> None:
    """PNG: X, Y, Z (model frame, m) over time of the reference and every column, and each column's
    d-yaw (deg, its yaw offset removed); vision gaps shaded red (where the vision column, or else the
    estimate, has no pose), GPS dropouts shaded blue. Call inside :func:`mst.atomic_output`."""
    from mst.eval.plots import _plt

    plt = _plt()
    colors = {"vision": "#4477aa", "GPS/AHRS": "#999933"}
    cols = list(tab.columns.items())
    vis = tab.columns.get("vision") or cols[-1][1]
    gaps = _gaps(vis.t_s) if vis.t_s is not None else []
    fig, axes = plt.subplots(4, 1, figsize=(11, 9), sharex=True)
    for k, lab in enumerate(["X [m]", "Y [m]", "Z [m]", "d-yaw [deg]"]):
        a = axes[k]
        if k < 3 and tab.ref_t_s is not None:
            a.plot(tab.ref_t_s, tab.ref_xyz_m[:, k], "-", color="#bbbbbb", lw=3, label="reference")
        for name, c in cols:
            y = c.xyz_m[:, k] if k < 3 else c.dyaw_deg
            tt = c.t_s
            if name != "GPS/AHRS" and len(tt) > 2:  # no line drawn across a gap
                cut = np.flatnonzero(np.diff(tt) > 1.5 * np.median(np.diff(tt))) + 1
                tt, y = np.insert(tt, cut, np.nan), np.insert(y, cut, np.nan)
            a.plot(tt, y, "." if name == "GPS/AHRS" else ".-", ms=2, lw=0.8, color=colors.get(name, "#cc3311"),
                   label=name)
        for g0, g1 in gaps:
            a.axvspan(g0, g1, color="#ffcccc", lw=0)
        for g0, g1 in tab.dropouts_s:
            a.axvspan(g0, g1, color="#cce0ff", lw=0, alpha=0.7)
        if k == 3:
            a.axhline(0, color="k", lw=0.5)
            a.set_xlabel("time [s]  (red: vision gaps, blue: GPS dropouts)")
        a.set_ylabel(lab)
    axes[0].legend(loc="upper right", fontsize=8, ncol=len(cols) + 1)
    axes[0].set_title(title or f"against {Path(tab.reference).name}")
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)
