"""Runners of ``mst nav simulate`` and ``mst nav fuse``: read the files, call the cores
(:func:`~mst.pipeline.nav.log.simulate_nav`, :func:`~mst.pipeline.nav.fusion.fuse_navigation`),
write the outputs atomically, return the summary; the pose-covariance side files (``.cov.csv``)."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np

from mst import InputError, atomic_outputs
from mst.pipeline.nav.fusion import FusionConfig, fuse_navigation
from mst.pipeline.nav.log import NavSimConfig

COV_COLS = [f"c{i}{j}" for i in range(6) for j in range(6)]


def cov_path_for(traj_path: str | os.PathLike) -> Path:
    """``traj.txt`` -> ``traj.cov.csv``."""
    p = Path(traj_path)
    return p.with_name(p.stem + ".cov.csv")


def format_cov_csv(t: np.ndarray, cov: np.ndarray, source: np.ndarray | None = None) -> str:
    """CSV text: ``t[,source],c00..c55`` (row-major 6x6, convention in the module docstring)."""
    out = io.StringIO()
    out.write("# pose covariance: (x y z [m, model frame], rx ry rz [rad, model-frame perturbation R = exp(r) R_est])\n")
    out.write(",".join(["t"] + (["source"] if source is not None else []) + COV_COLS) + "\n")
    flat = cov.reshape(len(t), 36)
    for i, ti in enumerate(t):
        out.write(f"{ti:.6f}," + (f"{source[i]}," if source is not None else "") + ",".join(f"{v:.6e}" for v in flat[i]) + "\n")
    return out.getvalue()


def read_cov_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a covariance side file: (t (N,), cov (N, 6, 6)); checks symmetry and positive diagonals."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "covariance file does not exist")
    rows = [r for r in csv.reader(io.StringIO(p.read_text())) if r and not r[0].lstrip().startswith("#")]
    if len(rows) < 2:
        raise InputError(p, "covariance file needs a header row and rows")
    hdr = [h.strip() for h in rows[0]]
    miss = [c for c in ["t"] + COV_COLS if c not in hdr]
    if miss:
        raise InputError(p, f"missing column(s) {', '.join(miss[:4])}{' ...' if len(miss) > 4 else ''}")
    idx = [hdr.index(c) for c in ["t"] + COV_COLS]
    try:
        a = np.array([[float(r[i]) for i in idx] for r in rows[1:]])
    except (ValueError, IndexError):
        raise InputError(p, "not a number or a short row") from None
    if not np.isfinite(a).all():
        raise InputError(p, "covariance holds NaN or infinite values")
    C = a[:, 1:].reshape(-1, 6, 6)
    if np.abs(C - np.swapaxes(C, 1, 2)).max() > 1e-9 * max(1.0, np.abs(C).max()) or (np.einsum("nii->ni", C) <= 0).any():
        raise InputError(p, "covariances must be symmetric with positive diagonals")
    return a[:, 0], C


def simulate_nav_files(gt_path, out_path, cfg: NavSimConfig) -> dict:
    """Read a TUM ground truth, simulate, write ``out_path`` and ``<stem>.truth.json`` atomically."""
    from mst.core.trajectory import read_tum
    from mst.pipeline.nav.log import simulate_nav, write_sim_outputs

    t, T = read_tum(gt_path)
    res = simulate_nav(t, T, cfg)
    out = Path(out_path)
    truth = out.with_name(out.stem + ".truth.json")
    with atomic_outputs(out, truth) as (tmp, tmp_truth):
        write_sim_outputs(res, tmp, tmp_truth)
    return {"nav": str(out), "truth": str(truth), **res.to_json()}


def _is_track_cov(path: Path) -> bool:
    """``mst track``'s ``.cov.csv`` (``frame,status,...,c00..c55``: the output pose's twist covariance)."""
    with open(path, newline="") as f:
        for line in f:
            if line.strip() and not line.lstrip().startswith("#"):
                hdr = [h.strip() for h in line.split(",")]
                return "frame" in hdr and "c00" in hdr and "t" not in hdr
    return False


def read_track_cov(cov_path: Path, traj_path, t_v: np.ndarray, T_v: np.ndarray, cfg: FusionConfig) -> np.ndarray:
    """The covariances (fusion convention) of the poses ``T_v`` (``T_model_cam`` at ``t_v``) from
    ``mst track``'s ``.cov.csv`` and the frame times of its ``.csv``.

    The tracker's rows hold the covariance ``C`` of the left twist ``T_cam_model' = exp(v, w)
    T_cam_model`` (camera frame); then ``T_model_cam' = T_model_cam exp(-(v, w))``: the camera
    centre moves by ``-R_mc v`` and the rotation by ``exp(-R_mc w)`` on the left, so the fusion's
    covariance is ``B C Bᵀ``, ``B = diag(R_mc, R_mc)``. ``slam`` rows hold the aid's propagated drift
    covariance (the same convention); rows without a covariance (a tracker older than that, or not
    positive definite as written) get ``cfg.vision_sigma_*`` x 3."""
    status_csv = Path(traj_path).with_suffix(".csv")
    if not status_csv.is_file():
        raise InputError(cov_path, f"mst track's covariance rows are per frame; their times are in {status_csv.name}, "
                                   "which is missing")
    with open(status_csv, newline="") as f:
        try:
            time_of = {int(r["frame"]): float(r["time"]) for r in csv.DictReader(f)}
        except (ValueError, KeyError, TypeError):
            raise InputError(status_csv, "not mst track's per-frame CSV (frame, time columns)") from None
    rows = [r for r in csv.DictReader(io.StringIO(cov_path.read_text()))]
    by_t: dict[float, np.ndarray] = {}
    for r in rows:
        try:
            k = int(r["frame"])
            vals = [r.get(f"c{i}{j}") or "" for i in range(6) for j in range(6)]
            C = np.array([float(v) for v in vals]).reshape(6, 6) if all(vals) else None
        except (ValueError, KeyError, TypeError):
            raise InputError(cov_path, f"not a number or a short row (frame {r.get('frame')})") from None
        if k in time_of and C is not None:
            if not np.isfinite(C).all() or (np.diag(C) <= 0).any():
                raise InputError(cov_path, f"frame {k}: covariance holds NaN/inf or a non-positive variance")
            by_t[round(time_of[k], 6)] = C
    s2 = np.array([cfg.vision_sigma_m**2] * 3 + [np.radians(cfg.vision_sigma_deg) ** 2] * 3)
    out = np.tile(np.diag(9.0 * s2), (len(t_v), 1, 1))
    got = [by_t.get(round(float(ti), 6)) for ti in t_v]
    has = np.array([c is not None for c in got], bool)
    if has.any():
        C = np.stack([c for c in got if c is not None])
        B = np.zeros((int(has.sum()), 6, 6))
        B[:, :3, :3] = B[:, 3:, 3:] = T_v[has, :3, :3]
        out[has] = B @ (0.5 * (C + np.swapaxes(C, 1, 2))) @ np.swapaxes(B, 1, 2)
    return out


def _vision_covariances(traj_path, t_v: np.ndarray, cov_path, cfg: FusionConfig, T_v: np.ndarray | None = None
                        ) -> np.ndarray:
    """The vision poses' covariances: the side file (given, or ``<stem>.cov.csv`` when present: the
    fusion's own format, or ``mst track``'s per-frame one), else ``cfg.vision_sigma_*`` (x9 for the
    SLAM frames of ``mst track``'s per-frame CSV beside it)."""
    cp = Path(cov_path) if cov_path else cov_path_for(traj_path)
    if (cov_path or cp.is_file()) and T_v is not None and cp.is_file() and _is_track_cov(cp):
        return read_track_cov(cp, traj_path, t_v, T_v, cfg)
    if cov_path or cp.is_file():
        t_c, C = read_cov_csv(cp)
        m = {round(x, 6): i for i, x in enumerate(t_c)}
        idx = [m.get(round(x, 6)) for x in t_v]
        if any(i is None for i in idx):
            raise InputError(cp, f"{sum(i is None for i in idx)} trajectory poses have no covariance row (times differ)")
        return C[idx]
    s2 = np.array([cfg.vision_sigma_m**2] * 3 + [np.radians(cfg.vision_sigma_deg) ** 2] * 3)
    cov = np.tile(np.diag(s2), (len(t_v), 1, 1))
    status_csv = Path(traj_path).with_suffix(".csv")
    if status_csv.is_file():  # mst track's per-frame status: SLAM-only frames are less certain
        with open(status_csv, newline="") as f:
            try:
                st = {round(float(r["time"]), 6): r.get("status") for r in csv.DictReader(f) if r.get("time")}
            except (ValueError, KeyError):
                st = {}  # not mst track's per-frame CSV: no statuses
        slam = np.array([st.get(round(x, 6)) == "slam" for x in t_v])
        cov[slam] *= 9.0
    return cov


def fuse_nav_files(traj_path: str | os.PathLike, nav_path: str | os.PathLike, out: str | os.PathLike,
                   cfg: FusionConfig, *, cov_path=None, offset=None, mount_path=None, m2w_path=None,
                   write_json: bool = False) -> tuple[dict, object]:
    """Fuse the trajectory file with the log; write ``out`` (TUM), ``<stem>.cov.csv`` and, with
    ``write_json``, ``<stem>.json`` (the summary) atomically. Returns ``(summary, FusionResult)``."""
    from mst.core.poses import read_rigid_transform
    from mst.core.trajectory import format_tum, read_tum
    from mst.pipeline.nav.log import read_mount_rotation, read_navlog

    t_v, T_v = read_tum(traj_path)
    nav = read_navlog(nav_path, offset=offset)
    cov = _vision_covariances(traj_path, t_v, cov_path, cfg, T_v)
    res = fuse_navigation(t_v, T_v, cov, nav, cfg, nav_name=nav_path,
                          R_body_cam=read_mount_rotation(mount_path) if mount_path else None,
                          T_world_model=read_rigid_transform(m2w_path, "model-to-world file") if m2w_path else None)
    out = Path(out)
    cov_out = cov_path_for(out)
    json_out = out.with_suffix(".json") if write_json else None
    summary = {"traj": str(out), "cov": str(cov_out), "vision": str(traj_path), "nav": str(nav_path), **res.to_json(),
               "config": cfg.to_dict()}
    with atomic_outputs(out, cov_out, json_out) as (tmp, tmp_cov, tmp_json):
        tmp.write_text(f"# mst nav fuse ({cfg.mode}): TUM camera pose in the model frame, every frame; covariance in {cov_out.name}\n"
                       + format_tum(res.t, res.T_model_cam))
        tmp_cov.write_text(format_cov_csv(res.t, res.cov, np.where(res.has_vision, "vision", "nav")))
        if tmp_json is not None:
            tmp_json.write_text(json.dumps(summary, indent=2) + "\n")
    return summary, res
