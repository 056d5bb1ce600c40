"""Runners of ``mst nav simulate`` and ``mst nav fuse``: read the files, call the cores
(:func:`~mst.pipeline.navlog.simulate_nav`, :func:`~mst.pipeline.navfusion.fuse_navigation`),
write the outputs atomically, return the summary."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np

from mst import InputError, atomic_outputs
from mst.pipeline.navfusion import FusionConfig, cov_path_for, format_cov_csv, fuse_navigation, read_cov_csv
from mst.pipeline.navlog import NavSimConfig


def simulate_nav_files(gt_path, out_path, cfg: NavSimConfig) -> dict:
    """Read a TUM ground truth, simulate, write ``out_path`` and ``<stem>.truth.json`` atomically."""
    from mst.core.poses import read_tum
    from mst.pipeline.navlog import simulate_nav, write_sim_outputs

    t, T = read_tum(gt_path)
    res = simulate_nav(t, T, cfg)
    out = Path(out_path)
    truth = out.with_name(out.stem + ".truth.json")
    with atomic_outputs(out, truth) as (tmp, tmp_truth):
        write_sim_outputs(res, tmp, tmp_truth)
    return {"nav": str(out), "truth": str(truth), **res.to_json()}


def _vision_covariances(traj_path, t_v: np.ndarray, cov_path, cfg: FusionConfig) -> np.ndarray:
    """The vision poses' covariances: the side file (given, or ``<stem>.cov.csv`` when present), else
    ``cfg.vision_sigma_*`` (x9 for the SLAM frames of ``mst track``'s per-frame CSV beside it)."""
    cp = Path(cov_path) if cov_path else cov_path_for(traj_path)
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
    from mst.core.poses import format_tum, read_rigid_transform, read_tum
    from mst.pipeline.navlog import read_mount_rotation, read_navlog

    t_v, T_v = read_tum(traj_path)
    nav = read_navlog(nav_path, offset=offset)
    cov = _vision_covariances(traj_path, t_v, cov_path, cfg)
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
